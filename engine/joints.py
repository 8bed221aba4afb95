"""Joint constraint rows: position-level residuals and their velocity Jacobians, per joint type.

Every bilateral row k of a joint has a residual phi_k(q) (zero when the joint is assembled) and a
Jacobian row with d(phi_k)/dt = J_c . u_c + J_p . u_p exactly (tests check it against finite
differences). Rows, in the order of engine.pack.ROW_KINDS:
- position rows: the anchor separation d = p_c - p_p along the world axes (revolute, spherical,
  universal, fixed) or along two parent-frame directions normal to the axis (prismatic,
  cylindrical, inline; an inline joint has no other rows) [m];
- angular rows: the child axis dotted with two parent directions normal to the parent axis
  (revolute, cylindrical), parent axis . child axis2 (universal), or 2 vec(q_rel) of the
  relative rotation in the parent anchor frame (prismatic, fixed) [rad].
A joint with a finite lower (upper) limit adds a unilateral LIMIT row on q - lower (upper - q),
active near the limit (see limit_row), inert (zero Jacobian, zero impulse) elsewhere.
A joint with armature or viscous damping adds a DYNAMICS row along its free coordinate with
compliance 1/(a + dt b); a drive adds another with compliance 1/(dt kd + dt^2 kp), the bias of
the implicit PD law and the bounds +/- dt * effort_limit, so that only the motor's torque is
clamped (the rotor inertia and joint friction act beside it).
"""

import warp as wp

from engine.model import UNBOUNDED, ModelArrays, WorkArrays
from engine.spatial import relative_rotation, twist, wrap_angle

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

JOINT_REVOLUTE = wp.constant(0)
JOINT_PRISMATIC = wp.constant(1)
JOINT_SPHERICAL = wp.constant(2)
JOINT_UNIVERSAL = wp.constant(3)
JOINT_CYLINDRICAL = wp.constant(4)
JOINT_FIXED = wp.constant(5)
JOINT_INLINE = wp.constant(6)


@wp.func
def bilateral_row_count(joint_type: int):
    """Number of bilateral rows of a joint type."""
    if joint_type == JOINT_SPHERICAL:
        return 3
    if joint_type == JOINT_INLINE:
        return 2
    if joint_type == JOINT_UNIVERSAL or joint_type == JOINT_CYLINDRICAL:
        return 4
    if joint_type == JOINT_FIXED:
        return 6
    return 5


# A joint's rows split into this many parts, one per lane of the fused step (engine.fused): its
# bilateral rows 0-5 one each (parts past the joint's count are empty), then its coordinate rows
# (limits, armature, drive) together. part < 0 in joint_rows_of / joint_residuals_of: all of them.
JOINT_PARTS = wp.constant(7)
COORDINATE_PART = wp.constant(6)


@wp.func
def part_rows(joint_type: int, part: int):
    """Bilateral rows [begin, end) of a part of a joint and whether it holds the coordinate rows."""
    count = bilateral_row_count(joint_type)
    if part < 0:
        return 0, count, True
    return part, wp.min(part + 1, count), part == COORDINATE_PART


@wp.func
def normal_basis(a: wp.vec3, k: int):
    """Unit vector k (0 or 1) of an orthonormal pair normal to the unit vector a."""
    helper = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(a[0]) > 0.7:
        helper = wp.vec3(0.0, 1.0, 0.0)
    t1 = wp.normalize(wp.cross(a, helper))
    if k == 0:
        return t1
    return wp.cross(a, t1)


@wp.func
def lever_arm_exact(X: wp.transform, low: wp.transform, r: wp.vec3):
    """R r in float64 for the rotation of the compensated pose X + low (engine.State), its
    quaternion normalized in float64."""
    q = wp.transform_get_rotation(X)
    q_low = wp.transform_get_rotation(low)
    q64 = wp.normalize(wp.quatd(wp.float64(q[0]) + wp.float64(q_low[0]), wp.float64(q[1]) + wp.float64(q_low[1]),
                                wp.float64(q[2]) + wp.float64(q_low[2]), wp.float64(q[3]) + wp.float64(q_low[3])))
    return wp.quat_rotate(q64, wp.vec3d(r))


