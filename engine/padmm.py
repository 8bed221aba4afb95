"""Proximal ADMM on every world's dual problem at once.

In preconditioned variables (engine.dynamics), with proximal weight eta, penalty rho_i per row
(row_penalty: the world's rho, except on the free rows of this step, those whose bounds are out
of play, which keep Tuning.free_rho) and the factor L L^T = P D P + diag(eta + rho_i), each
iteration of an active world does (rho standing for each row's rho_i; the functions of each line)
    padmm_rhs_of:     rhs = -v_f - s + eta x + rho y_hat + z_hat, with the De Saxce correction
                      s = mu |z_hat_t| on contact normal rows
    solve:            x = (L L^T)^-1 rhs (engine.linalg.dense or engine.linalg.sparse)
    padmm_project_of: y = Pi(x - z_hat / rho): clamp to [lo, hi] (bilateral, drive, limit rows),
                      Coulomb cone per contact triplet;  z = z_hat - rho (x - y)
    row_residuals, padmm_decide: residuals r_p = |x - y|_inf,
                      r_d = |eta (x - x_prev) + rho (y - y_hat)|_inf, complementarity
                      r_c = max |y . z| over limit rows and contact triplets; stop when r_p, r_d
                      <= tolerance + relative_tolerance * |y|_inf and r_c <= that times |y|_inf,
                      or at the iteration cap; Nesterov momentum with restart; penalty update
                      (which asks for a new factor), balancing r_p against the dual residual of
                      the rows whose penalty is the world's rho (not the free rows)
    padmm_accelerate_of: y_hat = y + beta (y - y_prev), z_hat = z + beta (z - z_prev)
    factor:           only for worlds whose penalty changed (rho_update), or in which a free drive
                      row met its bound (it takes the world's rho from then on)
Kernels: padmm_start (the world's state, the warm start, the shifts of the first factor and the
first right-hand side), then per iteration the solve and padmm_update (everything after the
solve up to the next iteration's right-hand side, a thread block per world; a world that stops
writes its impulses lambda = P y there), then the factors it asked for: two or three launches an
iteration (measurements: benchmarks/results/README.md, "Maximal path: design notes"). The fused
step (engine.fused) calls the same per-row functions, padmm_decide (with the penalty rule
rho_update) and project_cone inside its one kernel.
The loop runs under wp.capture_while on a device counter of active worlds, so it can be
captured into a CUDA graph; converged, capped and diverged worlds do no more work.
"""

import warp as wp

from engine.linalg import dense, sparse
from engine.linalg.lanes import block_max, block_sum, block_sync
from engine.model import (ROW_ANGULAR, ROW_CONTACT_NORMAL, ROW_CONTACT_TANGENT, ROW_DYNAMICS, ROW_LIMIT, ROW_LINEAR,
                          ModelArrays, WorkArrays)

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

RHO_MIN = wp.constant(1.0e-5)
RHO_MAX = wp.constant(1.0e3)
RHO_FACTOR = wp.constant(4.0)
RHO_BALANCE = wp.constant(10.0)
RESTART_RATIO = wp.constant(0.999)
STALL_WINDOW = wp.constant(10)  # iterations between Tuning.stall_ratio's checks


@wp.func
def row_penalty(free: int, rho: float, rho_free: float):
    """The ADMM penalty of one row: the world's rho, except on free rows (padmm_warmstart_of's row_free:
    bilateral joint rows, and drive rows whose warm start lies well inside their effort limits),
    whose projection is the identity (y = x, z = 0): they need only the proximal pull, so they keep
    rho_free (Tuning.free_rho; 0 with cap_joint_penalty off: the world's rho). Above it, the large
    rho that contacts and saturated drives ask for would turn them into a slow proximal-point
    iteration (a soft mode of eigenvalue lambda shrinks only by rho / (lambda + rho) per
    iteration); below it, the factor of a mechanism with redundant joint rows (singular, shifted by
    eta + rho only) loses float32 digits in proportion to 1 / (eta + rho), and the penalty update
    would drive rho down on free rows, whose primal residual is zero."""
    if free != 0 and rho_free > 0.0:
        return rho_free
    return rho


