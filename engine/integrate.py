"""Time integration: velocity update from the impulses, pose update on SE(3), projection of the
poses back onto the constraint manifold, and the divergence guard.

Semi-implicit Euler: u+ = u_free + M^-1 J^T lambda, then x+ = x + dt v+, q+ = exp(dt w+) q.
Moreau-Jean: q_mid = q + dt/2 u; dynamics at q_mid; q+ = q_mid + dt/2 u+ (engine.step).
Compensated summation: the twists and the chain of configurations the dynamics run on (Moreau-Jean:
the midpoints) are sums of small increments to large values; each keeps a low part (engine.State's
body_qd_low and body_q_low) holding what float32 rounded off, so that the state walks by the
rounding of the increments, not by that of the state (an estimate: benchmarks/results/README.md,
"Engine design notes (moved from the code)"). Tuning.compensated_state turns it off (plain float32
sums; the low parts stay zero).
Position projection (Gauss-Newton): with the residuals phi(q+) of the bilateral rows, solve
(P D P + sigma I) x = -P phi over the bilateral rows and move every body by M^-1 J^T (P x): one
damped Newton step on the constraint manifold per iteration. A batch whose rows are all bilateral
joint rows reuses the factor the PADMM solve already holds; any other batch factors its bilateral
block once per step (dense: the other rows made identity; sparse: likewise on the PADMM's pattern,
or on a pattern of the bilateral rows alone, Tuning.sparse_projection_pattern).
"""

import warp as wp

from engine.linalg import dense, sparse
from engine.linalg.lanes import block_max, block_sync
from engine.dynamics import free_velocity_of
from engine.joints import joint_residuals_of
from engine.model import ROW_ANGULAR, ROW_LINEAR, ModelArrays, WorkArrays
from engine.spatial import advance_pose, pose_step, two_sum

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only


@wp.func
def add_row_share(total: wp.spatial_vector, world: int, b: int, i: int, row_body_c: wp.array2d(dtype=wp.int32),
                  row_body_p: wp.array2d(dtype=wp.int32), row_MJ_c: wp.array2d(dtype=wp.spatial_vector),
                  row_MJ_p: wp.array2d(dtype=wp.spatial_vector), weight: wp.array2d(dtype=float),
                  row_precond: wp.array2d(dtype=float), scale_by_precond: int):
    """total plus row i's share of body b's sum, (M^-1 J^T)_b,i weight_i (times P_i when asked;
    nothing where the row does not act on b)."""
    s = weight[world, i]
    if scale_by_precond != 0:
        s = s * row_precond[world, i]
    if row_body_c[world, i] == b:
        total += s * row_MJ_c[world, i]
    if row_body_p[world, i] == b:
        total += s * row_MJ_p[world, i]
    return total


@wp.func
def row_sum_listed(world: int, b: int, m: ModelArrays, w: WorkArrays, weight: wp.array2d(dtype=float),
                   scale_by_precond: int):
    """sum over this step's rows touching body b of (M^-1 J^T)_b * weight (times P when asked), in
    row order: the body's joint, drive and limit rows through its list (engine.pack.body_row_lists),
    then the contact rows by a scan (a scan of every row per body costs O(bodies x rows) loads)."""
    total = wp.spatial_vector()
    for k in range(m.body_row_begin[world, b], m.body_row_end[world, b]):
        code = m.body_row[world, k]
        i = code >> 1
        s = weight[world, i]
        if scale_by_precond != 0:
            s = s * w.row_precond[world, i]
        if (code & 1) == 0:
            total += s * w.row_MJ_c[world, i]
        else:
            total += s * w.row_MJ_p[world, i]
    for i in range(m.contact_row_start[world], w.row_count[world]):
        total = add_row_share(total, world, b, i, w.row_body_c, w.row_body_p, w.row_MJ_c, w.row_MJ_p, weight,
                              w.row_precond, scale_by_precond)
    return total