@wp.func
def joint_frames(body_q: wp.array2d(dtype=wp.transform), body_q_low: wp.array2d(dtype=wp.transform), world: int,
                 parent: int, child: int, X_p: wp.transform, X_c: wp.transform, exact: int):
    """World anchor frames of a joint, the lever arms from each COM to its anchor [m], and d, the
    child anchor minus the parent anchor [m], the joint's position error, from the compensated
    poses (body_q + body_q_low: engine.State; body_q_low zeros where there are none): COM
    difference (exact for nearby COMs), low parts, lever arms. With ``exact`` d is summed in
    float64 and rounded once, so the residuals the position projection corrects stay below the
    float32 rounding of positions and lever arms, which near a singular configuration the
    projection would amplify into motion. The float32 sum serves the rows of the dynamics, whose
    residuals only feed Baumgarte's bias."""
    X_wp = X_p
    r_p = wp.vec3(0.0)
    C = body_q[world, child]
    low_c = body_q_low[world, child]
    X_wc = C * X_c
    r_c = wp.quat_rotate(wp.transform_get_rotation(C), wp.transform_get_translation(X_c))
    x_p = wp.transform_get_translation(X_p)
    low_p = wp.transform(wp.vec3(0.0), wp.quat(0.0, 0.0, 0.0, 0.0))
    P = wp.transform_identity()
    if parent >= 0:
        P = body_q[world, parent]
        low_p = body_q_low[world, parent]
        X_wp = P * X_p
        r_p = wp.quat_rotate(wp.transform_get_rotation(P), wp.transform_get_translation(X_p))
        x_p = wp.transform_get_translation(P)
    x_c = wp.transform_get_translation(C)
    if exact == 0:
        d = ((x_c - x_p) + (wp.transform_get_translation(low_c) - wp.transform_get_translation(low_p))) + (r_c - r_p)
        return X_wp, X_wc, r_p, r_c, d
    gap = (wp.vec3d(x_c) - wp.vec3d(x_p) + wp.vec3d(wp.transform_get_translation(low_c))
           + lever_arm_exact(C, low_c, wp.transform_get_translation(X_c)))
    if parent >= 0:
        gap = gap - wp.vec3d(wp.transform_get_translation(low_p)) - lever_arm_exact(P, low_p,
                                                                                   wp.transform_get_translation(X_p))
    return X_wp, X_wc, r_p, r_c, wp.vec3(gap)


@wp.func
def position_row(n: wp.vec3, d: wp.vec3, r_p: wp.vec3, r_c: wp.vec3, parent_frame_direction: bool):
    """Row phi = n . d; when n turns with the parent, its rotation adds n x d to J_p's angular part."""
    extra = wp.vec3(0.0)
    if parent_frame_direction:
        extra = wp.cross(n, d)
    return twist(n, wp.cross(r_c, n)), twist(-n, -wp.cross(r_p, n) + extra), wp.dot(n, d)


@wp.func
def alignment_row(u: wp.vec3, v: wp.vec3):
    """Row phi = u . v with u turning with the parent and v with the child."""
    g = wp.cross(v, u)
    zero = wp.vec3(0.0)
    return twist(zero, g), twist(zero, -g), wp.dot(u, v)


@wp.func
def bilateral_row(joint_type: int, k: int, X_wp: wp.transform, X_wc: wp.transform, r_p: wp.vec3,
                  r_c: wp.vec3, d: wp.vec3, axis: wp.vec3, axis2: wp.vec3):
    """Jacobian (J_c, J_p) and residual phi of bilateral row k of a joint (joint_frames' values)."""
    q_p = wp.transform_get_rotation(X_wp)
    q_c = wp.transform_get_rotation(X_wc)
    sliding = joint_type == JOINT_PRISMATIC or joint_type == JOINT_CYLINDRICAL or joint_type == JOINT_INLINE
    n_position = 3
    if sliding:
        n_position = 2
    if k < n_position:
        if sliding:
            return position_row(wp.quat_rotate(q_p, normal_basis(axis, k)), d, r_p, r_c, True)
        n = wp.vec3(0.0)
        n[k] = 1.0
        return position_row(n, d, r_p, r_c, False)
    a = k - n_position
    if joint_type == JOINT_REVOLUTE or joint_type == JOINT_CYLINDRICAL:
        return alignment_row(wp.quat_rotate(q_p, normal_basis(axis, a)), wp.quat_rotate(q_c, axis))
    if joint_type == JOINT_UNIVERSAL:
        return alignment_row(wp.quat_rotate(q_p, axis), wp.quat_rotate(q_c, axis2))
    # prismatic and fixed: phi = 2 vec(q_rel), d(phi)/dt = (s I - [v]x) R_p^T (w_c - w_p)
    q_rel = relative_rotation(q_p, q_c)
    v = wp.vec3(q_rel[0], q_rel[1], q_rel[2])
    s = q_rel[3]
    e = wp.vec3(0.0)
    e[a] = 1.0
    row_parent_frame = s * e - wp.cross(e, v)  # row a of (s I - [v]x) is s e_a^T - (e_a x v)^T
    g = wp.quat_rotate(q_p, row_parent_frame)
    zero = wp.vec3(0.0)
    return twist(zero, g), twist(zero, -g), 2.0 * v[a]


