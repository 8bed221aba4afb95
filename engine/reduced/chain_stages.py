"""The pieces of the closed chains' step kernel (engine.reduced.chain_kernel): its device data
(ChainArrays, the packed batch; ChainWork, each world's scratch and step results) and its stages
as Warp functions: kinematics along the tree, loop errors and rows, the mass matrix's L^T D L
factor and solves along the ancestors, the lanes' dense Cholesky, ground-contact candidates and
the contacts' factor. Each is shared by the lanes of a world's thread block, with the barriers
its docstring states, so that the kernel reads as its sequence of stages.
"""

import functools
from typing import Any

import warp as wp

from engine.collide import plane_point, plane_point_count
from engine.linalg.lanes import block_sync, clock, tile_set
from engine.reduced.chain_layout import KIND_LINEAR, KIND_REVOLUTE, KIND_ROOT
from engine.model import FORCE_BODY_WRENCH, FORCE_JOINT_SPRING, FORCE_LINEAR_SPRING
from engine.spatial import hinge_angle, spring_tension, two_sum, wrap_angle

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["ChainArrays", "ChainWork", "DIVERGED", "EFFORT_LIMIT", "STAGES"]

vec8f = wp.types.vector(length=8, dtype=float)  # a shape's candidate points' distances


@wp.struct
class ChainArrays:
    tree_count: wp.array(dtype=wp.int32)
    depth_count: wp.array(dtype=wp.int32)
    loop_count: wp.array(dtype=wp.int32)
    row_count: wp.array(dtype=wp.int32)
    gravity: wp.array(dtype=wp.vec3)
    parent: wp.array2d(dtype=wp.int32)
    by_depth: wp.array2d(dtype=wp.int32)  # the entries ordered by depth (roots first)
    depth_start: wp.array2d(dtype=wp.int32)  # where depth d starts in by_depth (depth_count + 1 of them)
    level: wp.array2d(dtype=wp.int32)  # entry k's ancestors (its chain's length to the root)
    ancestor: wp.array2d(dtype=wp.int32)  # packed like M~: row k's ancestors, roots first, then k
    row_start: wp.array2d(dtype=wp.int32)  # where row k of the packed M~ starts (rows of level + 1 entries)
    first_child: wp.array2d(dtype=wp.int32)  # tree index of body k's first child, -1: none
    child_count: wp.array2d(dtype=wp.int32)
    joint_parent: wp.array2d(dtype=wp.transform)
    joint_child: wp.array2d(dtype=wp.transform)
    axis: wp.array2d(dtype=wp.vec3)
    com: wp.array2d(dtype=wp.vec3)
    mass: wp.array2d(dtype=float)
    inertia: wp.array2d(dtype=wp.mat33)
    armature: wp.array2d(dtype=float)
    damping: wp.array2d(dtype=float)
    kp: wp.array2d(dtype=float)
    kd: wp.array2d(dtype=float)
    q_target: wp.array2d(dtype=float)
    v_target: wp.array2d(dtype=float)
    body_out: wp.array2d(dtype=wp.int32)  # spec body index of tree body k
    loop_body: wp.array3d(dtype=wp.int32)  # (W, L, 2)
    loop_anchor: wp.array3d(dtype=wp.transform)  # (W, L, 2)
    loop_axis: wp.array2d(dtype=wp.vec3)
    loop_t1: wp.array2d(dtype=wp.vec3)
    loop_t2: wp.array2d(dtype=wp.vec3)
    row_loop: wp.array2d(dtype=wp.int32)
    row_part: wp.array2d(dtype=wp.int32)  # 0-2 position, 3-4 angular, 5 a loop joint's rate (soft)
    row_compliance: wp.array2d(dtype=float)  # soft rows: 1 / (armature + dt damping), else 0
    row_keep: wp.array2d(dtype=float)  # soft rows: armature / (armature + dt damping), else 0
    kind: wp.array2d(dtype=wp.int32)  # KIND_* of entry k
    sub_of: wp.array2d(dtype=wp.int32)  # the entry whose subtree coordinate k moves (a floating root's: the root)
    effort: wp.array2d(dtype=float)  # drive effort limit (checked, not enforced; inf: none)
    shape_count: wp.array(dtype=wp.int32)
    shape_entry: wp.array2d(dtype=wp.int32)  # tree entry of the shape's body
    shape_type: wp.array2d(dtype=wp.int32)
    shape_X: wp.array2d(dtype=wp.transform)  # in the body frame
    shape_size: wp.array2d(dtype=wp.vec3)
    shape_mu: wp.array2d(dtype=float)  # friction with the ground (geometric mean)
    ground_normal: wp.array(dtype=wp.vec3)
    ground_offset: wp.array(dtype=float)
    contact_capacity: wp.array(dtype=wp.int32)
    prefix: wp.array(dtype=wp.int32)  # leading entries that are a chain all others descend from (<= MAX_PREFIX)
    loop_inline: wp.array2d(dtype=wp.int32)  # 1: an inline loop (its rows' rates at its second anchor)


