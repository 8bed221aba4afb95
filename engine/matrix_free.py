"""Matrix-free solves with the per-world Delassus operator: no (rows x rows) matrix is ever formed.

The operator of a world is A v = P J M^-1 J^T P v + (P R P + sigma) v. engine.dynamics already
holds M^-1 J^T of every row (row_MJ_c, row_MJ_p), so one product costs two passes over the rows:
scatter the row impulses P v into one twist per body (M^-1 J^T P v), then gather every row's
velocity J (...) and scale by P. Memory is O(bodies + rows) per world instead of O(rows^2), so
worlds of any size run (multi-legged walkers, large robots), where the dense tile factor is
limited to engine.pack.MAX_DENSE_ROWS rows.

Linear systems A x = b are solved by Conjugate Residual (A is symmetric positive definite for
sigma > 0), one thread block per world (128 threads over the rows on a GPU), warm-started from the
caller's x:
- inside PADMM the solve is inexact: it stops once the residual is below
  ``inner_tolerance_ratio`` times the outer iteration's own residual (inexact ADMM), or at
  ``inner_iterations``;
- for the position projection it stops at a relative residual of 1e-6 or 4 x inner_iterations.
"""

import warp as wp

from engine.model import ROW_ANGULAR, ROW_LINEAR

__all__ = ["TILED_BLOCK", "solve"]


@wp.func
def _row_used(bilateral_only: int, kind: int):
    return bilateral_only == 0 or kind == ROW_LINEAR or kind == ROW_ANGULAR


TILED_BLOCK = 128  # threads per world in the GPU form


