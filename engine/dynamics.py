"""The dual problem of a step: free velocities, Delassus matrix, free row velocities, bounds.

With u_free = u + dt M^-1 h (gravity, external wrenches, gyroscopic terms) the rows ask for
J u+ + R lambda = c with u+ = u_free + M^-1 J^T lambda, i.e. D lambda + v_f = 0 (bilateral rows)
with D = J M^-1 J^T + R and v_f = J u_free - c. The solver works in preconditioned variables
x = P^-1 lambda with P = diag(D)^-1/2: matrix P D P (unit diagonal), vector P v_f, bounds lo / P.

Force elements (engine.forces) and Control.joint_effort on undriven joints enter h as body
wrenches (force_wrench_of), evaluated explicitly at the poses and twists the free velocities are
computed from: Moreau-Jean's midpoint poses and the step's starting twists, semi-implicit Euler's
starting poses and twists. Each body sums the slots acting on it in slot order (no atomics), so
the staged kernel (forced_free_velocity) and the fused step add them in the same order.
"""

import warp as wp

from engine.linalg import sparse
from engine.joints import JOINT_REVOLUTE, body_twist, joint_coordinate_row, joint_frames
from engine.model import (
    FORCE_BODY_WRENCH,
    FORCE_JOINT_EFFORT,
    FORCE_JOINT_SPRING,
    FORCE_JOINT_TORQUE,
    FORCE_LINEAR_SPRING,
    ROW_CONTACT_NORMAL,
    ROW_CONTACT_TANGENT,
    UNBOUNDED,
    ForceArrays,
    ModelArrays,
    WorkArrays,
)
from engine.spatial import (gyroscopic_implicit_midpoint, spring_tension, twist, two_sum, world_inertia_inverse,
                            wrap_angle)

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only


@wp.func
def body_term(body_of_row: int, J: wp.spatial_vector, other_body: int, MJ_other: wp.spatial_vector):
    """J_i,b . (M^-1 J_j,b^T) when both rows act on the same (non-world) body, else 0."""
    if body_of_row >= 0 and body_of_row == other_body:
        return wp.dot(J, MJ_other)
    return 0.0


@wp.func
def free_velocity_of(world: int, b: int, m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform),
                     body_qd: wp.array2d(dtype=wp.spatial_vector), body_qd_low: wp.array2d(dtype=wp.spatial_vector),
                     body_f: wp.array2d(dtype=wp.spatial_vector), compensated: int,
                     body_qd_low_out: wp.array2d(dtype=wp.spatial_vector)):
    """u_free = u + dt M^-1 (m g + f) into w.body_qd_free, with the gyroscopic torque integrated by
    the implicit midpoint rule; ``compensated``: summed with compensation, u + body_qd_low is the
    twist and the free twist's rounding error goes to body_qd_low_out (engine.State); else a
    float32 sum."""
    dt = m.world_dt[world]
    q = wp.transform_get_rotation(body_q[world, b])
    u = body_qd[world, b]
    f = body_f[world, b]
    dv = dt * (m.world_gravity[world] + m.body_inv_mass[world, b] * wp.spatial_top(f))
    omega = wp.spatial_bottom(u)
    change = gyroscopic_implicit_midpoint(wp.quat_rotate_inv(q, omega), m.body_inertia[world, b], dt)
    dw = wp.quat_rotate(q, change) + dt * (world_inertia_inverse(q, m.body_inv_inertia[world, b])
                                           * wp.spatial_bottom(f))
    if compensated == 0:
        w.body_qd_free[world, b] = u + twist(dv, dw)
        return
    free, low = two_sum(u, body_qd_low[world, b] + twist(dv, dw))
    w.body_qd_free[world, b] = free
    body_qd_low_out[world, b] = low


@wp.func
def body_pose(body_q: wp.array2d(dtype=wp.transform), world: int, body: int):
    """Pose of a body, the identity for the world (-1)."""
    if body < 0:
        return wp.transform_identity()
    return body_q[world, body]