@wp.struct
class ChainLoads:
    """What loads the chains besides gravity and drives, apart from ChainArrays so that a step kernel
    without force elements or a Control takes NoLoads instead (smaller launch parameters)."""

    # force elements (apply_forces), F padded slots per world: engine.model's FORCE_* kind; the tree
    # entries of their two sides (-1: the world or a welded body); each side's frame in its body's
    # frame (the world's where the entry is -1): a spring's point, a joint's anchor (child, parent);
    # vectors: a body wrench's force and torque, a joint's axis in the parent anchor frame (first);
    # coefficients: stiffness, damping, rest length or angle, and a joint torque's effort or a
    # spring's tension_only (1)
    force_count: wp.array(dtype=wp.int32)
    force_kind: wp.array2d(dtype=wp.int32)
    force_entry: wp.array3d(dtype=wp.int32)  # (W, F, 2)
    force_frame: wp.array3d(dtype=wp.transform)  # (W, F, 2)
    force_vec: wp.array3d(dtype=wp.vec3)  # (W, F, 2)
    force_coef: wp.array2d(dtype=wp.vec4)
    # a Control's targets (apply_control): the tree entry of each spec body (-1: welded to the world);
    # each spec joint's two sides' entries (child, parent; -1: the world or a welded body; both -1:
    # no effort, a joint that is not revolute), its parent anchor frame in the parent's body frame
    # (the world's where the parent side is -1) and its axis in that frame
    control_body: wp.array2d(dtype=wp.int32)  # (W, B)
    control_joint: wp.array3d(dtype=wp.int32)  # (W, J, 2)
    control_frame: wp.array2d(dtype=wp.transform)  # (W, J)
    control_axis: wp.array2d(dtype=wp.vec3)  # (W, J)
    # the Control's own arrays (ChainModel.loads_for; (1, 1) zeros without one)
    body_f: wp.array2d(dtype=wp.spatial_vector)  # (W, B) force, torque at each spec body's centre of mass
    joint_effort: wp.array2d(dtype=float)  # (W, J)


@wp.struct
class NoLoads:
    """The loads argument of a step kernel compiled without force elements and Control."""
    unused: int


@wp.struct
class ChainWork:
    pose: wp.array2d(dtype=wp.transform)  # body frames
    centre: wp.array2d(dtype=wp.vec3)  # centres of mass
    lin: wp.array2d(dtype=wp.vec3)  # coordinates' linear parts (the origin's velocity at a unit rate)
    axis: wp.array2d(dtype=wp.vec3)  # and angular parts (joint axes, world)
    omega: wp.array2d(dtype=wp.vec3)
    vel: wp.array2d(dtype=wp.vec3)
    alpha: wp.array2d(dtype=wp.vec3)  # velocity-product angular acceleration
    acc: wp.array2d(dtype=wp.vec3)  # velocity-product linear acceleration of the centre of mass
    inertia: wp.array2d(dtype=wp.mat33)  # world-frame inertia about the centre of mass
    wrench_t: wp.array2d(dtype=wp.vec3)  # per body, then per subtree: torque about the origin
    wrench_f: wp.array2d(dtype=wp.vec3)  # and force
    sub_mass: wp.array2d(dtype=float)  # per body, then per subtree: mass,
    sub_moment: wp.array2d(dtype=wp.vec3)  # first moment about the origin
    sub_inertia: wp.array2d(dtype=wp.mat33)  # and inertia about the origin
    force_n: wp.array2d(dtype=wp.vec3)  # subtree's inertia applied to the joint's motion: torque
    force_f: wp.array2d(dtype=wp.vec3)  # and force
    phi: wp.array2d(dtype=float)  # every loop's six errors (W, 6 L; the sixth, its rate row's, is 0)
    dirs: wp.array2d(dtype=wp.vec3)  # and directions
    ends: wp.array2d(dtype=wp.vec3)  # anchor points, 2 per loop
    # during a step its initial angles, rates and floating roots' centre-of-mass frames (restored
    # where it diverges); between Moreau-Jean steps the angles and root frames the last step left
    # (left_here), the rates it started from (the next midpoint's extrapolation; an entry a contact
    # impulse moved: its final rate) and, in root_start's x of an angle's entry, the angle's low part
    # (angle_low)
    q_start: wp.array2d(dtype=float)
    u_start: wp.array2d(dtype=float)
    root_start: wp.array2d(dtype=wp.transform)
    diverged: wp.array(dtype=wp.int32)  # 0 running, DIVERGED or EFFORT_LIMIT (frozen)
    contact_count: wp.array(dtype=wp.int32)
    contact_slot: wp.array2d(dtype=wp.int32)  # candidate slot of each active contact
    contact_impulse: wp.array2d(dtype=wp.vec3)  # per candidate slot: the last impulse (normal, t1, t2), warm start
    contact_rho: wp.array(dtype=float)  # the contacts' penalty at the end of the last step (0: none yet)
    contact_dropped: wp.array(dtype=wp.int32)  # contacts within the margin beyond the capacity (last step)
    contact_overflow: wp.array(dtype=wp.int32)  # 1: this step found more contacts than the first kernel holds
    contact_redone: wp.array(dtype=wp.int32)  # steps the full-capacity kernel took over since the packing
    iterations: wp.array(dtype=wp.int32)  # PADMM iterations of the last step
    projections: wp.array(dtype=wp.int32)  # Gauss-Newton corrections of the last step (the floors stop them)
    stage_clock: wp.array2d(dtype=wp.int64)  # ChainModel.step(stages=True): clock readings (W, len(STAGES) + 1)
    matrix: wp.array3d(dtype=float)  # record: M~ (W, N, N)
    rows: wp.array3d(dtype=float)  # record: G (W, R, N)


POSES = wp.constant(0)  # kinematics' detail: body poses, joint points and axes
VELOCITIES = wp.constant(1)  # and the bodies' velocities
DYNAMICS = wp.constant(2)  # and the velocity-product accelerations and the world-frame inertias
DIVERGED = wp.constant(1)  # ChainWork.diverged: non-finite or faster than max_speed
EFFORT_LIMIT = wp.constant(2)  # a drive's torque past its effort limit


