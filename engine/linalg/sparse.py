"""Sparse direct solves of the per-world Delassus matrix, device side: the matrix on the factor's
pattern, its L S L^T factor and the solves, following the schedules that
engine.linalg.sparse_analysis made once per topology.

One warp per world (one thread on the CPU), level by level with a barrier between levels (the
block's in the factor, the warp's in the solves), so results are deterministic: each entry is
summed by one lane, or by one warp in a fixed order. A level of supernode blocks: in the factor,
every entry of its block columns less its products with earlier blocks' columns, in parallel;
then a lane per block for the block's own triangle and a lane per row below it (or, for a large
block, the warp column by column); in a substitution, every row less its entries outside its
block, in parallel, then a lane per block substitutes the block's triangle. The solve keeps its
vector in shared memory; the factor stays in global memory.

Both kernels are bound by the latency of their chain of dependent steps and by their issued
instructions: the inner sums are native code on raw addresses that load four products per pass
(entry_products, substitute_level, factor_level_blocks); the forward substitution reads a
row-major copy of the factor (SparseSystem.L_rows) and multiplies by the reciprocal diagonal
(SparseSystem.L_inv); with enough worlds of one topology a block of 32 worlds shares the solve's
schedule in shared memory (shared_solve_kernel). The matrix build stages a world's rows in shared
memory (staged_matrix_kernel). Per step: roots (body nodes), prepare (the row map and the matrix),
factor and solve. The kernels take the system's buffers as one SystemArrays argument. The
measurements behind each choice: benchmarks/results/README.md, "Maximal path: design notes".
"""

import functools
from typing import Any

import warp as wp

from engine.linalg.lanes import block_sync, group_sum, tile_set, warp_sync
from engine.linalg.sparse_analysis import (
    BACKWARD,
    BLOCK_LEVEL,
    BLOCK_RECORD,
    FACTOR,
    FACTOR_LEVEL,
    FORWARD,
    PHASE_BITS,
    RECIPE_BODY_DIAGONAL,
    RECIPE_ROW_BODY,
    RECIPE_ROWS,
    RECIPE_ZERO,
    TOGETHER_BIT,
    SparsePatterns,
    SparseSystem,
    SystemArrays,
)
from engine.model import ROW_ANGULAR, ROW_LINEAR, ModelArrays, WorkArrays

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["factor", "matrix", "matrix_block", "prepare", "roots", "shared_solve_kernel", "solve", "sparse_block",
           "sparse_factor", "sparse_matrix", "staged_matrix_kernel", "vector_size"]

# Register cap per thread of the factor and solve kernels: at most 64 lets 32 one-warp blocks (the
# hardware's limit) stay on each multiprocessor.
SPARSE_REGISTERS = 64
VECTOR_STEP = 64  # shared tiles are sized in steps of this many elements (one kernel per size)
MATRIX_BLOCK = 256  # threads per world (a block) of the matrix build on a GPU