@wp.func
def spring_gap_of(world: int, k: int, fa: ForceArrays, body_q: wp.array2d(dtype=wp.transform)):
    """Linear spring k's gap from its point on body a to its point on body b (world frame [m]) and
    the two points' offsets from their bodies' centres of mass: (gap, r_a, r_b)."""
    X_a = body_pose(body_q, world, fa.force_body_a[world, k])
    X_c = body_pose(body_q, world, fa.force_body_b[world, k])
    r_a = wp.quat_rotate(wp.transform_get_rotation(X_a), fa.force_point_a[world, k])
    r_c = wp.quat_rotate(wp.transform_get_rotation(X_c), fa.force_point_b[world, k])
    return (wp.transform_get_translation(X_c) - wp.transform_get_translation(X_a)) + (r_c - r_a), r_a, r_c


@wp.func
def spring_wrench_of(world: int, k: int, b: int, fa: ForceArrays, body_q: wp.array2d(dtype=wp.transform),
                     body_qd: wp.array2d(dtype=wp.spatial_vector)):
    """Wrench (force, torque about the COM; world frame) of linear spring k on body b (one of its
    two bodies): tension T = k (L - L0) + c dL/dt along the points' line, pulling a towards b;
    tension-only: none while L < L0 and never a push."""
    a = fa.force_body_a[world, k]
    c = fa.force_body_b[world, k]
    gap, r_a, r_c = spring_gap_of(world, k, fa, body_q)
    u_a = body_twist(body_qd, world, a)
    u_c = body_twist(body_qd, world, c)
    coef = wp.vec4(fa.force_stiffness[world, k], fa.force_damping[world, k], fa.force_rest[world, k],
                   float(fa.force_tension_only[world, k]))
    n, tension = spring_tension(coef, gap, (wp.spatial_top(u_c) + wp.cross(wp.spatial_bottom(u_c), r_c))
                                - (wp.spatial_top(u_a) + wp.cross(wp.spatial_bottom(u_a), r_a)))
    if b == a:
        f = tension * n
        return twist(f, wp.cross(r_a, f))
    f = -tension * n
    return twist(f, wp.cross(r_c, f))


@wp.func
def joint_force_wrench_of(world: int, k: int, b: int, kind: int, m: ModelArrays, fa: ForceArrays,
                          body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector),
                          no_low: wp.array2d(dtype=wp.transform), joint_effort: wp.array2d(dtype=float)):
    """Wrench on body b (the joint's child or parent) of joint slot k: generalized force tau on
    the joint coordinate (spring: -k (q - q0) - c dq; torque: its effort; Control.joint_effort),
    mapped by the coordinate's Jacobian: J_c^T tau on the child, J_p^T tau on the parent (equal
    and opposite torques about the axis of a revolute joint, forces along a prismatic one's)."""
    j = fa.force_joint[world, k]
    jtype = m.joint_type[world, j]
    child = m.joint_child[world, j]
    parent = m.joint_parent[world, j]
    tau = float(0.0)
    if kind == FORCE_JOINT_TORQUE:
        tau = fa.force_effort[world, k]
    elif kind == FORCE_JOINT_EFFORT:
        tau = joint_effort[world, j]
    X_wp, X_wc, r_p, r_c, d = joint_frames(body_q, no_low, world, parent, child, m.joint_X_p[world, j],
                                           m.joint_X_c[world, j], 0)
    J_c, J_p, q = joint_coordinate_row(jtype, X_wp, X_wc, r_p, r_c, d, m.joint_axis[world, j])
    if kind == FORCE_JOINT_SPRING:
        error = q - fa.force_rest[world, k]
        if jtype == JOINT_REVOLUTE:
            error = wrap_angle(error)
        dq = wp.dot(J_c, body_twist(body_qd, world, child)) + wp.dot(J_p, body_twist(body_qd, world, parent))
        tau = -fa.force_stiffness[world, k] * error - fa.force_damping[world, k] * dq
    if b == child:
        return tau * J_c
    return tau * J_p