@wp.func
def free_body(m: ChainArrays, w: ChainWork, world: int, k: int, kind: int, u: wp.array2d(dtype=float),
              root: wp.array2d(dtype=wp.transform), detail: int):
    """Entry k of a floating root: the root body's pose from its centre-of-mass frame root[world, r]
    (r = sub_of[k], the root's entry), the coordinate's parts (a unit world axis e, linear: (0, e),
    angular about the centre of mass c: (e, c x e)), and with detail VELOCITIES the root's rates
    u[r - 5 .. r] (centre-of-mass velocity, angular velocity); its velocity-product accelerations are 0."""
    r = m.sub_of[world, k]
    Xc = root[world, r]
    c = wp.transform_get_translation(Xc)
    rot = wp.transform_get_rotation(Xc)
    w.pose[world, k] = wp.transform(c - wp.quat_rotate(rot, m.com[world, r]), rot)
    w.centre[world, k] = c
    e = m.axis[world, k]
    if kind == KIND_LINEAR:
        w.axis[world, k] = wp.vec3()
        w.lin[world, k] = e
    else:
        w.axis[world, k] = e
        w.lin[world, k] = wp.cross(c, e)
    if detail >= VELOCITIES:
        w.omega[world, k] = wp.vec3(u[world, r - 2], u[world, r - 1], u[world, r])
        w.vel[world, k] = wp.vec3(u[world, r - 5], u[world, r - 4], u[world, r - 3])
        if detail >= DYNAMICS:
            w.alpha[world, k] = wp.vec3()
            w.acc[world, k] = wp.vec3()
            Rb = wp.quat_to_matrix(rot)
            w.inertia[world, k] = Rb * m.inertia[world, k] * wp.transpose(Rb)


@wp.func
def kinematics_body(m: ChainArrays, w: ChainWork, world: int, k: int, q: wp.array2d(dtype=float),
                    u: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.transform), detail: int):
    """Pose, coordinate parts (joint axis a and a's moment p x a about the origin, p the joint point)
    of tree entry k from its parent's (already done) and its joint's angle; with detail VELOCITIES
    its velocities, with DYNAMICS also its velocity-product accelerations and world-frame inertia.
    A floating root's entries: free_body."""
    kind = m.kind[world, k]
    if kind != KIND_REVOLUTE:
        free_body(m, w, world, k, kind, u, root, detail)
        return
    par = m.parent[world, k]
    Xp = wp.transform_identity()
    cpar = wp.vec3()
    if par >= 0:
        Xp = w.pose[world, par]
        cpar = w.centre[world, par]
    Xj = wp.transform_multiply(Xp, m.joint_parent[world, k])
    a_local = m.axis[world, k]
    aw = wp.quat_rotate(wp.transform_get_rotation(Xj), a_local)
    pj = wp.transform_get_translation(Xj)
    Xq = wp.transform_multiply(Xj, wp.transform(wp.vec3(), wp.quat_from_axis_angle(a_local, q[world, k])))
    Xb = wp.transform_multiply(Xq, m.joint_child[world, k])
    c = wp.transform_point(Xb, m.com[world, k])
    w.pose[world, k] = Xb
    w.centre[world, k] = c
    w.lin[world, k] = wp.cross(pj, aw)
    w.axis[world, k] = aw
    if detail >= VELOCITIES:
        uk = u[world, k]
        wpar = wp.vec3()
        vpar = wp.vec3()
        if par >= 0:
            wpar = w.omega[world, par]
            vpar = w.vel[world, par]
        omega = wpar + aw * uk
        r_pj = pj - cpar
        r_b = c - pj
        w.omega[world, k] = omega
        w.vel[world, k] = vpar + wp.cross(wpar, r_pj) + wp.cross(omega, r_b)
        if detail >= DYNAMICS:
            apar = wp.vec3()
            lpar = wp.vec3()
            if par >= 0:
                apar = w.alpha[world, par]
                lpar = w.acc[world, par]
            alpha = apar + wp.cross(wpar, aw * uk)
            acc_pj = lpar + wp.cross(apar, r_pj) + wp.cross(wpar, wp.cross(wpar, r_pj))
            w.alpha[world, k] = alpha
            w.acc[world, k] = acc_pj + wp.cross(alpha, r_b) + wp.cross(omega, wp.cross(omega, r_b))
            Rb = wp.quat_to_matrix(wp.transform_get_rotation(Xb))
            w.inertia[world, k] = Rb * m.inertia[world, k] * wp.transpose(Rb)


@wp.func
def kinematics(m: ChainArrays, w: ChainWork, world: int, lane: int, lanes: int, q: wp.array2d(dtype=float),
               u: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.transform), detail: int):
    """The tree's kinematics level by level (a lane per entry) to ``detail``. Entered after a barrier;
    leaves one."""
    for level in range(m.depth_count[world]):
        for t in range(m.depth_start[world, level] + lane, m.depth_start[world, level + 1], lanes):
            kinematics_body(m, w, world, m.by_depth[world, t], q, u, root, detail)
        block_sync()


@wp.func
def body_out(m: ChainArrays, w: ChainWork, world: int, k: int, body_q: wp.array2d(dtype=wp.transform),
             body_qd: wp.array2d(dtype=wp.spatial_vector)):
    """Entry k's spec body (if it has one) into body_q, body_qd: its centre-of-mass pose and twist
    from kinematics (VELOCITIES)."""
    b = m.body_out[world, k]
    if b >= 0:
        body_q[world, b] = wp.transform(w.centre[world, k], wp.transform_get_rotation(w.pose[world, k]))
        body_qd[world, b] = wp.spatial_vector(w.vel[world, k], w.omega[world, k])


@wp.func
def turned(X: wp.transform, dc: wp.vec3, r: wp.vec3):
    """The frame X moved by dc and turned by the rotation vector r (world frame)."""
    rot = wp.transform_get_rotation(X)
    angle = wp.length(r)
    if angle > 0.0:
        rot = wp.normalize(wp.quat_from_axis_angle(r / angle, angle) * rot)
    return wp.transform(wp.transform_get_translation(X) + dc, rot)


