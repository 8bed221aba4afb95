"""The fused step: one kernel launch advances every world by a whole step, one thread block per world.

A small mechanism (a four-bar has 24 constraint rows) leaves a GPU idle between the ~40 kernels
and the conditional PADMM loop of the staged step (engine.step). The fused kernel runs the same
stages for one world in one warp and calls the same per-joint, per-body and per-row functions as
the staged kernels (so both paths compute the same physics); the lanes share the world's bodies,
joints and rows, with a block barrier wherever a stage reads what another lane wrote:

1. midpoint poses (Moreau-Jean), joint rows, free velocities, row operators and the dense
   preconditioned Delassus matrix of the world's n rows, in shared memory;
2. PADMM with the world's own early exit, its penalty updates refactoring the matrix
   (engine.linalg.dense's per-lane Cholesky factor and solves, in shared memory);
3. velocity update, pose integration, Gauss-Newton projection onto the joint constraints
   (the factor reused, or the bilateral block refactored, exactly as the staged dense path does);
4. divergence guard.

Shared memory keeps the factor's and the substitutions' dependent loads on the SM; a register cap
(FUSED_REGISTERS) lets more worlds share an SM. On the CPU a block is one thread and the same code
runs serially. It takes batches without contact shapes whose padded rows fit ``FUSED_MAX_ROWS``;
Tuning.step_kernel chooses: "auto" (fused where it fits), "fused" (error where it does not)
or "staged". On a GPU, small problems (INVERSE_MAX_ROWS) solve through G = L^-1, formed after
every factor, instead of substituting (fused_inverse); the lanes share a body's sums over rows
and a joint's rows where a few lanes would otherwise work while the rest wait (fused_sharing);
a block of one warp's first lanes reduces the residuals with warp shuffles (engine.linalg.lanes).
Per-stage cycle counts: fused_profile. Measurements behind these choices, and what was tried and
not kept: benchmarks/results/README.md, "Maximal path: design notes".
"""

from typing import Any

import numpy as np
import warp as wp

from engine.dynamics import body_term, forced_free_velocity_of, free_velocity_of, row_operator_of
from engine.integrate import (
    add_impulse_of,
    add_row_share,
    advance_pose_of,
    guard_divergence_of,
    integrate_pose_of,
    midpoint_pose_of,
    move_body_of,
    projection_penalty,
)
from engine.joints import JOINT_PARTS, joint_residuals_of, joint_rows_of
from engine.linalg.dense import cholesky_lanes, cholesky_solve_lanes, inverse_solve_lanes, triangular_inverse_lanes
from engine.linalg.lanes import block_max, block_sum, block_sync, clock, group_sum, lane_max2, lane_reduce6, tile_set
from engine.model import ROW_ANGULAR, ROW_LINEAR, ForceArrays, ModelArrays, WorkArrays
from engine.padmm import (
    padmm_accelerate_of,
    padmm_decide,
    padmm_output_of,
    padmm_project_of,
    padmm_rhs_of,
    padmm_warmstart_of,
    row_penalty,
    row_residuals,
)

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["FUSED_MAX_ROWS", "FUSED_REGISTERS", "SHARE_BODY_SUMS", "SHARE_JOINT_PARTS", "STAGES", "fused_block",
           "fused_fits", "fused_inverse", "fused_profile", "fused_sharing", "fused_step", "sharing_used", "warp_lanes"]

FUSED_MAX_ROWS = 64
FUSED_REGISTERS = 128  # register cap per thread: 158 uncapped leave 12 worlds per SM, 128 allow 16


def fused_block(device) -> int:
    """Threads (lanes) per world of the fused step: one warp (benchmarks/results/README.md, "The fused
    step"); one on the CPU, where a block is one thread and the lanes' loops run serially."""
    if not wp.get_device(device).is_cuda:
        return 1
    return 32


def fused_fits(has_contacts: bool, max_rows: int, dense: bool) -> bool:
    """Whether a batch can take the fused step."""
    return dense and not has_contacts and max_rows <= FUSED_MAX_ROWS


def warp_lanes(block: int) -> bool:
    """Whether a fused block of ``block`` threads is one warp's first lanes (a power of two up to
    32), whose sums and maxima then take warp shuffles instead of shared-memory tile reductions."""
    return 1 < block <= 32 and block & (block - 1) == 0