def vector_size(system: SparseSystem) -> int:
    """Elements of a world's shared vector or stage: its positions rounded up to VECTOR_STEP."""
    return -(-system.nodes // VECTOR_STEP) * VECTOR_STEP


def matrix_block(device) -> int:
    """Threads per world of the matrix build (sparse_matrix): MATRIX_BLOCK on a GPU, one on the CPU."""
    return MATRIX_BLOCK if wp.get_device(device).is_cuda else 1


def sparse_block(device) -> int:
    """Threads per world of the sparse kernels: one warp on a GPU, one thread on the CPU."""
    return 32 if wp.get_device(device).is_cuda else 1


@wp.kernel
def map_joint_rows(contact_row_start: wp.array(dtype=wp.int32), real_out: wp.array2d(dtype=wp.int32)):
    """Factor rows below a world's first contact row are its joint rows; contact slots start unused (-1)."""
    world, v = wp.tid()
    real = int(-1)
    if v < contact_row_start[world]:
        real = v
    real_out[world, v] = real


@wp.kernel
def map_contact_rows(contact_row_start: wp.array(dtype=wp.int32), contact_count: wp.array(dtype=wp.int32),
                     contact_key: wp.array2d(dtype=wp.int32), real_out: wp.array2d(dtype=wp.int32)):
    """Contact k (rows start + 3k ..) fills the factor rows of its candidate slot (key = pair * 4 + m)."""
    world, k = wp.tid()
    if k >= contact_count[world]:
        return
    start = contact_row_start[world]
    slot = start + 3 * contact_key[world, k]
    for t in range(3):
        real_out[world, slot + t] = start + 3 * k + t


@wp.func
def _node_row(pat: SparsePatterns, s: SystemArrays, p: int, pos: int, world: int):
    """This step's row of the factor's position pos (-1: unused, a body node or padding)."""
    r = pat.perm[p, pos]
    if r < 0:
        return -1
    return s.real[world, r]


@wp.func
def _bilateral(world: int, i: int, n: int, row_kind: wp.array2d(dtype=wp.int32)):
    """Whether row i (-1: none) is a bilateral joint row in use this step (n rows)."""
    if i < 0 or i >= n:
        return False
    kind = row_kind[world, i]
    return kind == ROW_LINEAR or kind == ROW_ANGULAR


@wp.func
def group_width(mode: int, phase: int, lanes: int):
    """Lanes that share each item of this level and phase (at most the block's)."""
    return wp.min(1 << ((mode >> (PHASE_BITS * phase)) & 7), lanes)


# Raw addresses and the inner sums of the factor and the solves in native code: Warp's array
# indexing wraps negative indices and scales each index by the array's runtime stride, and these
# sums are most of the kernels' issued instructions. The arrays passed are contiguous (allocated
# by engine.linalg.sparse_analysis.make_system and build_patterns).
@functools.cache
def _row_address(dtype):
    """Address of a row of a 2-d array of one type."""

    @wp.func_native("return (wp::uint64)(reinterpret_cast<char*>(a.data) + (size_t)row * a.strides[0]);")
    def row_address(a: wp.array2d(dtype=dtype), row: int) -> wp.uint64:
        """Address of row ``row`` of a 2-d array."""

    return row_address


@functools.cache
def _element_address(dtype):
    """Address of an element of a contiguous 1-d array of one type."""

    @wp.func_native("return (wp::uint64)(a.data + offset);")
    def element_address(a: wp.array(dtype=dtype), offset: int) -> wp.uint64:
        """Address of element ``offset`` of a contiguous 1-d array."""

    return element_address


row_address, int_row_address = _row_address(float), _row_address(wp.int32)
int_address, pair_address = _element_address(wp.int32), _element_address(wp.vec2i)


@functools.cache
def _tile_address(size: int, dtype):
    """Address of an element of a shared tile of one size and type (its storage is contiguous)."""

    @wp.func_native("return (wp::uint64)(t.data.ptr + offset);")
    def tile_address(t: wp.tile(dtype=dtype, shape=(size,), storage="shared"), offset: int) -> wp.uint64: ...

    return tile_address


_ENTRY_PRODUCTS = """
const float* l = reinterpret_cast<const float*>(factor);
const int* ab = reinterpret_cast<const int*>(pairs);
auto product = [&](long long u) -> float {  // update pair u: L_ik s_k L_jk
#if defined(__CUDA_ARCH__)
    const int2 pair = __ldg(reinterpret_cast<const int2*>(ab) + u);
    const int a = pair.x, b = pair.y;
#else
    const int a = ab[2 * u], b = ab[2 * u + 1];
#endif
    const float x = l[a ^ (a >> 31)];  // a < 0: column -1 - a, a body node's (s_k = -1)
    return (a < 0 ? -x : x) * l[b];
};
float acc = value;
const long long last = end, step = stride;  // 64-bit indices: the compiler steps the addresses themselves
long long u = begin + first;
for (; u + 3 * step < last; u += 4 * step)  // four products per pass: their loads are in flight together
    acc -= product(u) + product(u + step) + product(u + 2 * step) + product(u + 3 * step);
for (; u < last; u += step)
    acc -= product(u);
return acc;
"""


@wp.func_native(_ENTRY_PRODUCTS)
def entry_products(factor: wp.uint64, pairs: wp.uint64, begin: int, end: int, first: int, stride: int,
                   value: float) -> float:
    """value minus the sum of L_ik s_k L_jk over the update pairs begin + first, + stride, ... < end
    (pairs: the topology's update_ab, a negative first index -1 - k for a body node's column,
    s_k = -1; factor: the world's factor values). The value is an argument so that its load is in
    flight with the products'."""


_GATHER_COPY = """
float* out = reinterpret_cast<float*>(destination);
const float* in = reinterpret_cast<const float*>(source);
const int* at = reinterpret_cast<const int*>(index);
auto put = [&](int k, float v) { out[k] = reciprocal ? 1.0f / fabsf(v) : v; };
int k = lane;
for (; k + 3 * lanes < count; k += 4 * lanes) {  // four at a time: their loads are in flight together
    const float v0 = in[at[k]], v1 = in[at[k + lanes]], v2 = in[at[k + 2 * lanes]], v3 = in[at[k + 3 * lanes]];
    put(k, v0);
    put(k + lanes, v1);
    put(k + 2 * lanes, v2);
    put(k + 3 * lanes, v3);
}
for (; k < count; k += lanes)
    put(k, in[at[k]]);
"""


@wp.func_native(_GATHER_COPY)
def gather_copy(destination: wp.uint64, source: wp.uint64, index: wp.uint64, count: int, reciprocal: int, lane: int,
                lanes: int):
    """destination[k] = source[index[k]] (reciprocal: 1 / |source[index[k]]|) for k = lane, lane +
    lanes, ... < count."""


_SUBSTITUTE_LEVEL = """
// one level of supernode blocks of a substitution from a solve schedule (solve_schedule's layout,
// at ``schedule``): each row subtracts its entries outside its block, then a lane per block
// substitutes the block's own triangle
const int* plan = reinterpret_cast<const int*>(schedule);
const float* inverse_diagonal = reinterpret_cast<const float*>(inverse);
float* x = reinterpret_cast<float*>(vector);
const bool forward = phase == 1;  // FORWARD: rows gather their entries left of the block from the row-major copy
const float* values = reinterpret_cast<const float*>(forward ? rows : factor);
const int* index = plan + (forward ? blob_row : blob_entry);
const int* level_plan = plan + LEVEL_INTS * level;
const int range = forward ? 3 : 5;  // the record's forward or backward gather range
const int* records = plan + blob_diag;
const int first = level_plan[0];
const int end = first + level_plan[1];
int width = 1 << ((level_plan[2] >> (3 * phase)) & 7);
width = width < lanes ? width : lanes;
auto gather = [&](long long k, long long stop, long long stride) -> float {  // 64-bit: the addresses step
    float acc = 0.0f;
    for (; k + 3 * stride < stop; k += 4 * stride)  // four entries per pass: their loads are in flight together
        acc += (values[k] * x[index[k]] + values[k + stride] * x[index[k + stride]]
                + values[k + 2 * stride] * x[index[k + 2 * stride]]
                + values[k + 3 * stride] * x[index[k + 3 * stride]]);
    for (; k < stop; k += stride)
        acc += values[k] * x[index[k]];
    return acc;
};
if (width > 1) {  // the warp shares each row's gather
    for (int d = first; d < end; ++d) {
        const int* record = records + RECORD * d;
        float total = gather(record[range] + lane, record[range + 1], lanes);
#if defined(__CUDA_ARCH__)
        for (int offset = lanes >> 1; offset > 0; offset >>= 1)
            total += __shfl_xor_sync(0xffffffffu, total, offset);
#endif
        if (lane == 0)
            x[record[0]] -= total;
    }
} else {  // one row per lane
    for (int d = first + lane; d < end; d += lanes) {
        const int* record = records + RECORD * d;
        x[record[0]] -= gather(record[range], record[range + 1], 1);
    }
}
#if defined(__CUDA_ARCH__)
__syncwarp();
#endif
const int* blocks = plan + blob_block;
for (int b = level_plan[3] + lane; b < level_plan[3] + level_plan[4]; b += lanes) {
    const int* member = records + RECORD * blocks[b];  // the block's first record
    const int size = member[1];
    if (forward) {  // row t: its last t entries are the block's columns 0 .. t - 1
        for (int t = 0; t < size; ++t) {
            const int* record = member + RECORD * t;
            const float* own = values + record[4];
            const int j = record[0];
            float acc = x[j];
            for (int k = 0; k < t; ++k)
                acc -= own[k] * x[member[RECORD * k]];
            x[j] = acc * inverse_diagonal[j];
        }
    } else {  // column t: its first size - 1 - t entries below the diagonal are the block's rows t + 1 ..
        for (int t = size - 1; t >= 0; --t) {
            const int* record = member + RECORD * t;
            const float* own = values + (record[5] - (size - 1 - t));  // own[c - t - 1]: row c of the block
            const int j = record[0];
            float acc = x[j];
            for (int c = t + 1; c < size; ++c)
                acc -= own[c - t - 1] * x[member[RECORD * c]];
            x[j] = acc * inverse_diagonal[j];
        }
    }
}
""".replace("RECORD", str(BLOCK_RECORD)).replace("LEVEL_INTS", str(BLOCK_LEVEL))


@wp.func_native(_SUBSTITUTE_LEVEL)
def substitute_level(schedule: wp.uint64, level: int, phase: int, blob_diag: int, blob_block: int, blob_row: int,
                     blob_entry: int, factor: wp.uint64, rows: wp.uint64, inverse: wp.uint64, vector: wp.uint64,
                     lane: int, lanes: int):
    """One level of supernode blocks (solve_blocks) of the forward (phase FORWARD: rows gather
    their entries left of their block from the row-major copy ``rows``) or backward (columns
    gather their entries below the block from ``factor``) substitution of one world from its
    solve schedule (solve_schedule's layout, at ``schedule``, in shared or global memory): each
    row subtracts its gather, then a lane per block substitutes the block's triangle,
    v_j = (v_j - sum) / |L_jj| with the factor's reciprocal diagonal (``inverse``). The vector at
    ``vector``. Gathers: a row per lane, or the warp shares each row (a warp-shuffle sum;
    ``lanes`` must then be the whole warp)."""


_FACTOR_LEVEL_BLOCKS = """
// the triangles of a level's supernode blocks (a lane per block) and the rows below them (a lane per
// row), once their products with earlier blocks' columns are subtracted (sparse_factor)
const int* records = reinterpret_cast<const int*>(schedule) + blob_diag;
const int* block_list = reinterpret_cast<const int*>(schedule) + blob_block;
const int* below = reinterpret_cast<const int*>(rows);
const int* diagonal = reinterpret_cast<const int*>(diagonals);
const int* body = reinterpret_cast<const int*>(bodies);
float* l = reinterpret_cast<float*>(factor);
// a block's rows rho: its members (rho < size), then the rows below it (rho = size + r). Column k's
// entries below its diagonal are rows k + 1, k + 2, ..: row rho is entry rho - k - 1 from ``column``
auto column = [&](const int* member, int size, int k) -> long long {
    return member[RECORD * k + 5] - (size - 1 - k);
};
auto sign = [&](const int* member, int k) -> float { return body[member[RECORD * k]] >= 0 ? -1.0f : 1.0f; };
auto pivot_of = [&](const int* member, int size, int t) {  // s_t L_tt from the block's columns before t
    const int j = member[RECORD * t];
    float pivot = l[diagonal[j]];
    for (int k = 0; k < t; ++k) {
        const float x = l[column(member, size, k) + (t - k - 1)];
        pivot -= sign(member, k) * x * x;
    }
    l[diagonal[j]] = body[j] >= 0 ? -sqrtf(-pivot) : sqrtf(pivot);
};
auto entry_of = [&](const int* member, int size, int t, int rho) {  // row rho's entry in column t
    const long long at = column(member, size, t) + (rho - t - 1);
    float value = l[at];
    for (int k = 0; k < t; ++k) {
        const long long ck = column(member, size, k);
        value -= l[ck + (rho - k - 1)] * sign(member, k) * l[ck + (t - k - 1)];
    }
    l[at] = value / l[diagonal[member[RECORD * t]]];
};
if (together) {  // the warp takes the blocks one after the other, column by column with its rows below
    for (int b = block_first; b < block_first + blocks; ++b) {
        const int* member = records + RECORD * block_list[b];
        const int size = member[1];
        const int last = RECORD * (size - 1);
        const int height = size + member[last + 6] - member[last + 5];  // its members and the rows below
        for (int t = 0; t < size; ++t) {
            if (lane == 0)
                pivot_of(member, size, t);
#if defined(__CUDA_ARCH__)
            __syncwarp();
#endif
            for (int rho = t + 1 + lane; rho < height; rho += lanes)
                entry_of(member, size, t, rho);
#if defined(__CUDA_ARCH__)
            __syncwarp();
#endif
        }
    }
    return;
}
for (int b = block_first + lane; b < block_first + blocks; b += lanes) {  // a lane per block
    const int* member = records + RECORD * block_list[b];  // the block's first record
    const int size = member[1];
    for (int t = 0; t < size; ++t) {
        pivot_of(member, size, t);
        for (int rho = t + 1; rho < size; ++rho)
            entry_of(member, size, t, rho);
    }
}
#if defined(__CUDA_ARCH__)
__syncwarp();
#endif
for (int q = row_first + lane; q < row_end; q += lanes) {  // a row below a block: its entries left to right
    const int* member = records + RECORD * below[2 * q];
    const int size = member[1];
    for (int t = 0; t < size; ++t)
        entry_of(member, size, t, size + below[2 * q + 1]);
}
""".replace("RECORD", str(BLOCK_RECORD))


@wp.func_native(_FACTOR_LEVEL_BLOCKS)
def factor_level_blocks(schedule: wp.uint64, blob_diag: int, blob_block: int, block_first: int, blocks: int,
                        rows: wp.uint64, row_first: int, row_end: int, diagonals: wp.uint64, bodies: wp.uint64,
                        factor: wp.uint64, together: int, lane: int, lanes: int):
    """Steps (2) and (3) of a level of factor_blocks on one world's factor (``factor``), once its
    block columns' products with earlier blocks are subtracted: a lane per block (blocks
    ``block_first`` .. of the solve schedule's block list, at ``schedule``) computes the pivots
    s_t L_tt and the entries of the block's triangle, then (after a warp barrier) a lane per row
    below a block (``rows``: factor_blocks' rows below, ``row_first`` .. ``row_end``) divides that
    row's entries by the triangle. With ``together`` the warp takes the blocks one after the
    other instead, column by column: a lane computes the pivot, then the lanes share the column's
    rows, in the block and below it, with a warp barrier after each (factor_blocks chooses).
    ``diagonals``: the diagonal entry of each position; ``bodies``: each position's body (>= 0: a
    body node, s = -1)."""


@wp.kernel
def body_roots(body_count: wp.array(dtype=wp.int32), body_inv_inertia: wp.array2d(dtype=wp.mat33),
               body_q: wp.array2d(dtype=wp.transform), root: wp.array2d(dtype=wp.mat33)):
    """R_q C with C C^T the body-frame inverse inertia (Cholesky; zero columns where it is
    singular): a square root of the world-frame inverse inertia, for the body nodes."""
    world, b = wp.tid()
    if b >= body_count[world]:
        return
    A = body_inv_inertia[world, b]
    l00 = wp.sqrt(wp.max(A[0, 0], 0.0))
    l10 = float(0.0)
    l20 = float(0.0)
    if l00 > 0.0:
        l10 = A[1, 0] / l00
        l20 = A[2, 0] / l00
    l11 = wp.sqrt(wp.max(A[1, 1] - l10 * l10, 0.0))
    l21 = float(0.0)
    if l11 > 0.0:
        l21 = (A[2, 1] - l20 * l10) / l11
    l22 = wp.sqrt(wp.max(A[2, 2] - l20 * l20 - l21 * l21, 0.0))
    C = wp.mat33(l00, 0.0, 0.0, l10, l11, 0.0, l20, l21, l22)
    root[world, b] = wp.quat_to_matrix(wp.transform_get_rotation(body_q[world, b])) * C


@wp.func
def _matrix_entry(pat: SparsePatterns, s: SystemArrays, p: int, eb: int, e: int, world: int,
                  row_J_c: wp.array2d(dtype=wp.spatial_vector), row_J_p: wp.array2d(dtype=wp.spatial_vector),
                  row_MJ_c: wp.array2d(dtype=wp.spatial_vector), row_MJ_p: wp.array2d(dtype=wp.spatial_vector),
                  row_compliance: wp.array2d(dtype=float), row_precond: wp.array2d(dtype=float),
                  body_inv_mass: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.mat33)):
    """Entry e of a world's matrix on the factor's pattern, following its matrix_recipe (the rows'
    and bodies' arrays: WorkArrays' and ModelArrays' of the same names, root: WorkArrays.sparse_root)."""
    code = pat.entry_recipe[eb + e]
    kind = code & 3
    value = float(0.0)
    if kind == RECIPE_BODY_DIAGONAL:
        value = -1.0
    elif kind == RECIPE_ROWS:
        pi = pat.entry_i[eb + e]
        pj = pat.entry_j[eb + e]
        i = _node_row(pat, s, p, pi, world)
        j = _node_row(pat, s, p, pj, world)
        if i >= 0 and j >= 0:  # both rows in use this step
            d = float(0.0)
            if code & 4 != 0:
                d += wp.dot(row_J_c[world, i], row_MJ_c[world, j])
            if code & 8 != 0:
                d += wp.dot(row_J_c[world, i], row_MJ_p[world, j])
            if code & 16 != 0:
                d += wp.dot(row_J_p[world, i], row_MJ_c[world, j])
            if code & 32 != 0:
                d += wp.dot(row_J_p[world, i], row_MJ_p[world, j])
            if i == j:
                d += row_compliance[world, i]
            value = row_precond[world, i] * d * row_precond[world, j]
        elif pi == pj:
            value = 1.0
    elif kind == RECIPE_ROW_BODY:
        position = pat.entry_i[eb + e]
        if code & 4 != 0:
            position = pat.entry_j[eb + e]
        i = _node_row(pat, s, p, position, world)
        if i >= 0:
            J = row_J_c[world, i]
            if code & 8 != 0:
                J = row_J_p[world, i]
            c = (code >> 4) & 7
            b = code >> 8
            if c < 3:
                value = wp.spatial_top(J)[c] * wp.sqrt(body_inv_mass[world, b])
            else:
                R = root[world, b]
                value = wp.dot(wp.spatial_bottom(J), wp.vec3(R[0, c - 3], R[1, c - 3], R[2, c - 3]))
            value = row_precond[world, i] * value
    return value