def _tiled_kernel(bodies: int):
    """Conjugate Residual with one thread block per world: the block's threads share the world's
    rows (row i on thread i mod block_dim), scatter the row impulses into a shared-memory tile of
    ``bodies`` body twists and reduce the dot products over the block; the loop exits for the whole
    block at once. On the CPU a block is one thread (the same kernel, the same results)."""

    @wp.func
    def apply_tiled(
        world: int,
        lane: int,
        stride: int,
        sweeps: int,
        n: int,
        bilateral_only: int,
        sigma: float,
        row_kind: wp.array2d(dtype=wp.int32),
        row_body_c: wp.array2d(dtype=wp.int32),
        row_body_p: wp.array2d(dtype=wp.int32),
        row_J_c: wp.array2d(dtype=wp.spatial_vector),
        row_J_p: wp.array2d(dtype=wp.spatial_vector),
        row_MJ_c: wp.array2d(dtype=wp.spatial_vector),
        row_MJ_p: wp.array2d(dtype=wp.spatial_vector),
        row_precond: wp.array2d(dtype=float),
        row_compliance: wp.array2d(dtype=float),
        v: wp.array2d(dtype=float),
        out: wp.array2d(dtype=float),
    ):
        acc = wp.tile_zeros(shape=bodies, dtype=wp.spatial_vector, storage="shared")
        for k in range(sweeps):
            i = lane + k * stride
            c = int(-1)
            p = int(-1)
            to_c = wp.spatial_vector()
            to_p = wp.spatial_vector()
            if i < n:
                if _row_used(bilateral_only, row_kind[world, i]):
                    impulse = row_precond[world, i] * v[world, i]
                    c = row_body_c[world, i]
                    p = row_body_p[world, i]
                    to_c = impulse * row_MJ_c[world, i]
                    to_p = impulse * row_MJ_p[world, i]
            wp.tile_scatter_add(acc, wp.max(c, 0), to_c, c >= 0)
            wp.tile_scatter_add(acc, wp.max(p, 0), to_p, p >= 0)
        for k in range(sweeps):
            i = lane + k * stride
            if i < n:
                value = float(0.0)
                if _row_used(bilateral_only, row_kind[world, i]):
                    c = row_body_c[world, i]
                    p = row_body_p[world, i]
                    velocity = float(0.0)
                    if c >= 0:
                        velocity += wp.dot(row_J_c[world, i], wp.tile_extract(acc, c))
                    if p >= 0:
                        velocity += wp.dot(row_J_p[world, i], wp.tile_extract(acc, p))
                    pi = row_precond[world, i]
                    value = pi * velocity + (sigma + pi * pi * row_compliance[world, i]) * v[world, i]
                out[world, i] = value

    @wp.func
    def block_sum(value: float):
        return wp.tile_extract(wp.tile_sum(wp.tile(value)), 0)

    @wp.func
    def block_max(value: float):
        return wp.tile_extract(wp.tile_max(wp.tile(value)), 0)

    @wp.kernel(module="unique")
    def conjugate_residual_tiled(
        bilateral_only: int,
        max_iterations: int,
        ratio: float,
        relative_floor: float,
        row_kind: wp.array2d(dtype=wp.int32),
        padmm_tolerance: wp.array(dtype=float),
        row_count: wp.array(dtype=wp.int32),
        mask: wp.array(dtype=wp.int32),
        sigma: wp.array(dtype=float),
        outer_iterations: wp.array(dtype=wp.int32),
        residual_primal: wp.array(dtype=float),
        residual_dual: wp.array(dtype=float),
        row_body_c: wp.array2d(dtype=wp.int32),
        row_body_p: wp.array2d(dtype=wp.int32),
        row_J_c: wp.array2d(dtype=wp.spatial_vector),
        row_J_p: wp.array2d(dtype=wp.spatial_vector),
        row_MJ_c: wp.array2d(dtype=wp.spatial_vector),
        row_MJ_p: wp.array2d(dtype=wp.spatial_vector),
        row_precond: wp.array2d(dtype=float),
        row_compliance: wp.array2d(dtype=float),
        rhs: wp.array2d(dtype=float),
        r: wp.array2d(dtype=float),
        p: wp.array2d(dtype=float),
        Ar: wp.array2d(dtype=float),
        Ap: wp.array2d(dtype=float),
        x: wp.array2d(dtype=float),
        inner_iterations: wp.array(dtype=wp.int32),
    ):
        world, lane = wp.tid()
        if mask[world] == 0:
            return
        stride = wp.block_dim()
        n = row_count[world]
        sweeps = (n + stride - 1) // stride
        s = sigma[world]
        apply_tiled(world, lane, stride, sweeps, n, bilateral_only, s, row_kind, row_body_c, row_body_p, row_J_c,
                    row_J_p, row_MJ_c, row_MJ_p, row_precond, row_compliance, x, Ap)
        res = float(0.0)
        scale = float(0.0)
        for k in range(sweeps):
            i = lane + k * stride
            if i < n:
                ri = float(0.0)
                if _row_used(bilateral_only, row_kind[world, i]):
                    ri = rhs[world, i] - Ap[world, i]
                    scale = wp.max(scale, wp.abs(rhs[world, i]))
                else:
                    x[world, i] = 0.0
                r[world, i] = ri
                p[world, i] = ri
                res = wp.max(res, wp.abs(ri))
        res = block_max(res)
        scale = block_max(scale)
        tol = relative_floor * scale + 1.0e-12
        if bilateral_only == 0:
            outer = scale
            if outer_iterations[world] > 0:
                outer = wp.max(residual_primal[world], residual_dual[world])
            tol = wp.max(ratio * outer, 1.0e-3 * padmm_tolerance[world])
        if res <= tol:
            return
        apply_tiled(world, lane, stride, sweeps, n, bilateral_only, s, row_kind, row_body_c, row_body_p, row_J_c,
                    row_J_p, row_MJ_c, row_MJ_p, row_precond, row_compliance, r, Ar)
        rAr = float(0.0)
        for k in range(sweeps):
            i = lane + k * stride
            if i < n:
                Ap[world, i] = Ar[world, i]
                rAr += r[world, i] * Ar[world, i]
        rAr = block_sum(rAr)
        count = int(0)
        for _k in range(max_iterations):
            ApAp = float(0.0)
            for k in range(sweeps):
                i = lane + k * stride
                if i < n:
                    ApAp += Ap[world, i] * Ap[world, i]
            ApAp = block_sum(ApAp)
            if ApAp <= 1.0e-30 or rAr <= 0.0:
                break
            alpha = rAr / ApAp
            res = float(0.0)
            for k in range(sweeps):
                i = lane + k * stride
                if i < n:
                    x[world, i] = x[world, i] + alpha * p[world, i]
                    ri = r[world, i] - alpha * Ap[world, i]
                    r[world, i] = ri
                    res = wp.max(res, wp.abs(ri))
            res = block_max(res)
            count += 1
            if res <= tol:
                break
            apply_tiled(world, lane, stride, sweeps, n, bilateral_only, s, row_kind, row_body_c, row_body_p,
                        row_J_c, row_J_p, row_MJ_c, row_MJ_p, row_precond, row_compliance, r, Ar)
            rAr_new = float(0.0)
            for k in range(sweeps):
                i = lane + k * stride
                if i < n:
                    rAr_new += r[world, i] * Ar[world, i]
            rAr_new = block_sum(rAr_new)
            beta = rAr_new / rAr
            rAr = rAr_new
            for k in range(sweeps):
                i = lane + k * stride
                if i < n:
                    p[world, i] = r[world, i] + beta * p[world, i]
                    Ap[world, i] = Ar[world, i] + beta * Ap[world, i]
        if lane == 0:
            inner_iterations[world] = inner_iterations[world] + count

    return conjugate_residual_tiled


_TILED = {}


def solve(model, rhs, mask, x, *, bilateral_only: bool = False) -> None:
    """Solve A x = rhs per world (mask != 0) in place, warm-started from x.

    bilateral_only: the operator of the bilateral joint rows alone (position projection, solved to
    a relative residual of 1e-6); otherwise all rows, solved inexactly for PADMM.
    """
    work, cfg = model.work, model.config
    cap = cfg.inner_iterations * (4 if bilateral_only else 1)
    bodies = model.max_bodies
    if bodies not in _TILED:
        _TILED[bodies] = _tiled_kernel(bodies)
    wp.launch_tiled(_TILED[bodies], dim=[model.num_worlds], block_dim=TILED_BLOCK, device=model.device,
                    inputs=[int(bilateral_only), cap, float(cfg.inner_tolerance_ratio), 1.0e-6, model.row_kind,
                            model.padmm_tolerance, work.row_count, mask, work.sigma, work.iterations,
                            work.residual_primal, work.residual_dual, work.row_body_c, work.row_body_p,
                            work.row_J_c, work.row_J_p, work.row_MJ_c, work.row_MJ_p, work.row_precond,
                            work.row_compliance, rhs, work.cr_r, work.cr_p, work.cr_Ar, work.cr_Ap],
                    outputs=[x, work.inner_iterations])