@wp.func
def spring_potential_of(world: int, k: int, m: ModelArrays, fa: ForceArrays, body_q: wp.array2d(dtype=wp.transform),
                        no_low: wp.array2d(dtype=wp.transform)):
    """Potential energy [J] stored in force slot k at the poses body_q: 1/2 k s^2 of a linear spring
    stretched by s (a tension-only one: only while stretched) or of a joint spring displaced by s
    from its rest position; 0 for the other slots."""
    kind = fa.force_kind[world, k]
    stretch = float(0.0)
    if kind == FORCE_LINEAR_SPRING:
        gap, r_a, r_c = spring_gap_of(world, k, fa, body_q)
        stretch = wp.length(gap) - fa.force_rest[world, k]
        if fa.force_tension_only[world, k] != 0 and stretch < 0.0:
            stretch = 0.0
    elif kind == FORCE_JOINT_SPRING:
        j = fa.force_joint[world, k]
        jtype = m.joint_type[world, j]
        X_wp, X_wc, r_p, r_c, d = joint_frames(body_q, no_low, world, m.joint_parent[world, j],
                                               m.joint_child[world, j], m.joint_X_p[world, j], m.joint_X_c[world, j], 0)
        J_c, J_p, q = joint_coordinate_row(jtype, X_wp, X_wc, r_p, r_c, d, m.joint_axis[world, j])
        stretch = q - fa.force_rest[world, k]
        if jtype == JOINT_REVOLUTE:
            stretch = wrap_angle(stretch)
    return 0.5 * fa.force_stiffness[world, k] * stretch * stretch


@wp.func
def force_wrench_of(world: int, b: int, m: ModelArrays, fa: ForceArrays, body_q: wp.array2d(dtype=wp.transform),
                    body_qd: wp.array2d(dtype=wp.spatial_vector), no_low: wp.array2d(dtype=wp.transform),
                    joint_effort: wp.array2d(dtype=float)):
    """Sum of the wrenches of world's force slots on body b (force, torque about the COM; world
    frame) at the poses body_q and twists body_qd, in slot order."""
    total = wp.spatial_vector()
    for i in range(fa.force_body_start[world, b], fa.force_body_start[world, b + 1]):  # the slots on body b
        k = fa.force_body_slot[world, i]
        kind = fa.force_kind[world, k]
        if kind == FORCE_JOINT_EFFORT:
            if joint_effort[world, fa.force_joint[world, k]] == 0.0:
                continue  # an undriven joint's Control slot, unused: no frames to compute
        if kind == FORCE_LINEAR_SPRING:
            total += spring_wrench_of(world, k, b, fa, body_q, body_qd)
        elif kind == FORCE_BODY_WRENCH:
            total += twist(fa.force_force[world, k], fa.force_torque[world, k])
        else:
            total += joint_force_wrench_of(world, k, b, kind, m, fa, body_q, body_qd, no_low, joint_effort)
    return total


@wp.func
def forced_free_velocity_of(world: int, b: int, m: ModelArrays, fa: ForceArrays, w: WorkArrays,
                            body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector),
                            body_qd_low: wp.array2d(dtype=wp.spatial_vector),
                            body_f: wp.array2d(dtype=wp.spatial_vector), joint_effort: wp.array2d(dtype=float),
                            compensated: int, body_qd_low_out: wp.array2d(dtype=wp.spatial_vector)):
    """w.body_f_total = body_f + the force slots' wrenches (force_wrench_of), then the free
    velocity under it (free_velocity_of). Reads every body's pose: call it once all are set."""
    w.body_f_total[world, b] = body_f[world, b] + force_wrench_of(world, b, m, fa, body_q, body_qd, w.no_low,
                                                                  joint_effort)
    free_velocity_of(world, b, m, w, body_q, body_qd, body_qd_low, w.body_f_total, compensated, body_qd_low_out)