@wp.kernel
def sparse_matrix(pat: SparsePatterns, s: SystemArrays, m: ModelArrays, w: WorkArrays):
    """This step's matrix on the factor's pattern into s.A (once per step; every factor of the step
    starts from it): P D P between rows (without the body nodes' share), U between rows and body
    nodes, -I on body nodes; zero off the matrix's own pattern, the identity on unused rows and
    padding. Each entry follows its matrix_recipe: only the Jacobians of the bodies its rows share
    are loaded. One thread block per world (matrix_block threads), so that a world's Jacobians are
    loaded into one multiprocessor's cache."""
    world, lane = wp.tid()
    lanes = wp.block_dim()
    p = pat.world_pattern[world]
    eb = pat.entry_base[p]
    entries = pat.entry_base[p + 1] - eb
    e = lane
    while e < entries:
        s.A[world, e] = _matrix_entry(pat, s, p, eb, e, world, w.row_J_c, w.row_J_p, w.row_MJ_c, w.row_MJ_p,
                                      w.row_compliance, w.row_precond, m.body_inv_mass, w.sparse_root)
        e += lanes


# The matrix build with the rows staged in shared memory (staged_matrix_kernel): per position of the
# factor STAGE_FLOATS floats, component by component (structure of arrays): J_c, J_p, M^-1 J_c,
# M^-1 J_p scaled by the row's preconditioner (24), the diagonal's compliance term, 1 where the
# position stands for a row this step.
STAGE_FLOATS = 26
STAGE_MATRIX = True  # the staged build where it fits (False: sparse_matrix always; read at each build)
STAGE_BYTES = 64 * 1024  # larger stages keep sparse_matrix