@wp.kernel
def apply_impulses(m: ModelArrays, w: WorkArrays, row_lambda: wp.array2d(dtype=float), compensated: int,
                   body_q: wp.array2d(dtype=wp.transform), body_q_low_in: wp.array2d(dtype=wp.transform),
                   body_qd_out: wp.array2d(dtype=wp.spatial_vector), body_q_out: wp.array2d(dtype=wp.transform),
                   body_q_low_out: wp.array2d(dtype=wp.transform), body_qd_low: wp.array2d(dtype=wp.spatial_vector)):
    """u+ = w.body_qd_free + M^-1 J^T lambda (add_impulse_of), then a whole pose step from body_q
    with u+ (advance_pose_of): one pass over the bodies instead of two. body_qd_low: in, the free
    twists' low parts; out, the new twists'."""
    world, b = wp.tid()
    if b >= m.body_count[world]:
        return
    add_impulse_of(world, b, row_sum_listed(world, b, m, w, row_lambda, 0), w.body_qd_free, compensated, body_qd_out,
                   body_qd_low)
    advance_pose_of(world, b, m.world_dt, body_q, body_q_low_in, body_qd_out, compensated, body_q_out, body_q_low_out)


@wp.func
def add_impulse_of(world: int, b: int, du: wp.spatial_vector, body_qd_free: wp.array2d(dtype=wp.spatial_vector),
                   compensated: int, body_qd_out: wp.array2d(dtype=wp.spatial_vector),
                   body_qd_low: wp.array2d(dtype=wp.spatial_vector)):
    """u+ = u_free + du; ``compensated``: with compensation, body_qd_low holds the free twist's low
    part on entry and the new twist's on return."""
    if compensated == 0:
        body_qd_out[world, b] = body_qd_free[world, b] + du
        return
    u, low = two_sum(body_qd_free[world, b], body_qd_low[world, b] + du)
    body_qd_out[world, b] = u
    body_qd_low[world, b] = low


@wp.func
def integrate_pose_of(world: int, b: int, world_dt: wp.array(dtype=float), fraction: float,
                      body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector),
                      body_q_out: wp.array2d(dtype=wp.transform)):
    """x+ = x + h v, q+ = exp(h w) q with h = fraction * dt."""
    body_q_out[world, b] = pose_step(body_q[world, b], body_qd[world, b], fraction * world_dt[world])


@wp.func
def midpoint_of(X: wp.transform, o: wp.spatial_vector, u: wp.spatial_vector, h: float):
    """The pose X with the output projection o undone, then moved by h u."""
    return pose_step(pose_step(X, -o, 1.0), u, h)


MIDPOINT_MATCH = wp.constant(1.0e-5)  # relative: the float32 roundings of the pose operations (~80 ulp)


@wp.func
def midpoint_pose_of(world: int, b: int, m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform),
                     body_q_offset: wp.array2d(dtype=wp.spatial_vector), body_qd: wp.array2d(dtype=wp.spatial_vector),
                     body_q_low: wp.array2d(dtype=wp.transform), body_q_next: wp.array2d(dtype=wp.transform),
                     compensated: int):
    """Moreau-Jean's midpoint into w.body_q_mid (and w.body_q_mid_low): undo the last step's output
    projection (body_q_offset: translation [m] and rotation vector [rad] it moved the body by),
    then half a pose step with the twist. ``compensated``: the last step left the next midpoint as
    the pair body_q_next + body_q_low (State). Where the midpoint found from the state matches
    body_q_next to within the roundings of these pose steps (MIDPOINT_MATCH), the step continues
    from that pair exactly, so the motion does not depend on whether the output was projected;
    otherwise (poses or twists set by hand, a new State) from the midpoint found, plus body_q_low
    (at most that much off)."""
    mid = midpoint_of(body_q[world, b], body_q_offset[world, b], body_qd[world, b], 0.5 * m.world_dt[world])
    if compensated == 0:
        w.body_q_mid[world, b] = mid
        return
    low = body_q_low[world, b]
    nxt = body_q_next[world, b]
    t = wp.transform_get_translation(mid)
    r = wp.transform_get_rotation(mid)
    dp = t - wp.transform_get_translation(nxt)
    dr = r - wp.transform_get_rotation(nxt)
    reach = MIDPOINT_MATCH * (1.0 + wp.max(wp.abs(t[0]), wp.max(wp.abs(t[1]), wp.abs(t[2]))))
    same = wp.max(wp.abs(dp[0]), wp.max(wp.abs(dp[1]), wp.abs(dp[2]))) <= reach
    same = same and wp.max(wp.max(wp.abs(dr[0]), wp.abs(dr[1])), wp.max(wp.abs(dr[2]), wp.abs(dr[3]))) <= MIDPOINT_MATCH
    if same:
        w.body_q_mid[world, b] = nxt
        w.body_q_mid_low[world, b] = low
        return
    t, t_low = two_sum(t, wp.transform_get_translation(low))
    r, r_low = two_sum(r, wp.transform_get_rotation(low))
    w.body_q_mid[world, b] = wp.transform(t, r)
    w.body_q_mid_low[world, b] = wp.transform(t_low, r_low)


