"""Dense Cholesky factors and solves of the per-world Delassus matrix P D P + diag(shift).

Two forms of the same arithmetic: whole-batch kernels on Warp tiles (one tile block per world,
``wp.tile_cholesky``; engine.padmm's and engine.integrate's dense path, a kernel per tile size),
and per-lane functions that the lanes of one world's block call inside a larger kernel
(engine.fused: a left-looking factor with the lanes sharing each column, substitutions with the
lanes sharing each row's updates, or products with G = L^-1 where a chain of dependent
substitution steps costs more than forming G). Worlds whose mask entry is 0 return at once.
"""

import functools
from typing import Any

import warp as wp

from engine.linalg.lanes import block_sync, tile_set
from engine.model import ROW_ANGULAR, ROW_LINEAR

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["BLOCK_DIM", "cholesky_factor_kernel", "cholesky_lanes", "cholesky_solve_kernel", "cholesky_solve_lanes",
           "factor", "inverse_solve_lanes", "is_bilateral", "matrix_entry", "solve", "triangular_inverse_lanes"]

BLOCK_DIM = 64  # threads per world of the tile kernels


@functools.cache
def cholesky_factor_kernel(size: int):
    """Kernel: factor_out[w] = chol(matrix[w] + diag(shift[w])) for worlds with mask[w] != 0."""

    @wp.kernel(enable_backward=False, module="unique")
    def cholesky_factor(
        matrix: wp.array3d(dtype=float),
        shift: wp.array2d(dtype=float),
        mask: wp.array(dtype=wp.int32),
        factor_out: wp.array3d(dtype=float),
    ):
        world = wp.tid()
        if mask[world] == 0:
            return
        a = wp.tile_load(matrix[world], shape=(size, size))
        shifted = wp.tile_diag_add(a, wp.tile_load(shift[world], shape=size))
        wp.tile_store(factor_out[world], wp.tile_cholesky(shifted))

    return cholesky_factor


@functools.cache
def cholesky_solve_kernel(size: int):
    """Kernel: x_out[w] = (L L^T)^-1 rhs[w] with L = factor[w], for worlds with mask[w] != 0."""

    @wp.kernel(enable_backward=False, module="unique")
    def cholesky_solve(
        factor: wp.array3d(dtype=float),
        rhs: wp.array2d(dtype=float),
        mask: wp.array(dtype=wp.int32),
        x_out: wp.array2d(dtype=float),
    ):
        world = wp.tid()
        if mask[world] == 0:
            return
        lower = wp.tile_load(factor[world], shape=(size, size))
        b = wp.tile_load(rhs[world], shape=size)
        wp.tile_store(x_out[world], wp.tile_cholesky_solve(lower, b))

    return cholesky_solve


def factor(matrix, shift, mask, factor_out):
    """Factor every masked world's matrix with shift added to its diagonal (shapes (W, R, R), (W, R),
    (W,), (W, R, R))."""
    size = matrix.shape[1]
    wp.launch_tiled(cholesky_factor_kernel(size), dim=[matrix.shape[0]], inputs=[matrix, shift, mask],
                    outputs=[factor_out], block_dim=BLOCK_DIM, device=matrix.device)


def solve(factor_matrix, rhs, mask, x_out):
    """Solve with the stored factors (shapes (W, R, R), (W, R), (W,), (W, R))."""
    size = factor_matrix.shape[1]
    wp.launch_tiled(cholesky_solve_kernel(size), dim=[factor_matrix.shape[0]], inputs=[factor_matrix, rhs, mask],
                    outputs=[x_out], block_dim=BLOCK_DIM, device=factor_matrix.device)


@wp.func
def is_bilateral(kind: int):
    """True for a joint row (linear or angular), False for contact and limit rows."""
    return kind == ROW_LINEAR or kind == ROW_ANGULAR


@wp.func
def matrix_entry(world: int, i: int, j: int, bilateral_only: int, row_kind: wp.array2d(dtype=wp.int32), matrix: Any):
    """P D P (i, j) from the world's shared matrix tile, or with bilateral_only its bilateral joint
    block (identity elsewhere)."""
    if bilateral_only != 0:
        if not (is_bilateral(row_kind[world, i]) and is_bilateral(row_kind[world, j])):
            if i == j:
                return 1.0
            return 0.0
    return matrix[i, j]