@wp.func
def joint_coordinate_row(joint_type: int, X_wp: wp.transform, X_wc: wp.transform, r_p: wp.vec3,
                         r_c: wp.vec3, d: wp.vec3, axis: wp.vec3):
    """Jacobian (J_c, J_p) of the joint's free coordinate and its value q [rad] or [m]."""
    q_p = wp.transform_get_rotation(X_wp)
    a_w = wp.quat_rotate(q_p, axis)
    zero = wp.vec3(0.0)
    if joint_type == JOINT_PRISMATIC:
        return twist(a_w, wp.cross(r_c, a_w)), twist(-a_w, -wp.cross(r_p, a_w) + wp.cross(a_w, d)), wp.dot(a_w, d)
    q_rel = relative_rotation(q_p, wp.transform_get_rotation(X_wc))
    angle = 2.0 * wp.atan2(wp.dot(wp.vec3(q_rel[0], q_rel[1], q_rel[2]), axis), q_rel[3])
    return twist(zero, a_w), twist(zero, -a_w), angle


@wp.func
def body_twist(body_qd: wp.array2d(dtype=wp.spatial_vector), world: int, body: int):
    """Twist of a body, zero for the world (-1)."""
    if body < 0:
        return wp.spatial_vector()
    return body_qd[world, body]


@wp.func
def write_row(world: int, row: int, J_c: wp.spatial_vector, J_p: wp.spatial_vector, bias: float, compliance: float,
              lo: float, hi: float, w: WorkArrays):
    """Store one row; dynamics rows have no position residual."""
    w.row_J_c[world, row] = J_c
    w.row_J_p[world, row] = J_p
    w.row_bias[world, row] = bias
    w.row_compliance[world, row] = compliance
    w.row_lo[world, row] = lo
    w.row_hi[world, row] = hi
    w.row_residual[world, row] = 0.0


@wp.func
def limit_row(world: int, row: int, side: float, gap: float, gap_rate: float, J_c: wp.spatial_vector,
              J_p: wp.spatial_vector, dt: float, margin: float, stabilization: float, w: WorkArrays):
    """Unilateral limit row on gap = side (q - limit) >= 0, active within margin (+ one step of
    approach); separated: the gap may close, no more; violated: pushed back by stabilization."""
    if gap < margin + dt * wp.max(-gap_rate, 0.0):
        bias = -gap / dt
        if gap < 0.0:
            bias = stabilization * (-gap) / dt
        write_row(world, row, side * J_c, side * J_p, bias, 0.0, 0.0, UNBOUNDED, w)
    else:  # inert row: no coupling, impulse fixed at zero
        zero = wp.spatial_vector()
        write_row(world, row, zero, zero, 0.0, 1.0, 0.0, 0.0, w)


