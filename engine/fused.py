"""The fused step: one kernel launch advances every world by a whole step, one thread per world.

A small mechanism (a four-bar has 20 constraint rows) leaves a GPU idle between the ~40 kernels
and the conditional PADMM loop of the staged step (engine.step): the staged four-bar costs the same
0.8 ms per step for 1 world as for 4096. The fused kernel runs the same stages, serially in the
thread of its world, and calls the same per-joint, per-body and per-row functions as the staged
kernels (so both paths compute the same physics):

1. midpoint poses (Moreau-Jean), joint rows, free velocities, row operators and the dense
   preconditioned Delassus matrix of the world's n rows (no padding);
2. PADMM with the world's own early exit, its penalty updates refactoring the matrix in place
   (a serial Cholesky factor of the n x n matrix, no tile);
3. velocity update, pose integration, Gauss-Newton projection onto the joint constraints
   (the factor reused, or the bilateral block refactored, exactly as the staged dense path does);
4. divergence guard.

It takes batches without contact shapes whose padded rows fit ``FUSED_MAX_ROWS``: measured on an
H100 at 4096 worlds, the fused step wins at 24 rows (four-bar: 0.47 against 1.62 ms per step) and
40 rows (six-bar: 1.35 against 1.92 ms) and loses at 56 (10-link chain: 3.05 against 1.88 ms), where
one thread's serial factor and solves cost more than the staged path's launches. SolverConfig.step_kernel chooses:
"auto" (fused where it fits), "fused" (error where it does not) or "staged".
"""

from __future__ import annotations

import warp as wp

from engine.dynamics import body_term, free_velocity_of, row_operator_of
from engine.integrate import apply_impulses_of, apply_projection_of, guard_divergence_of, integrate_pose_of
from engine.joints import joint_residuals_of, joint_rows_of
from engine.model import ROW_ANGULAR, ROW_LINEAR
from engine.padmm import (
    padmm_accelerate_of,
    padmm_decide,
    padmm_output_of,
    padmm_project_of,
    padmm_rhs_of,
    padmm_warmstart_of,
    row_residuals,
)

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["FUSED_MAX_ROWS", "fused_block", "fused_fits", "fused_step"]

FUSED_MAX_ROWS = 48
WARPS_PER_SM = 4  # the fused step is latency-bound: spread the worlds so that every SM has a few warps