_STAGED_ROWS = """
// entry (pi, pj) of P D P between two rows from the staged rows (component c of position k at
// stage[c * size + k]); bits 2-5 of the recipe: the body terms child-child, child-parent, parent-child,
// parent-parent
const float* stage = reinterpret_cast<const float*>(staged);
if (stage[25 * size + pi] == 0.0f || stage[25 * size + pj] == 0.0f)  // a row not in use this step
    return pi == pj ? 1.0f : 0.0f;
auto dot = [&](int a, int b) -> float {
    float acc = 0.0f;
    for (int c = 0; c < 6; ++c)
        acc += stage[(a + c) * size + pi] * stage[(b + c) * size + pj];
    return acc;
};
float d = pi == pj ? stage[24 * size + pi] : 0.0f;
if (code & 4) d += dot(0, 12);
if (code & 8) d += dot(0, 18);
if (code & 16) d += dot(6, 12);
if (code & 32) d += dot(6, 18);
return d;
"""


@wp.func_native(_STAGED_ROWS)
def staged_rows_entry(staged: wp.uint64, size: int, code: int, pi: int, pj: int) -> float:
    """A RECIPE_ROWS entry of the matrix (positions pi, pj) from the rows staged in shared memory
    (staged_matrix_kernel's layout, ``size`` positions per component)."""