@wp.func
def advance(m: ChainArrays, world: int, k: int, q: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.transform),
            u: wp.array2d(dtype=float), scale: float):
    """Entry k's coordinate moved by scale times its rate: an angle directly, a floating root's frame
    by its six rates at once (on its root entry; its other entries do nothing)."""
    kind = m.kind[world, k]
    if kind == KIND_REVOLUTE:
        q[world, k] = q[world, k] + scale * u[world, k]
    elif kind == KIND_ROOT:
        root[world, k] = turned(root[world, k], scale * wp.vec3(u[world, k - 5], u[world, k - 4], u[world, k - 3]),
                                scale * wp.vec3(u[world, k - 2], u[world, k - 1], u[world, k]))


@wp.func
def left_here(m: ChainArrays, w: ChainWork, world: int, k: int, q: wp.array2d(dtype=float),
              root: wp.array2d(dtype=wp.transform)):
    """Whether entry k is bit for bit where the last Moreau-Jean step left it (ChainWork's q_start
    and root_start between steps): then u_start holds the rates that step started from and
    angle_low the angle's low part. A state reset (ChainModel.state) or set in between differs in
    its angles or frames, as does the first step after packing (root_start all 0)."""
    same = q[world, k] == w.q_start[world, k]
    kind = m.kind[world, k]
    b = w.root_start[world, k]
    if kind == KIND_ROOT:
        a = root[world, k]
        for c in range(7):
            if a[c] != b[c]:
                same = False
    elif kind == KIND_REVOLUTE and b[6] != 1.0:  # (keep_angle_low's identity rotation)
        same = False
    return same


@wp.func
def angle_low(m: ChainArrays, w: ChainWork, world: int, k: int):
    """Between Moreau-Jean steps: the part of entry k's angle that float32 q could not hold (the
    rounding error of its compensated sums; 0 for an entry that is no angle)."""
    if m.kind[world, k] == KIND_REVOLUTE:
        return w.root_start[world, k][0]
    return 0.0


@wp.func
def keep_angle_low(m: ChainArrays, w: ChainWork, world: int, k: int, low: float):
    """At a Moreau-Jean step's end: entry k's angle's low part into root_start (which only a root
    entry's frame uses), x of a frame with the identity rotation. Why: the angles' float32
    increments round at every step, a random walk (1e-5 rad over 2 s at 0.5 ms on the four-bar)
    larger than the midpoint step's own error below 1 ms."""
    if m.kind[world, k] == KIND_REVOLUTE:
        w.root_start[world, k] = wp.transform(wp.vec3(low, 0.0, 0.0), wp.quat_identity())


@wp.func
def correction(X: Any, lam: Any, i: int, R: int):
    """Row i of X applied to lam = A^-1 phi (the kept rows' errors): coordinate i's Gauss-Newton
    correction (X A^-1 phi)_i."""
    acc = float(0.0)
    for r in range(R):
        acc += X[i, r] * lam[r]
    return acc


@wp.func
def project(m: ChainArrays, world: int, k: int, q: wp.array2d(dtype=float),
            root: wp.array2d(dtype=wp.transform), X: Any, lam: Any, R: int, low: Any, compensated: int):
    """Entry k's coordinate moved by its Gauss-Newton correction -X A^-1 phi (lam = A^-1 phi; a
    floating root's six at once, on its root entry). compensated: an angle's sum keeps its rounding
    error in the shared vector low (the kernel's angles' low parts)."""
    kind = m.kind[world, k]
    if kind == KIND_REVOLUTE:
        if compensated != 0:
            angle, rest = two_sum(q[world, k], low[k] - correction(X, lam, k, R))
            q[world, k] = angle
            tile_set(low, k, rest)
        else:
            q[world, k] = q[world, k] - correction(X, lam, k, R)
    elif kind == KIND_ROOT:
        dc = wp.vec3(correction(X, lam, k - 5, R), correction(X, lam, k - 4, R),
                     correction(X, lam, k - 3, R))
        dr = wp.vec3(correction(X, lam, k - 2, R), correction(X, lam, k - 1, R),
                     correction(X, lam, k, R))
        root[world, k] = turned(root[world, k], -dc, -dr)


@wp.func
def loop_errors(m: ChainArrays, w: ChainWork, world: int, lane: int, lanes: int):
    """Every loop's anchor points, row directions and five errors (a lane per loop)."""
    for li in range(lane, m.loop_count[world], lanes):
        xa = wp.vec3()
        xb = wp.vec3()
        qa = wp.quat_identity()
        qb = wp.quat_identity()
        for side in range(2):
            b = m.loop_body[world, li, side]
            X = m.loop_anchor[world, li, side]
            if b >= 0:
                X = wp.transform_multiply(w.pose[world, b], X)
            if side == 0:
                xa = wp.transform_get_translation(X)
                qa = wp.transform_get_rotation(X)
            else:
                xb = wp.transform_get_translation(X)
                qb = wp.transform_get_rotation(X)
        axis = m.loop_axis[world, li]
        cross = wp.cross(wp.quat_rotate(qa, axis), wp.quat_rotate(qb, axis))
        gap = xb - xa
        for part in range(6):
            d = wp.vec3()
            if part == 0:
                d = wp.quat_rotate(qa, wp.vec3(1.0, 0.0, 0.0))
            elif part == 1:
                d = wp.quat_rotate(qa, wp.vec3(0.0, 1.0, 0.0))
            elif part == 2:
                d = wp.quat_rotate(qa, wp.vec3(0.0, 0.0, 1.0))
            elif part == 3:
                d = wp.quat_rotate(qa, m.loop_t1[world, li])
            elif part == 4:
                d = wp.quat_rotate(qa, m.loop_t2[world, li])
            else:  # the joint's rate about its axis (armature and damping rows): no error
                d = wp.quat_rotate(qa, axis)
            e = wp.dot(d, gap)
            if part == 5:
                e = 0.0
            elif part >= 3:
                e = wp.dot(d, cross)
            w.phi[world, 6 * li + part] = e
            w.dirs[world, 6 * li + part] = d
        w.ends[world, 2 * li] = xa
        w.ends[world, 2 * li + 1] = xb