TILE_ROWS = 16  # the shared matrices are sized in steps of this many rows (one kernel per size; the sizes of
# engine.linalg.lanes.tile_set)


# On a GPU, worlds padded to at most this many rows solve with G = L^-1 (fused_inverse; measured:
# benchmarks/results/README.md, "Maximal path: design notes").
INVERSE_MAX_ROWS = 32


def fused_inverse(device, max_rows: int) -> bool:
    """Whether the fused step solves through G = L^-1 instead of substituting: on a GPU, where a
    substitution is a chain of 2 n dependent steps and a product with G none, for padded problems
    of at most INVERSE_MAX_ROWS rows (G takes a third matrix tile of shared memory). On the CPU a
    block is one thread and forming G only adds work."""
    return wp.get_device(device).is_cuda and max_rows <= INVERSE_MAX_ROWS


@wp.func
def delassus_lower_of(world: int, i: int, w: WorkArrays, matrix: Any):
    """Row i of P D P left of the diagonal, mirrored, into the world's shared matrix tile:
    engine.dynamics.delassus_entry's arithmetic with row i loaded once and the pairs of rows
    without a common body skipped (their entry is 0)."""
    ci = w.row_body_c[world, i]
    pi = w.row_body_p[world, i]
    Jci = w.row_J_c[world, i]
    Jpi = w.row_J_p[world, i]
    precond_i = w.row_precond[world, i]
    for j in range(i + 1):
        cj = w.row_body_c[world, j]
        pj = w.row_body_p[world, j]
        d = float(0.0)
        if (ci >= 0 and (ci == cj or ci == pj)) or (pi >= 0 and (pi == cj or pi == pj)):
            MJ_c = w.row_MJ_c[world, j]
            MJ_p = w.row_MJ_p[world, j]
            d = body_term(ci, Jci, cj, MJ_c) + body_term(ci, Jci, pj, MJ_p)
            d += body_term(pi, Jpi, cj, MJ_c) + body_term(pi, Jpi, pj, MJ_p)
        if i == j:
            d += w.row_compliance[world, i]
        value = precond_i * d * w.row_precond[world, j]
        tile_set(matrix, i, j, value)
        tile_set(matrix, j, i, value)


# Stages of the fused step whose cycles fused_profile counts (summed over a stage's passes).
STAGES = ("rows", "delassus", "factor", "padmm_rhs", "padmm_solve", "padmm_project", "padmm_decide",
          "padmm_accelerate_refactor", "velocity", "projection_factor", "projection_residuals", "projection_rhs",
          "projection_solve", "projection_apply", "end_of_step")
_STAGE = {name: k for k, name in enumerate(STAGES)}


@wp.func
def tick(stamps: wp.array2d(dtype=wp.int64), world: int, k: int, lane: int, last: wp.int64):
    """Lane 0 adds the cycles since ``last`` to stage k's count; returns the counter now."""
    now = clock()
    if lane == 0:
        stamps[world, k] = stamps[world, k] + (now - last)
    return now

_KERNELS = {}


# How the lanes share a world's joints and bodies (bit flags; engine.pack leaves model.fused_sharing
# None: fused_sharing chooses): a joint's rows one part each (engine.joints.JOINT_PARTS) instead of
# a joint each, where one pass of the lanes takes every part; each body's sums over rows by a group
# of lanes (body_row_sum) instead of one lane.
SHARE_JOINT_PARTS = wp.constant(1)
SHARE_BODY_SUMS = wp.constant(2)


def fused_sharing(device) -> int:
    """Both forms of sharing on a GPU; none on the CPU (one lane: they would only add work)."""
    return int(SHARE_JOINT_PARTS | SHARE_BODY_SUMS) if wp.get_device(device).is_cuda else 0


def sharing_used(model) -> int:
    """The sharing flags of model.fused_sharing (None: fused_sharing), less the body sums' groups
    on the CPU and for blocks that are not whole warps (their shuffles need every lane of a warp)."""
    sharing = fused_sharing(model.device) if model.fused_sharing is None else int(model.fused_sharing)
    block = fused_block(model.device) if model.fused_block is None else model.fused_block
    if not model.device.is_cuda or block % 32 != 0:
        sharing &= ~int(SHARE_BODY_SUMS)
    return sharing