@wp.func
def rho_update(rho: float, r_p: float, r_d: float):
    """The adaptive penalty rule: the penalty RHO_FACTOR times larger where the primal residual r_p
    exceeds RHO_BALANCE times the dual residual r_d, RHO_FACTOR times smaller in the opposite case,
    within [RHO_MIN, RHO_MAX]; else rho unchanged (the caller refactors when it changes)."""
    new_rho = rho
    if r_p > RHO_BALANCE * r_d:
        new_rho = wp.min(rho * RHO_FACTOR, RHO_MAX)
    elif r_d > RHO_BALANCE * r_p:
        new_rho = wp.max(rho / RHO_FACTOR, RHO_MIN)
    return new_rho


@wp.func
def row_is_free(kind: int, x: float, lo: float, hi: float):
    """1 for a row whose bounds stay out of play this step: a bilateral joint row, or a drive row
    whose warm-start impulse x is within half of its effort limits; else 0."""
    if kind == ROW_LINEAR or kind == ROW_ANGULAR:
        return 1
    if kind == ROW_DYNAMICS and 2.0 * x > lo and 2.0 * x < hi:
        return 1
    return 0


@wp.func
def padmm_warmstart_of(world: int, i: int, warmstart_scale: float, m: ModelArrays, w: WorkArrays,
                       row_lambda: wp.array2d(dtype=float)):
    """Start row i from the last step's impulses row_lambda, in this step's preconditioned
    variables (x = y = y_hat, z = z_hat = 0), and mark whether it is free this step (row_is_free);
    returns x and the flag."""
    x = wp.clamp(warmstart_scale * row_lambda[world, i] / w.row_precond[world, i], w.lo[world, i], w.hi[world, i])
    free = row_is_free(m.row_kind[world, i], x, w.lo[world, i], w.hi[world, i])
    w.row_free[world, i] = free
    w.x[world, i] = x
    w.y[world, i] = x
    w.y_hat[world, i] = x
    w.z[world, i] = 0.0
    w.z_hat[world, i] = 0.0
    return x, free


@wp.kernel
def padmm_start(warmstart_scale: float, m: ModelArrays, w: WorkArrays, row_lambda: wp.array2d(dtype=float),
                row_lambda_out: wp.array2d(dtype=float)):
    """Start every world's PADMM (a thread per row; row 0 writes the world's state): activate
    worlds with rows that have neither diverged nor been halted, keeping the last penalty; warm
    start from the last step's impulses row_lambda (padmm_warmstart_of), set each row's shift
    eta + rho_i for the factor (all active worlds are flagged for one) and the first iteration's
    right-hand side (padmm_rhs_of, with z_hat = 0). A world that does not iterate outputs zero
    impulses here (the others in padmm_update, when they stop). Also the worlds the step's
    projection moves: the active ones with bilateral joint rows (w.project)."""
    world, i = wp.tid()
    active = int(0)
    if w.row_count[world] > 0 and w.diverged[world] == 0 and w.halted[world] == 0:
        active = 1
    r = w.rho[world]
    if r <= 0.0:
        r = m.padmm_rho_init[world]
    if i == 0:
        if active != 0:
            wp.atomic_add(w.active_count, 0, 1)
        w.active[world] = active
        w.valid[world] = active
        w.needs_factor[world] = active
        w.demote[world] = 0
        w.converged[world] = 0
        w.iterations[world] = 0
        w.rho[world] = r
        w.momentum[world] = 1.0
        w.momentum_beta[world] = 0.0
        w.merit[world] = 1.0e30
        w.project[world] = wp.where(active != 0 and m.bilateral_row_count[world] > 0, 1, 0)
    if active == 0:
        row_lambda_out[world, i] = 0.0
        return
    x, free = padmm_warmstart_of(world, i, warmstart_scale, m, w, row_lambda)
    w.x_prev[world, i] = x
    eta = m.padmm_eta[world]
    r_i = row_penalty(free, r, m.padmm_rho_free[world])
    w.row_shift[world, i] = eta + r_i
    w.rhs[world, i] = -w.v_f[world, i] + eta * x + r_i * x  # padmm_rhs_of's sum with y_hat = x, z_hat = 0