@functools.cache
def staged_matrix_kernel(size: int):
    """sparse_matrix with each world's rows staged in shared memory first: a block per world
    copies, for every position of the factor that stands for a row this step, its Jacobians and
    M^-1 J scaled by the preconditioner, component by component (STAGE_FLOATS per position), so
    that an entry between two rows reads shared memory instead of looking its rows up and loading
    their spatial vectors. Entries with body nodes follow sparse_matrix."""
    staged = STAGE_FLOATS * size
    stage_address = _tile_address(staged, float)

    @wp.kernel(enable_backward=False, module="unique")
    def sparse_matrix_staged(pat: SparsePatterns, s: SystemArrays, m: ModelArrays, w: WorkArrays):
        """This step's matrix on the factor's pattern into s.A, as sparse_matrix, from rows staged
        in shared memory."""
        world, lane = wp.tid()
        lanes = wp.block_dim()
        stage = wp.tile_zeros(shape=staged, dtype=float, storage="shared")
        p = pat.world_pattern[world]
        row_J_c, row_J_p, row_MJ_c, row_MJ_p = w.row_J_c, w.row_J_p, w.row_MJ_c, w.row_MJ_p
        row_compliance, row_precond = w.row_compliance, w.row_precond
        k = lane
        while k < pat.perm.shape[1]:
            r = _node_row(pat, s, p, k, world)
            if r >= 0:
                scale = row_precond[world, r]
                Jc = row_J_c[world, r] * scale
                Jp = row_J_p[world, r] * scale
                Mc = row_MJ_c[world, r] * scale
                Mp = row_MJ_p[world, r] * scale
                for c in range(6):
                    tile_set(stage, c * size + k, Jc[c])
                    tile_set(stage, (6 + c) * size + k, Jp[c])
                    tile_set(stage, (12 + c) * size + k, Mc[c])
                    tile_set(stage, (18 + c) * size + k, Mp[c])
                tile_set(stage, 24 * size + k, scale * row_compliance[world, r] * scale)
                tile_set(stage, 25 * size + k, 1.0)
            k += lanes
        block_sync()
        at = stage_address(stage, 0)
        eb = pat.entry_base[p]
        entries = pat.entry_base[p + 1] - eb
        e = lane
        while e < entries:
            code = pat.entry_recipe[eb + e]
            value = float(0.0)
            if code & 3 == RECIPE_ROWS:
                value = staged_rows_entry(at, size, code, pat.entry_i[eb + e], pat.entry_j[eb + e])
            elif code & 3 != RECIPE_ZERO:
                value = _matrix_entry(pat, s, p, eb, e, world, row_J_c, row_J_p, row_MJ_c, row_MJ_p, row_compliance,
                                      row_precond, m.body_inv_mass, w.sparse_root)
            s.A[world, e] = value
            e += lanes

    return sparse_matrix_staged


