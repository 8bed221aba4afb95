"""Matrix-free solves with the per-world Delassus operator: no (rows x rows) matrix is ever formed.

The operator of a world is A v = P J M^-1 J^T P v + (P R P + S) v, S the diagonal shift per row
(work.row_shift: eta + the row's ADMM penalty). engine.dynamics already
holds M^-1 J^T of every row (row_MJ_c, row_MJ_p), so one product costs two passes over the rows:
scatter the row impulses P v into one twist per body (M^-1 J^T P v), then gather every row's
velocity J (...) and scale by P. Memory is O(bodies + rows) per world instead of O(rows^2), so
worlds of any size run (multi-legged walkers, large robots), where the dense tile factor is
limited to engine.pack.MAX_DENSE_ROWS rows.

Linear systems A x = b are solved by Conjugate Residual (A is symmetric positive definite for
S > 0), one thread block per world (128 threads over the rows on a GPU), warm-started from the
caller's x:
- inside PADMM the solve is inexact: it stops once the residual is below
  ``inner_tolerance_ratio`` times the outer iteration's own residual (inexact ADMM), or at
  ``inner_iterations``;
- for the position projection it stops at a relative residual of ``projection_tolerance`` or
  4 x inner_iterations.
"""

from typing import Any

import warp as wp

from engine.model import ROW_ANGULAR, ROW_LINEAR

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["TILED_BLOCK", "block_max", "block_sum", "solve"]


@wp.func
def _row_used(bilateral_only: int, kind: int):
    return bilateral_only == 0 or kind == ROW_LINEAR or kind == ROW_ANGULAR


TILED_BLOCK = 128  # threads per world in the GPU form


@wp.func
def block_sum(value: float):
    """Sum of ``value`` over the threads of the block (every thread gets it)."""
    return wp.tile_extract(wp.tile_sum(wp.tile(value)), 0)


@wp.func
def block_max(value: float):
    """Largest ``value`` over the threads of the block (every thread gets it)."""
    return wp.tile_extract(wp.tile_max(wp.tile(value)), 0)