@wp.func
def padmm_rhs_of(world: int, i: int, m: ModelArrays, w: WorkArrays):
    """rhs = -v_f + eta x + rho_i y_hat + z_hat with the row's penalty rho_i (and remember x)."""
    xi = w.x[world, i]
    w.x_prev[world, i] = xi
    de_saxce = float(0.0)
    if m.row_kind[world, i] == ROW_CONTACT_NORMAL and i + 2 < w.row_friction.shape[1]:
        de_saxce = w.row_friction[world, i] * wp.length(wp.vec2(w.z_hat[world, i + 1], w.z_hat[world, i + 2]))
    r = row_penalty(w.row_free[world, i], w.rho[world], m.padmm_rho_free[world])
    w.rhs[world, i] = -w.v_f[world, i] - de_saxce + m.padmm_eta[world] * xi + r * w.y_hat[world, i] + w.z_hat[world, i]


@wp.func
def project_cone(normal: float, t1: float, t2: float, mu: float):
    """Euclidean projection of (normal, t1, t2) onto the cone |t| <= mu normal."""
    tangent = wp.sqrt(t1 * t1 + t2 * t2)
    if tangent <= mu * normal:
        return wp.vec3(normal, t1, t2)
    if mu * tangent <= -normal:
        return wp.vec3(0.0)
    n = (normal + mu * tangent) / (1.0 + mu * mu)
    scale = mu * n / tangent
    return wp.vec3(n, scale * t1, scale * t2)


@wp.func
def padmm_project_of(world: int, i: int, m: ModelArrays, w: WorkArrays):
    """y = projection of x - z_hat / rho_i onto the row's set; z = z_hat - rho_i (x - y) (the last
    y and z into y_prev, z_prev). The thread of a contact normal row projects its whole triplet
    onto the friction cone. A free drive row whose bound comes into play is marked (row_free 2,
    demote) to lose its own penalty at the next penalty update, which refactors (padmm_decide;
    padmm_update's new shifts)."""
    kind = m.row_kind[world, i]
    if kind == ROW_CONTACT_TANGENT and i < w.row_count[world]:
        return
    r = w.rho[world]
    if kind == ROW_CONTACT_NORMAL and i < w.row_count[world]:
        v = wp.vec3(0.0)
        for k in range(3):
            v[k] = w.x[world, i + k] - w.z_hat[world, i + k] / r
        proj = project_cone(v[0], v[1], v[2], w.row_friction[world, i])
        for k in range(3):
            w.y_prev[world, i + k] = w.y[world, i + k]
            w.z_prev[world, i + k] = w.z[world, i + k]
            w.y[world, i + k] = proj[k]
            w.z[world, i + k] = w.z_hat[world, i + k] - r * (w.x[world, i + k] - proj[k])
        return
    free = w.row_free[world, i]
    r = row_penalty(free, r, m.padmm_rho_free[world])
    xi = w.x[world, i]
    zh = w.z_hat[world, i]
    yi = wp.clamp(xi - zh / r, w.lo[world, i], w.hi[world, i])
    if free == 1 and r != w.rho[world] and yi != xi - zh / r:
        w.row_free[world, i] = 2
        w.demote[world] = 1
    w.y_prev[world, i] = w.y[world, i]
    w.z_prev[world, i] = w.z[world, i]
    w.y[world, i] = yi
    w.z[world, i] = zh - r * (xi - yi)