@wp.kernel
def forced_free_velocity(m: ModelArrays, fa: ForceArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform),
                         body_qd: wp.array2d(dtype=wp.spatial_vector), body_qd_low: wp.array2d(dtype=wp.spatial_vector),
                         body_f: wp.array2d(dtype=wp.spatial_vector), joint_effort: wp.array2d(dtype=float),
                         compensated: int, body_qd_low_out: wp.array2d(dtype=wp.spatial_vector)):
    """u_free = u + dt M^-1 (m g + f + force slots) (forced_free_velocity_of), a thread per body."""
    world, b = wp.tid()
    if b >= m.body_count[world]:
        return
    forced_free_velocity_of(world, b, m, fa, w, body_q, body_qd, body_qd_low, body_f, joint_effort, compensated,
                            body_qd_low_out)


@wp.kernel
def free_velocity(m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform),
                  body_qd: wp.array2d(dtype=wp.spatial_vector), body_qd_low: wp.array2d(dtype=wp.spatial_vector),
                  body_f: wp.array2d(dtype=wp.spatial_vector), compensated: int,
                  body_qd_low_out: wp.array2d(dtype=wp.spatial_vector)):
    """u_free = u + dt M^-1 (m g + f) (free_velocity_of)."""
    world, b = wp.tid()
    if b >= m.body_count[world]:
        return
    free_velocity_of(world, b, m, w, body_q, body_qd, body_qd_low, body_f, compensated, body_qd_low_out)


@wp.func
def mass_weighted(body: int, J: wp.spatial_vector, inv_mass: float, inv_inertia_world: wp.mat33):
    """M^-1 J^T for one body (zero for the world)."""
    if body < 0:
        return wp.spatial_vector()
    return twist(inv_mass * wp.spatial_top(J), inv_inertia_world * wp.spatial_bottom(J))


@wp.func
def row_mass_weighted(world: int, i: int, m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform)):
    """M^-1 J^T of a row for its child and parent body, and the diagonal J M^-1 J^T."""
    c = w.row_body_c[world, i]
    p = w.row_body_p[world, i]
    MJ_c = wp.spatial_vector()
    MJ_p = wp.spatial_vector()
    if c >= 0:
        MJ_c = mass_weighted(c, w.row_J_c[world, i], m.body_inv_mass[world, c], world_inertia_inverse(
            wp.transform_get_rotation(body_q[world, c]), m.body_inv_inertia[world, c]))
    if p >= 0:
        MJ_p = mass_weighted(p, w.row_J_p[world, i], m.body_inv_mass[world, p], world_inertia_inverse(
            wp.transform_get_rotation(body_q[world, p]), m.body_inv_inertia[world, p]))
    return MJ_c, MJ_p, wp.dot(w.row_J_c[world, i], MJ_c) + wp.dot(w.row_J_p[world, i], MJ_p)


@wp.func
def row_operator_of(world: int, i: int, m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform)):
    """Row i's M^-1 J^T at the poses body_q, its Jacobi preconditioner P (one value per contact
    triplet, so the friction cone keeps its shape), and its preconditioned v_f and bounds."""
    if i >= w.row_count[world]:
        w.row_precond[world, i] = 1.0
        w.v_f[world, i] = 0.0
        w.lo[world, i] = 0.0
        w.hi[world, i] = 0.0
        return
    MJ_c, MJ_p, diagonal = row_mass_weighted(world, i, m, w, body_q)
    diagonal += w.row_compliance[world, i]
    kind = m.row_kind[world, i]
    if kind == ROW_CONTACT_NORMAL or kind == ROW_CONTACT_TANGENT:
        first = m.contact_row_start[world] + 3 * ((i - m.contact_row_start[world]) // 3)
        for k in range(3):
            _a, _b, other = row_mass_weighted(world, first + k, m, w, body_q)
            diagonal = wp.max(diagonal, other + w.row_compliance[world, first + k])
    w.row_MJ_c[world, i] = MJ_c
    w.row_MJ_p[world, i] = MJ_p
    v_free = wp.dot(w.row_J_c[world, i], body_twist(w.body_qd_free, world, w.row_body_c[world, i]))
    v_free += wp.dot(w.row_J_p[world, i], body_twist(w.body_qd_free, world, w.row_body_p[world, i]))
    precond = 1.0 / wp.sqrt(wp.max(diagonal, 1.0e-20))
    w.row_precond[world, i] = precond
    w.v_f[world, i] = precond * (v_free - w.row_bias[world, i])
    lo = w.row_lo[world, i]
    hi = w.row_hi[world, i]
    if lo > -UNBOUNDED:
        lo = lo / precond
    if hi < UNBOUNDED:
        hi = hi / precond
    w.lo[world, i] = lo
    w.hi[world, i] = hi


@wp.kernel
def row_operators(m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform)):
    """Every row's operators (row_operator_of)."""
    world, i = wp.tid()
    row_operator_of(world, i, m, w, body_q)