@wp.func
def joint_task(t: int, nj: int, split: int):
    """Joint and part of lane task t: with ``split`` part t // nj of joint t % nj (the lanes that
    take the same part of different joints run the same branch), else all of joint t."""
    if split != 0:
        return t % nj, t // nj
    return t, -1


@wp.func
def body_group(nb: int, lanes: int):
    """Lanes that share each body's sum over rows (body_row_sum): a power of two, as many as the
    block holds for all nb bodies at once (at most a warp; one on the CPU)."""
    g = int(1)
    while 2 * g <= 32 and 2 * g * nb <= lanes:
        g = 2 * g
    return g


@wp.func
def body_row_sum(world: int, t: int, g: int, nb: int, n: int, w: WorkArrays, weight: wp.array2d(dtype=float),
                 scale_by_precond: int):
    """The sum over the rows touching body t // g of (M^-1 J^T)_b weight (times P when asked;
    engine.integrate.row_sum_listed), shared by the aligned group of g lanes
    t, t + 1, ..: each sums the rows t % g, t % g + g, .. (whose loads are then in flight on g
    lanes at once instead of one after the other on one), and the group adds its parts with warp
    shuffles; every lane of the group gets the total (zero past the last body). Every lane of the
    warp must call it."""
    b = t // g
    total = wp.spatial_vector()
    if b < nb:
        for i in range(t % g, n, g):
            total = add_row_share(total, world, b, i, w.row_body_c, w.row_body_p, w.row_MJ_c, w.row_MJ_p, weight,
                                  w.row_precond, scale_by_precond)
    if g > 1:
        total = wp.spatial_vector(group_sum(total[0], g), group_sum(total[1], g), group_sum(total[2], g),
                                  group_sum(total[3], g), group_sum(total[4], g), group_sum(total[5], g))
    return total