@wp.func
def row_residuals(world: int, i: int, eta: float, rho: float, rho_free: float, m: ModelArrays, w: WorkArrays):
    """Row i's share of a world's PADMM residuals: |y|, primal |x - y|, dual, complementarity, the
    merit increment (rho_i |dy|^2 + |dz|^2 / rho_i), with the row's penalty rho_i, and the dual
    residual again where rho_i is the world's rho, else 0 (the penalty update balances the rows it
    rescales: a free row keeps its penalty, and its primal residual is zero)."""
    kind = m.row_kind[world, i]
    r = row_penalty(w.row_free[world, i], rho, rho_free)
    dy = w.y[world, i] - w.y_hat[world, i]
    dz = w.z[world, i] - w.z_hat[world, i]
    r_p = wp.abs(w.x[world, i] - w.y[world, i])
    r_d = wp.abs(eta * (w.x[world, i] - w.x_prev[world, i]) + r * dy)
    r_c = float(0.0)
    if kind == ROW_LIMIT:
        r_c = wp.abs(w.y[world, i] * w.z[world, i])
    elif kind == ROW_CONTACT_NORMAL:
        gap = (w.y[world, i] * w.z[world, i] + w.y[world, i + 1] * w.z[world, i + 1]
               + w.y[world, i + 2] * w.z[world, i + 2])
        r_c = wp.abs(gap)
    r_b = r_d
    if w.row_free[world, i] != 0 and rho_free > 0.0:
        r_b = 0.0
    return wp.abs(w.y[world, i]), r_p, r_d, r_c, r * dy * dy + dz * dz / r, r_b


@wp.func
def padmm_decide(world: int, r_p: float, r_d: float, r_c: float, r_b: float, scale: float, change: float,
                 max_iterations: int, relative_tolerance: float, rho_update_interval: int, adaptive_rho: int,
                 acceleration: int, padmm_tolerance: wp.array(dtype=float), rho: wp.array(dtype=float),
                 active: wp.array(dtype=wp.int32), converged: wp.array(dtype=wp.int32),
                 iterations: wp.array(dtype=wp.int32), momentum: wp.array(dtype=float),
                 momentum_beta: wp.array(dtype=float), merit: wp.array(dtype=float),
                 needs_factor: wp.array(dtype=wp.int32), residual_primal: wp.array(dtype=float),
                 residual_dual: wp.array(dtype=float), residual_complementarity: wp.array(dtype=float),
                 demote: wp.array(dtype=wp.int32), stall_ratio: float, stall_reference: wp.array(dtype=float)):
    """End of a PADMM iteration of one world from its residuals: count it, stop (returns 1) when
    converged, capped or stalled (stall_ratio > 0: the largest residual not below stall_ratio times
    its value STALL_WINDOW iterations earlier, kept in stall_reference), else set the momentum for
    padmm_accelerate_of and update the penalty from r_p against r_b, the dual residual of the rows
    whose penalty it sets (row_residuals; zero where all rows are free: no update), and at the same
    iterations give the world's penalty to drive rows that met their bounds (the arrays: WorkArrays'
    and ModelArrays' of the same names)."""
    r = rho[world]
    its = iterations[world] + 1
    iterations[world] = its
    residual_primal[world] = r_p
    residual_dual[world] = r_d
    residual_complementarity[world] = r_c
    tol = padmm_tolerance[world] + relative_tolerance * scale
    done = r_p <= tol and r_d <= tol and r_c <= tol * scale
    stalled = False
    if stall_ratio > 0.0 and its % STALL_WINDOW == 0:
        worst = wp.max(r_p, r_d)
        stalled = its >= 2 * STALL_WINDOW and worst > stall_ratio * stall_reference[world]
        stall_reference[world] = worst
    if done or stalled or its >= max_iterations:
        active[world] = 0
        if done:
            converged[world] = 1
        return 1
    beta = float(0.0)
    if acceleration != 0 and change < RESTART_RATIO * merit[world]:
        a = momentum[world]
        a_next = 0.5 * (1.0 + wp.sqrt(1.0 + 4.0 * a * a))
        beta = (a - 1.0) / a_next
        momentum[world] = a_next
    else:
        momentum[world] = 1.0
    merit[world] = change
    if adaptive_rho != 0 and its % rho_update_interval == 0:
        new_rho = rho_update(r, r_p, r_b)
        if new_rho != r:
            rho[world] = new_rho
            needs_factor[world] = 1
            momentum[world] = 1.0
            merit[world] = 1.0e30
            beta = 0.0
    if demote[world] != 0 and its % rho_update_interval == 0:
        demote[world] = 0
        needs_factor[world] = 1
    if needs_factor[world] != 0 and beta != 0.0:  # a row's penalty changed (a drive met its bound): restart
        momentum[world] = 1.0
        merit[world] = 1.0e30
        beta = 0.0
    momentum_beta[world] = beta
    return 0