@wp.kernel(enable_backward=False, module="unique", cuda_max_registers=SPARSE_REGISTERS)
def sparse_factor(pat: SparsePatterns, s: SystemArrays, mask: wp.array(dtype=wp.int32),
                  shift: wp.array2d(dtype=float), bilateral_only: int, row_count: wp.array(dtype=wp.int32),
                  row_kind: wp.array2d(dtype=wp.int32)):
    """L S L^T = A + diag(shift) into s.L for worlds with mask != 0 (shift per row of this step;
    rows of the pattern that stand for no row get shift[world, 0], body nodes none), A = s.A from
    sparse_matrix (with bilateral_only: its bilateral joint block and the body nodes, the identity
    elsewhere). S is -1 on body nodes, +1 elsewhere; a diagonal entry holds s_j L_jj. Level of
    supernode blocks by level (factor_blocks): the products with earlier blocks, then the blocks'
    triangles and the rows below them (factor_level_blocks). Then s.L_rows: the entries left of
    each diagonal row by row (in row_entry's order), so that the forward substitution reads them
    without an index load in between, and s.L_inv: 1 / |L_jj| by position, so that a substitution
    multiplies instead of dividing. The factor stays in global memory (benchmarks/results/README.md)."""
    world, lane = wp.tid()
    lanes = wp.block_dim()
    if mask[world] == 0:
        return
    p = pat.world_pattern[world]
    eb = pat.entry_base[p]
    ub = pat.update_base[p]
    entries = pat.entry_base[p + 1] - eb
    n = row_count[world]
    Lw = s.L[world]
    Lp = row_address(s.L, world)
    pairs = pair_address(pat.update_ab, ub)
    e = lane
    while e < entries:
        value = s.A[world, e]
        shifted = pat.entry_shifted[eb + e]  # a row's diagonal: its position
        if bilateral_only != 0:
            pi = pat.entry_i[eb + e]
            pj = pat.entry_j[eb + e]
            i = _node_row(pat, s, p, pi, world)
            j = _node_row(pat, s, p, pj, world)
            if not ((pat.node_body[p, pi] >= 0 or _bilateral(world, i, n, row_kind))
                    and (pat.node_body[p, pj] >= 0 or _bilateral(world, j, n, row_kind))):
                value = 0.0
                if pi == pj:
                    value = 1.0
        if shifted >= 0:
            row = _node_row(pat, s, p, shifted, world)
            if row < 0 or row >= n:
                row = 0
            value += shift[world, row]
        Lw[e] = value
        e += lanes
    block_sync()
    fb = pat.factor_base[p]
    schedule = int_address(pat.solve_blob, p * pat.blob_size)
    below = pair_address(pat.below_row, pat.below_base[p])
    diagonals = int_row_address(pat.diag, p)
    bodies = int_row_address(pat.node_body, p)
    for level in range(pat.factor_base[p + 1] - fb):
        q = FACTOR_LEVEL * (fb + level)
        first = pat.factor_plan[q]
        end = pat.factor_plan[q + 1]
        if group_width(pat.factor_plan[q + 2], FACTOR, lanes) > 1:  # the lanes share each entry's products
            for k in range(first, end):
                slot = pat.factor_slot[eb + k]  # (entry, its products with earlier blocks' columns)
                e = slot[0]
                total = -group_sum(entry_products(Lp, pairs, slot[1], slot[2], lane, lanes, 0.0), lanes)
                if lane == 0:
                    Lw[e] = Lw[e] - total
        else:  # one entry per lane, in order of their products, most first
            k = first + lane
            while k < end:
                slot = pat.factor_slot[eb + k]
                e = slot[0]
                Lw[e] = entry_products(Lp, pairs, slot[1], slot[2], 0, 1, Lw[e])
                k += lanes
        block_sync()
        together = (pat.factor_plan[q + 2] >> TOGETHER_BIT) & 1
        factor_level_blocks(schedule, pat.blob_diag, pat.blob_block, pat.factor_plan[q + 3], pat.factor_plan[q + 4],
                            below, pat.factor_plan[q + 5], pat.factor_plan[q + 6], diagonals, bodies, Lp, together,
                            lane, lanes)
        block_sync()
    rb = pat.row_base[p]
    gather_copy(row_address(s.L_rows, world), Lp, int_address(pat.row_entry, rb), pat.row_base[p + 1] - rb, 0, lane,
                lanes)
    gather_copy(row_address(s.L_inv, world), Lp, int_row_address(pat.diag, p), pat.perm.shape[1], 1, lane, lanes)