@wp.func
def loop_rows_of(m: ChainArrays, w: ChainWork, world: int, par: Any, r: int, G: Any, X: Any,
                 u: wp.array2d(dtype=float), inline: int):
    """Kept row r of G (and of G^T in X), by one lane: the row's rate from each tree joint that moves
    either of its loop's bodies (walking up from each; the second body's joints count +, the first's
    -; a common ancestor's cancel in the angular rows and nearly so in the position rows). The
    tiles' other entries stay 0. Returns (G u)_r, summed along the same walks. inline (compiled in
    only for batches with inline loops): an inline loop's rows take both bodies' rates at its second
    anchor (its directions turn with the first body while the anchors part along its axis)."""
    rate = float(0.0)
    li = m.row_loop[world, r]
    part = m.row_part[world, r]
    d = w.dirs[world, 6 * li + part]
    for side in range(2):
        sign = float(1.0)
        if side == 0:
            sign = -1.0
        x = w.ends[world, 2 * li + side]
        if inline != 0:
            if m.loop_inline[world, li] != 0:
                x = w.ends[world, 2 * li + 1]
        j = m.loop_body[world, li, side]
        while j >= 0:
            aj = w.axis[world, j]
            value = sign * wp.dot(d, aj)
            if part < 3:
                value = sign * wp.dot(d, wp.cross(aj, x) + w.lin[world, j])
            total = G[r, j] + value
            tile_set(G, r, j, total)
            tile_set(X, j, r, total)
            rate += value * u[world, j]
            j = par[j]
    return rate


@wp.func
def point_motion(w: ChainWork, world: int, b: int, x: wp.vec3):
    """Velocity and velocity-product acceleration of body b's point at x (kinematics' DYNAMICS
    pass; b < 0: the world, at rest)."""
    if b < 0:
        return wp.vec3(), wp.vec3()
    r = x - w.centre[world, b]
    om = w.omega[world, b]
    return w.vel[world, b] + wp.cross(om, r), w.acc[world, b] + wp.cross(w.alpha[world, b], r) + wp.cross(
        om, wp.cross(om, r))


@wp.func
def loop_row_bias(m: ChainArrays, w: ChainWork, world: int, r: int, inline: int):
    """Kept row r's velocity-product term: d/dt (G_r(q) u) at fixed rates, from kinematics' DYNAMICS
    pass (its rates). Moreau-Jean asks G_r(q_mid) u+ = -dt/2 of it, so that u+ is tangent to the
    loops where the step ends (G_r(q+) u+ = 0 to second order) instead of at the midpoint. Position
    rows d . (v_b(x_b) - v_a(x_a)) with d turning with body a; angular rows d . (w_b - w_a); an
    inline loop's rows take both bodies at its second anchor (loop_rows_of), which moves with b."""
    li = m.row_loop[world, r]
    part = m.row_part[world, r]
    d = w.dirs[world, 6 * li + part]
    a = m.loop_body[world, li, 0]
    b = m.loop_body[world, li, 1]
    wa = wp.vec3()
    wb = wp.vec3()
    alpha_a = wp.vec3()
    alpha_b = wp.vec3()
    if a >= 0:
        wa = w.omega[world, a]
        alpha_a = w.alpha[world, a]
    if b >= 0:
        wb = w.omega[world, b]
        alpha_b = w.alpha[world, b]
    turn = wp.cross(wa, d)  # d's rate
    if part >= 3:
        return wp.dot(turn, wb - wa) + wp.dot(d, alpha_b - alpha_a)
    xb = w.ends[world, 2 * li + 1]
    xa = w.ends[world, 2 * li]
    twice = float(1.0)
    if inline != 0:
        if m.loop_inline[world, li] != 0:  # body a's velocity at x_b, which moves with body b: w_a x (v_b - v_a) more
            xa = xb
            twice = 2.0
    vb, acc_b = point_motion(w, world, b, xb)
    va, acc_a = point_motion(w, world, a, xa)
    return twice * wp.dot(turn, vb - va) + wp.dot(d, acc_b - acc_a)


@wp.func
def factor_lanes(lane: int, lanes: int, n: int, A: Any, diag: Any, relative: float):
    """Lower Cholesky factor of the n x n shared tile A (its lower triangle, plus relative * A_jj on
    the diagonal): the factor's entries below the diagonal overwrite A's, its diagonal goes to the
    shared vector diag (A's own diagonal is kept). Left-looking, the lanes share each column's entries,
    every lane forms the pivot; one barrier per column. Entered after a barrier."""
    for j in range(n):
        s = A[j, j] * (1.0 + relative)
        for k in range(j):
            s -= A[j, k] * A[j, k]
        d = wp.sqrt(wp.max(s, 1.0e-30))
        inv = 1.0 / d
        for i in range(j + 1 + lane, n, lanes):
            t = A[i, j]
            for k in range(j):
                t -= A[i, k] * A[j, k]
            tile_set(A, i, j, t * inv)
        if lane == 0:
            tile_set(diag, j, d)
        block_sync()


# the step's stages as ChainModel.step(stages=True) times them (ChainModel.stage_cycles)
STAGES = ("kinematics and own terms", "subtree sums, forces, loop errors", "M~ and G", "tree factor",
          "X = M~^-1 G^T", "A = G X", "the loops' velocity solve", "contact candidates", "Y = M~^-1 J^T",
          "P J^T = Y - X A^-1 G Y", "J, v_f, D", "preconditioner, warm start", "contact factor and PADMM",
          "integration", "projections, velocities, guard", "output")