@wp.kernel
def padmm_update(max_iterations: int, relative_tolerance: float, rho_update_interval: int, adaptive_rho: int,
                 acceleration: int, reshift: int, stall_ratio: float, m: ModelArrays, w: WorkArrays,
                 row_lambda_out: wp.array2d(dtype=float)):
    """The rest of a PADMM iteration of one world once its solve has given x (one thread block per
    world, its rows spread over the threads), in the order of the module's docstring: the
    projection (padmm_project_of); the residuals, the stop test, the momentum and the penalty
    update (padmm_decide); then for a world that stops its impulses (padmm_output_of), else the
    extrapolation (padmm_accelerate_of), the shifts of a new factor where one is asked for
    (``reshift``: refactors; the caller factors those worlds next) and the next iteration's
    right-hand side (padmm_rhs_of). One launch instead of five."""
    world, lane = wp.tid()
    if w.active[world] == 0:
        return
    stride = wp.block_dim()
    rows = w.y.shape[1]
    sweeps = (rows + stride - 1) // stride
    n = w.row_count[world]
    r = w.rho[world]
    eta = m.padmm_eta[world]
    cap = m.padmm_rho_free[world]
    if lane == 0:
        w.needs_factor[world] = 0  # the last iteration's factor is done
    for k in range(sweeps):
        i = lane + k * stride
        if i < rows:
            padmm_project_of(world, i, m, w)
    block_sync()  # a contact triplet's rows are projected by its normal row's thread
    r_p = float(0.0)
    r_d = float(0.0)
    r_c = float(0.0)
    r_b = float(0.0)
    change = float(0.0)
    scale = float(0.0)
    for k in range((n + stride - 1) // stride):
        i = lane + k * stride
        if i < n:
            s_i, p_i, d_i, c_i, m_i, b_i = row_residuals(world, i, eta, r, cap, m, w)
            scale = wp.max(scale, s_i)
            r_p = wp.max(r_p, p_i)
            r_d = wp.max(r_d, d_i)
            r_c = wp.max(r_c, c_i)
            r_b = wp.max(r_b, b_i)
            change += m_i
    r_p = block_max(r_p)
    r_d = block_max(r_d)
    r_c = block_max(r_c)
    r_b = block_max(r_b)
    scale = block_max(scale)
    change = block_sum(change)
    if lane == 0:
        if padmm_decide(world, r_p, r_d, r_c, r_b, scale, change, max_iterations, relative_tolerance,
                        rho_update_interval, adaptive_rho, acceleration, m.padmm_tolerance, w.rho, w.active,
                        w.converged, w.iterations, w.momentum, w.momentum_beta, w.merit, w.needs_factor,
                        w.residual_primal, w.residual_dual, w.residual_complementarity, w.demote, stall_ratio,
                        w.stall_reference) != 0:
            wp.atomic_sub(w.active_count, 0, 1)
    block_sync()  # the decision, the momentum and the penalty reach every thread
    if w.active[world] == 0:
        for k in range(sweeps):
            i = lane + k * stride
            if i < rows:
                padmm_output_of(world, i, w, row_lambda_out)
        return
    new_shifts = reshift != 0 and w.needs_factor[world] != 0
    r = w.rho[world]
    for k in range(sweeps):
        i = lane + k * stride
        if i < rows:
            padmm_accelerate_of(world, i, w)
            if new_shifts:
                if w.row_free[world, i] == 2:  # a drive that met its bound: the world's penalty from now on
                    w.row_free[world, i] = 0
                w.row_shift[world, i] = eta + row_penalty(w.row_free[world, i], r, cap)
    block_sync()  # the De Saxce term reads the triplet's other rows
    for k in range(sweeps):
        i = lane + k * stride
        if i < rows:
            padmm_rhs_of(world, i, m, w)


UPDATE_BLOCK = 64  # padmm_update's threads per world on a GPU (rows spread over them); one on the CPU


@wp.func
def padmm_accelerate_of(world: int, i: int, w: WorkArrays):
    """y_hat = y + beta (y - y_prev), z_hat = z + beta (z - z_prev)."""
    beta = w.momentum_beta[world]
    w.y_hat[world, i] = w.y[world, i] + beta * (w.y[world, i] - w.y_prev[world, i])
    w.z_hat[world, i] = w.z[world, i] + beta * (w.z[world, i] - w.z_prev[world, i])


@wp.func
def padmm_output_of(world: int, i: int, w: WorkArrays, row_lambda_out: wp.array2d(dtype=float)):
    """Impulses lambda = P y [N s]/[N m s]; zero on padded rows and in frozen worlds."""
    value = 0.0
    if i < w.row_count[world] and w.diverged[world] == 0 and w.halted[world] == 0:
        value = w.row_precond[world, i] * w.y[world, i]
    row_lambda_out[world, i] = value


def factor_flagged(model):
    """Factor P D P + diag(row_shift) for the worlds flagged in needs_factor (padmm_start, or
    padmm_update where a penalty changed; the next padmm_update clears the flags)."""
    work = model.work
    if model.linear_solver == "dense":
        dense.factor(work.delassus, work.row_shift, work.needs_factor, work.factor)
    elif model.linear_solver == "sparse":
        sparse.factor(model, work.row_shift, work.needs_factor)


def refactors(model) -> bool:
    """Whether an iteration can ask for new shifts, and so a new factor: with the penalty update,
    or with the free rows' own penalty (a drive row that meets its bound takes the world's). Not in
    a batch of bilateral joint rows alone when they keep their own penalty: their projection is the
    identity, so the primal residual and the balanced dual residual are both zero and no row is
    demoted (the batch's rows as packed, Model.has_unilateral_or_drive_rows)."""
    cfg = model.config
    if not (cfg.tuning.adaptive_rho or cfg.tuning.cap_joint_penalty):
        return False
    return bool(model.has_unilateral_or_drive_rows or not cfg.tuning.cap_joint_penalty)


def padmm_iteration(model, row_lambda_out):
    """One PADMM iteration of every active world (the body of the captured loop): the solve with
    the right-hand side the last launch left, padmm_update (which writes a stopping world's
    impulses into row_lambda_out (W, R)), and the new factors it asks for."""
    work, cfg = model.work, model.config
    if model.linear_solver == "dense":
        dense.solve(work.factor, work.rhs, work.active, work.x)
    else:
        sparse.solve(model, work.rhs, work.active, work.x)
    again = refactors(model)  # the new shifts and the factors that follow them
    wp.launch_tiled(padmm_update, dim=[model.num_worlds], block_dim=UPDATE_BLOCK, device=model.device,
                    inputs=[cfg.max_iterations, float(cfg.relative_tolerance), cfg.tuning.rho_update_interval,
                            int(cfg.tuning.adaptive_rho), int(cfg.tuning.acceleration), int(again),
                            float(cfg.tuning.stall_ratio), model.arrays, work.arrays, row_lambda_out])
    if again:
        factor_flagged(model)


def solve_padmm(model, row_lambda_warm, row_lambda_out):
    """Solve every world's dual problem (built by engine.dynamics) into row_lambda_out, starting
    from the impulses row_lambda_warm (W, R): padmm_start, the factor of every active world, then
    padmm_iteration until every world has stopped (captured as a conditional loop)."""
    work, tuning = model.work, model.config.tuning
    work.active_count.zero_()
    wp.launch(padmm_start, dim=(model.num_worlds, model.max_rows), device=model.device,
              inputs=[(1.0 - tuning.warmstart_decay) if tuning.warmstart else 0.0, model.arrays, work.arrays,
                      row_lambda_warm, row_lambda_out])
    if model.linear_solver == "sparse":
        sparse.prepare(model)
    factor_flagged(model)
    wp.capture_while(work.active_count, padmm_iteration, model=model, row_lambda_out=row_lambda_out)


__all__ = ["factor_flagged", "padmm_iteration", "project_cone", "refactors", "rho_update", "row_penalty",
           "solve_padmm"]