@wp.func
def _gather_rhs(v: Any, vb: int, pat: SparsePatterns, s: SystemArrays, p: int, world: int,
                rhs: wp.array2d(dtype=float), lane: int, lanes: int):
    """The right-hand side by the factor's positions into v from offset vb (0 at a position that
    stands for no row this step); the caller places the barrier."""
    k = lane
    while k < pat.perm.shape[1]:
        r = _node_row(pat, s, p, k, world)
        value = float(0.0)
        if r >= 0:
            value = rhs[world, r]
        tile_set(v, vb + k, value)
        k += lanes


@wp.func
def _scatter_solution(v: Any, vb: int, pat: SparsePatterns, s: SystemArrays, p: int, world: int,
                      row_count: wp.array(dtype=wp.int32), lane: int, lanes: int, x_out: wp.array2d(dtype=float)):
    """x_out from the solved vector (at offset vb of v), zero on the rows not in use this step."""
    k = lane
    while k < pat.perm.shape[1]:
        r = _node_row(pat, s, p, k, world)
        if r >= 0:
            x_out[world, r] = v[vb + k]
        k += lanes
    k = row_count[world] + lane
    while k < x_out.shape[1]:
        x_out[world, k] = 0.0
        k += lanes


@functools.cache
def solve_kernel(size: int):
    """Solve kernel with the world's vector in a shared tile of ``size`` rows and its schedule read
    from global memory (the factor stays in global memory: benchmarks/results/README.md)."""
    vector_address = _tile_address(size, float)

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=SPARSE_REGISTERS)
    def sparse_solve(pat: SparsePatterns, s: SystemArrays, mask: wp.array(dtype=wp.int32),
                     rhs: wp.array2d(dtype=float), row_count: wp.array(dtype=wp.int32), x_out: wp.array2d(dtype=float)):
        """x = (L S L^T)^-1 rhs for worlds with mask != 0: forward substitution level of supernode
        blocks by level (rows gather their entries left of their block, then a lane per block
        substitutes its triangle), the signs S (body nodes), backward in reverse (columns gather
        their entries below their block, then the blocks); the lanes take one row each or share
        each row's gather. Body nodes start from 0 and their values are dropped."""
        world, lane = wp.tid()
        lanes = wp.block_dim()
        v = wp.tile_zeros(shape=size, dtype=float, storage="shared")
        if mask[world] == 0:
            return
        p = pat.world_pattern[world]
        _gather_rhs(v, 0, pat, s, p, world, rhs, lane, lanes)
        block_sync()
        _substitute_all(pat, s, p, world, int_address(pat.solve_blob, p * pat.blob_size), vector_address(v, 0), lane,
                        lanes)
        _scatter_solution(v, 0, pat, s, p, world, row_count, lane, lanes, x_out)

    return sparse_solve


@wp.func_native("reinterpret_cast<float*>(vector)[k] = -reinterpret_cast<float*>(vector)[k];")
def _negate_at(vector: wp.uint64, k: int):
    """v_k = -v_k of a vector at an address."""


@wp.func
def _substitute_all(pat: SparsePatterns, s: SystemArrays, p: int, world: int, schedule: wp.uint64, vector: wp.uint64,
                    lane: int, lanes: int):
    """Forward substitution, the body nodes' signs, backward substitution of one world (one warp;
    one thread on the CPU) with its factor in s, from its schedule, level of supernode blocks by
    level with warp barriers."""
    factor = row_address(s.L, world)
    rows = row_address(s.L_rows, world)
    inverse = row_address(s.L_inv, world)
    levels = pat.solve_levels[p]
    for level in range(levels):
        substitute_level(schedule, level, FORWARD, pat.blob_diag, pat.blob_block, pat.blob_row, pat.blob_entry, factor,
                         rows, inverse, vector, lane, lanes)
        warp_sync()
    if pat.has_body_nodes[p] != 0:
        k = lane
        while k < pat.perm.shape[1]:
            if pat.node_body[p, k] >= 0:
                _negate_at(vector, k)
            k += lanes
        warp_sync()
    for back in range(levels):
        substitute_level(schedule, levels - 1 - back, BACKWARD, pat.blob_diag, pat.blob_block, pat.blob_row,
                         pat.blob_entry, factor, rows, inverse, vector, lane, lanes)
        warp_sync()


# The solve with its schedule in shared memory (shared_solve_kernel), on GPUs for batches of one
# topology large enough to give at least half of the multiprocessors a block of 32 worlds (one warp
# each); the others keep the global kernel.
SOLVE_WORLDS_PER_BLOCK = 32
SOLVE_SHARED = True  # the shared-schedule solve where it fits (False: the global kernel; read at each solve)
SOLVE_SHARED_BYTES = 160 * 1024  # larger schedules and vectors keep the global kernel (a block holds at most 227 KiB)