@wp.func
def stamp(w: ChainWork, world: int, lane: int, stage: int):
    """Lane 0 reads the clock into work.stage_clock[world, stage] (the end of stage - 1, the start
    of stage)."""
    if lane == 0:
        w.stage_clock[world, stage] = clock()


@wp.func
def solve_lanes(lane: int, lanes: int, n: int, L: Any, diag: Any, x: Any):
    """The shared vector x := (L L^T)^-1 x (factor_lanes' L and diag), the lanes sharing each
    column's updates: a barrier per column, 2 n in all. Entered after a barrier; leaves one."""
    for j in range(n):  # L y = x: x[i] -= L_ij y_j below column j, y_j = x[j] / d_j once x[j] is final
        yj = x[j] / diag[j]
        for i in range(j + 1 + lane, n, lanes):
            tile_set(x, i, x[i] - L[i, j] * yj)
        block_sync()
    for i in range(lane, n, lanes):
        tile_set(x, i, x[i] / diag[i])
    block_sync()
    for step in range(n):  # L^T z = y, the last column first
        j = n - 1 - step
        zj = x[j] / diag[j]
        for i in range(lane, j, lanes):
            tile_set(x, i, x[i] - L[j, i] * zj)
        block_sync()
    for i in range(lane, n, lanes):
        tile_set(x, i, x[i] / diag[i])
    block_sync()


@wp.func
def solve_column(n: int, L: Any, diag: Any, x: Any, col: int):
    """Column ``col`` of the shared tile x := (L L^T)^-1 x[:, col] (factor_lanes' L and diag), by one lane."""
    for i in range(n):
        s = x[i, col]
        for k in range(i):
            s -= L[i, k] * x[k, col]
        tile_set(x, i, col, s / diag[i])
    for step in range(n):
        i = n - 1 - step
        s = x[i, col]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k, col]
        tile_set(x, i, col, s / diag[i])


@wp.func
def tree_factor(m: ChainArrays, world: int, lane: int, lanes: int, lvl: Any, start: Any, n: int, H: Any):
    """In place: the mass matrix (packed in H: row k's entries against its ancestors and itself at
    start[k] + the column's level, a dense run ordered roots first; breadth-first order, parents
    first) as L^T D L, L unit lower triangular with entries only where the column is an ancestor of
    the row (no fill: the subtrees stay apart), D on the diagonal. Work: the sum over entries of their
    level squared, instead of n^3 / 6. Eliminating entry k (leaves first) subtracts
    H_ki H_kj / H_kk from every entry (i, j) of its ancestors' rows, j up to i: the lanes share those
    pairs (distinct entries, reading row k, which no other pair writes), a barrier per entry; row k is
    never touched again, so its division by H_kk waits for one pass at the end. Entered after a
    barrier; leaves one."""
    for step in range(n):
        k = n - 1 - step
        lk = lvl[k]
        if lk > 0:  # (every lane alike)
            ok = start[k]
            hkk = H[ok + lk]
            for e in range(lane, lk * (lk + 1) / 2, lanes):  # pair e: ancestor at level li, its entry p <= li
                li = int((wp.sqrt(8.0 * float(e) + 1.0) - 1.0) * 0.5)
                if (li + 1) * (li + 2) / 2 <= e:
                    li += 1
                elif li * (li + 1) / 2 > e:
                    li -= 1
                p = e - li * (li + 1) / 2
                ei = start[m.ancestor[world, ok + li]] + p
                hki = H[ok + li]
                tile_set(H, ei, H[ei] - hki * H[ok + p] / hkk)
            block_sync()
    for k in range(lane, n, lanes):
        ok = start[k]
        lk = lvl[k]
        hkk = H[ok + lk]
        for p in range(lk):
            tile_set(H, ok + p, H[ok + p] / hkk)
    block_sync()


@functools.cache
def tree_solves(unroll: int):
    """tree_solve_column and tree_solve_vector for batches whose prefixes (ChainArrays.prefix) are at
    most ``unroll`` long (MAX_PREFIX, or 0 where no world has one: no unrolled code, whose registers
    cost time; see benchmarks/results/README.md, "Reduced closed chains: design notes")."""

    @wp.func
    def tree_solve_column(par: Any, lvl: Any, start: Any, n: int, pre: int, H: Any, x: Any, col: int):
        """Column col of the shared tile x := M^-1 x[:, col] with tree_factor's L^T D L, by one lane:
        L^T leaves first, D, then L roots first, each along the ancestors only. The first pass skips the
        entries still 0 (a column of G^T or J^T is nonzero only along a few bodies' ancestors, and the
        pass keeps it so). The first pre entries (pre <= unroll) are a chain that is every entry's
        ancestry's start (a floating root's six): an entry's ancestors among them are entries 0 .. j at
        its row's first j + 1 places, taken unrolled instead of walking the parents."""
        for step in range(n):
            i = n - 1 - step
            xi = x[i, col]
            if xi != 0.0:
                e = start[i] + lvl[i]
                j = par[i]
                while j >= pre:
                    e -= 1
                    tile_set(x, j, col, x[j, col] - H[e] * xi)
                    j = par[j]
                b = start[i]
                for t in range(wp.static(unroll)):
                    if t <= j:
                        tile_set(x, t, col, x[t, col] - H[b + t] * xi)
        for i in range(n):
            e = start[i] + lvl[i]
            s = x[i, col] / H[e]
            j = par[i]
            while j >= pre:
                e -= 1
                s -= H[e] * x[j, col]
                j = par[j]
            b = start[i]
            for t in range(wp.static(unroll)):  # (from the deepest: the walk's order)
                p = wp.static(unroll - 1) - t
                if p <= j:
                    s -= H[b + p] * x[p, col]
            tile_set(x, i, col, s)

    @wp.func
    def tree_solve_vector(par: Any, lvl: Any, start: Any, n: int, pre: int, H: Any, x: Any):
        """The shared vector x := M^-1 x with tree_factor's L^T D L, by one lane (as tree_solve_column)."""
        for step in range(n):
            i = n - 1 - step
            xi = x[i]
            e = start[i] + lvl[i]
            j = par[i]
            while j >= pre:
                e -= 1
                tile_set(x, j, x[j] - H[e] * xi)
                j = par[j]
            b = start[i]
            for t in range(wp.static(unroll)):
                if t <= j:
                    tile_set(x, t, x[t] - H[b + t] * xi)
        for i in range(n):
            e = start[i] + lvl[i]
            s = x[i] / H[e]
            j = par[i]
            while j >= pre:
                e -= 1
                s -= H[e] * x[j]
                j = par[j]
            b = start[i]
            for t in range(wp.static(unroll)):
                p = wp.static(unroll - 1) - t
                if p <= j:
                    s -= H[b + p] * x[p]
            tile_set(x, i, s)

    return tree_solve_column, tree_solve_vector