def _make_kernel(tile_rows: int, max_registers: int, timed: bool = False, with_inverse: bool = False,
                 compensated: bool = True, shuffled: bool = False, forced: bool = False):
    """The fused step for worlds of at most tile_rows rows: the world's matrix and factor live in
    shared-memory tiles of that size (the loads of a factor or substitution never leave the SM).
    With ``timed`` lane 0 adds each stage's cycles (STAGES) into stamps. With ``with_inverse`` the
    solves multiply by G = L^-1, formed once per factor, instead of substituting. ``compensated``:
    Tuning.compensated_state (without it the low parts are neither read nor written).
    ``shuffled``: the block is one warp's first lanes (warp_lanes), whose sums and maxima over the
    world's rows take warp shuffles (lane_reduce6, lane_max2) instead of tile reductions.
    ``forced``: the batch has force slots, whose wrenches join body_f in the free velocities
    (engine.dynamics.forced_free_velocity_of, as the staged step: midpoint poses, starting twists)."""
    inverse_rows = tile_rows if with_inverse else 1
    comp = 1 if compensated else 0

    @wp.func
    def factor_world(world: int, lane: int, lanes: int, n: int, sigma: float, sigma_free: float, bilateral_only: int,
                     row_kind: wp.array2d(dtype=wp.int32), row_free: wp.array2d(dtype=wp.int32), D: Any, F: Any,
                     G: Any):
        """cholesky_lanes into F, then (with_inverse) G = F^-1."""
        cholesky_lanes(world, lane, lanes, n, sigma, sigma_free, bilateral_only, row_kind, row_free, D, F)
        if wp.static(with_inverse):
            triangular_inverse_lanes(lane, lanes, n, F, G)

    @wp.func
    def solve_world(world: int, lane: int, lanes: int, n: int, F: Any, G: Any, rhs: wp.array2d(dtype=float),
                    x: wp.array2d(dtype=float), acc: Any, sol: Any):
        """x = (F F^T)^-1 rhs: products with G (with_inverse) or substitutions with F."""
        if wp.static(with_inverse):
            inverse_solve_lanes(world, lane, lanes, n, G, rhs, x, acc, sol)
        else:
            cholesky_solve_lanes(world, lane, lanes, n, F, rhs, x, acc, sol)

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=max_registers)
    def fused_step_kernel(
        m: ModelArrays,
        fa: ForceArrays,
        w: WorkArrays,
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
        stall_ratio: float,
        position_iterations: int,
        mask_projection: int,
        velocity_update: int,
        velocity_floor: float,
        skip_floor: float,
        skip_floor_angular: float,
        max_speed: float,
        sharing: int,
        project_output: int,
        body_q_in: wp.array2d(dtype=wp.transform),
        body_qd_in: wp.array2d(dtype=wp.spatial_vector),
        body_q_offset_in: wp.array2d(dtype=wp.spatial_vector),
        body_q_low_in: wp.array2d(dtype=wp.transform),
        body_qd_low_in: wp.array2d(dtype=wp.spatial_vector),
        body_q_next_in: wp.array2d(dtype=wp.transform),
        row_lambda_in: wp.array2d(dtype=float),
        joint_target_position: wp.array2d(dtype=float),
        joint_target_velocity: wp.array2d(dtype=float),
        joint_effort: wp.array2d(dtype=float),
        body_f: wp.array2d(dtype=wp.spatial_vector),
        # out
        body_q_out: wp.array2d(dtype=wp.transform),
        body_qd_out: wp.array2d(dtype=wp.spatial_vector),
        body_q_offset_out: wp.array2d(dtype=wp.spatial_vector),
        body_q_low_out: wp.array2d(dtype=wp.transform),
        body_qd_low_out: wp.array2d(dtype=wp.spatial_vector),
        body_q_next_out: wp.array2d(dtype=wp.transform),
        row_lambda_out: wp.array2d(dtype=float),
        stamps: wp.array2d(dtype=wp.int64),
    ):
        """One whole step of one world (engine.step's stages) in one thread block: the lanes share the
        world's bodies, joints and rows, with a barrier wherever a stage reads what another lane wrote.
        Every loop bound and branch that contains a barrier is the same on all lanes of the block."""
        world, lane = wp.tid()
        lanes = wp.block_dim()
        D = wp.tile_zeros(shape=(tile_rows, tile_rows), dtype=float, storage="shared")  # P D P of the world
        F = wp.tile_zeros(shape=(tile_rows, tile_rows), dtype=float, storage="shared")  # its Cholesky factor
        G = wp.tile_zeros(shape=(inverse_rows, inverse_rows), dtype=float, storage="shared")  # L^-1
        acc = wp.tile_zeros(shape=tile_rows, dtype=float, storage="shared")  # substitution vectors
        sol = wp.tile_zeros(shape=tile_rows, dtype=float, storage="shared")
        nb = m.body_count[world]
        nj = m.joint_count[world]
        last = wp.int64(0)
        if wp.static(timed):
            last = clock()
        # 1. configuration of the dynamics: the midpoint (Moreau-Jean) or the start of the step
        for b in range(lane, nb, lanes):
            if moreau != 0:
                midpoint_pose_of(world, b, m, w, body_q_in, body_q_offset_in, body_qd_in, body_q_low_in, body_q_next_in,
                                 comp)
            else:
                w.body_q_mid[world, b] = body_q_in[world, b]
                if wp.static(compensated):
                    w.body_q_mid_low[world, b] = body_q_low_in[world, b]
        block_sync()
        joint_tasks = nj
        split = int(0)
        # split where one pass of the lanes takes every part (more passes were slower); a one-thread
        # block (the CPU) runs the parts one after the other, when asked
        if (sharing & SHARE_JOINT_PARTS) != 0 and (nj * JOINT_PARTS <= lanes or lanes == 1):
            split = 1
            joint_tasks = nj * JOINT_PARTS
        for t in range(lane, joint_tasks, lanes):
            j, part = joint_task(t, nj, split)
            joint_rows_of(world, j, part, m, w, baumgarte, limit_margin, limit_stabilization, w.body_q_mid,
                          w.body_q_mid_low, body_qd_in, joint_target_position, joint_target_velocity, joint_effort)
        # 2. the dual problem
        n = w.row_count[world]
        max_rows = row_lambda_out.shape[1]
        for b in range(lane, nb, lanes):  # (every midpoint pose is set: block_sync after stage 1)
            if wp.static(forced):
                forced_free_velocity_of(world, b, m, fa, w, w.body_q_mid, body_qd_in, body_qd_low_in, body_f,
                                        joint_effort, comp, body_qd_low_out)
            else:
                free_velocity_of(world, b, m, w, w.body_q_mid, body_qd_in, body_qd_low_in, body_f, comp,
                                 body_qd_low_out)
        block_sync()
        for i in range(lane, max_rows, lanes):
            row_operator_of(world, i, m, w, w.body_q_mid)
        block_sync()
        if wp.static(timed):
            last = tick(stamps, world, wp.static(_STAGE["rows"]), lane, last)
        for i in range(lane, n, lanes):
            delassus_lower_of(world, i, w, D)
        # 3. PADMM (as engine.padmm's padmm_start, then iterations until this world stops)
        eta = m.padmm_eta[world]
        active = int(0)
        if n > 0 and w.diverged[world] == 0 and w.halted[world] == 0:
            active = 1
        valid = active
        rho = w.rho[world]
        cap = m.padmm_rho_free[world]
        if rho <= 0.0:
            rho = m.padmm_rho_init[world]
        sigma = eta + rho
        block_sync()  # every lane has read rho before lane 0 writes it
        if wp.static(timed):
            last = tick(stamps, world, wp.static(_STAGE["delassus"]), lane, last)
        if lane == 0:
            w.active[world] = active
            w.valid[world] = active
            w.needs_factor[world] = 0
            w.demote[world] = 0
            w.converged[world] = 0
            w.iterations[world] = 0
            w.rho[world] = rho
            w.momentum[world] = 1.0
            w.momentum_beta[world] = 0.0
            w.merit[world] = 1.0e30
        block_sync()
        if active != 0:
            for i in range(lane, n, lanes):
                padmm_warmstart_of(world, i, warmstart_scale, m, w, row_lambda_in)
            block_sync()  # the factor reads every row's free flag
            factor_world(world, lane, lanes, n, sigma, eta + row_penalty(1, rho, cap), 0, m.row_kind, w.row_free,
                         D, F, G)
        if wp.static(timed):
            last = tick(stamps, world, wp.static(_STAGE["factor"]), lane, last)
        while active != 0:
            for i in range(lane, n, lanes):
                padmm_rhs_of(world, i, m, w)
            block_sync()
            if wp.static(timed):
                last = tick(stamps, world, wp.static(_STAGE["padmm_rhs"]), lane, last)
            solve_world(world, lane, lanes, n, F, G, w.rhs, w.x, acc, sol)
            if wp.static(timed):
                last = tick(stamps, world, wp.static(_STAGE["padmm_solve"]), lane, last)
            r = w.rho[world]
            r_p = float(0.0)
            r_d = float(0.0)
            r_c = float(0.0)
            r_b = float(0.0)
            change = float(0.0)
            scale = float(0.0)
            for i in range(lane, n, lanes):
                padmm_project_of(world, i, m, w)
                s_i, p_i, d_i, c_i, m_i, b_i = row_residuals(world, i, eta, r, cap, m, w)
                scale = wp.max(scale, s_i)
                r_p = wp.max(r_p, p_i)
                r_d = wp.max(r_d, d_i)
                r_c = wp.max(r_c, c_i)
                r_b = wp.max(r_b, b_i)
                change += m_i
            if wp.static(shuffled):
                reduced = lane_reduce6(scale, r_p, r_d, r_c, r_b, change, lanes)
                scale = reduced[0]
                r_p = reduced[1]
                r_d = reduced[2]
                r_c = reduced[3]
                r_b = reduced[4]
                change = reduced[5]
            elif lanes > 1:
                scale = block_max(scale)
                r_p = block_max(r_p)
                r_d = block_max(r_d)
                r_c = block_max(r_c)
                r_b = block_max(r_b)
                change = block_sum(change)
            if wp.static(timed):
                last = tick(stamps, world, wp.static(_STAGE["padmm_project"]), lane, last)
            if lane == 0:
                padmm_decide(world, r_p, r_d, r_c, r_b, scale, change, max_iterations, relative_tolerance,
                             rho_update_interval, adaptive_rho, acceleration, m.padmm_tolerance, w.rho, w.active,
                             w.converged, w.iterations, w.momentum, w.momentum_beta, w.merit, w.needs_factor,
                             w.residual_primal, w.residual_dual, w.residual_complementarity, w.demote, stall_ratio,
                             w.stall_reference)
            block_sync()
            if wp.static(timed):
                last = tick(stamps, world, wp.static(_STAGE["padmm_decide"]), lane, last)
            active = w.active[world]
            if active != 0:
                for i in range(lane, n, lanes):
                    padmm_accelerate_of(world, i, w)
                if w.needs_factor[world] != 0:
                    for i in range(lane, n, lanes):
                        if w.row_free[world, i] == 2:  # a drive that met its bound: the world's penalty
                            w.row_free[world, i] = 0
                    rho_now = w.rho[world]
                    sigma = eta + rho_now
                    block_sync()  # every lane has read the flag before lane 0 clears it
                    if lane == 0:
                        w.needs_factor[world] = 0
                    factor_world(world, lane, lanes, n, sigma, eta + row_penalty(1, rho_now, cap), 0, m.row_kind,
                                 w.row_free, D, F, G)
                if wp.static(timed):
                    last = tick(stamps, world, wp.static(_STAGE["padmm_accelerate_refactor"]), lane, last)

        for i in range(lane, max_rows, lanes):
            padmm_output_of(world, i, w, row_lambda_out)
        block_sync()
        # 4. velocity update and poses (engine.integrate.apply_impulses, each body's rows summed
        # by a group of lanes)
        group = int(1)
        if (sharing & SHARE_BODY_SUMS) != 0:
            group = body_group(nb, lanes)
        body_tasks = (nb * group + lanes - 1) // lanes * lanes  # whole blocks: the shuffles take every lane
        for t in range(lane, body_tasks, lanes):
            du = body_row_sum(world, t, group, nb, n, w, row_lambda_out, 0)
            b = t // group
            if b < nb and t % group == 0:
                add_impulse_of(world, b, du, w.body_qd_free, comp, body_qd_out, body_qd_low_out)
                advance_pose_of(world, b, m.world_dt, w.body_q_mid, w.body_q_mid_low, body_qd_out, comp, body_q_out,
                                body_q_low_out)
                body_q_offset_out[world, b] = wp.spatial_vector()
        # 5. Gauss-Newton projection onto the joint constraints (engine.integrate.project_positions) of
        # the next step's configuration with SHAKE's velocity update; Moreau-Jean then projects the
        # end of the step, half-way there, for output only (engine.step)
        project = int(0)
        if position_iterations > 0 and valid != 0 and m.bilateral_row_count[world] > 0:
            project = 1
        target = eta + projection_penalty(m.padmm_rho_init[world], m.padmm_rho_free[world])
        # the PADMM factor's joint rows carry this shift (their penalty stays free_rho; cap off:
        # eta + the world's rho): reused unless other rows need taking out of the matrix
        refactor = project != 0 and mask_projection != 0
        block_sync()  # cholesky_lanes is entered after a barrier
        if wp.static(timed):
            last = tick(stamps, world, wp.static(_STAGE["velocity"]), lane, last)
        if lane == 0:
            w.project[world] = project
            if project == 0:  # as engine.integrate.projection_pass leaves it for such a world
                w.projection_mask[world] = 0
        if project != 0:
            if refactor:
                factor_world(world, lane, lanes, n, target, target, mask_projection, m.row_kind, w.row_free, D, F, G)
            if wp.static(timed):
                last = tick(stamps, world, wp.static(_STAGE["projection_factor"]), lane, last)
            passes = position_iterations
            shake = position_iterations
            if moreau != 0 and project_output != 0:  # the output projection gets as many iterations (engine.step)
                passes = 2 * shake
            for _it in range(passes):
                output = _it >= shake
                if output and _it == shake:  # the end of the step, from the midpoint
                    block_sync()
                    for b in range(lane, nb, lanes):
                        if wp.static(compensated):
                            body_q_next_out[world, b] = body_q_out[world, b]
                        integrate_pose_of(world, b, m.world_dt, 0.5, w.body_q_mid, body_qd_out, body_q_out)
                    block_sync()
                for t in range(lane, joint_tasks, lanes):
                    j, part = joint_task(t, nj, split)
                    if output:  # the end of the step: float32 poses only
                        joint_residuals_of(world, j, part, m, body_q_out, w.no_low, 0, w.row_residual)
                    else:
                        joint_residuals_of(world, j, part, m, body_q_out, body_q_low_out, comp, w.row_residual)
                block_sync()
                if wp.static(timed):
                    last = tick(stamps, world, wp.static(_STAGE["projection_residuals"]), lane, last)
                linear = float(0.0)
                angular = float(0.0)
                for i in range(lane, n, lanes):
                    kind = m.row_kind[world, i]
                    phi = float(0.0)  # engine.integrate.bilateral_residual_of, the row's kind loaded once
                    if kind == ROW_LINEAR or kind == ROW_ANGULAR:
                        phi = w.row_residual[world, i]
                    w.rhs[world, i] = -w.row_precond[world, i] * phi
                    if kind == ROW_LINEAR:
                        linear = wp.max(linear, wp.abs(phi))
                    elif kind == ROW_ANGULAR:
                        angular = wp.max(angular, wp.abs(phi))
                if wp.static(shuffled):
                    both = lane_max2(linear, angular, lanes)
                    linear = both[0]
                    angular = both[1]
                elif lanes > 1:
                    linear = block_max(linear)
                    angular = block_max(angular)
                largest = wp.max(linear, angular)
                skip = linear <= skip_floor and angular <= skip_floor_angular
                update = int(0)
                if largest > velocity_floor and not output:  # above float32 rounding: SHAKE's velocity update
                    update = velocity_update
                block_sync()
                if wp.static(timed):
                    last = tick(stamps, world, wp.static(_STAGE["projection_rhs"]), lane, last)
                if lane == 0:  # as engine.integrate.projection_pass records it
                    w.projection_mask[world] = wp.where(skip, 0, 1)
                if skip:  # the correction would be rounding: skip the iteration
                    continue
                solve_world(world, lane, lanes, n, F, G, w.rhs, w.delta, acc, sol)
                if wp.static(timed):
                    last = tick(stamps, world, wp.static(_STAGE["projection_solve"]), lane, last)
                for t in range(lane, body_tasks, lanes):  # engine.integrate.apply_projection
                    dx = body_row_sum(world, t, group, nb, n, w, w.delta, 1)
                    b = t // group
                    if b < nb and t % group == 0:
                        move_body_of(world, b, dx, m.world_dt, update, wp.where(output, 1, 0), comp, body_q_out,
                                     body_qd_out, body_q_offset_out, body_q_low_out, body_qd_low_out)
                block_sync()
                if wp.static(timed):
                    last = tick(stamps, world, wp.static(_STAGE["projection_apply"]), lane, last)
        if moreau != 0 and (project == 0 or project_output == 0):  # the end of the step, half-way, unprojected
            block_sync()
            for b in range(lane, nb, lanes):
                if wp.static(compensated):
                    body_q_next_out[world, b] = body_q_out[world, b]
                integrate_pose_of(world, b, m.world_dt, 0.5, w.body_q_mid, body_qd_out, body_q_out)
        # 6. divergence guard
        block_sync()
        if lane == 0:
            guard_divergence_of(world, m, w, max_speed, body_q_in, body_qd_in, body_q_offset_in, body_q_low_in,
                                body_qd_low_in, body_q_next_in, body_q_out, body_qd_out, body_q_offset_out,
                                body_q_low_out, body_qd_low_out, body_q_next_out)
        if wp.static(timed):
            block_sync()
            last = tick(stamps, world, wp.static(_STAGE["end_of_step"]), lane, last)

    return fused_step_kernel