def fused_block(num_worlds: int, device) -> int:
    """Worlds (threads) per block: few enough that every SM gets WARPS_PER_SM warps, at most 32."""
    device = wp.get_device(device)
    if not device.is_cuda:
        return 1
    return max(1, min(32, num_worlds // (WARPS_PER_SM * device.sm_count)))


def fused_fits(has_contacts: bool, max_rows: int, dense: bool) -> bool:
    """Whether a batch can take the fused step."""
    return dense and not has_contacts and max_rows <= FUSED_MAX_ROWS


@wp.struct
class StepModel:
    """The model arrays the fused step reads."""

    body_count: wp.array(dtype=wp.int32)
    body_inv_mass: wp.array2d(dtype=float)
    body_inertia: wp.array2d(dtype=wp.mat33)
    body_inv_inertia: wp.array2d(dtype=wp.mat33)
    world_gravity: wp.array(dtype=wp.vec3)
    world_dt: wp.array(dtype=float)
    joint_count: wp.array(dtype=wp.int32)
    joint_type: wp.array2d(dtype=wp.int32)
    joint_parent: wp.array2d(dtype=wp.int32)
    joint_child: wp.array2d(dtype=wp.int32)
    joint_X_p: wp.array2d(dtype=wp.transform)
    joint_X_c: wp.array2d(dtype=wp.transform)
    joint_axis: wp.array2d(dtype=wp.vec3)
    joint_axis2: wp.array2d(dtype=wp.vec3)
    joint_row_start: wp.array2d(dtype=wp.int32)
    joint_inertia_row: wp.array2d(dtype=wp.int32)
    joint_drive_row: wp.array2d(dtype=wp.int32)
    joint_armature: wp.array2d(dtype=float)
    joint_damping: wp.array2d(dtype=float)
    joint_stiffness: wp.array2d(dtype=float)
    joint_drive_damping: wp.array2d(dtype=float)
    joint_effort_limit: wp.array2d(dtype=float)
    joint_limit_lower: wp.array2d(dtype=float)
    joint_limit_upper: wp.array2d(dtype=float)
    joint_limit_lower_row: wp.array2d(dtype=wp.int32)
    joint_limit_upper_row: wp.array2d(dtype=wp.int32)
    row_kind: wp.array2d(dtype=wp.int32)
    contact_row_start: wp.array(dtype=wp.int32)
    padmm_eta: wp.array(dtype=float)
    padmm_rho_init: wp.array(dtype=float)
    padmm_tolerance: wp.array(dtype=float)
    bilateral_row_count: wp.array(dtype=wp.int32)


@wp.struct
class StepWork:
    """The workspace arrays the fused step writes (those of engine.model.Workspace)."""

    body_qd_free: wp.array2d(dtype=wp.spatial_vector)
    body_q_mid: wp.array2d(dtype=wp.transform)
    row_count: wp.array(dtype=wp.int32)
    row_body_c: wp.array2d(dtype=wp.int32)
    row_body_p: wp.array2d(dtype=wp.int32)
    row_J_c: wp.array2d(dtype=wp.spatial_vector)
    row_J_p: wp.array2d(dtype=wp.spatial_vector)
    row_MJ_c: wp.array2d(dtype=wp.spatial_vector)
    row_MJ_p: wp.array2d(dtype=wp.spatial_vector)
    row_bias: wp.array2d(dtype=float)
    row_compliance: wp.array2d(dtype=float)
    row_lo: wp.array2d(dtype=float)
    row_hi: wp.array2d(dtype=float)
    row_residual: wp.array2d(dtype=float)
    row_precond: wp.array2d(dtype=float)
    row_friction: wp.array2d(dtype=float)
    v_f: wp.array2d(dtype=float)
    lo: wp.array2d(dtype=float)
    hi: wp.array2d(dtype=float)
    x: wp.array2d(dtype=float)
    x_prev: wp.array2d(dtype=float)
    y: wp.array2d(dtype=float)
    y_prev: wp.array2d(dtype=float)
    y_hat: wp.array2d(dtype=float)
    z: wp.array2d(dtype=float)
    z_prev: wp.array2d(dtype=float)
    z_hat: wp.array2d(dtype=float)
    rhs: wp.array2d(dtype=float)
    delta: wp.array2d(dtype=float)
    delassus: wp.array3d(dtype=float)
    factor: wp.array3d(dtype=float)
    rho: wp.array(dtype=float)
    sigma: wp.array(dtype=float)
    residual_primal: wp.array(dtype=float)
    residual_dual: wp.array(dtype=float)
    residual_complementarity: wp.array(dtype=float)
    momentum: wp.array(dtype=float)
    momentum_beta: wp.array(dtype=float)
    merit: wp.array(dtype=float)
    iterations: wp.array(dtype=wp.int32)
    converged: wp.array(dtype=wp.int32)
    valid: wp.array(dtype=wp.int32)
    project: wp.array(dtype=wp.int32)
    active: wp.array(dtype=wp.int32)
    needs_factor: wp.array(dtype=wp.int32)
    diverged: wp.array(dtype=wp.int32)
    halted: wp.array(dtype=wp.int32)


@wp.func
def is_bilateral(kind: int):
    return kind == ROW_LINEAR or kind == ROW_ANGULAR


@wp.func
def matrix_entry(world: int, i: int, j: int, bilateral_only: int, row_kind: wp.array2d(dtype=wp.int32),
                 matrix: wp.array3d(dtype=float)):
    """P D P (i, j), or with bilateral_only its bilateral joint block (identity elsewhere)."""
    if bilateral_only != 0:
        if not (is_bilateral(row_kind[world, i]) and is_bilateral(row_kind[world, j])):
            if i == j:
                return 1.0
            return 0.0
    return matrix[world, i, j]


@wp.func
def cholesky_of(world: int, n: int, sigma: float, bilateral_only: int, row_kind: wp.array2d(dtype=wp.int32),
                matrix: wp.array3d(dtype=float), factor: wp.array3d(dtype=float)):
    """Lower Cholesky factor of the world's n x n matrix + sigma I (column by column)."""
    for j in range(n):
        s = matrix_entry(world, j, j, bilateral_only, row_kind, matrix) + sigma
        for k in range(j):
            s -= factor[world, j, k] * factor[world, j, k]
        d = wp.sqrt(wp.max(s, 1.0e-30))
        factor[world, j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            t = matrix_entry(world, i, j, bilateral_only, row_kind, matrix)
            for k in range(j):
                t -= factor[world, i, k] * factor[world, j, k]
            factor[world, i, j] = t * inv


@wp.func
def cholesky_solve_of(world: int, n: int, factor: wp.array3d(dtype=float), rhs: wp.array2d(dtype=float),
                      x: wp.array2d(dtype=float)):
    """x = (L L^T)^-1 rhs for the world's n rows (forward, then backward substitution in x)."""
    for i in range(n):
        t = rhs[world, i]
        for k in range(i):
            t -= factor[world, i, k] * x[world, k]
        x[world, i] = t / factor[world, i, i]
    for step in range(n):
        i = n - 1 - step
        t = x[world, i]
        for k in range(i + 1, n):
            t -= factor[world, k, i] * x[world, k]
        x[world, i] = t / factor[world, i, i]


@wp.func
def delassus_lower_of(world: int, i: int, row_body_p: wp.array2d(dtype=wp.int32),
                      row_body_c: wp.array2d(dtype=wp.int32), row_J_c: wp.array2d(dtype=wp.spatial_vector),
                      row_J_p: wp.array2d(dtype=wp.spatial_vector), row_MJ_c: wp.array2d(dtype=wp.spatial_vector),
                      row_MJ_p: wp.array2d(dtype=wp.spatial_vector), row_compliance: wp.array2d(dtype=float),
                      row_precond: wp.array2d(dtype=float), matrix: wp.array3d(dtype=float)):
    """Row i of P D P left of the diagonal, mirrored: engine.dynamics.delassus_entry's arithmetic with
    row i loaded once and the pairs of rows without a common body skipped (their entry is 0)."""
    ci = row_body_c[world, i]
    pi = row_body_p[world, i]
    Jci = row_J_c[world, i]
    Jpi = row_J_p[world, i]
    precond_i = row_precond[world, i]
    for j in range(i + 1):
        cj = row_body_c[world, j]
        pj = row_body_p[world, j]
        d = float(0.0)
        if (ci >= 0 and (ci == cj or ci == pj)) or (pi >= 0 and (pi == cj or pi == pj)):
            MJ_c = row_MJ_c[world, j]
            MJ_p = row_MJ_p[world, j]
            d = body_term(ci, Jci, cj, MJ_c) + body_term(ci, Jci, pj, MJ_p)
            d += body_term(pi, Jpi, cj, MJ_c) + body_term(pi, Jpi, pj, MJ_p)
        if i == j:
            d += row_compliance[world, i]
        value = precond_i * d * row_precond[world, j]
        matrix[world, i, j] = value
        matrix[world, j, i] = value


@wp.kernel(enable_backward=False)
def fused_step_kernel(
    m: StepModel,
    w: StepWork,
    moreau: int,
    baumgarte: float,
    limit_margin: float,
    limit_stabilization: float,
    warmstart_scale: float,
    max_iterations: int,
    relative_tolerance: float,
    rho_update_interval: int,
    adaptive_rho: int,
    acceleration: int,
    position_iterations: int,
    mask_projection: int,
    velocity_update: int,
    max_speed: float,
    body_q_in: wp.array2d(dtype=wp.transform),
    body_qd_in: wp.array2d(dtype=wp.spatial_vector),
    row_lambda_in: wp.array2d(dtype=float),
    joint_target_position: wp.array2d(dtype=float),
    joint_target_velocity: wp.array2d(dtype=float),
    joint_effort: wp.array2d(dtype=float),
    body_f: wp.array2d(dtype=wp.spatial_vector),
    # out
    body_q_out: wp.array2d(dtype=wp.transform),
    body_qd_out: wp.array2d(dtype=wp.spatial_vector),
    row_lambda_out: wp.array2d(dtype=float),
):
    """One whole step of one world (engine.step's stages in one thread)."""
    world = wp.tid()
    nb = m.body_count[world]
    fraction = 1.0
    # 1. configuration of the dynamics: the midpoint (Moreau-Jean) or the start of the step
    for b in range(nb):
        if moreau != 0:
            integrate_pose_of(world, b, m.body_count, m.world_dt, 0.5, body_q_in, body_qd_in, w.body_q_mid)
        else:
            w.body_q_mid[world, b] = body_q_in[world, b]
    if moreau != 0:
        fraction = 0.5
    for j in range(m.joint_count[world]):
        joint_rows_of(world, j, m.joint_count, m.joint_type, m.joint_parent, m.joint_child, m.joint_X_p, m.joint_X_c,
                      m.joint_axis, m.joint_axis2, m.joint_row_start, m.joint_inertia_row, m.joint_drive_row,
                      m.joint_armature, m.joint_damping, m.joint_stiffness, m.joint_drive_damping,
                      m.joint_effort_limit, m.joint_limit_lower, m.joint_limit_upper, m.joint_limit_lower_row,
                      m.joint_limit_upper_row, m.world_dt, baumgarte, limit_margin, limit_stabilization,
                      w.body_q_mid, body_qd_in, joint_target_position, joint_target_velocity, joint_effort,
                      w.row_J_c, w.row_J_p, w.row_bias, w.row_compliance, w.row_lo, w.row_hi, w.row_residual)
    # 2. the dual problem
    n = w.row_count[world]
    max_rows = row_lambda_out.shape[1]
    for b in range(nb):
        free_velocity_of(world, b, m.body_count, m.body_inv_mass, m.body_inertia, m.body_inv_inertia, m.world_gravity,
                         m.world_dt, w.body_q_mid, body_qd_in, body_f, w.body_qd_free)
    for i in range(max_rows):
        row_operator_of(world, i, m.row_kind, m.contact_row_start, m.body_inv_mass, m.body_inv_inertia, w.row_count,
                        w.row_body_p, w.row_body_c, w.body_q_mid, w.body_qd_free, w.row_J_c, w.row_J_p, w.row_bias,
                        w.row_compliance, w.row_lo, w.row_hi, w.row_MJ_c, w.row_MJ_p, w.row_precond, w.v_f, w.lo,
                        w.hi)
    for i in range(n):
        delassus_lower_of(world, i, w.row_body_p, w.row_body_c, w.row_J_c, w.row_J_p, w.row_MJ_c, w.row_MJ_p,
                          w.row_compliance, w.row_precond, w.delassus)
    # 3. PADMM (padmm_setup, padmm_warmstart, then iterations until this world stops)
    eta = m.padmm_eta[world]
    active = int(0)
    if n > 0 and w.diverged[world] == 0 and w.halted[world] == 0:
        active = 1
    w.active[world] = active
    w.valid[world] = active
    w.needs_factor[world] = 0
    w.converged[world] = 0
    w.iterations[world] = 0
    if w.rho[world] <= 0.0:
        w.rho[world] = m.padmm_rho_init[world]
    w.momentum[world] = 1.0
    w.momentum_beta[world] = 0.0
    w.merit[world] = 1.0e30
    if active != 0:
        for i in range(n):
            padmm_warmstart_of(world, i, warmstart_scale, row_lambda_in, w.row_precond, w.active, w.lo, w.hi, w.x,
                               w.y, w.y_hat, w.z, w.z_hat)
        w.sigma[world] = eta + w.rho[world]
        cholesky_of(world, n, w.sigma[world], 0, m.row_kind, w.delassus, w.factor)
    while active != 0:
        for i in range(n):
            padmm_rhs_of(world, i, m.padmm_eta, m.row_kind, w.rho, w.active, w.row_friction, w.v_f, w.x, w.y_hat,
                         w.z_hat, w.x_prev, w.rhs)
        cholesky_solve_of(world, n, w.factor, w.rhs, w.x)
        for i in range(n):
            padmm_project_of(world, i, m.row_kind, w.row_count, w.row_friction, w.rho, w.active, w.lo, w.hi, w.x,
                             w.z_hat, w.y, w.z, w.y_prev, w.z_prev)
        r = w.rho[world]
        r_p = float(0.0)
        r_d = float(0.0)
        r_c = float(0.0)
        change = float(0.0)
        scale = float(0.0)
        for i in range(n):
            s_i, p_i, d_i, c_i, m_i = row_residuals(world, i, eta, r, m.row_kind, w.x, w.x_prev, w.y, w.y_hat, w.z,
                                                    w.z_hat)
            scale = wp.max(scale, s_i)
            r_p = wp.max(r_p, p_i)
            r_d = wp.max(r_d, d_i)
            r_c = wp.max(r_c, c_i)
            change += m_i
        if padmm_decide(world, r_p, r_d, r_c, scale, change, max_iterations, relative_tolerance,
                        rho_update_interval, adaptive_rho, acceleration, m.padmm_tolerance, w.rho, w.active,
                        w.converged, w.iterations, w.momentum, w.momentum_beta, w.merit, w.needs_factor,
                        w.residual_primal, w.residual_dual, w.residual_complementarity) != 0:
            active = 0
        else:
            for i in range(n):
                padmm_accelerate_of(world, i, w.active, w.momentum_beta, w.y, w.y_prev, w.z, w.z_prev, w.y_hat,
                                    w.z_hat)
            if w.needs_factor[world] != 0:
                w.sigma[world] = eta + w.rho[world]
                cholesky_of(world, n, w.sigma[world], 0, m.row_kind, w.delassus, w.factor)
                w.needs_factor[world] = 0
    for i in range(max_rows):
        padmm_output_of(world, i, w.row_count, w.row_precond, w.y, w.diverged, w.halted, row_lambda_out)
    # 4. velocity update and poses
    for b in range(nb):
        apply_impulses_of(world, b, m.body_count, w.row_count, w.row_body_c, w.row_body_p, w.row_MJ_c, w.row_MJ_p,
                          row_lambda_out, w.row_precond, w.body_qd_free, body_qd_out)
    for b in range(nb):
        integrate_pose_of(world, b, m.body_count, m.world_dt, fraction, w.body_q_mid, body_qd_out, body_q_out)
    # 5. Gauss-Newton projection onto the joint constraints (engine.integrate.project_positions)
    project = int(0)
    if position_iterations > 0 and w.valid[world] != 0 and m.bilateral_row_count[world] > 0:
        project = 1
    w.project[world] = project
    if project != 0:
        target = eta + m.padmm_rho_init[world]
        if mask_projection != 0 or w.sigma[world] > target:
            w.sigma[world] = target
            cholesky_of(world, n, target, mask_projection, m.row_kind, w.delassus, w.factor)
        for _it in range(position_iterations):
            for j in range(m.joint_count[world]):
                joint_residuals_of(world, j, m.joint_count, m.joint_type, m.joint_parent, m.joint_child, m.joint_X_p,
                                   m.joint_X_c, m.joint_axis, m.joint_axis2, m.joint_row_start, m.joint_inertia_row,
                                   m.joint_drive_row, body_q_out, w.row_residual)
            for i in range(n):
                value = 0.0
                if is_bilateral(m.row_kind[world, i]):
                    value = -w.row_precond[world, i] * w.row_residual[world, i]
                w.rhs[world, i] = value
            cholesky_solve_of(world, n, w.factor, w.rhs, w.delta)
            for b in range(nb):
                apply_projection_of(world, b, m.body_count, w.row_count, w.row_body_c, w.row_body_p, w.valid,
                                    m.world_dt, velocity_update, fraction, w.row_MJ_c, w.row_MJ_p, w.row_precond,
                                    w.delta, body_q_out, body_qd_out)
    # 6. divergence guard
    guard_divergence_of(world, m.body_count, body_q_in, body_qd_in, w.halted, max_speed, body_q_out, body_qd_out,
                        w.diverged)


def _filled(struct_type, source):
    """An instance of a Warp struct whose fields are the same-named arrays of ``source``."""
    instance = struct_type()
    for name in struct_type.vars:
        setattr(instance, name, getattr(source, name))
    return instance


def fused_step(model, state_in, state_out, control) -> None:
    """Advance every world of a fused batch (engine.pack chose it) by one step in one launch."""
    if model._fused_structs is None:
        model._fused_structs = (_filled(StepModel, model), _filled(StepWork, model.work))
    m, w = model._fused_structs
    cfg = model.config
    if model.fused_block is None:
        model.fused_block = fused_block(model.num_worlds, model.device)
    wp.launch(fused_step_kernel, dim=model.num_worlds, block_dim=model.fused_block, device=model.device,
              inputs=[m, w, int(cfg.integrator.value == "moreau"), float(cfg.baumgarte), float(cfg.limit_margin),
                      float(cfg.limit_stabilization), 1.0 if cfg.warmstart else 0.0, cfg.max_iterations,
                      float(cfg.relative_tolerance), cfg.rho_update_interval, int(cfg.adaptive_rho),
                      int(cfg.acceleration), cfg.position_iterations if model.has_bilateral_rows else 0,
                      int(model.has_unilateral_or_drive_rows), int(cfg.projection_velocity_update),
                      float(cfg.max_speed), state_in.body_q, state_in.body_qd, state_in.row_lambda,
                      control.joint_target_position, control.joint_target_velocity, control.joint_effort,
                      control.body_f],
              outputs=[state_out.body_q, state_out.body_qd, state_out.row_lambda])