@wp.func
def advance_pose_of(world: int, b: int, world_dt: wp.array(dtype=float), body_q: wp.array2d(dtype=wp.transform),
                    body_q_low_in: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector),
                    compensated: int, body_q_out: wp.array2d(dtype=wp.transform),
                    body_q_low_out: wp.array2d(dtype=wp.transform)):
    """The next configuration of the dynamics, body_q moved by dt times the twist; ``compensated``:
    body_q + body_q_low_in moved (advance_pose), as a (body_q_out, body_q_low_out) pair."""
    u = body_qd[world, b]
    if compensated == 0:
        body_q_out[world, b] = pose_step(body_q[world, b], u, world_dt[world])
        return
    X, low = advance_pose(body_q[world, b], body_q_low_in[world, b], wp.spatial_top(u), wp.spatial_bottom(u),
                          world_dt[world])
    body_q_out[world, b] = X
    body_q_low_out[world, b] = low


@wp.kernel
def midpoint_free_velocity(m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform),
                           body_q_offset: wp.array2d(dtype=wp.spatial_vector),
                           body_qd: wp.array2d(dtype=wp.spatial_vector), body_q_low: wp.array2d(dtype=wp.transform),
                           body_q_next: wp.array2d(dtype=wp.transform),
                           body_qd_low: wp.array2d(dtype=wp.spatial_vector),
                           body_f: wp.array2d(dtype=wp.spatial_vector), compensated: int,
                           body_qd_free_low: wp.array2d(dtype=wp.spatial_vector)):
    """Moreau-Jean's midpoint configuration of every body (midpoint_pose_of), then its free
    velocity there (engine.dynamics.free_velocity_of): one pass over the bodies instead of two."""
    world, b = wp.tid()
    if b >= m.body_count[world]:
        return
    midpoint_pose_of(world, b, m, w, body_q, body_q_offset, body_qd, body_q_low, body_q_next, compensated)
    free_velocity_of(world, b, m, w, w.body_q_mid, body_qd, body_qd_low, body_f, compensated, body_qd_free_low)


@wp.kernel
def integrate_poses(m: ModelArrays, fraction: float, body_q: wp.array2d(dtype=wp.transform),
                    body_qd: wp.array2d(dtype=wp.spatial_vector), keep: int,
                    body_q_out: wp.array2d(dtype=wp.transform), body_q_kept: wp.array2d(dtype=wp.transform),
                    body_q_offset: wp.array2d(dtype=wp.spatial_vector)):
    """x+ = x + h v, q+ = exp(h w) q with h = fraction * dt into body_q_out; first, for every body
    slot (padding included), body_q_kept = body_q_out's pose before it (where ``keep``) and
    body_q_offset = 0: Moreau-Jean's end of a step (engine.step), one launch instead of a copy, a
    fill and a launch."""
    world, b = wp.tid()
    if keep != 0:
        body_q_kept[world, b] = body_q_out[world, b]
    body_q_offset[world, b] = wp.spatial_vector()
    if b >= m.body_count[world]:
        return
    integrate_pose_of(world, b, m.world_dt, fraction, body_q, body_qd, body_q_out)


@wp.func
def bilateral_residual_of(world: int, i: int, m: ModelArrays, w: WorkArrays):
    """phi_i of a bilateral joint row [m]/[rad], the row the projection corrects; 0 on drive,
    limit, contact and padded rows."""
    kind = m.row_kind[world, i]
    if i < w.row_count[world] and (kind == ROW_LINEAR or kind == ROW_ANGULAR):
        return w.row_residual[world, i]
    return 0.0