def fused_kernel(max_rows: int, max_registers: int = FUSED_REGISTERS, timed: bool = False, inverse: bool = False,
                 compensated: bool = True, shuffled: bool = False, forced: bool = False):
    """The fused step kernel for a padded row count (cached per tile size, register cap, timing,
    solve form, compensated state, reductions by warp shuffles and force slots)."""
    tile_rows = max(TILE_ROWS, -(-max_rows // TILE_ROWS) * TILE_ROWS)
    if tile_rows > FUSED_MAX_ROWS:
        raise ValueError(f"the fused step takes at most {FUSED_MAX_ROWS} rows per world, not {max_rows}")
    key = (tile_rows, max_registers, timed, inverse, compensated, shuffled, forced)
    if key not in _KERNELS:
        _KERNELS[key] = _make_kernel(*key)
    return _KERNELS[key]


def fused_step(model, state_in, state_out, control, stamps=None, project_output: bool = True) -> None:
    """Advance every world of a fused batch (engine.pack chose it) by one step in one launch; with
    ``stamps`` (int64, (num_worlds, len(STAGES))) the timed kernel records the cycle counter at
    the end of each stage (fused_profile); ``project_output`` as engine.step's."""
    cfg, tuning = model.config, model.config.tuning
    if model.fused_block is None:
        model.fused_block = fused_block(model.device)
    timed = stamps is not None
    inverse = model.fused_inverse
    if inverse is None:
        inverse = fused_inverse(model.device, model.max_rows)
    sharing = sharing_used(model)
    if stamps is None:  # the untimed kernel never touches it
        stamps = model._fused_no_stamps
    # warp shuffles on a GPU only (Warp's CPU blocks of several threads, wp.config.enable_cpu_blocks, are not warps)
    shuffled = warp_lanes(model.fused_block) and wp.get_device(model.device).is_cuda
    forced = bool(getattr(model, "has_forces", False))
    kernel = fused_kernel(model.max_rows, model.fused_registers, timed, inverse, tuning.compensated_state, shuffled,
                          forced)
    wp.launch_tiled(kernel, dim=[model.num_worlds], block_dim=model.fused_block, device=model.device,
                    inputs=[model.arrays, model.force_arrays, model.work.arrays, int(cfg.integrator.value == "moreau"),
                            float(cfg.baumgarte), float(cfg.limit_margin), float(cfg.limit_stabilization),
                            (1.0 - tuning.warmstart_decay) if tuning.warmstart else 0.0, cfg.max_iterations,
                            float(cfg.relative_tolerance), tuning.rho_update_interval, int(tuning.adaptive_rho),
                            int(tuning.acceleration), float(tuning.stall_ratio),
                            cfg.position_iterations if model.has_bilateral_rows else 0,
                            int(model.has_unilateral_or_drive_rows), int(tuning.projection_velocity_update),
                            float(tuning.projection_velocity_floor), float(tuning.projection_skip_floor),
                            float(tuning.projection_skip_floor_angular), float(cfg.max_speed), int(sharing),
                            int(project_output), state_in.body_q, state_in.body_qd, state_in.body_q_offset,
                            state_in.body_q_low, state_in.body_qd_low, state_in.body_q_next, state_in.row_lambda,
                            control.joint_target_position, control.joint_target_velocity, control.joint_effort,
                            control.body_f],
                    outputs=[state_out.body_q, state_out.body_qd, state_out.body_q_offset, state_out.body_q_low,
                             state_out.body_qd_low, state_out.body_q_next, state_out.row_lambda, stamps])


def fused_profile(model, state, control, steps: int = 20) -> dict:
    """Cycles per stage of the fused step (STAGES: a stage's cycles summed over its passes in a
    step, as lane 0 of each world's block counts them; medians over worlds and ``steps`` steps) and
    the median whole step; all 0 on the CPU. Advances ``state`` by ``steps`` (>= 1) steps."""
    if steps < 1:
        raise ValueError(f"fused_profile: steps must be >= 1, got {steps}")
    W = model.num_worlds
    stamps = wp.zeros((W, len(STAGES)), dtype=wp.int64, device=model.device)
    other = model.state()
    samples = []
    for _ in range(steps):
        stamps.zero_()
        fused_step(model, state, other, control, stamps=stamps)
        samples.append(stamps.numpy().astype(np.float64))
        state, other = other, state
    if steps % 2:  # the caller's state object holds the latest step
        for name in ("body_q", "body_qd", "body_q_offset", "body_q_low", "body_qd_low", "body_q_next", "row_lambda"):
            wp.copy(getattr(other, name), getattr(state, name))
    t = np.stack(samples).reshape(-1, len(STAGES))
    out = {name: float(np.median(t[:, k])) for k, name in enumerate(STAGES)}
    out["step"] = float(np.median(t.sum(axis=1)))
    return out