@wp.func
def delassus_entry(world: int, i: int, j: int, w: WorkArrays):
    """Entry (i, j) of P (J M^-1 J^T + R) P for two rows of a world (the sparse solver's matrix
    follows engine.linalg.sparse_analysis.matrix_recipe instead)."""
    ci = w.row_body_c[world, i]
    pi = w.row_body_p[world, i]
    cj = w.row_body_c[world, j]
    pj = w.row_body_p[world, j]
    Jci = w.row_J_c[world, i]
    Jpi = w.row_J_p[world, i]
    d = body_term(ci, Jci, cj, w.row_MJ_c[world, j]) + body_term(ci, Jci, pj, w.row_MJ_p[world, j])
    d += body_term(pi, Jpi, cj, w.row_MJ_c[world, j]) + body_term(pi, Jpi, pj, w.row_MJ_p[world, j])
    if i == j:
        d += w.row_compliance[world, i]
    return w.row_precond[world, i] * d * w.row_precond[world, j]


@wp.kernel
def delassus(w: WorkArrays, delassus_out: wp.array3d(dtype=float)):
    """Preconditioned Delassus matrix P (J M^-1 J^T + R) P; identity on padded rows."""
    world, i, j = wp.tid()
    n = w.row_count[world]
    if i >= n or j >= n:
        value = 0.0
        if i == j:
            value = 1.0
        delassus_out[world, i, j] = value
        return
    delassus_out[world, i, j] = delassus_entry(world, i, j, w)


def build_dual_problem(model, body_q, body_qd, body_qd_low, body_f, body_qd_low_out,
                       free_velocities: bool = True):
    """Free velocities, row operators and (dense solver) the preconditioned Delassus matrix of every
    world; body_qd_low: the twists' low parts, body_qd_low_out: the free twists' (engine.State).
    free_velocities=False: work.body_qd_free (and body_qd_low_out) are already this step's
    (engine.integrate.midpoint_free_velocity)."""
    work, m, w = model.work, model.arrays, model.work.arrays
    W, device = model.num_worlds, model.device
    if free_velocities:
        wp.launch(free_velocity, dim=(W, model.max_bodies), device=device,
                  inputs=[m, w, body_q, body_qd, body_qd_low, body_f, int(model.config.tuning.compensated_state),
                          body_qd_low_out])
    wp.launch(row_operators, dim=(W, model.max_rows), device=device, inputs=[m, w, body_q])
    if model.linear_solver == "sparse":
        sparse.roots(model, body_q)
    if model.linear_solver != "dense":
        return  # the sparse factor (engine.linalg.sparse) builds its matrix from row_J and row_MJ
    wp.launch(delassus, dim=(W, model.max_rows, model.max_rows), device=device, inputs=[w, work.delassus])


def forced_free_velocities(model, body_q, body_qd, body_qd_low, control, body_qd_low_out) -> None:
    """Launch forced_free_velocity for the batch (a model with force slots): the free velocities
    under Control.body_f plus the force slots, at the poses body_q and twists body_qd."""
    wp.launch(forced_free_velocity, dim=(model.num_worlds, model.max_bodies), device=model.device,
              inputs=[model.arrays, model.force_arrays, model.work.arrays, body_q, body_qd, body_qd_low,
                      control.body_f, control.joint_effort, int(model.config.tuning.compensated_state),
                      body_qd_low_out])


__all__ = ["build_dual_problem", "force_wrench_of", "forced_free_velocities"]
