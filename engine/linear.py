"""Dense batched linear algebra on the per-world Delassus matrices: one tile block per world.

Each world's (max_rows x max_rows) matrix is loaded as one Warp tile, shifted on its diagonal and
factored with ``wp.tile_cholesky``; solves reuse the stored factor. Kernels are specialized per
tile size by cached factories. Worlds whose mask entry is 0 return at once.
"""

import functools

import warp as wp

__all__ = ["block_sync", "cholesky_factor_kernel", "cholesky_solve_kernel", "factor", "solve", "tile_set"]

BLOCK_DIM = 64

_SYNC = """
#if defined(__CUDA_ARCH__)
__syncthreads();
#endif
"""


@wp.func_native(_SYNC)
def block_sync():
    """Barrier of the thread block (a no-op on the CPU, where a block is one thread). Unlike the
    tile operations it may sit in code that only some blocks reach, but every thread of a block
    must reach it."""


def _define_tile_set():
    """Element writes into shared tiles (overloads of one tile_set: a 2-D float tile, a 1-D float
    tile and a 1-D int32 tile), which, unlike Warp's tile element assignment, do not end in a block
    barrier: the lanes write different entries in divergent code and the callers place the
    barriers. Warp matches a tile argument by its dtype alone, so each overload serves every shape
    (the 8 x 8 and 8 in the signatures are placeholders; the native code indexes the actual tile)."""

    @wp.func_native("t.data(wp::tile_coord(i, j)) = value;")
    def tile_set(t: wp.tile(dtype=float, shape=(8, 8), storage="shared"), i: int, j: int, value: float):
        """t[i, j] = value, without a barrier."""

    @wp.func_native("t.data(wp::tile_coord(i)) = value;")
    def tile_set(t: wp.tile(dtype=float, shape=(8,), storage="shared"), i: int, value: float):  # noqa: F811
        """t[i] = value, without a barrier."""

    @wp.func_native("t.data(wp::tile_coord(i)) = value;")
    def tile_set(t: wp.tile(dtype=wp.int32, shape=(8,), storage="shared"), i: int, value: int):  # noqa: F811
        """t[i] = value, without a barrier."""

    return tile_set


tile_set = _define_tile_set()


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