GATE_BLOCK = 64  # threads per world of projection_pass on a GPU (one on the CPU)


@wp.func
def move_body_of(world: int, b: int, dx: wp.spatial_vector, world_dt: wp.array(dtype=float), velocity_update: int,
                 record_offset: int, compensated: int, body_q: wp.array2d(dtype=wp.transform),
                 body_qd: wp.array2d(dtype=wp.spatial_vector), body_q_offset: wp.array2d(dtype=wp.spatial_vector),
                 body_q_low: wp.array2d(dtype=wp.transform), body_qd_low: wp.array2d(dtype=wp.spatial_vector)):
    """Body b's share of apply_projection, given its displacement dx = (M^-1 J^T P delta)_b. With
    ``compensated`` the projection of the dynamics' next configuration (no offset recorded) moves
    the compensated pose and twist (body_q_low, body_qd_low); the output projection moves the
    float32 pose only."""
    X = body_q[world, b]
    if record_offset != 0 or compensated == 0:
        body_q[world, b] = pose_step(X, dx, 1.0)
    else:
        X, low = advance_pose(X, body_q_low[world, b], wp.spatial_top(dx), wp.spatial_bottom(dx), 1.0)
        body_q[world, b] = X
        body_q_low[world, b] = low
    if record_offset != 0:
        body_q_offset[world, b] = body_q_offset[world, b] + dx
    if velocity_update != 0:
        if compensated == 0:
            body_qd[world, b] = body_qd[world, b] + dx / world_dt[world]
        else:
            u, u_low = two_sum(body_qd[world, b], body_qd_low[world, b] + dx / world_dt[world])
            body_qd[world, b] = u
            body_qd_low[world, b] = u_low


@wp.kernel
def apply_projection(m: ModelArrays, w: WorkArrays, velocity_update: int, record_offset: int, compensated: int,
                     body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector),
                     body_q_offset: wp.array2d(dtype=wp.spatial_vector), body_q_low: wp.array2d(dtype=wp.transform),
                     body_qd_low: wp.array2d(dtype=wp.spatial_vector)):
    """In the worlds of w.projection_mask, move each body by M^-1 J^T (P w.delta): translation [m]
    and rotation vector [rad]; with velocity_update, and where the world's gate is open (its joint
    error is above the rounding floor), add the same displacement / dt to the twist (SHAKE: the
    step stays symplectic); with record_offset, add the displacement to body_q_offset (an output
    projection the next Moreau-Jean midpoint undoes)."""
    world, b = wp.tid()
    if b >= m.body_count[world] or w.projection_mask[world] == 0:
        return
    dx = row_sum_listed(world, b, m, w, w.delta, 1)
    move_body_of(world, b, dx, m.world_dt, velocity_update * w.projection_gate[world], record_offset, compensated,
                 body_q, body_qd, body_q_offset, body_q_low, body_qd_low)