@wp.func
def cholesky_lanes(world: int, lane: int, lanes: int, n: int, sigma: float, sigma_free: float,
                   bilateral_only: int, row_kind: wp.array2d(dtype=wp.int32), row_free: wp.array2d(dtype=wp.int32),
                   matrix: Any, factor: Any):
    """Lower Cholesky factor of the world's n x n matrix plus a diagonal shift (sigma_free on the
    free rows of engine.padmm.row_is_free, sigma on the others) (shared tiles), column by column
    (left-looking): every lane forms the column's pivot, the lanes share the column's entries below
    it; one barrier per column. The dot products run in the serial order. Entered after a barrier."""
    for j in range(n):
        shift = sigma
        if row_free[world, j] != 0:
            shift = sigma_free
        s = matrix_entry(world, j, j, bilateral_only, row_kind, matrix) + shift
        for k in range(j):
            s -= factor[j, k] * factor[j, k]
        d = wp.sqrt(wp.max(s, 1.0e-30))
        inv = 1.0 / d
        if lane == 0:
            tile_set(factor, j, j, d)
        for i in range(j + 1 + lane, n, lanes):
            t = matrix_entry(world, i, j, bilateral_only, row_kind, matrix)
            for k in range(j):
                t -= factor[i, k] * factor[j, k]
            tile_set(factor, i, j, t * inv)
        block_sync()


@wp.func
def cholesky_solve_lanes(world: int, lane: int, lanes: int, n: int, factor: Any, rhs: wp.array2d(dtype=float),
                         x: wp.array2d(dtype=float), acc: Any, sol: Any):
    """x = (L L^T)^-1 rhs for the world's n rows: column-oriented substitutions in two shared
    vectors (acc, sol), the lanes sharing each column's updates (one barrier per row). Entered
    after a barrier; leaves x written and a barrier behind."""
    for i in range(lane, n, lanes):
        tile_set(acc, i, rhs[world, i])
    block_sync()
    for i in range(n):  # forward: L y = rhs, y into sol
        yi = acc[i] / factor[i, i]
        if lane == 0:
            tile_set(sol, i, yi)
        for k in range(i + 1 + lane, n, lanes):
            tile_set(acc, k, acc[k] - factor[k, i] * yi)
        block_sync()
    for step in range(n):  # backward: L^T x = y, partial sums in sol, the solution into acc
        i = n - 1 - step
        xi = sol[i] / factor[i, i]
        if lane == 0:
            tile_set(acc, i, xi)
        for k in range(lane, i, lanes):
            tile_set(sol, k, sol[k] - factor[i, k] * xi)
        block_sync()
    for i in range(lane, n, lanes):
        x[world, i] = acc[i]
    block_sync()


@wp.func
def triangular_inverse_lanes(lane: int, lanes: int, n: int, factor: Any, inverse: Any):
    """G = L^-1 of the world's n x n lower factor into the shared tile ``inverse`` (its lower
    triangle), the lanes taking one column each by forward substitution on a unit vector. Entered
    after a barrier; leaves a barrier behind."""
    for j in range(lane, n, lanes):
        tile_set(inverse, j, j, 1.0 / factor[j, j])
        for i in range(j + 1, n):
            s = float(0.0)
            for k in range(j, i):
                s += factor[i, k] * inverse[k, j]
            tile_set(inverse, i, j, -s / factor[i, i])
    block_sync()


@wp.func
def inverse_solve_lanes(world: int, lane: int, lanes: int, n: int, inverse: Any, rhs: wp.array2d(dtype=float),
                        x: wp.array2d(dtype=float), acc: Any, sol: Any):
    """x = G^T (G rhs) = (L L^T)^-1 rhs with G = L^-1 (triangular_inverse_lanes): two triangular
    products, each lane forming whole entries (no chain of dependent substitution steps). Entered
    after a barrier; leaves x written and a barrier behind."""
    for i in range(lane, n, lanes):
        tile_set(acc, i, rhs[world, i])
    block_sync()
    for i in range(lane, n, lanes):  # y = G rhs
        s = float(0.0)
        for k in range(i + 1):
            s += inverse[i, k] * acc[k]
        tile_set(sol, i, s)
    block_sync()
    for k in range(lane, n, lanes):  # x = G^T y
        s = float(0.0)
        for i in range(k, n):
            s += inverse[i, k] * sol[i]
        x[world, k] = s
    block_sync()