def _tiled_kernel(bodies: int, rows: int, sweeps: int):
    """Conjugate Residual with one thread block per world: thread ``lane`` owns rows lane * sweeps
    + k (k < ``sweeps``; the rows of one joint mostly on one thread, so that fewer threads add
    into the same body at once) and keeps their iterates in registers; the world's row Jacobians
    (J and M^-1 J^T of both bodies) are loaded once into shared-memory tiles of ``rows`` rows, the
    row impulses are scattered into a shared tile of ``bodies`` body twists and dot products are
    reduced over the block; the loop exits for the whole block at once. On the CPU a block is one
    thread owning every row (sweeps = rows; the same kernel, the same results)."""
    rowvec = wp.types.vector(length=sweeps, dtype=float)
    rowint = wp.types.vector(length=sweeps, dtype=wp.int32)

    @wp.func
    def apply_tiled(
        lane: int,
        n: int,
        used: rowint,
        body_c: rowint,
        body_p: rowint,
        precond: rowvec,
        diag: rowvec,
        J_c: Any,
        J_p: Any,
        MJ_c: Any,
        MJ_p: Any,
        v: rowvec,
    ):
        acc = wp.tile_zeros(shape=bodies, dtype=wp.spatial_vector, storage="shared")
        for k in range(sweeps):
            i = lane * sweeps + k
            c = int(-1)  # noqa: UP018 (a Warp variable, not a constant)
            p = int(-1)  # noqa: UP018
            to_c = wp.spatial_vector()
            to_p = wp.spatial_vector()
            if i < n and used[k] != 0:
                impulse = precond[k] * v[k]
                c = body_c[k]
                p = body_p[k]
                if c >= 0:
                    to_c = impulse * wp.tile_extract(MJ_c, i)
                if p >= 0:
                    to_p = impulse * wp.tile_extract(MJ_p, i)
            wp.tile_scatter_add(acc, wp.max(c, 0), to_c, c >= 0)
            wp.tile_scatter_add(acc, wp.max(p, 0), to_p, p >= 0)
        out = rowvec()
        for k in range(sweeps):
            i = lane * sweeps + k
            if i < n and used[k] != 0:
                c = body_c[k]
                p = body_p[k]
                velocity = float(0.0)
                if c >= 0:
                    velocity += wp.dot(wp.tile_extract(J_c, i), wp.tile_extract(acc, c))
                if p >= 0:
                    velocity += wp.dot(wp.tile_extract(J_p, i), wp.tile_extract(acc, p))
                out[k] = precond[k] * velocity + diag[k] * v[k]
        return out

    @wp.func
    def dot(a: rowvec, b: rowvec):
        total = float(0.0)
        for k in range(sweeps):
            total += a[k] * b[k]
        return block_sum(total)

    @wp.func
    def norm_inf(a: rowvec):
        largest = float(0.0)
        for k in range(sweeps):
            largest = wp.max(largest, wp.abs(a[k]))
        return block_max(largest)

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
        row_shift: wp.array2d(dtype=float),
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
        x: wp.array2d(dtype=float),
        inner_iterations: wp.array(dtype=wp.int32),
    ):
        world, lane = wp.tid()
        if mask[world] == 0:
            return
        n = row_count[world]
        J_c = wp.tile_load(row_J_c[world], shape=rows, storage="shared")
        J_p = wp.tile_load(row_J_p[world], shape=rows, storage="shared")
        MJ_c = wp.tile_load(row_MJ_c[world], shape=rows, storage="shared")
        MJ_p = wp.tile_load(row_MJ_p[world], shape=rows, storage="shared")
        used = rowint()
        body_c = rowint()
        body_p = rowint()
        precond = rowvec()
        diag = rowvec()
        b = rowvec()
        xk = rowvec()
        scale = float(0.0)
        for k in range(sweeps):
            i = lane * sweeps + k
            if i < n:
                if _row_used(bilateral_only, row_kind[world, i]):
                    used[k] = 1
                    body_c[k] = row_body_c[world, i]
                    body_p[k] = row_body_p[world, i]
                    pi = row_precond[world, i]
                    precond[k] = pi
                    diag[k] = row_shift[world, i] + pi * pi * row_compliance[world, i]
                    b[k] = rhs[world, i]
                    xk[k] = x[world, i]
                    scale = wp.max(scale, wp.abs(b[k]))
        Ax = apply_tiled(lane, n, used, body_c, body_p, precond, diag, J_c, J_p, MJ_c, MJ_p, xk)
        r = b - Ax
        res = norm_inf(r)
        scale = block_max(scale)
        tol = relative_floor * scale + 1.0e-12
        if bilateral_only == 0:
            outer = scale
            if outer_iterations[world] > 0:
                outer = wp.max(residual_primal[world], residual_dual[world])
            tol = wp.max(ratio * outer, 1.0e-3 * padmm_tolerance[world])
        count = int(0)
        if res > tol:
            p = r
            Ar = apply_tiled(lane, n, used, body_c, body_p, precond, diag, J_c, J_p, MJ_c, MJ_p, r)
            Ap = Ar
            rAr = dot(r, Ar)
            for _k in range(max_iterations):
                ApAp = dot(Ap, Ap)
                if ApAp <= 1.0e-30 or rAr <= 0.0:
                    break
                alpha = rAr / ApAp
                xk = xk + alpha * p
                r = r - alpha * Ap
                count += 1
                if norm_inf(r) <= tol:
                    break
                Ar = apply_tiled(lane, n, used, body_c, body_p, precond, diag, J_c, J_p, MJ_c, MJ_p, r)
                rAr_new = dot(r, Ar)
                beta = rAr_new / rAr
                rAr = rAr_new
                p = r + beta * p
                Ap = Ar + beta * Ap
        for k in range(sweeps):
            i = lane * sweeps + k
            if i < n:
                x[world, i] = xk[k]  # 0 on rows left out of the operator
        if lane == 0:
            inner_iterations[world] = inner_iterations[world] + count

    return conjugate_residual_tiled


_TILED = {}


def solve(model, rhs, mask, x, *, bilateral_only: bool = False) -> None:
    """Solve A x = rhs per world (mask != 0) in place, warm-started from x.

    bilateral_only: the operator of the bilateral joint rows alone (position projection, solved to
    a relative residual of config.projection_tolerance); otherwise all rows, solved inexactly for
    PADMM.
    """
    work, cfg = model.work, model.config
    cap = cfg.inner_iterations * (4 if bilateral_only else 1)
    rows = model.max_rows
    threads = TILED_BLOCK if wp.get_device(model.device).is_cuda else 1  # a block is one CPU thread
    key = (model.max_bodies, rows, (rows + threads - 1) // threads)
    if key not in _TILED:
        _TILED[key] = _tiled_kernel(*key)
    wp.launch_tiled(_TILED[key], dim=[model.num_worlds], block_dim=TILED_BLOCK, device=model.device,
                    inputs=[int(bilateral_only), cap, float(cfg.inner_tolerance_ratio), float(cfg.projection_tolerance), model.row_kind,
                            model.padmm_tolerance, work.row_count, mask, work.row_shift, work.iterations,

                            work.residual_primal, work.residual_dual, work.row_body_c, work.row_body_p,
                            work.row_J_c, work.row_J_p, work.row_MJ_c, work.row_MJ_p, work.row_precond,
                            work.row_compliance, rhs],
                    outputs=[x, work.inner_iterations])