@wp.func
def projection_gates(world: int, lane: int, stride: int, m: ModelArrays, w: WorkArrays, floor: float,
                     skip_floor: float, skip_floor_angular: float):
    """A world's gate and mask from its largest bilateral joint errors (w.row_residual; the thread
    block's rows spread over its threads; every thread must call it, and every thread gets both):
    gate 1 where the largest error exceeds floor (the projection iteration may update the
    velocities), else 0 (the correction is mostly rounding); mask ``w.project[world]`` where the
    largest linear error exceeds skip_floor or the largest angular one skip_floor_angular, else 0
    (the iteration is skipped). Drive, limit, contact and padded rows do not count."""
    n = w.row_count[world]
    error_linear = float(0.0)
    error_angular = float(0.0)
    for k in range((n + stride - 1) // stride):
        i = lane + k * stride
        if i < n:
            kind = m.row_kind[world, i]
            if kind == ROW_LINEAR:
                error_linear = wp.max(error_linear, wp.abs(w.row_residual[world, i]))
            elif kind == ROW_ANGULAR:
                error_angular = wp.max(error_angular, wp.abs(w.row_residual[world, i]))
    error_linear = block_max(error_linear)
    error_angular = block_max(error_angular)
    opened = wp.where(wp.max(error_linear, error_angular) > floor, 1, 0)
    move = wp.where(error_linear > skip_floor or error_angular > skip_floor_angular, w.project[world], 0)
    return opened, move


@wp.kernel
def projection_pass(m: ModelArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform),
                    body_q_low: wp.array2d(dtype=wp.transform), exact: int, floor: float, skip_floor: float,
                    skip_floor_angular: float):
    """The start of a Gauss-Newton iteration of project_positions for one world (a thread block per
    world, its joints and rows spread over the threads): the joint residuals at body_q into
    w.row_residual (engine.joints.joint_residuals_of; exact: the float64 sums), the world's gate
    and mask (projection_gates) into w.projection_gate and w.projection_mask and, where the mask is
    set, the solve's right-hand side -P phi on the bilateral joint rows into w.rhs (0 on drive,
    limit, contact and padded rows). One launch instead of three."""
    world, lane = wp.tid()
    stride = wp.block_dim()
    nj = m.joint_count[world]
    for k in range((nj + stride - 1) // stride):
        j = lane + k * stride
        if j < nj:
            joint_residuals_of(world, j, -1, m, body_q, body_q_low, exact, w.row_residual)
    block_sync()
    opened, move = projection_gates(world, lane, stride, m, w, floor, skip_floor, skip_floor_angular)
    if lane == 0:
        w.projection_gate[world] = opened
        w.projection_mask[world] = move
    if move == 0:
        return
    rows = w.rhs.shape[1]
    for k in range((rows + stride - 1) // stride):
        i = lane + k * stride
        if i < rows:
            w.rhs[world, i] = -w.row_precond[world, i] * bilateral_residual_of(world, i, m, w)


@wp.func
def transform_finite(X: wp.transform):
    """True when all seven components of the pose are finite."""
    ok = True
    for k in range(7):
        if not wp.isfinite(X[k]):
            ok = False
    return ok


@wp.func
def twist_finite(u: wp.spatial_vector):
    """True when all six components of the twist are finite."""
    ok = True
    for k in range(6):
        if not wp.isfinite(u[k]):
            ok = False
    return ok


@wp.func
def guard_divergence_of(world: int, m: ModelArrays, w: WorkArrays, max_speed: float,
                        body_q_in: wp.array2d(dtype=wp.transform), body_qd_in: wp.array2d(dtype=wp.spatial_vector),
                        body_q_offset_in: wp.array2d(dtype=wp.spatial_vector),
                        body_q_low_in: wp.array2d(dtype=wp.transform),
                        body_qd_low_in: wp.array2d(dtype=wp.spatial_vector),
                        body_q_next_in: wp.array2d(dtype=wp.transform), body_q_out: wp.array2d(dtype=wp.transform),
                        body_qd_out: wp.array2d(dtype=wp.spatial_vector),
                        body_q_offset_out: wp.array2d(dtype=wp.spatial_vector),
                        body_q_low_out: wp.array2d(dtype=wp.transform),
                        body_qd_low_out: wp.array2d(dtype=wp.spatial_vector),
                        body_q_next_out: wp.array2d(dtype=wp.transform)):
    """Flag a world (w.diverged) whose new state (the _out arrays) is not finite, or in which a
    body's centre of mass moves faster than max_speed [m/s], and freeze it at its last state (the
    _in arrays); a halted world (w.halted: engine.rollout's halt) stays frozen as well, without the
    flag."""
    n = m.body_count[world]
    bad = w.diverged[world] != 0
    for b in range(n):
        u = body_qd_out[world, b]
        if not (transform_finite(body_q_out[world, b]) and twist_finite(u)):
            bad = True
        elif wp.length(wp.spatial_top(u)) > max_speed:
            bad = True
    if bad:
        w.diverged[world] = 1
    if bad or w.halted[world] != 0:
        for b in range(n):
            body_q_out[world, b] = body_q_in[world, b]
            body_qd_out[world, b] = body_qd_in[world, b]
            body_q_offset_out[world, b] = body_q_offset_in[world, b]
            body_q_low_out[world, b] = body_q_low_in[world, b]
            body_qd_low_out[world, b] = body_qd_low_in[world, b]
            body_q_next_out[world, b] = body_q_next_in[world, b]


@wp.kernel
def guard_divergence(m: ModelArrays, w: WorkArrays, max_speed: float, body_q_in: wp.array2d(dtype=wp.transform),
                     body_qd_in: wp.array2d(dtype=wp.spatial_vector),
                     body_q_offset_in: wp.array2d(dtype=wp.spatial_vector),
                     body_q_low_in: wp.array2d(dtype=wp.transform),
                     body_qd_low_in: wp.array2d(dtype=wp.spatial_vector),
                     body_q_next_in: wp.array2d(dtype=wp.transform), body_q_out: wp.array2d(dtype=wp.transform),
                     body_qd_out: wp.array2d(dtype=wp.spatial_vector),
                     body_q_offset_out: wp.array2d(dtype=wp.spatial_vector),
                     body_q_low_out: wp.array2d(dtype=wp.transform),
                     body_qd_low_out: wp.array2d(dtype=wp.spatial_vector),
                     body_q_next_out: wp.array2d(dtype=wp.transform)):
    """The divergence guard of every world (guard_divergence_of)."""
    world = wp.tid()
    guard_divergence_of(world, m, w, max_speed, body_q_in, body_qd_in, body_q_offset_in, body_q_low_in,
                        body_qd_low_in, body_q_next_in, body_q_out, body_qd_out, body_q_offset_out, body_q_low_out,
                        body_qd_low_out, body_q_next_out)


@wp.kernel
def bilateral_block(m: ModelArrays, w: WorkArrays, delassus: wp.array3d(dtype=float)):
    """Keep the bilateral joint block of P D P; other rows and columns become the identity."""
    world, i, j = wp.tid()
    ki = m.row_kind[world, i]
    kj = m.row_kind[world, j]
    keep_i = i < w.row_count[world] and (ki == ROW_LINEAR or ki == ROW_ANGULAR)
    keep_j = j < w.row_count[world] and (kj == ROW_LINEAR or kj == ROW_ANGULAR)
    if not (keep_i and keep_j):
        value = 0.0
        if i == j:
            value = 1.0
        delassus[world, i, j] = value


@wp.func
def projection_penalty(rho_init: float, rho_free: float):
    """The penalty part of the shift of a projection factor's joint rows: the free rows' penalty
    (engine.padmm.row_penalty), or the initial rho where they take the world's."""
    if rho_free > 0.0:
        return rho_free
    return rho_init


@wp.kernel
def projection_shift(m: ModelArrays, w: WorkArrays):
    """Worlds to project: valid ones with bilateral joint rows; flag them (w.project,
    w.needs_factor) for a factor of the projection's own, with the shift eta + rho_free
    (Tuning.free_rho; rho_init with cap_joint_penalty off) on every row (w.row_shift): for batches
    with drive, limit or contact rows, or no factor to reuse (project_positions; otherwise the
    PADMM's factor serves, its joint rows shifted alike: engine.padmm.row_penalty). One thread per
    row; row 0 writes the world's flags."""
    world, i = wp.tid()
    project = int(0)
    if w.valid[world] != 0 and m.bilateral_row_count[world] > 0:
        project = 1
        w.row_shift[world, i] = m.padmm_eta[world] + projection_penalty(m.padmm_rho_init[world],
                                                                        m.padmm_rho_free[world])
    if i == 0:
        w.needs_factor[world] = project
        w.project[world] = project


def project_positions(model, body_q, body_qd, *, iterations=None,
                      velocity_update=None, body_q_offset=None, prepare=True, body_q_low=None, body_qd_low=None):
    """Gauss-Newton projection of body_q onto the joint constraints.

    iterations: Gauss-Newton steps (config.position_iterations when None).
    velocity_update: add each displacement / dt to body_qd (config's
    projection_velocity_update when None). body_q_offset: accumulate the displacements there
    (Moreau-Jean's output projection: float32 poses only). Otherwise, with
    config.tuning.compensated_state, the poses and twists are moved with compensation and body_q_low,
    body_qd_low (their low parts) are required.
    prepare=False reuses the factor of an earlier call this step.
    """
    work, device, m, w = model.work, model.device, model.arrays, model.work.arrays
    iterations = model.config.position_iterations if iterations is None else iterations
    if velocity_update is None:
        velocity_update = model.config.tuning.projection_velocity_update
    if iterations == 0 or not model.has_bilateral_rows:
        return  # nothing to project: no joints in the batch
    dense_solver = model.linear_solver == "dense"  # else sparse
    # the bilateral rows' own system: its solves write those rows of delta alone, and the others stay
    # zero (delta is allocated zero and nothing else writes it)
    own_pattern = model.sparse_projection if model.linear_solver == "sparse" else None
    if prepare:
        # Only the bilateral joint rows are projected. Drive, limit and contact rows are decoupled
        # from the projection (their rows and columns become identity, or are left out of its own
        # pattern) and a large ADMM penalty would damp the Gauss-Newton steps: such worlds get a
        # factor of their own (the PADMM's factor, and with the sparse solver its matrix, are free
        # now: the next step rebuilds both, and the projection's own system may share their buffers).
        if dense_solver and model.has_unilateral_or_drive_rows:
            wp.launch(bilateral_block, dim=(model.num_worlds, model.max_rows, model.max_rows), device=device,
                      inputs=[m, w, work.delassus])
        if model.has_unilateral_or_drive_rows:  # a factor of the projection's own
            wp.launch(projection_shift, dim=(model.num_worlds, model.max_rows), device=device, inputs=[m, w])
        # else the PADMM's factor serves: engine.padmm.padmm_start set the worlds to project, and every
        # flag for a new factor is clear once the PADMM's loop has ended
        if dense_solver:
            if model.has_unilateral_or_drive_rows:  # else no world is flagged: the PADMM's factor serves
                dense.factor(work.delassus, work.row_shift, work.needs_factor, work.factor)
        elif own_pattern is not None:  # the bilateral rows on a pattern of their own (sparse_projection_pattern)
            sparse.matrix(model, own_pattern)
            sparse.factor(model, work.row_shift, work.needs_factor, system=own_pattern)
        elif model.has_unilateral_or_drive_rows:  # else no world is flagged: the PADMM's factor serves
            sparse.factor(model, work.row_shift, work.needs_factor, bilateral_only=True)
    record = body_q_offset is not None
    compensated = model.config.tuning.compensated_state
    if not record and compensated and (body_q_low is None or body_qd_low is None):
        raise ValueError("project_positions: the compensated projection needs body_q_low and body_qd_low")
    # any (W, B) arrays of the right types where unused (the output projection writes no low parts)
    offset = body_q_offset if record else work.body_qd_free
    q_low = work.no_low if body_q_low is None else body_q_low
    qd_low = work.body_qd_free if body_qd_low is None else body_qd_low
    tuning = model.config.tuning
    # the worlds whose joint error is above tuning.projection_skip_floor (angular: projection_skip_floor_angular)
    mask = work.projection_mask
    for k in range(iterations):
        # the residuals (float64 sums where the dynamics move on), the gate and mask, the rhs
        wp.launch_tiled(projection_pass, dim=[model.num_worlds], block_dim=GATE_BLOCK, device=device,
                        inputs=[m, w, body_q, q_low, int(compensated and not record),
                                float(tuning.projection_velocity_floor), float(tuning.projection_skip_floor),
                                float(tuning.projection_skip_floor_angular)])
        if dense_solver:
            dense.solve(work.factor, work.rhs, mask, work.delta)
        else:
            sparse.solve(model, work.rhs, mask, work.delta, system=own_pattern)
        wp.launch(apply_projection, dim=(model.num_worlds, model.max_bodies), device=device,
                  inputs=[m, w, int(velocity_update), int(record), int(compensated), body_q, body_qd, offset, q_low,
                          qd_low])


__all__ = ["add_impulse_of", "advance_pose_of", "apply_impulses", "guard_divergence",
           "integrate_poses", "midpoint_free_velocity", "move_body_of",
           "project_positions"]