@functools.cache
def shared_solve_kernel(size: int, worlds: int, blob_size: int):
    """The solve with each block's schedule in shared memory: a block of ``worlds`` warps (one
    world each) copies the solve schedule of its first world's analysis (solve_schedule) into
    shared memory once, then every warp substitutes its own world level by level with warp
    barriers only; a world of another analysis reads its schedule from global memory. The levels'
    bounds, the positions' records and the column and row indices are then shared-memory loads,
    and a level's chain of dependent steps keeps one global load (the factor's values)."""
    vector_size = size * worlds
    vector_address = _tile_address(vector_size, float)
    blob_address = _tile_address(blob_size, wp.int32)

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=SPARSE_REGISTERS)
    def sparse_solve_shared(pat: SparsePatterns, s: SystemArrays, mask: wp.array(dtype=wp.int32),
                            rhs: wp.array2d(dtype=float), row_count: wp.array(dtype=wp.int32), num_worlds: int,
                            x_out: wp.array2d(dtype=float)):
        """x = (L S L^T)^-1 rhs for worlds with mask != 0 (as solve_kernel's sparse_solve)."""
        block, t = wp.tid()
        lanes = wp.block_dim() // worlds
        slot = t // lanes
        lane = t - slot * lanes
        world = block * worlds + slot
        p0 = pat.world_pattern[block * worlds]
        schedule = wp.tile_load(pat.solve_blob, shape=(blob_size,), offset=(p0 * blob_size,), storage="shared")
        v = wp.tile_zeros(shape=vector_size, dtype=float, storage="shared")
        if world >= num_worlds:
            return
        if mask[world] == 0:
            return
        p = pat.world_pattern[world]
        vb = slot * size
        _gather_rhs(v, vb, pat, s, p, world, rhs, lane, lanes)
        warp_sync()
        schedule_at = int_address(pat.solve_blob, p * blob_size)
        if p == p0:
            schedule_at = blob_address(schedule, 0)
        _substitute_all(pat, s, p, world, schedule_at, vector_address(v, vb), lane, lanes)
        _scatter_solution(v, vb, pat, s, p, world, row_count, lane, lanes, x_out)

    return sparse_solve_shared


def factor(model, shift, mask, bilateral_only: bool = False, system: SparseSystem | None = None) -> None:
    """Factor P D P + diag(shift) (shift (W, R) per row; or the bilateral joint block) of every
    masked world into the system's L (system: the model's PADMM system when None)."""
    system = model.sparse_system if system is None else system
    wp.launch_tiled(sparse_factor, dim=[model.num_worlds], block_dim=sparse_block(model.device), device=model.device,
                    inputs=[system.pat, system.arrays, mask, shift, int(bilateral_only), model.work.row_count,
                            model.row_kind])


def solve(model, rhs, mask, x_out, shared: bool | None = None, system: SparseSystem | None = None) -> None:
    """x_out = (L S L^T)^-1 rhs with the system's stored factors, for every masked world (rows of
    x_out below row_count that the system's factor rows do not stand for are left alone). shared:
    the schedule in shared memory (shared_solve_kernel; None: SOLVE_SHARED on GPUs for batches
    of one topology). system: the model's PADMM system when None."""
    system = model.sparse_system if system is None else system
    size, device, lanes = vector_size(system), wp.get_device(model.device), sparse_block(model.device)
    if shared is None:
        shared = (SOLVE_SHARED and device.is_cuda and len(system.analyses) == 1
                  and model.num_worlds >= SOLVE_WORLDS_PER_BLOCK * device.sm_count // 2
                  and 4 * (system.pat.blob_size + SOLVE_WORLDS_PER_BLOCK * size) <= SOLVE_SHARED_BYTES)
    arguments = [system.pat, system.arrays, mask, rhs, model.work.row_count]
    if shared:
        worlds = SOLVE_WORLDS_PER_BLOCK if device.is_cuda else 1
        wp.launch_tiled(shared_solve_kernel(size, worlds, system.pat.blob_size), dim=[-(-model.num_worlds // worlds)],
                        block_dim=lanes * worlds, device=device, inputs=[*arguments, model.num_worlds, x_out])
    else:
        wp.launch_tiled(solve_kernel(size), dim=[model.num_worlds], block_dim=lanes, device=device,
                        inputs=[*arguments, x_out])


def matrix(model, system: SparseSystem) -> None:
    """This step's P D P on the system's pattern (system.A), from the rows built by engine.dynamics."""
    size = vector_size(system)
    kernel = staged_matrix_kernel(size) if STAGE_MATRIX and 4 * STAGE_FLOATS * size <= STAGE_BYTES else sparse_matrix
    wp.launch_tiled(kernel, dim=[model.num_worlds], block_dim=matrix_block(model.device), device=model.device,
                    inputs=[system.pat, system.arrays, model.arrays, model.work.arrays])


def prepare(model) -> None:
    """Once per step, after the dual problem is built: which of this step's rows each factor row
    of the PADMM system stands for, and the matrix's values on its pattern."""
    work, W, system = model.work, model.num_worlds, model.sparse_system
    if model.has_contacts:  # else the map is fixed at packing (engine.pack)
        wp.launch(map_joint_rows, dim=(W, system.rows), inputs=[model.contact_row_start],
                  outputs=[system.real], device=model.device)
        wp.launch(map_contact_rows, dim=(W, model.contact_capacity),
                  inputs=[model.contact_row_start, work.contact_count, work.contact_key],
                  outputs=[system.real], device=model.device)
    matrix(model, system)


def roots(model, body_q) -> None:
    """Once per step, with the configuration of the dynamics: the square roots of the body nodes'
    inverse inertias (nothing to do where no topology keeps body nodes)."""
    if model.sparse_body_nodes:  # either system's
        wp.launch(body_roots, dim=(model.num_worlds, model.max_bodies), device=model.device,
                  inputs=[model.body_count, model.body_inv_inertia, body_q], outputs=[model.work.sparse_root])