@wp.func
def own_terms(m: ChainArrays, w: ChainWork, world: int, k: int, g: wp.vec3):
    """Body k's own mass, first moment and inertia about the origin, and its gravity, inertial and
    gyroscopic wrench (torque about the origin, force), into the subtree accumulators."""
    mk = m.mass[world, k]
    c = w.centre[world, k]
    inertia = w.inertia[world, k]
    om = w.omega[world, k]
    f = mk * (g - w.acc[world, k])
    w.wrench_t[world, k] = -(inertia * w.alpha[world, k]) - wp.cross(om, inertia * om) + wp.cross(c, f)
    w.wrench_f[world, k] = f
    w.sub_mass[world, k] = mk
    w.sub_moment[world, k] = mk * c
    w.sub_inertia[world, k] = inertia + mk * (wp.dot(c, c) * wp.identity(n=3, dtype=float) - wp.outer(c, c))


@wp.func
def side_frame(m: ChainLoads, w: ChainWork, world: int, f: int, side: int):
    """Force slot f's frame of ``side`` in the world at the kinematics' poses."""
    e = m.force_entry[world, f, side]
    X = m.force_frame[world, f, side]
    if e < 0:
        return X
    return wp.transform_multiply(w.pose[world, e], X)


@wp.func
def point_velocity(w: ChainWork, world: int, e: int, x: wp.vec3):
    """Velocity of the world point x moving with entry e's body (0 for the world, -1)."""
    if e < 0:
        return wp.vec3()
    return w.vel[world, e] + wp.cross(w.omega[world, e], x - w.centre[world, e])


@wp.func
def push(w: ChainWork, world: int, e: int, f: wp.vec3, x: wp.vec3, t: wp.vec3):
    """Force f at the world point x and torque t onto entry e's wrench (torque about the origin);
    the world (-1) takes nothing."""
    if e >= 0:
        w.wrench_f[world, e] = w.wrench_f[world, e] + f
        w.wrench_t[world, e] = w.wrench_t[world, e] + wp.cross(x, f) + t


@wp.func
def apply_forces(m: ChainLoads, w: ChainWork, world: int):
    """The force elements' wrenches added to their bodies' own terms (after own_terms, before the
    subtree sums; one lane, slot order), at the kinematics' poses and velocities: a spring-damper's
    tension k (L - L0) + c dL/dt along its points' line (tension_only: never a push), a joint
    element's torque tau about the joint's world axis on its child and -tau on its parent (spring:
    tau = -k wrap(angle - rest) - c rate, the angle from the two anchor frames as the maximal plan
    measures it, so tree and loop joints alike), a body wrench's force at the centre of mass."""
    for f in range(m.force_count[world]):
        kind = m.force_kind[world, f]
        e0 = m.force_entry[world, f, 0]
        e1 = m.force_entry[world, f, 1]
        coef = m.force_coef[world, f]
        zero = wp.vec3()
        if kind == FORCE_LINEAR_SPRING:
            xa = wp.transform_get_translation(side_frame(m, w, world, f, 0))
            xb = wp.transform_get_translation(side_frame(m, w, world, f, 1))
            n, tension = spring_tension(coef, xb - xa,
                                        point_velocity(w, world, e1, xb) - point_velocity(w, world, e0, xa))
            push(w, world, e0, tension * n, xa, zero)
            push(w, world, e1, -tension * n, xb, zero)
        elif kind == FORCE_BODY_WRENCH:
            if e0 >= 0:
                push(w, world, e0, m.force_vec[world, f, 0], w.centre[world, e0], m.force_vec[world, f, 1])
        else:  # a joint spring or torque on a revolute joint
            rot_c = wp.transform_get_rotation(side_frame(m, w, world, f, 0))
            rot_p = wp.transform_get_rotation(side_frame(m, w, world, f, 1))
            axis = m.force_vec[world, f, 0]
            a_w = wp.quat_rotate(rot_p, axis)
            tau = coef[3]
            if kind == FORCE_JOINT_SPRING:
                angle = hinge_angle(rot_p, rot_c, axis)
                rate = float(0.0)
                if e0 >= 0:
                    rate += wp.dot(a_w, w.omega[world, e0])
                if e1 >= 0:
                    rate -= wp.dot(a_w, w.omega[world, e1])
                tau = -coef[0] * wrap_angle(angle - coef[2]) - coef[1] * rate
            push(w, world, e0, zero, zero, tau * a_w)
            push(w, world, e1, zero, zero, -tau * a_w)


