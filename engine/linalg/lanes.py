"""What the lanes of one world's thread block share: barriers, barrier-free writes into shared
tiles, sums and maxima over the lanes, and the cycle clock.

The step kernels give each world a thread block (one warp on a GPU, one thread on the CPU) and
place their own barriers; these are the pieces they all use, written once. Tile reductions
(block_sum, block_max) work for any block; warp shuffles (group_sum, lane_max2, lane_reduce6)
need the lanes of one warp and reduce several values in one pass without a barrier. On the CPU a
block is one thread: the barriers are no-ops and a value is its own sum and maximum.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["block_max", "block_sum", "block_sync", "clock", "group_sum", "lane_max2", "lane_reduce6", "tile_set",
           "warp_sync"]

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


_WARP_SYNC = """
#if defined(__CUDA_ARCH__)
__syncwarp();
#endif
"""


@wp.func_native(_WARP_SYNC)
def warp_sync():
    """Barrier of the warp's lanes (memory ordering among them included; a no-op on the CPU)."""


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


@wp.func
def block_sum(value: float):
    """Sum of ``value`` over the threads of the block (every thread gets it)."""
    return wp.tile_extract(wp.tile_sum(wp.tile(value)), 0)


@wp.func
def block_max(value: float):
    """Largest ``value`` over the threads of the block (every thread gets it)."""
    return wp.tile_extract(wp.tile_max(wp.tile(value)), 0)


_GROUP_SUM = """
float total = value;
#if defined(__CUDA_ARCH__)
for (int offset = width >> 1; offset > 0; offset >>= 1) total += __shfl_xor_sync(0xffffffffu, total, offset);
#endif
return total;
"""


@wp.func_native(_GROUP_SUM)
def group_sum(value: float, width: int) -> float:
    """Sum over each aligned group of ``width`` lanes of a warp (every lane of the group gets it;
    all 32 lanes must call); the value itself on the CPU, where a block is one thread."""


_LANE_MAX2 = """
#if defined(__CUDA_ARCH__)
unsigned int mask = width >= 32 ? 0xffffffffu : ((1u << width) - 1u);
for (int offset = width >> 1; offset > 0; offset >>= 1) {
    a = fmaxf(a, __shfl_xor_sync(mask, a, offset));
    b = fmaxf(b, __shfl_xor_sync(mask, b, offset));
}
#endif
return wp::vec2(a, b);
"""


@wp.func_native(_LANE_MAX2)
def lane_max2(a: float, b: float, width: int) -> wp.vec2:
    """The largest a and b over a block of ``width`` threads (a power of two up to 32: one warp's
    first lanes), both reduced in one pass of warp shuffles without a block barrier; CUDA only
    (engine.fused asks for it on GPUs alone)."""


_LANE_REDUCE6 = """
#if defined(__CUDA_ARCH__)
unsigned int mask = width >= 32 ? 0xffffffffu : ((1u << width) - 1u);
for (int offset = width >> 1; offset > 0; offset >>= 1) {
    float v0 = __shfl_xor_sync(mask, m0, offset);
    float v1 = __shfl_xor_sync(mask, m1, offset);
    float v2 = __shfl_xor_sync(mask, m2, offset);
    float v3 = __shfl_xor_sync(mask, m3, offset);
    float v4 = __shfl_xor_sync(mask, m4, offset);
    float v5 = __shfl_xor_sync(mask, s5, offset);
    m0 = fmaxf(m0, v0); m1 = fmaxf(m1, v1); m2 = fmaxf(m2, v2); m3 = fmaxf(m3, v3); m4 = fmaxf(m4, v4);
    s5 = s5 + v5;
}
#endif
return wp::spatial_vector(wp::vec3(m0, m1, m2), wp::vec3(m3, m4, s5));
"""


@wp.func_native(_LANE_REDUCE6)
def lane_reduce6(m0: float, m1: float, m2: float, m3: float, m4: float, s5: float, width: int) -> wp.spatial_vector:
    """The largest m0..m4 and the sum of s5 over a block of ``width`` threads (as lane_max2: one
    pass of warp shuffles; the butterfly leaves the same sum, to the bit, in every lane)."""


_CLOCK = """
#if defined(__CUDA_ARCH__)
return clock64();
#else
return (long long)__builtin_readcyclecounter();
#endif
"""


@wp.func_native(_CLOCK)
def clock() -> wp.int64:
    """The multiprocessor's cycle counter on CUDA, the processor's on the CPU."""
    ...