@wp.func
def joint_rows_of(world: int, j: int, part: int, m: ModelArrays, w: WorkArrays, baumgarte: float,
                  limit_margin: float, limit_stabilization: float, body_q: wp.array2d(dtype=wp.transform),
                  body_q_low: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector),
                  joint_target_position: wp.array2d(dtype=float), joint_target_velocity: wp.array2d(dtype=float),
                  joint_effort: wp.array2d(dtype=float)):
    """Rows of joint j at the poses body_q (+ body_q_low) into w: J, bias c, compliance R and
    bounds, so that J u+ + R lambda = c; all of them (part < 0) or one part (JOINT_PARTS)."""
    jtype = m.joint_type[world, j]
    begin, end, coordinate = part_rows(jtype, part)
    inertia_row = m.joint_inertia_row[world, j]
    drive_row = m.joint_drive_row[world, j]
    lower_row = m.joint_limit_lower_row[world, j]
    upper_row = m.joint_limit_upper_row[world, j]
    if inertia_row < 0 and drive_row < 0 and lower_row < 0 and upper_row < 0:
        coordinate = False
    if begin >= end and not coordinate:
        return
    parent = m.joint_parent[world, j]
    child = m.joint_child[world, j]
    X_wp, X_wc, r_p, r_c, d = joint_frames(body_q, body_q_low, world, parent, child, m.joint_X_p[world, j],
                                           m.joint_X_c[world, j], 0)
    dt = m.world_dt[world]
    start = m.joint_row_start[world, j]
    for k in range(begin, end):
        J_c, J_p, phi = bilateral_row(jtype, k, X_wp, X_wc, r_p, r_c, d, m.joint_axis[world, j],
                                      m.joint_axis2[world, j])
        row = start + k
        w.row_J_c[world, row] = J_c
        w.row_J_p[world, row] = J_p
        w.row_bias[world, row] = -baumgarte / dt * phi
        w.row_compliance[world, row] = 0.0
        w.row_lo[world, row] = -UNBOUNDED
        w.row_hi[world, row] = UNBOUNDED
        w.row_residual[world, row] = phi
    if not coordinate:
        return
    J_c, J_p, q = joint_coordinate_row(jtype, X_wp, X_wc, r_p, r_c, d, m.joint_axis[world, j])
    dq = wp.dot(J_c, body_twist(body_qd, world, child)) + wp.dot(J_p, body_twist(body_qd, world, parent))
    if lower_row >= 0:
        limit_row(world, lower_row, 1.0, q - m.joint_limit_lower[world, j], dq, J_c, J_p, dt, limit_margin,
                  limit_stabilization, w)
    if upper_row >= 0:
        limit_row(world, upper_row, -1.0, m.joint_limit_upper[world, j] - q, -dq, J_c, J_p, dt, limit_margin,
                  limit_stabilization, w)
    if inertia_row >= 0:
        # armature a and damping b: lambda = a dq - (a + dt b) dq+
        armature = m.joint_armature[world, j]
        m_a = armature + dt * m.joint_damping[world, j]
        write_row(world, inertia_row, J_c, J_p, armature * dq / m_a, 1.0 / m_a, -UNBOUNDED, UNBOUNDED, w)
    if drive_row >= 0:
        # implicit PD: lambda = dt (kp (q_t - q) + kd dq_t + tau) - (dt kd + dt^2 kp) dq+, |lambda| <= dt effort
        kp = m.joint_stiffness[world, j]
        kd = m.joint_drive_damping[world, j]
        error = joint_target_position[world, j] - q
        if jtype == JOINT_REVOLUTE:
            error = wrap_angle(error)
        m_d = dt * kd + dt * dt * kp
        impulse = dt * (kp * error + kd * joint_target_velocity[world, j] + joint_effort[world, j])
        bound = dt * m.joint_effort_limit[world, j]
        if m_d > 0.0:
            write_row(world, drive_row, J_c, J_p, impulse / m_d, 1.0 / m_d, -bound, bound, w)
        else:  # pure feed-forward effort: a fixed impulse
            fixed = wp.clamp(impulse, -bound, bound)
            write_row(world, drive_row, J_c, J_p, 0.0, 1.0, fixed, fixed, w)


@wp.func
def joint_thread(t: int, parts: int):
    """Joint and part (-1: all of it) of thread t of the joint kernels: a joint's parts on
    consecutive threads, so that a warp's stores of their rows (consecutive in a world) are
    contiguous."""
    if parts > 1:
        return t // parts, t % parts
    return t, -1


def joint_parts(device) -> int:
    """Threads per joint of the staged joint_rows kernel: JOINT_PARTS on a GPU (measured:
    benchmarks/results/README.md), one on the CPU (its threads run one after the other, and the
    parts would repeat each joint's frames)."""
    return int(JOINT_PARTS) if wp.get_device(device).is_cuda else 1