@wp.func
def apply_control(m: ChainLoads, w: ChainWork, world: int):
    """A Control's wrenches added to the bodies' own terms (after own_terms, before the subtree sums;
    one lane) at the kinematics' poses: body_f[world, b] (force, torque; world frame) at spec body
    b's centre of mass, and joint_effort[world, j] as the torque tau about spec joint j's world axis
    (its parent anchor frame's) on its child and -tau on its parent: for a tree joint exactly tau on
    its coordinate (either direction of the tree), for a loop joint the pair the maximal plan
    applies. Bodies welded to the world take nothing."""
    for b in range(m.control_body.shape[1]):
        e = m.control_body[world, b]
        if e >= 0:
            f = m.body_f[world, b]
            push(w, world, e, wp.spatial_top(f), w.centre[world, e], wp.spatial_bottom(f))
    zero = wp.vec3()
    for j in range(m.control_joint.shape[1]):
        ec = m.control_joint[world, j, 0]
        ep = m.control_joint[world, j, 1]
        if ec >= 0 or ep >= 0:
            X = m.control_frame[world, j]
            if ep >= 0:
                X = wp.transform_multiply(w.pose[world, ep], X)
            torque = m.joint_effort[world, j] * wp.quat_rotate(wp.transform_get_rotation(X), m.control_axis[world, j])
            push(w, world, ec, zero, zero, torque)
            push(w, world, ep, zero, zero, -torque)


@wp.func
def add_children(m: ChainArrays, w: ChainWork, world: int, k: int):
    """Body k's subtree sums: its own terms plus its children's subtree sums (the children are
    contiguous in the breadth-first order)."""
    first = m.first_child[world, k]
    if first >= 0:
        sm = w.sub_mass[world, k]
        sh = w.sub_moment[world, k]
        sI = w.sub_inertia[world, k]
        st = w.wrench_t[world, k]
        sf = w.wrench_f[world, k]
        for c in range(first, first + m.child_count[world, k]):
            sm += w.sub_mass[world, c]
            sh += w.sub_moment[world, c]
            sI += w.sub_inertia[world, c]
            st += w.wrench_t[world, c]
            sf += w.wrench_f[world, c]
        w.sub_mass[world, k] = sm
        w.sub_moment[world, k] = sh
        w.sub_inertia[world, k] = sI
        w.wrench_t[world, k] = st
        w.wrench_f[world, k] = sf


@wp.func
def candidates_within(cand: Any, shapes: int, margin: float):
    """How many of plane_candidates' rows of ``shapes`` shapes lie within the margin."""
    count = int(0)
    for slot in range(4 * shapes):
        if cand[slot, 3] < margin:
            count += 1
    return count


@wp.func
def plane_candidates(m: ChainArrays, w: ChainWork, world: int, s: int, n: wp.vec3, off: float, margin: float,
                     cand: Any):
    """Shape s's candidate contacts against the ground plane into rows 4 s .. 4 s + 3 of the shared
    tile cand (point, distance; 1e30: none): a sphere's lowest point, a capsule's ends', and of a box's
    corners or a cylinder's rim points (engine.collide.plane_point) the 4 deepest within the margin,
    in their own order (a slot keeps its point from step to step while the same points are the
    deepest: the warm start's key; when they change, a slot's last impulse starts another point,
    which costs iterations, not accuracy)."""
    entry = m.shape_entry[world, s]
    X = wp.transform_multiply(w.pose[world, entry], m.shape_X[world, s])
    kind = m.shape_type[world, s]
    size = m.shape_size[world, s]
    count = plane_point_count(kind)
    depth = vec8f()  # each point's distance above the plane, evaluated once
    for k in range(count):
        depth[k] = wp.dot(n, plane_point(kind, X, size, n, k)) - off
    chosen = int(0)  # bit k: point k is kept
    if count <= 4:
        chosen = (1 << count) - 1
    else:
        for pick in range(4):  # the deepest unchosen point within the margin, four times
            best = int(-1)
            deepest = margin
            for k in range(count):
                if (chosen & (1 << k)) == 0 and depth[k] < deepest:
                    deepest = depth[k]
                    best = k
            if best >= 0:
                chosen = chosen | (1 << best)
    slot = 4 * s
    for k in range(count):
        if (chosen & (1 << k)) != 0:
            p = plane_point(kind, X, size, n, k)
            tile_set(cand, slot, 0, p[0])
            tile_set(cand, slot, 1, p[1])
            tile_set(cand, slot, 2, p[2])
            tile_set(cand, slot, 3, depth[k])
            slot += 1
    while slot < 4 * s + 4:
        tile_set(cand, slot, 3, 1.0e30)
        slot += 1


@wp.func
def contact_factor(lane: int, lanes: int, m3: int, D: Any, ddiag: Any, fdiag: Any, Finv: Any, shift: float):
    """Finv = (D + shift I)^-1 for the m3 x m3 contact matrix whose upper triangle (and ddiag, its
    diagonal) hold D: the lower triangle is refilled from the upper and factored in place
    (factor_lanes), then Finv a column per lane. Entered after a barrier; leaves one."""
    for e in range(lane, m3 * m3, lanes):
        a = e // m3
        b = e % m3
        if b < a:
            tile_set(D, a, b, D[b, a])
        elif a == b:
            tile_set(D, a, a, ddiag[a] + shift)
    block_sync()
    factor_lanes(lane, lanes, m3, D, fdiag, 0.0)
    for r in range(lane, m3, lanes):  # column r (symmetric: also row r), a lane per column
        for j in range(m3):
            value = float(0.0)
            if j == r:
                value = 1.0
            tile_set(Finv, j, r, value)
        solve_column(m3, D, fdiag, Finv, r)
    block_sync()


@wp.func
def contact_residuals(nc: int, res_p: Any, res_d: Any, res_y: Any):
    """The largest primal and dual residuals and impulse over the nc contacts (every lane alike)."""
    out = wp.vec3()
    for c in range(nc):
        out = wp.vec3(wp.max(out[0], res_p[c]), wp.max(out[1], res_d[c]), wp.max(out[2], res_y[c]))
    return out