@wp.kernel
def joint_rows(parts: int, m: ModelArrays, w: WorkArrays, baumgarte: float, limit_margin: float,
               limit_stabilization: float, body_q: wp.array2d(dtype=wp.transform),
               body_q_low: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector),
               joint_target_position: wp.array2d(dtype=float), joint_target_velocity: wp.array2d(dtype=float),
               joint_effort: wp.array2d(dtype=float)):
    """Rows of every joint (joint_rows_of): a thread per joint, or with parts > 1 per part of a
    joint (thread t: part t % parts of joint t // parts)."""
    world, t = wp.tid()
    j, part = joint_thread(t, parts)
    if j >= m.joint_count[world]:
        return
    joint_rows_of(world, j, part, m, w, baumgarte, limit_margin, limit_stabilization, body_q, body_q_low, body_qd,
                  joint_target_position, joint_target_velocity, joint_effort)


@wp.func
def joint_residuals_of(world: int, j: int, part: int, m: ModelArrays, body_q: wp.array2d(dtype=wp.transform),
                       body_q_low: wp.array2d(dtype=wp.transform), exact: int,
                       row_residual_out: wp.array2d(dtype=float)):
    """Position-level residuals of joint j's rows at body_q (0 for dynamics rows): all of them
    (part < 0) or one part (JOINT_PARTS); exact: joint_frames' float64 sum."""
    jtype = m.joint_type[world, j]
    begin, end, coordinate = part_rows(jtype, part)
    if begin < end:
        X_wp, X_wc, r_p, r_c, d = joint_frames(body_q, body_q_low, world, m.joint_parent[world, j],
                                               m.joint_child[world, j], m.joint_X_p[world, j],
                                               m.joint_X_c[world, j], exact)
        start = m.joint_row_start[world, j]
        for k in range(begin, end):
            J_c, J_p, phi = bilateral_row(jtype, k, X_wp, X_wc, r_p, r_c, d, m.joint_axis[world, j],
                                          m.joint_axis2[world, j])
            row_residual_out[world, start + k] = phi
    if not coordinate:
        return
    if m.joint_inertia_row[world, j] >= 0:
        row_residual_out[world, m.joint_inertia_row[world, j]] = 0.0
    if m.joint_drive_row[world, j] >= 0:
        row_residual_out[world, m.joint_drive_row[world, j]] = 0.0


@wp.kernel
def joint_residuals(m: ModelArrays, body_q: wp.array2d(dtype=wp.transform), body_q_low: wp.array2d(dtype=wp.transform),
                    exact: int, row_residual_out: wp.array2d(dtype=float)):
    """Position-level residuals of every joint's rows at body_q (joint_residuals_of), a thread per
    joint."""
    world, j = wp.tid()
    if j >= m.joint_count[world]:
        return
    joint_residuals_of(world, j, -1, m, body_q, body_q_low, exact, row_residual_out)


def compute_joint_rows(model, body_q, body_qd, control, body_q_low=None):
    """Launch joint_rows for the batch into model.work; body_q_low: the poses' low parts
    (engine.State), None for none."""
    cfg, parts = model.config, joint_parts(model.device)
    wp.launch(joint_rows, dim=(model.num_worlds, model.max_joints * parts), device=model.device,
              inputs=[parts, model.arrays, model.work.arrays, float(cfg.baumgarte), float(cfg.limit_margin),
                      float(cfg.limit_stabilization), body_q, model.work.no_low if body_q_low is None else body_q_low,
                      body_qd, control.joint_target_position, control.joint_target_velocity, control.joint_effort])


def compute_joint_residuals(model, body_q, residual_out, body_q_low=None, exact=False):
    """Launch joint_residuals for the batch; body_q_low: the poses' low parts (engine.State), None
    for none; exact: sum the position errors in float64 (joint_frames)."""
    wp.launch(joint_residuals, dim=(model.num_worlds, model.max_joints), device=model.device,
              inputs=[model.arrays, body_q, model.work.no_low if body_q_low is None else body_q_low, int(exact),
                      residual_out])


__all__ = ["JOINT_CYLINDRICAL", "JOINT_FIXED", "JOINT_INLINE", "JOINT_PARTS", "JOINT_PRISMATIC", "JOINT_REVOLUTE",
           "JOINT_SPHERICAL", "JOINT_UNIVERSAL", "compute_joint_residuals", "compute_joint_rows"]
