"""Sparse direct solves with the per-world Delassus matrix: a Cholesky factor on the matrix's own
sparsity pattern, analysed on the host once per mechanism topology.

In maximal coordinates two constraint rows couple only when they act on a common body, so the
preconditioned Delassus matrix P D P of a linkage is sparse. Ordered by minimum degree, its
Cholesky factor stays sparse: a three-legs-per-side walker (336 factor rows with its contact
slots) has 6.0 k factor entries instead of 56 k dense and costs 85 k multiply-adds per factor
instead of 6.3 M; DR Legs hanging (186 rows) 2.8 k entries and 22 k multiply-adds, standing (264
rows with contact slots) 6.7 k and 106 k. A solve is then exact, where the matrix-free Conjugate
Residual solve (engine.matrix_free) stops after 25 operator products.

Contacts: a contact row's bodies change from step to step, but they always belong to one
collision pair, and each pair has four candidate slots (engine.collide). The factor therefore
has three rows for every candidate slot of every pair (bodies known in advance; slots a pair
never fills are padding), and each step ``prepare`` records which of the step's compacted rows
each factor row stands for (-1: unused, the identity).

Bodies as nodes: D = J M^-1 J^T couples every two rows that act on a common body, so a body with
many rows (a walker's torso carries 72: six legs' pivots and crank drives) puts all of them in
one dense block, the last ~90 columns of the factor, each its own level. Such a body can instead
enter the factor as six nodes of its own: with U = P J R (R R^T = M^-1 of those bodies) the
augmented matrix [[A, U], [U^T, -I]] has the Schur complement A + U U^T = P D P, and it is
quasi-definite, so an L S L^T factor (S = -1 on the body nodes) exists in any order; its rows
then couple only through a star. ``choose_body_nodes`` keeps the bodies that shorten the
estimated schedule. NVIDIA H100, 4096 worlds, same run: DR Legs standing 13.1 -> 7.0 ms per step
(factor entries 6.7 k -> 4.2 k, levels 95 -> 45), walkers in their gait 78 -> 53 ms per step
(levels 100 -> 36), same iterations and loop errors; DR Legs hanging keeps its plain schedule.

Host (``analyze``): a minimum-degree order of the factor rows (optionally weighted by the
elimination tree's height, for a shallower tree: ``shallowest``, SolverConfig.sparse_ordering), the
elimination tree, the factor's pattern, and schedules for the device:
- entries grouped by levels of the elimination tree (a column's level is one more than its
  children's highest), so that all columns of a level are computed at once;
- for every factor entry L_ij the pairs (L_ik, L_jk), k < j, whose products it subtracts
  (left-looking Cholesky);
- for every row of L its entries left of the diagonal (forward substitution), for every column
  its entries below the diagonal (backward substitution);
- supernode blocks (``supernodes``): chains of the elimination tree whose block of the factor is
  dense (a joint's five rows, the dense tail of the last columns), and levels of blocks; the
  factor and the solves go level of blocks by level (``factor_blocks``, ``solve_blocks``):
  DR Legs hanging has 71 levels of columns and 9 of blocks;
- per level and phase whether each lane takes its own items or the warp shares each item (a
  warp-shuffle sum), whichever has the shorter chain of dependent steps;
- per entry of the matrix, which of its rows' Jacobians it takes (``matrix_recipe``, from the
  factor rows' bodies, which a contact slot's rows share with their pair), so that the matrix
  build loads those alone instead of every row's bodies and both sides' Jacobians (NVIDIA H100,
  4096 worlds, per build: DR Legs hanging 0.36 -> 0.26 ms, standing as in Newton's example 0.53
  -> 0.41, the default walker 0.57 -> 0.41; the same bits). The build then runs a block per
  world with the world's rows staged in shared memory (staged_matrix_kernel: per step, hanging
  0.25 -> 0.15 ms, standing's two builds 0.71 -> 0.57).
Worlds of one topology share one analysis (``SparsePatterns`` holds each distinct one once);
only the factor's values are per world.

Device: one warp per world (one thread on the CPU); level by level with a barrier between levels
(the block's in the factor, the warp's in the solves), so results are deterministic (each entry
is summed by one lane, or by one warp in a fixed order). A level of blocks: in the factor, every
entry of its block columns less its products with earlier blocks' columns, in parallel; then a
lane per block for the block's own triangle and a lane per row below it (or, for a large block,
the warp column by column); in a substitution, every row less its entries outside its block, in
parallel, then a lane per block substitutes the block's triangle. NVIDIA H100, DR Legs at 4096
worlds, per step: solves hanging 0.69 -> 0.40 ms, standing 0.46 -> 0.33; factor hanging 0.62 ->
0.54, standing 1.52 -> 1.38 (the measurements below were made level of columns by level). The
solve keeps its vector in shared memory; the factor stays in global memory (copying it into
shared memory for every solve was 2.5x slower on an H100). Measured on an H100 at 4096 worlds
(benchmarks/results/README.md): DR Legs standing 15.4 ms per step (matrix-free 58 ms) with
loops closed to 6e-8 m (matrix-free 8e-4 m); hanging 3.3 ms (9.9 ms); random walkers 107 ms
(171 ms). Both kernels are bound by the latency of their chain of dependent steps: the level
schedule of DR Legs standing has a critical path of 6.3 k steps per factor and 2.5 k per solve,
and on the H100 a factor takes 1.4 ms and a solve 0.73 ms at 4096 worlds, 0.23 to 0.29 us (one
global-memory round trip) per step. The sums therefore load four products per pass, so that
their loads are in flight together (factor 10 to 25 % faster), and a step's chain of dependent
loads is kept short: each position carries its row's and column's ranges in one record of the
solve's schedule (now per supernode block: solve_blocks), the forward substitution reads a row-major copy of the factor
written after each factor (SparseSystem.L_rows) instead of looking each entry up (DR Legs hanging
4.2-4.4 -> 3.9 ms per step at 4096 worlds on an H100), and multiplies by the reciprocal diagonal
the factor leaves (SparseSystem.L_inv). With enough worlds of one topology, a
block of 32 worlds copies the solve's schedule into shared memory once (shared_solve_kernel), so
that a level waits on global memory only for the factor's values (DR Legs at 4096 worlds on an
H100: hanging 3.86 -> 3.65 ms per step, standing 5.96-6.12 -> 5.51). The factor's sums of
products and a solve's levels are native code on raw addresses (entry_products,
substitute_level): Warp's array indexing spends about eight integer instructions per load, and
both kernels are bound by their issued instructions (Nsight Compute: issue slots 62 % and 74 %
busy). NVIDIA H100, DR Legs at 4096 worlds, device clock, per step: hanging factor 0.835 -> 0.683
ms, solves 0.855 -> 0.690; standing factor 2.22 -> 1.87, solves 0.570 -> 0.456. Nsight Compute
then showed the factor waiting on loads (long scoreboard: 58 % of its stall samples): each
entry's value is now loaded before its sum, the matrix's copy reads one index per entry
(entry_shifted) instead of four, and the row-major copy and the reciprocal diagonal are gathered
four at a time (gather_copy): factor 0.684 -> 0.634 ms hanging, 1.86 -> 1.67 standing (same
call). Writing the copy and the reciprocals inside the level loop instead was 23-40 % slower.
The lanes take a level's entries in order of their number of products (now factor_blocks' slots),
so that a round's sums end together: factor 0.634-0.638 -> 0.584-0.587 ms hanging, 1.67 -> 1.57 standing.
"""

import dataclasses
import functools
from typing import Any

import numpy as np
import warp as wp

from engine.linear import block_sync
from engine.model import ROW_ANGULAR, ROW_LINEAR

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["SparsePatterns", "SparseSystem", "analyze", "batch_schedule_cost", "bilateral_factor_rows",
           "build_patterns", "choose_body_nodes", "factor", "make_system", "matrix", "prepare", "roots", "shallowest",
           "matrix_block", "shared_solve_kernel", "solve", "solve_schedule", "sparse_block"]


# Register cap per thread of the factor and solve kernels: at most 64 lets 32 one-warp blocks (the
# hardware's limit) stay on each multiprocessor. NVIDIA H100, 4096 worlds, one run, uncapped (two
# repeats) / 64 / 48: DR Legs standing 7.41, 6.96 / 6.54 / 7.17 ms per step, hanging 4.64, 5.62 /
# 4.52 / 4.70, walkers in their gait 48.3, 45.4 / 43.7 / 75.0 (factors 8.4, 8.1 / 7.1 / 8.5 ms).
SPARSE_REGISTERS = 64
VECTOR_STEP = 64  # shared tiles are sized in steps of this many elements (one kernel per size)


# Threads per world of the matrix build on a GPU (a block per world). NVIDIA H100, 4096 worlds, ms
# per step of the builds, a thread per entry / blocks of 128 / 256 / 512: DR Legs standing as in
# Newton's example 0.81 / 0.73 / 0.71 / 0.93, hanging 0.27 / 0.25 / 0.25 / 0.37.
MATRIX_BLOCK = 256


def matrix_block(device) -> int:
    """Threads per world of the matrix build (sparse_matrix): MATRIX_BLOCK on a GPU, one on the CPU."""
    return MATRIX_BLOCK if wp.get_device(device).is_cuda else 1


def sparse_block(device) -> int:
    """Threads per world of the sparse kernels: one warp on a GPU, one thread on the CPU."""
    return 32 if wp.get_device(device).is_cuda else 1


def minimum_degree(neighbours: list[set[int]], height_weight: float = 0.0) -> list[int]:
    """Elimination order by greedy minimum degree on the explicit elimination graph (ties go to
    the lowest index, so the order is reproducible). height_weight > 0: a node's key is its degree
    plus that weight times its level in the elimination tree so far (one more than the highest
    eliminated node it was a neighbour of, which the tree makes its descendant), so that among
    nodes of about the same degree the shallower go first and the tree stays short."""
    if height_weight < 0.0:
        raise ValueError(f"minimum_degree: height_weight must be >= 0, got {height_weight}")
    graph = [set(n) for n in neighbours]
    alive = set(range(len(graph)))
    height = [0] * len(graph)
    order = []
    while alive:
        if height_weight > 0.0:
            v = min(alive, key=lambda x: (len(graph[x]) + height_weight * height[x], x))
        else:
            v = min(alive, key=lambda x: (len(graph[x]), x))
        around = graph[v]
        for a in around:
            graph[a] |= around
            graph[a].discard(a)
            graph[a].discard(v)
            height[a] = max(height[a], height[v] + 1)
        graph[v] = set()
        alive.discard(v)
        order.append(v)
    return order


@dataclasses.dataclass
class Analysis:
    """The factor schedule of one topology (positions are places in the elimination order).

    Nodes: the factor rows (ids 0 .. rows - 1), then six for each body kept as a node of its own
    (``body_nodes``; ids rows + 6 k + c: body k's velocity component c scaled by a square root of
    its inverse mass matrix), then padding nodes (the identity) up to ``nodes``."""

    perm: np.ndarray  # (nodes,) position -> node id
    entry_i: np.ndarray  # (E,) row position of each factor entry
    entry_j: np.ndarray  # (E,) column position
    entry_coupled: np.ndarray  # (E,) 1 where the matrix entry itself can be non-zero (else fill)
    diag: np.ndarray  # (nodes,) entry of each column's diagonal
    col_begin: np.ndarray  # (nodes,) first entry below column j's diagonal
    col_end: np.ndarray  # (nodes,)
    update_begin: np.ndarray  # (E,) into update_a / update_b
    update_end: np.ndarray  # (E,)
    update_a: np.ndarray  # (U,) entry L_ik of each product subtracted from L_ij (-1 - entry: added, body node column)
    update_b: np.ndarray  # (U,) entry L_jk
    row_begin: np.ndarray  # (nodes,) into row_entry / row_col: the entries left of row j's diagonal
    row_end: np.ndarray  # (nodes,)
    row_entry: np.ndarray  # (N,)
    row_col: np.ndarray  # (N,) their column positions
    level_first: np.ndarray  # (levels,) first entry of each level (its diagonals come first)
    level_diag_end: np.ndarray  # (levels,) end of the level's diagonal entries
    level_end: np.ndarray  # (levels,)
    level_mode: np.ndarray  # (levels,) per phase (factor, forward, backward) log2 of the lanes sharing an item
    block_records: np.ndarray = None  # (nodes, BLOCK_RECORD) the solves' supernode schedule (solve_blocks)
    block_levels: np.ndarray = None  # (block levels, 5) first record, records, mode, first block, blocks
    block_first: np.ndarray = None  # (blocks,) record of each supernode block's first member, in level order
    factor_plan: np.ndarray = None  # (block levels, FACTOR_LEVEL) the factor's schedule by blocks (factor_blocks)
    factor_slots: np.ndarray = None  # (entries, 3) entry, its products with earlier blocks' columns
    factor_rows: np.ndarray = None  # (rows below blocks, 2) the block's first record, the row's index below it
    rows: int = 0  # factor rows (node ids below this are rows)
    body_nodes: tuple = ()  # bodies kept as nodes, in node order
    height_weight: float = 0.0  # of the elimination order (minimum_degree)
    factor_steps: int = 0  # estimated chain of dependent steps of a factor (schedule_steps)
    solve_steps: int = 0  # and of a solve (forward and backward)

    @property
    def entries(self) -> int:
        """Number of stored entries of the factor's pattern."""
        return len(self.entry_i)

    @property
    def nodes(self) -> int:
        """Rows, body nodes and padding nodes of the factor."""
        return len(self.perm)

    def node_row(self) -> np.ndarray:
        """(nodes,) factor row of each position, -1 for body and padding nodes."""
        return np.where(self.perm < self.rows, self.perm, -1).astype(np.int32)

    def node_body(self) -> np.ndarray:
        """(nodes,) body of each position's body node (-1 for rows and padding) and its component."""
        k = self.perm - self.rows
        body = np.full(len(self.perm), -1, np.int32)
        inside = (k >= 0) & (k < 6 * len(self.body_nodes))
        body[inside] = np.asarray(self.body_nodes, np.int32)[k[inside] // 6] if len(self.body_nodes) else -1
        return body, np.where(inside, k % 6, 0).astype(np.int32)


def analyze(row_body_c: np.ndarray, row_body_p: np.ndarray, body_nodes=(), nodes: int | None = None,
            blocks: bool = True, height_weight: float = 0.0) -> Analysis:
    """The factor schedule of one topology: rows i and j couple when they act on a common body
    (row_body_c, row_body_p: the bodies of every row, -1 for the world frame; a row with no body
    at all is a padding row, the identity).

    body_nodes: bodies whose rows are not coupled with each other through them; each gets six
    nodes instead (the augmented system [[A, U], [U^T, -I]] with U = P J R, R R^T = M^-1 of those
    bodies, whose Schur complement is A + U U^T = P D P: quasi-definite, so its LDL^T factor exists
    in any order, with negative pivots on the body nodes). A body acted on by many rows (a walker's
    torso: 72) makes all of them one dense block of the factor; as six nodes it costs a star.
    nodes: pad with identity nodes up to this many (every analysis of a batch has as many).
    blocks: add the supernode schedules of the device (with_blocks; off for trial analyses whose
    estimated cost alone is wanted). height_weight: of the elimination order (minimum_degree)."""
    rows = len(row_body_c)
    body_nodes = tuple(int(b) for b in body_nodes)
    own = rows + 6 * len(body_nodes)
    total = own if nodes is None else int(nodes)
    if total < own:
        raise ValueError(f"analyze: {total} nodes cannot hold {rows} rows and {len(body_nodes)} body nodes")
    body_rows: dict[int, list[int]] = {}
    for i in range(rows):
        for b in {int(row_body_c[i]), int(row_body_p[i])}:
            if b >= 0:
                body_rows.setdefault(b, []).append(i)
    neighbours = [set() for _ in range(total)]
    for b, members in body_rows.items():
        if b in body_nodes:
            first = rows + 6 * body_nodes.index(b)
            for i in members:
                neighbours[i].update(range(first, first + 6))
            for d in range(first, first + 6):
                neighbours[d].update(members)
        else:
            for i in members:
                neighbours[i].update(members)
    for i in range(total):
        neighbours[i].discard(i)
    perm = np.asarray(minimum_degree(neighbours, height_weight), np.int32)
    pos = np.empty(total, np.int64)
    pos[perm] = np.arange(total)
    negative = (perm >= rows) & (perm < own)  # body nodes' pivots are negative
    lower = [set() for _ in range(total)]  # the matrix's pattern below the diagonal, by column position
    for i in range(total):
        for j in neighbours[i]:
            if pos[i] > pos[j]:
                lower[pos[j]].add(int(pos[i]))
    coupled = [set(c) for c in lower]

    # symbolic factor: column patterns along the elimination tree
    cols = [set(s) for s in lower]
    parent = np.full(total, -1, np.int64)
    for j in range(total):
        if cols[j]:
            p = min(cols[j])
            parent[j] = p
            cols[p] |= cols[j] - {p}
    level = np.zeros(total, np.int64)
    for j in range(total):
        if parent[j] >= 0:
            level[parent[j]] = max(level[parent[j]], level[j] + 1)
    levels = int(level.max()) + 1 if total else 0

    # entries: per level its diagonals, then the columns' sub-diagonal entries (column by column)
    entry_i, entry_j, entry_coupled = [], [], []
    diag = np.zeros(total, np.int32)
    col_begin = np.zeros(total, np.int32)
    col_end = np.zeros(total, np.int32)
    level_first, level_diag_end, level_end = [], [], []
    by_level = [[] for _ in range(levels)]
    for j in range(total):
        by_level[level[j]].append(j)
    for members in by_level:
        level_first.append(len(entry_i))
        for j in members:
            diag[j] = len(entry_i)
            entry_i.append(j)
            entry_j.append(j)
            entry_coupled.append(1)
        level_diag_end.append(len(entry_i))
        for j in members:
            col_begin[j] = len(entry_i)
            for i in sorted(cols[j]):
                entry_i.append(i)
                entry_j.append(j)
                entry_coupled.append(1 if i in coupled[j] else 0)
            col_end[j] = len(entry_i)
        level_end.append(len(entry_i))
    entry_i = np.asarray(entry_i, np.int32)
    entry_j = np.asarray(entry_j, np.int32)
    E = len(entry_i)
    where = np.full((total, total), -1, np.int64)  # (i, j) -> entry
    where[entry_i, entry_j] = np.arange(E)

    # left-looking updates: L_ij -= L_ik s_k L_jk for every column k with both entries (s_k = -1
    # for body nodes: encoded in the first index as -1 - entry)
    targets, pair_a, pair_b = [], [], []
    for k in range(total):
        below = np.asarray(sorted(cols[k]), np.int64)
        if len(below) == 0:
            continue
        off = where[below, k]
        a, b = np.triu_indices(len(below))  # below[a] <= below[b]: column j = below[a], row i = below[b]
        targets.append(where[below[b], below[a]])
        pair_a.append(-1 - off[b] if negative[k] else off[b])
        pair_b.append(off[a])
    if targets:
        targets = np.concatenate(targets)
        order_u = np.argsort(targets, kind="stable")
        update_a = np.concatenate(pair_a)[order_u].astype(np.int32)
        update_b = np.concatenate(pair_b)[order_u].astype(np.int32)
        counts = np.bincount(targets, minlength=E)
    else:
        update_a = update_b = np.zeros(0, np.int32)
        counts = np.zeros(E, np.int64)
    update_end = np.cumsum(counts).astype(np.int32)
    update_begin = (update_end - counts).astype(np.int32)

    # rows of L left of the diagonal, for the forward substitution
    sub = entry_i != entry_j
    row_order = np.lexsort((entry_j[sub], entry_i[sub]))
    row_entry = np.flatnonzero(sub)[row_order].astype(np.int32)
    row_col = entry_j[row_entry].astype(np.int32)
    row_counts = np.bincount(entry_i[row_entry], minlength=total)
    row_end = np.cumsum(row_counts).astype(np.int32)
    row_begin = (row_end - row_counts).astype(np.int32)
    level_mode = np.zeros(levels, np.int32)
    steps = np.zeros(3, np.int64)
    for level, members in enumerate(by_level):
        first, end = level_first[level], level_end[level]
        diagonals = level_diag_end[level] - first  # the factor's lanes take each part in order of its products
        by_products = np.concatenate([np.sort(counts[first:first + diagonals])[::-1],
                                      np.sort(counts[first + diagonals:end])[::-1]])
        # the factor's and the substitutions' steps are estimated column by column, as before the
        # supernode blocks (factor_blocks, solve_blocks): the body nodes and projection patterns
        # chosen with this estimate are the measured ones
        phases = (by_products, row_counts[members], (col_end - col_begin)[members])
        for phase, lengths in enumerate(phases):
            shift, cost = group_shift(lengths, with_cost=True)
            level_mode[level] |= shift << (PHASE_BITS * phase)
            steps[phase] += cost + LEVEL_STEPS[phase]
    a = Analysis(perm, entry_i, entry_j, np.asarray(entry_coupled, np.int32), diag, col_begin, col_end,
                 update_begin, update_end, update_a, update_b, row_begin, row_end, row_entry, row_col,
                 np.asarray(level_first, np.int32), np.asarray(level_diag_end, np.int32),
                 np.asarray(level_end, np.int32), level_mode, rows=rows, body_nodes=body_nodes,
                 height_weight=float(height_weight), factor_steps=int(steps[0]), solve_steps=int(steps[1] + steps[2]))
    return with_blocks(a) if blocks else a


def with_blocks(a: Analysis) -> Analysis:
    """The analysis with its supernode schedules for the device (solve_blocks, factor_blocks),
    computed once."""
    if a.block_records is None:
        a.block_records, a.block_levels, a.block_first = solve_blocks(a)
        a.factor_plan, a.factor_slots, a.factor_rows = factor_blocks(a)
    return a


def supernodes(a: Analysis, cap: int | None = None) -> tuple[list[list[int]], np.ndarray]:
    """Fundamental supernodes of the factor's pattern: chains of positions m_0 < m_1 < ... of the
    elimination tree in which each member after the first has the one before as its only child,
    whose column pattern is the member itself and the member's own. Their block of the factor is
    dense, and the other columns of its rows lie left of m_0 (they descend from m_0). A joint's
    five rows are one such chain, and so is the dense tail of the last columns. At most ``cap``
    members each (BLOCK_ROWS). Returns the blocks (positions in chain order) and their levels
    (one more than the highest of the blocks below them)."""
    cap = BLOCK_ROWS if cap is None else cap
    n = a.nodes
    parent = np.where(a.col_end > a.col_begin, a.entry_i[np.minimum(a.col_begin, max(a.entries - 1, 0))], -1)
    children = np.bincount(parent[parent >= 0], minlength=n)
    only_child = np.full(n, -1, np.int64)
    for j in range(n):
        if parent[j] >= 0 and children[parent[j]] == 1:
            only_child[parent[j]] = j
    block = np.full(n, -1, np.int64)
    blocks: list[list[int]] = []
    for j in range(n):  # a chain's members come in increasing positions
        c = only_child[j]
        if c >= 0 and len(blocks[block[c]]) < cap:  # c, j's only child, is the last of its block
            below_c = a.entry_i[a.col_begin[c]:a.col_end[c]]
            below_j = a.entry_i[a.col_begin[j]:a.col_end[j]]
            if len(below_c) == len(below_j) + 1 and np.array_equal(below_c[1:], below_j):
                block[j] = block[c]
                blocks[block[c]].append(j)
                continue
        block[j] = len(blocks)
        blocks.append([j])
    level = np.zeros(len(blocks), np.int64)
    for b, members in enumerate(blocks):  # a block's children come before it
        top = parent[members[-1]]
        if top >= 0:
            level[block[top]] = max(level[block[top]], level[b] + 1)
    return blocks, level


def solve_blocks(a: Analysis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The solves' schedule by supernodes (supernodes): a level of the substitutions takes whole
    blocks. Forward, each row of a level's blocks first subtracts its entries left of its block
    (from L_rows, a lane per row or the warp per row), then a lane per block substitutes the
    block's triangle row by row (its rows' last entries); backward, each row subtracts its
    column's entries below the block, then a lane per block substitutes the block's triangle
    column by column (its columns' first entries). DR Legs hanging: 71 levels of single rows
    become 9 of blocks. Returns the records (one per position, in level order, BLOCK_RECORD
    ints: position, block size T, member index t, the forward gather's range in row_entry (the
    block's own entries follow it), the backward's in the column's entries (they precede it)),
    the levels (first record, records, mode: log2 of the lanes sharing a gather, forward and
    backward; first block, blocks) and each block's first record."""
    blocks, level = supernodes(a)
    levels = int(level.max()) + 1 if len(blocks) else 0
    records, block_first = [], []
    block_levels = np.zeros((levels, 5), np.int32)
    row_len = a.row_end - a.row_begin
    for lv in range(levels):
        block_levels[lv, 0], block_levels[lv, 3] = len(records), len(block_first)
        for b in np.flatnonzero(level == lv):
            members, T = blocks[b], len(blocks[b])
            block_first.append(len(records))
            for t, j in enumerate(members):
                fwd = (int(a.row_begin[j]), int(a.row_end[j]) - t)
                bwd = (int(a.col_begin[j]) + T - 1 - t, int(a.col_end[j]))
                if not (row_len[j] >= t and np.array_equal(a.row_col[fwd[1]:a.row_end[j]], members[:t])
                        and np.array_equal(a.entry_i[a.col_begin[j]:bwd[0]], members[t + 1:])):
                    raise AssertionError(f"solve_blocks: position {j} is not in a dense block of its chain")
                records.append((j, T, t, fwd[0], fwd[1], bwd[0], bwd[1]))
        block_levels[lv, 1] = len(records) - block_levels[lv, 0]
        block_levels[lv, 4] = len(block_first) - block_levels[lv, 3]
    records = np.asarray(records, np.int32).reshape(-1, BLOCK_RECORD)
    for lv in range(levels):
        part = records[block_levels[lv, 0]:block_levels[lv, 0] + block_levels[lv, 1]]
        for phase, (lo, hi) in ((FORWARD, (3, 4)), (BACKWARD, (5, 6))):
            block_levels[lv, 2] |= group_shift(part[:, hi] - part[:, lo]) << (PHASE_BITS * phase)
    return records, block_levels, np.asarray(block_first, np.int32)


def factor_blocks(a: Analysis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The factor's schedule by the solves' supernode blocks (solve_blocks), level of blocks by
    level: (1) every entry of the level's block columns less its products with the columns of
    earlier blocks (its update range without its last t pairs, t its column's member index: those
    are the block's own columns, the last of its list), the lanes taking the entries in order of
    their products (most first); (2) a lane per block factors the block's triangle (its own
    products, the pivots); (3) a lane per row below a block divides that row's entries by the
    triangle. Three barriers per level of blocks instead of two per level of single columns.
    Returns the plan (per level, FACTOR_LEVEL ints: first slot, slot end, mode (log2 of the lanes
    sharing an entry's products, the FACTOR phase), first block, blocks (in the solve schedule's
    block list), first row below, row end), the slots (entry, its range of products in update_ab)
    and the rows below the blocks (the block's first record, the row's index below the block)."""
    records = a.block_records
    plan, slots, below = [], [], []
    for first, count, _, first_block, blocks in a.block_levels:
        level_slots = []
        for d in range(first, first + count):
            j, T, t = (int(v) for v in records[d, :3])
            members = records[d - t:d - t + T, 0]
            for e in [int(a.diag[j])] + list(range(int(records[d, 5]) - (T - 1 - t), int(a.col_end[j]))):
                end = int(a.update_end[e]) - t
                if not np.array_equal(a.entry_j[a.update_b[end:a.update_end[e]]], members[:t]):
                    raise AssertionError(f"factor_blocks: entry {e}'s last products are not its block's columns")
                level_slots.append((e, int(a.update_begin[e]), end))
        level_slots.sort(key=lambda slot: slot[1] - slot[2])  # most products first (stable)
        slot_first, row_first = len(slots), len(below)
        slots += level_slots
        for b in a.block_first[first_block:first_block + blocks]:
            last = records[b + records[b, 1] - 1]  # its last member: the block's rows below are its column's
            below += [(int(b), r) for r in range(int(last[6] - last[5]))]
        mode = group_shift([hi - lo for _, lo, hi in level_slots]) << (PHASE_BITS * FACTOR)
        if blocks_together(records, a.block_first[first_block:first_block + blocks]):
            mode |= 1 << TOGETHER_BIT
        plan.append((slot_first, len(slots), mode, first_block, blocks, row_first, len(below)))
    return (np.asarray(plan, np.int32).reshape(-1, FACTOR_LEVEL), np.asarray(slots, np.int32).reshape(-1, 3),
            np.asarray(below, np.int32).reshape(-1, 2))


def blocks_together(records: np.ndarray, firsts) -> bool:
    """Whether a level's blocks (their first records) are factored by the warp together, block
    after block and column by column (two barriers per column), rather than a lane per block and
    a lane per row below (factor_blocks): whichever has the shorter chain of dependent steps. A
    lane's triangle of T costs T (T + 1) (T + 2) / 6 steps and a row below it T (T - 1) / 2;
    together, column t costs t for its pivot and (t + 1) per round of the warp over its rows."""
    sizes = np.array([records[b, 1] for b in firsts], np.int64)
    below = np.array([records[b + T - 1, 6] - records[b + T - 1, 5] for b, T in zip(firsts, sizes)], np.int64)
    triangles = sizes * (sizes + 1) * (sizes + 2) // 6
    rows = np.repeat(sizes * (sizes - 1) // 2, below)
    apart = (max(int(triangles[k::WARP_LANES].sum()) for k in range(min(WARP_LANES, len(sizes))))
             + (max(int(rows[k::WARP_LANES].sum()) for k in range(min(WARP_LANES, len(rows)))) if len(rows) else 0)
             + BARRIER_STEPS)
    together = sum(t + -(-(T - 1 - t + R) // WARP_LANES) * (t + 1) + 2 * BARRIER_STEPS
                   for T, R in zip(sizes, below) for t in range(T))
    return together < apart


# Dependent steps a level of columns costs besides its sums, per phase (factor: level bounds, the slot record
# (entry and update range), the entry's value, the division pass and two barriers; a substitution:
# level bounds, the diagonal's record, one barrier), and solves per factor in a step (PADMM
# iterations between penalty updates, plus the projections): the weights of schedule_cost.
LEVEL_STEPS = (8, 5, 5)
BLOCK_ROWS = 32  # most members of a supernode (supernodes): its rows' products take a lane each
BLOCK_RECORD = 7  # ints per position in the solves' supernode schedule (solve_blocks)
BLOCK_LEVEL = 5  # ints per level of it
FACTOR_LEVEL = 7  # ints per level of the factor's schedule by blocks (factor_blocks)
TOGETHER_BIT = wp.constant(9)  # of a level's mode in factor_blocks' plan: the warp factors its blocks together
# Dependent steps a warp barrier costs in blocks_together's estimate. NVIDIA H100, 4096 worlds, factor
# ms per step, never together / 5 / 1: DR Legs hanging 0.645 / 0.543 / 0.532, standing 1.414 / 1.376 /
# 1.340 (at 1 the standing's last five levels and hanging's last four go together).
BARRIER_STEPS = 1
SOLVES_PER_FACTOR = 4
BODY_NODE_ROWS = 12  # a body acted on by fewer rows never gains from nodes of its own (six of them)
# Candidate bodies (most rows first) tried per topology, and the share of the plain schedule's
# estimated cost below which the chosen set is used. The estimate is rough, favouring body nodes:
# DR Legs hanging's feet, 4 % shorter on paper, measured 0-5 % slower on an H100; with 16 tries
# hanging would take five bodies, 15 % shorter on paper, measured 1 % slower, so the set must save
# a fifth. NVIDIA H100, 4096 worlds, two repeats, 4 tries and a tenth / 16 tries and a fifth: DR Legs
# standing as in Newton's example 5.61, 5.63 / 5.36, 5.36 ms per step (bodies 0, 21, 22, 1 and then
# 3, 2, 4: estimated 16.2 k -> 12.9 k steps), standing on the file's gains 5.15, 5.15 / 5.06, 5.16
# (one body more), hanging 3.05, 3.06 (plain either way); walkers keep their torso alone.
BODY_NODE_TRIES = 16
BODY_NODE_MISSES = 4  # ... ending early after this many in a row that did not shorten it
BODY_NODE_GAIN = 0.8
# Height weights of the elimination orders that SolverConfig.sparse_ordering="shallow" tries besides
# plain minimum degree (minimum_degree, shallowest). Estimated schedules (schedule_cost) of plain
# minimum degree / weight 0.5 / 1 / 2, with each topology's body nodes (0.25 estimates as 0.5 on
# all but the default walker, and is kept on ties, being tried first): DR Legs hanging 11.6 / 8.6 /
# 8.9 / 8.6 k steps (71 -> 45-50 levels of columns, 9 -> 6-7 of blocks), standing as in Newton's
# example 12.6 / 10.3 / 14.7 / 14.7 k, its projection's own pattern 9.7 / 8.0 / 8.6 / 8.6 k, the
# default walker 7.5 / 6.4 / 6.4 / 6.3 k, a random Jansen walker 4.8 / 4.2 / 4.2 / 4.2 k (4.3 k in a
# batch padded to the larger walkers' nodes). A nested dissection (recursive separators of
# breadth-first levels) estimated longer than minimum degree on all but one of them.
HEIGHT_WEIGHTS = (0.25, 0.5, 1.0, 2.0)


def schedule_cost(a: Analysis) -> int:
    """Estimated dependent steps of a factor and the solves that use it."""
    return a.factor_steps + SOLVES_PER_FACTOR * a.solve_steps


def shallowest(row_body_c: np.ndarray, row_body_p: np.ndarray, base: Analysis, weights=()) -> Analysis:
    """Of ``base`` (an analysis with blocks) and the same topology and body nodes ordered with each
    height weight of ``weights`` (minimum_degree), the one with the shortest estimated schedule
    (schedule_cost; base where none is shorter)."""
    best = base
    for weight in weights:
        trial = analyze(row_body_c, row_body_p, base.body_nodes, blocks=False, height_weight=weight)
        if schedule_cost(trial) < schedule_cost(best):
            best = trial
    return with_blocks(best)


def choose_body_nodes(row_body_c: np.ndarray, row_body_p: np.ndarray) -> Analysis:
    """The analysis of one topology with the bodies that shorten its schedule kept as nodes:
    the bodies acted on by the most rows are tried one by one (greedy; at most BODY_NODE_TRIES,
    until BODY_NODE_MISSES in a row fail) and kept where schedule_cost drops, and the set is used
    where it saves a fifth or more (DR Legs standing as in Newton's example: seven bodies; a
    walker: its torso; DR Legs hanging: none)."""
    plain = best = analyze(row_body_c, row_body_p, blocks=False)
    bodies, counts = np.unique(np.concatenate([row_body_c, row_body_p]), return_counts=True)
    keep = bodies >= 0
    bodies, counts = bodies[keep], counts[keep]
    order = np.lexsort((bodies, -counts))
    chosen: list[int] = []
    misses = 0
    for b in bodies[order][:BODY_NODE_TRIES]:
        if counts[bodies == b][0] < BODY_NODE_ROWS or misses == BODY_NODE_MISSES:
            break
        trial = analyze(row_body_c, row_body_p, chosen + [int(b)], blocks=False)
        if schedule_cost(trial) < schedule_cost(best):
            best, chosen, misses = trial, chosen + [int(b)], 0
        else:
            misses += 1
    return with_blocks(best if schedule_cost(best) < BODY_NODE_GAIN * schedule_cost(plain) else plain)


WARP_LANES = 32
FACTOR, FORWARD, BACKWARD = wp.constant(0), wp.constant(1), wp.constant(2)  # the phases of level_mode
PHASE_BITS = wp.constant(3)  # level_mode holds log2 of the lane group width of the factor, forward and backward phases


def group_shift(lengths, with_cost: bool = False):
    """log2 of the lanes that share each item of a level (0: each lane takes its own items; 5: the
    warp takes the items one after the other), whichever has the shorter chain of dependent
    steps: items go round robin to 32 / g groups of g lanes, each spending ceil(length / g) steps
    per item plus log2(g) + 1 for its sum (shuffles counted twice made the native solves of DR
    Legs standing 6 % slower on an H100, three times 8 %)."""
    lengths = np.asarray(lengths, np.int64)
    if len(lengths) == 0:
        return (0, 0) if with_cost else 0
    best, best_cost = 0, None
    for shift in (0, 5):  # one lane or the whole warp per item (groups of 2 to 16 measured slower on an H100)
        g = 1 << shift
        groups = WARP_LANES // g
        per_item = -(-lengths // g) + shift + 1
        cost = max(int(per_item[k::groups].sum()) for k in range(min(groups, len(lengths))))
        if best_cost is None or cost < best_cost:
            best, best_cost = shift, cost
    return (best, best_cost) if with_cost else best


@wp.struct
class SparsePatterns:
    """The distinct analyses of a batch, concatenated (``*_base`` arrays hold each one's offset
    into the flat arrays; per-entry indices are relative to the analysis' first entry)."""

    world_pattern: wp.array(dtype=wp.int32)  # (W,) analysis of each world
    perm: wp.array2d(dtype=wp.int32)  # (P, N) factor row of each position (-1: a body or padding node)
    node_body: wp.array2d(dtype=wp.int32)  # (P, N) body of each position's body node (-1: a row or padding)
    has_body_nodes: wp.array(dtype=wp.int32)  # (P,)
    diag: wp.array2d(dtype=wp.int32)  # (P, N) the diagonal entry of each position
    entry_base: wp.array(dtype=wp.int32)  # (P + 1,)
    entry_i: wp.array(dtype=wp.int32)
    entry_j: wp.array(dtype=wp.int32)
    factor_base: wp.array(dtype=wp.int32)  # (P + 1,) first level of each analysis' factor plan
    factor_plan: wp.array(dtype=wp.int32)  # FACTOR_LEVEL ints per level of blocks (factor_blocks)
    factor_slot: wp.array(dtype=wp.vec3i)  # per slot (entry_base): its entry and its range of products in update_ab
    below_base: wp.array(dtype=wp.int32)  # (P + 1,)
    below_row: wp.array(dtype=wp.vec2i)  # rows below the blocks: the block's first record, the row's index
    update_base: wp.array(dtype=wp.int32)  # (P + 1,)
    update_ab: wp.array(dtype=wp.vec2i)  # (L_ik, L_jk) of each product, one 8-byte load
    row_base: wp.array(dtype=wp.int32)  # (P + 1,)
    row_entry: wp.array(dtype=wp.int32)
    entry_shifted: wp.array(dtype=wp.int32)  # per entry: a shifted position's diagonal its position, else -1
    entry_recipe: wp.array(dtype=wp.int32)  # per entry: how sparse_matrix computes it (matrix_recipe)
    solve_blob: wp.array(dtype=wp.int32)  # (P * blob_size,) each analysis' solve schedule (solve_schedule)
    solve_levels: wp.array(dtype=wp.int32)  # (P,) levels of supernode blocks of each analysis' solves
    blob_size: int
    blob_diag: int  # offsets in a schedule: per-position records, blocks, row_col, entry_i (levels at 0)
    blob_block: int
    blob_row: int
    blob_entry: int


def solve_schedule(a: Analysis, levels: int, nodes: int, row_entries: int, entries: int) -> np.ndarray:
    """One int array with all that a solve reads of an analysis, so that a thread block can copy
    it into shared memory at once (shared_solve_kernel). Layout, padded with zeros to the batch's
    largest analysis (``levels`` block levels, ``nodes``, ``row_entries``, ``entries``):
    - per level of supernode blocks (BLOCK_LEVEL ints, solve_blocks): its first record, its
      records, its mode, its first block, its blocks;
    - per position in level order (BLOCK_RECORD ints): its record (solve_blocks);
    - per block in level order: its first record (at most ``nodes`` blocks);
    - row_col (the column of each entry left of a diagonal, row by row);
    - entry_i (the row of each entry)."""
    blob = np.zeros(BLOCK_LEVEL * levels + (BLOCK_RECORD + 1) * nodes + row_entries + entries, np.int32)
    blob[:a.block_levels.size] = a.block_levels.reshape(-1)
    o = BLOCK_LEVEL * levels
    blob[o:o + a.block_records.size] = a.block_records.reshape(-1)
    o += BLOCK_RECORD * nodes
    blob[o:o + len(a.block_first)] = a.block_first
    o += nodes
    blob[o:o + len(a.row_col)] = a.row_col
    o += row_entries
    blob[o:o + a.entries] = a.entry_i
    return blob


def shifted_diagonals(a: Analysis) -> np.ndarray:
    """(E,) int32: for the diagonal entry of a position the factor's shift applies to (a factor row,
    or a padding node, which takes the world's first row's) that position; -1 elsewhere (body
    nodes and the entries off the diagonal)."""
    out = np.full(a.entries, -1, np.int32)
    positions = np.flatnonzero(a.node_body()[0] < 0)
    out[a.diag[positions]] = positions
    return out


# Codes of matrix_recipe (two low bits: what an entry of the matrix is)
RECIPE_ZERO, RECIPE_BODY_DIAGONAL = wp.constant(0), wp.constant(1)
RECIPE_ROWS, RECIPE_ROW_BODY = wp.constant(2), wp.constant(3)


def matrix_recipe(a: Analysis, row_body_c: np.ndarray, row_body_p: np.ndarray) -> np.ndarray:
    """(E,) int32: how sparse_matrix computes each entry of the matrix on the factor's pattern,
    from the factor rows' bodies (fixed per factor row: a contact slot's rows act on its pair's
    bodies), so that it loads only the Jacobians a value needs. Two low bits: RECIPE_ZERO (an entry
    the matrix does not couple: 0), RECIPE_BODY_DIAGONAL (-1), RECIPE_ROWS (two rows, or a row's
    diagonal: bits 2-5 the body terms child-child, child-parent, parent-child, parent-parent, of
    row i's side and row j's, on the bodies they share that are not nodes; 1 on the diagonal of a
    row unused this step or of a padding node), RECIPE_ROW_BODY (a row and a body node: bit 2 set when the row is at
    entry_j's position, bit 3 when it acts on the body as its parent, bits 4-6 the node's
    component, bits 8 up the body)."""
    node_row = a.node_row()
    node_body, node_comp = a.node_body()
    nodes = set(a.body_nodes)
    code = np.zeros(a.entries, np.int32)

    def row_terms(ri: int, rj: int) -> int:
        """RECIPE_ROWS with the body-term bits of factor rows ri and rj."""
        bits = RECIPE_ROWS
        for bit, (si, sj) in enumerate(((row_body_c, row_body_c), (row_body_c, row_body_p),
                                        (row_body_p, row_body_c), (row_body_p, row_body_p)), start=2):
            b = int(si[ri])
            if b >= 0 and b == int(sj[rj]) and b not in nodes:
                bits |= 1 << bit
        return bits

    for e in range(a.entries):
        pi, pj = int(a.entry_i[e]), int(a.entry_j[e])
        ri, rj = int(node_row[pi]), int(node_row[pj])
        bi, bj = int(node_body[pi]), int(node_body[pj])
        if pi == pj and bi >= 0:
            code[e] = RECIPE_BODY_DIAGONAL
        elif pi == pj:  # a row's diagonal, or a padding node's (the identity)
            code[e] = row_terms(ri, rj) if ri >= 0 else RECIPE_ROWS
        elif not a.entry_coupled[e]:
            code[e] = RECIPE_ZERO
        elif ri >= 0 and rj >= 0:
            code[e] = row_terms(ri, rj)
        elif (ri >= 0 and bj >= 0) or (rj >= 0 and bi >= 0):
            row, body, comp, swapped = (ri, bj, node_comp[pj], 0) if ri >= 0 else (rj, bi, node_comp[pi], 1)
            parent = int(row_body_c[row] != body)
            if row_body_c[row] != body and row_body_p[row] != body:
                raise AssertionError(f"matrix_recipe: entry {e} couples row {row} with body {body} it does not act on")
            code[e] = RECIPE_ROW_BODY | swapped << 2 | parent << 3 | int(comp) << 4 | body << 8
        else:
            raise AssertionError(f"matrix_recipe: entry {e} is coupled but joins no row (positions {pi}, {pj})")
    return code


def build_patterns(row_body_c: np.ndarray, row_body_p: np.ndarray, device, body_nodes: bool = True,
                   ordering: str = "minimum_degree") -> tuple[SparsePatterns, list[Analysis], int]:
    """Analyse every distinct topology of a batch once and upload the schedules.

    row_body_c, row_body_p: (W, V) bodies of every world's factor rows (engine.pack: its joint
    rows, then three rows per candidate contact slot of each collision pair, then padding).
    body_nodes: keep the bodies that shorten a schedule as nodes of the factor (choose_body_nodes).
    ordering: "minimum_degree", or "shallow": then each topology keeps the elimination order of
    minimum degree or of minimum degree with a height weight (HEIGHT_WEIGHTS), whichever has the
    shortest estimated schedule (shallowest; SolverConfig.sparse_ordering).
    Returns the device struct, the analyses (all with as many nodes) and the largest factor
    (entries per world)."""
    if ordering not in ("minimum_degree", "shallow"):
        raise ValueError(f"build_patterns: ordering must be 'minimum_degree' or 'shallow', not {ordering!r}")
    weights = HEIGHT_WEIGHTS if ordering == "shallow" else ()
    keys: dict[tuple, int] = {}
    sources: list[int] = []
    analyses: list[Analysis] = []
    world_pattern = np.zeros(len(row_body_c), np.int32)
    for w in range(len(row_body_c)):
        key = (row_body_c[w].tobytes(), row_body_p[w].tobytes())
        if key not in keys:
            keys[key] = len(analyses)
            sources.append(w)
            base = (choose_body_nodes(row_body_c[w], row_body_p[w]) if body_nodes
                    else analyze(row_body_c[w], row_body_p[w]))
            analyses.append(shallowest(row_body_c[w], row_body_p[w], base, weights))
        world_pattern[w] = keys[key]
    nodes = max(a.nodes for a in analyses)
    analyses = [a if a.nodes == nodes else analyze(row_body_c[w], row_body_p[w], a.body_nodes, nodes=nodes,
                                                   height_weight=a.height_weight)
                for a, w in zip(analyses, sources)]

    def base(sizes):
        return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32)

    def arr(value, dtype=wp.int32):
        return wp.array(np.ascontiguousarray(value), dtype=dtype, device=device)

    def flat(name):
        return arr(np.concatenate([getattr(a, name) for a in analyses]).astype(np.int32))

    s = SparsePatterns()
    s.world_pattern = arr(world_pattern)
    s.perm = arr(np.stack([a.node_row() for a in analyses]))
    s.node_body = arr(np.stack([a.node_body()[0] for a in analyses]))
    s.has_body_nodes = arr(np.array([int(len(a.body_nodes) > 0) for a in analyses], np.int32))
    s.diag = arr(np.stack([a.diag for a in analyses]).astype(np.int32))
    s.entry_base = arr(base([a.entries for a in analyses]))
    s.update_base = arr(base([len(a.update_a) for a in analyses]))
    s.row_base = arr(base([len(a.row_entry) for a in analyses]))
    s.update_ab = arr(np.concatenate([np.stack([a.update_a, a.update_b], axis=1) for a in analyses]).astype(np.int32),
                      dtype=wp.vec2i)
    s.factor_base = arr(base([len(a.factor_plan) for a in analyses]))
    s.factor_plan = arr(np.concatenate([a.factor_plan.reshape(-1) for a in analyses]))
    s.factor_slot = arr(np.concatenate([a.factor_slots for a in analyses]), dtype=wp.vec3i)
    s.below_base = arr(base([len(a.factor_rows) for a in analyses]))
    s.below_row = arr(np.concatenate([a.factor_rows for a in analyses]).reshape(-1, 2), dtype=wp.vec2i)
    for name in ("entry_i", "entry_j", "row_entry"):
        setattr(s, name, flat(name))
    s.entry_shifted = arr(np.concatenate([shifted_diagonals(a) for a in analyses]))
    s.entry_recipe = arr(np.concatenate([matrix_recipe(a, row_body_c[w], row_body_p[w])
                                         for a, w in zip(analyses, sources)]))
    levels = max(len(a.block_levels) for a in analyses)
    row_entries = max(len(a.row_col) for a in analyses)
    entries = max(a.entries for a in analyses)
    s.solve_blob = arr(np.concatenate([solve_schedule(a, levels, nodes, row_entries, entries) for a in analyses]))
    s.solve_levels = arr(np.array([len(a.block_levels) for a in analyses], np.int32))
    s.blob_size = BLOCK_LEVEL * levels + (BLOCK_RECORD + 1) * nodes + row_entries + entries
    s.blob_diag = BLOCK_LEVEL * levels
    s.blob_block = s.blob_diag + BLOCK_RECORD * nodes
    s.blob_row = s.blob_block + nodes
    s.blob_entry = s.blob_row + row_entries
    return s, analyses, max(a.entries for a in analyses)


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
def _node_row(pat: SparsePatterns, p: int, pos: int, world: int, real: wp.array2d(dtype=wp.int32)):
    """This step's row of the factor's position pos (-1: unused, a body node or padding)."""
    r = pat.perm[p, pos]
    if r < 0:
        return -1
    return real[world, r]


@wp.func
def _used(world: int, i: int, n: int, bilateral_only: int, row_kind: wp.array2d(dtype=wp.int32)):
    if i < 0 or i >= n:
        return False
    if bilateral_only != 0:
        kind = row_kind[world, i]
        return kind == ROW_LINEAR or kind == ROW_ANGULAR
    return True


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


@wp.func
def group_width(mode: int, phase: int, lanes: int):
    """Lanes that share each item of this level and phase (at most the block's)."""
    return wp.min(1 << ((mode >> (PHASE_BITS * phase)) & 7), lanes)


@functools.cache
def _vector_setter(size: int):
    """Element writes into a shared vector tile of one size without the block barrier of Warp's
    tile element assignment (lanes write different elements in divergent code)."""

    @wp.func_native("t.data(wp::tile_coord(i)) = value;")
    def tile_store_at(t: wp.tile(dtype=float, shape=(size,), storage="shared"), i: int, value: float): ...

    return tile_store_at


# Raw addresses and the inner sums of the factor and the solves in native code. Warp's array
# indexing wraps negative indices and scales each index by the array's runtime stride in 64 bits
# (about eight integer instructions per load); both kernels are bound by their issued
# instructions (Nsight Compute: issue slots 62 % (factor) and 74 % (solve) busy), and these sums
# are most of them. The arrays passed are contiguous (allocated by engine.sparse).
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
def body_roots(
    body_count: wp.array(dtype=wp.int32),
    body_inv_inertia: wp.array2d(dtype=wp.mat33),
    body_q: wp.array2d(dtype=wp.transform),
    # out
    root: wp.array2d(dtype=wp.mat33),
):
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
def _matrix_entry(pat: SparsePatterns, p: int, eb: int, e: int, world: int,
                  row_J_c: wp.array2d(dtype=wp.spatial_vector), row_J_p: wp.array2d(dtype=wp.spatial_vector),
                  row_MJ_c: wp.array2d(dtype=wp.spatial_vector), row_MJ_p: wp.array2d(dtype=wp.spatial_vector),
                  row_compliance: wp.array2d(dtype=float), row_precond: wp.array2d(dtype=float),
                  body_inv_mass: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.mat33),
                  real: wp.array2d(dtype=wp.int32)):
    """Entry e of a world's matrix on the factor's pattern, following its matrix_recipe."""
    code = pat.entry_recipe[eb + e]
    kind = code & 3
    value = float(0.0)
    if kind == RECIPE_BODY_DIAGONAL:
        value = -1.0
    elif kind == RECIPE_ROWS:
        pi = pat.entry_i[eb + e]
        pj = pat.entry_j[eb + e]
        i = _node_row(pat, p, pi, world, real)
        j = _node_row(pat, p, pj, world, real)
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
        i = _node_row(pat, p, position, world, real)
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
def sparse_matrix(
    pat: SparsePatterns,
    row_J_c: wp.array2d(dtype=wp.spatial_vector),
    row_J_p: wp.array2d(dtype=wp.spatial_vector),
    row_MJ_c: wp.array2d(dtype=wp.spatial_vector),
    row_MJ_p: wp.array2d(dtype=wp.spatial_vector),
    row_compliance: wp.array2d(dtype=float),
    row_precond: wp.array2d(dtype=float),
    body_inv_mass: wp.array2d(dtype=float),
    root: wp.array2d(dtype=wp.mat33),
    real: wp.array2d(dtype=wp.int32),
    # out
    A: wp.array2d(dtype=float),
):
    """This step's matrix on the factor's pattern (once per step; every factor of the step starts
    from it): P D P between rows (without the body nodes' share), U between rows and body nodes,
    -I on body nodes; zero off the matrix's own pattern, the identity on unused rows and padding.
    Each entry follows its matrix_recipe: only the Jacobians of the bodies its rows share are
    loaded. One thread block per world (matrix_block threads), so that a world's Jacobians are
    loaded into one multiprocessor's cache: with a thread per entry, a world's entries went to
    blocks on many multiprocessors, each of which loaded all its rows."""
    world, lane = wp.tid()
    lanes = wp.block_dim()
    p = pat.world_pattern[world]
    eb = pat.entry_base[p]
    entries = pat.entry_base[p + 1] - eb
    e = lane
    while e < entries:
        A[world, e] = _matrix_entry(pat, p, eb, e, world, row_J_c, row_J_p, row_MJ_c, row_MJ_p, row_compliance,
                                    row_precond, body_inv_mass, root, real)
        e += lanes


# The matrix build with the rows staged in shared memory (staged_matrix_kernel): per position of the
# factor STAGE_FLOATS floats, component by component (structure of arrays): J_c, J_p, M^-1 J_c,
# M^-1 J_p scaled by the row's preconditioner (24), the diagonal's compliance term, 1 where the
# position stands for a row this step.
# NVIDIA H100, 4096 worlds, ms per step of the builds, sparse_matrix / staged (256 threads per world,
# 512): DR Legs hanging 0.252, 0.256 / 0.152, 0.156 / 0.218, 0.216; standing as in Newton's example
# (two builds) 0.712, 0.713 / 0.565, 0.567 / 0.709, 0.710.
STAGE_FLOATS = 26
STAGE_MATRIX = True
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
    stage_set = _vector_setter(staged)
    stage_address = _tile_address(staged, float)

    @wp.kernel(enable_backward=False, module="unique")
    def sparse_matrix_staged(
        pat: SparsePatterns,
        row_J_c: wp.array2d(dtype=wp.spatial_vector),
        row_J_p: wp.array2d(dtype=wp.spatial_vector),
        row_MJ_c: wp.array2d(dtype=wp.spatial_vector),
        row_MJ_p: wp.array2d(dtype=wp.spatial_vector),
        row_compliance: wp.array2d(dtype=float),
        row_precond: wp.array2d(dtype=float),
        body_inv_mass: wp.array2d(dtype=float),
        root: wp.array2d(dtype=wp.mat33),
        real: wp.array2d(dtype=wp.int32),
        # out
        A: wp.array2d(dtype=float),
    ):
        """This step's matrix on the factor's pattern, as sparse_matrix, from rows staged in
        shared memory."""
        world, lane = wp.tid()
        lanes = wp.block_dim()
        stage = wp.tile_zeros(shape=staged, dtype=float, storage="shared")
        p = pat.world_pattern[world]
        k = lane
        while k < pat.perm.shape[1]:
            r = _node_row(pat, p, k, world, real)
            if r >= 0:
                scale = row_precond[world, r]
                Jc = row_J_c[world, r] * scale
                Jp = row_J_p[world, r] * scale
                Mc = row_MJ_c[world, r] * scale
                Mp = row_MJ_p[world, r] * scale
                for c in range(6):
                    stage_set(stage, c * size + k, Jc[c])
                    stage_set(stage, (6 + c) * size + k, Jp[c])
                    stage_set(stage, (12 + c) * size + k, Mc[c])
                    stage_set(stage, (18 + c) * size + k, Mp[c])
                stage_set(stage, 24 * size + k, scale * row_compliance[world, r] * scale)
                stage_set(stage, 25 * size + k, 1.0)
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
                value = _matrix_entry(pat, p, eb, e, world, row_J_c, row_J_p, row_MJ_c, row_MJ_p, row_compliance,
                                      row_precond, body_inv_mass, root, real)
            A[world, e] = value
            e += lanes

    return sparse_matrix_staged


@wp.kernel(enable_backward=False, module="unique", cuda_max_registers=SPARSE_REGISTERS)
def sparse_factor(
    pat: SparsePatterns,
    mask: wp.array(dtype=wp.int32),
    shift: wp.array2d(dtype=float),
    bilateral_only: int,
    row_count: wp.array(dtype=wp.int32),
    row_kind: wp.array2d(dtype=wp.int32),
    real: wp.array2d(dtype=wp.int32),
    A: wp.array2d(dtype=float),
    # out
    L: wp.array2d(dtype=float),
    L_rows: wp.array2d(dtype=float),
    L_inv: wp.array2d(dtype=float),
):
    """L S L^T = A + diag(shift) for worlds with mask != 0 (shift per row of this step; rows of the
    pattern that stand for no row get shift[world, 0], body nodes none), A from sparse_matrix
    (with bilateral_only: its bilateral joint block and the body nodes, the identity elsewhere).
    S is -1 on body nodes, +1 elsewhere; a diagonal entry holds s_j L_jj. Level of supernode
    blocks by level (factor_blocks): the products with earlier blocks, then the blocks' triangles
    and the rows below them (factor_level_blocks). Then L_rows: the entries
    left of each diagonal row by row (in row_entry's order), so that the forward substitution reads
    them without an index load in between, and L_inv: 1 / |L_jj| by position, so that a
    substitution multiplies instead of dividing. The factor stays in global memory:
    keeping it in shared memory while it is computed was 2x slower on an H100 (DR Legs standing,
    4096 worlds), as fewer worlds then fit on each multiprocessor at once."""
    world, lane = wp.tid()
    lanes = wp.block_dim()
    if mask[world] == 0:
        return
    p = pat.world_pattern[world]
    eb = pat.entry_base[p]
    ub = pat.update_base[p]
    entries = pat.entry_base[p + 1] - eb
    n = row_count[world]
    Lw = L[world]
    Lp = row_address(L, world)
    pairs = pair_address(pat.update_ab, ub)
    e = lane
    while e < entries:
        value = A[world, e]
        shifted = pat.entry_shifted[eb + e]  # a row's diagonal: its position
        if bilateral_only != 0:
            pi = pat.entry_i[eb + e]
            pj = pat.entry_j[eb + e]
            i = _node_row(pat, p, pi, world, real)
            j = _node_row(pat, p, pj, world, real)
            if not ((pat.node_body[p, pi] >= 0 or _used(world, i, n, 1, row_kind))
                    and (pat.node_body[p, pj] >= 0 or _used(world, j, n, 1, row_kind))):
                value = 0.0
                if pi == pj:
                    value = 1.0
        if shifted >= 0:
            row = _node_row(pat, p, shifted, world, real)
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
    gather_copy(row_address(L_rows, world), Lp, int_address(pat.row_entry, rb), pat.row_base[p + 1] - rb, 0, lane,
                lanes)
    gather_copy(row_address(L_inv, world), Lp, int_row_address(pat.diag, p), pat.perm.shape[1], 1, lane, lanes)


@wp.func
def _rhs_of(pat: SparsePatterns, p: int, k: int, world: int, real: wp.array2d(dtype=wp.int32),
            rhs: wp.array2d(dtype=float)):
    """The right-hand side at the factor's position k (0 where it stands for no row this step)."""
    r = _node_row(pat, p, k, world, real)
    if r >= 0:
        return rhs[world, r]
    return 0.0


@wp.func
def _scatter_solution(v: Any, vb: int, pat: SparsePatterns, p: int, world: int, real: wp.array2d(dtype=wp.int32),
                      row_count: wp.array(dtype=wp.int32), lane: int, lanes: int, x_out: wp.array2d(dtype=float)):
    """x_out from the solved vector (at offset vb of v), zero on the rows not in use this step."""
    k = lane
    while k < pat.perm.shape[1]:
        r = _node_row(pat, p, k, world, real)
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
    from global memory (the factor stays in global memory: copying it into shared memory for each
    solve was 2.5x slower on an H100)."""
    vector_set = _vector_setter(size)
    vector_address = _tile_address(size, float)

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=SPARSE_REGISTERS)
    def sparse_solve(
        pat: SparsePatterns,
        mask: wp.array(dtype=wp.int32),
        L: wp.array2d(dtype=float),
        L_rows: wp.array2d(dtype=float),
        L_inv: wp.array2d(dtype=float),
        rhs: wp.array2d(dtype=float),
        real: wp.array2d(dtype=wp.int32),
        row_count: wp.array(dtype=wp.int32),
        # out
        x_out: wp.array2d(dtype=float),
    ):
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
        rows = pat.perm.shape[1]
        k = lane
        while k < rows:
            vector_set(v, k, _rhs_of(pat, p, k, world, real, rhs))
            k += lanes
        block_sync()
        _substitute_all(pat, p, int_address(pat.solve_blob, p * pat.blob_size), row_address(L, world),
                        row_address(L_rows, world), row_address(L_inv, world), vector_address(v, 0), lane, lanes)
        _scatter_solution(v, 0, pat, p, world, real, row_count, lane, lanes, x_out)

    return sparse_solve


_WARP_SYNC = """
#if defined(__CUDA_ARCH__)
__syncwarp();
#endif
"""


@wp.func_native(_WARP_SYNC)
def warp_sync():
    """Barrier of the warp's lanes (memory ordering among them included; a no-op on the CPU)."""


@wp.func_native("reinterpret_cast<float*>(vector)[k] = -reinterpret_cast<float*>(vector)[k];")
def _negate_at(vector: wp.uint64, k: int):
    """v_k = -v_k of a vector at an address."""


@wp.func
def _substitute_all(pat: SparsePatterns, p: int, schedule: wp.uint64, factor: wp.uint64, rows: wp.uint64,
                    inverse: wp.uint64, vector: wp.uint64, lane: int, lanes: int):
    """Forward substitution, the body nodes' signs, backward substitution of one world (one warp;
    one thread on the CPU) from its schedule, level of supernode blocks by level with warp
    barriers."""
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
# topology, 32 worlds (one warp each) per thread block. NVIDIA H100, 4096 worlds, ms per step,
# schedule from global memory / shared with 4, 8, 16 worlds per block (one run): DR Legs hanging
# 3.87 / 4.62, 3.75, 3.68; standing 5.71 / 6.34, 5.59, 5.50; random walkers (two topologies, so
# half of the worlds still read theirs from global memory) 32.0 / 40.3, 35.7, 33.2: those keep the
# global kernel. A second run, global / 16 / 32 worlds per block: hanging 3.84 / 3.69 / 3.64,
# standing 5.72 / 5.55 / 5.47, the default walker (one topology) 26.6 / 24.9 / 24.5. Fewer worlds
# leave multiprocessors idle with 32 per block (DR Legs hanging at 1024 worlds: 2.58 ms, against
# 2.42 with the global kernel in a later run), so only batches that give at least half of the
# multiprocessors a block take it.
SOLVE_WORLDS_PER_BLOCK = 32
SOLVE_SHARED = True
SOLVE_SHARED_BYTES = 160 * 1024  # larger schedules and vectors keep the global kernel (an H100 block holds 227 KB)


@functools.cache
def shared_solve_kernel(size: int, worlds: int, blob_size: int):
    """The solve with each block's schedule in shared memory: a block of ``worlds`` warps (one
    world each) copies the solve schedule of its first world's analysis (solve_schedule) into
    shared memory once, then every warp substitutes its own world level by level with warp
    barriers only; a world of another analysis reads its schedule from global memory. The levels'
    bounds, the positions' records and the column and row indices are then shared-memory loads,
    and a level's chain of dependent steps keeps one global load (the factor's values)."""
    vector_size = size * worlds
    vector_set = _vector_setter(vector_size)
    vector_address = _tile_address(vector_size, float)
    blob_address = _tile_address(blob_size, wp.int32)

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=SPARSE_REGISTERS)
    def sparse_solve_shared(
        pat: SparsePatterns,
        mask: wp.array(dtype=wp.int32),
        L: wp.array2d(dtype=float),
        L_rows: wp.array2d(dtype=float),
        L_inv: wp.array2d(dtype=float),
        rhs: wp.array2d(dtype=float),
        real: wp.array2d(dtype=wp.int32),
        row_count: wp.array(dtype=wp.int32),
        num_worlds: int,
        # out
        x_out: wp.array2d(dtype=float),
    ):
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
        rows = pat.perm.shape[1]
        k = lane
        while k < rows:
            vector_set(v, vb + k, _rhs_of(pat, p, k, world, real, rhs))
            k += lanes
        warp_sync()
        schedule_at = int_address(pat.solve_blob, p * blob_size)
        if p == p0:
            schedule_at = blob_address(schedule, 0)
        _substitute_all(pat, p, schedule_at, row_address(L, world), row_address(L_rows, world),
                        row_address(L_inv, world), vector_address(v, vb), lane, lanes)
        _scatter_solution(v, vb, pat, p, world, real, row_count, lane, lanes, x_out)

    return sparse_solve_shared


@dataclasses.dataclass
class SparseSystem:
    """A batch's factor schedules (one per topology) and the per-world buffers of one factor:
    pat and analyses from build_patterns, rows (factor rows per world), nodes (positions per
    world), A and L (W, entries) the matrix on the pattern and its factor, L_rows (W, entries left
    of the diagonals) the factor's rows for the forward substitution, L_inv (W, nodes) the
    reciprocals 1 / |L_jj| of its diagonal by position, real (W, rows) the row of
    this step each factor row stands for (-1: unused). A model has the PADMM's system (all rows,
    contact slots included: real rewritten every step where the batch has contacts, else fixed at
    packing) and, where its batch has rows besides its
    bilateral joint rows and SolverConfig.sparse_projection_pattern asks for it, the projection's
    (the bilateral joint rows alone: real fixed at packing), which uses the PADMM's buffers for its
    matrix and factor where they are wide enough (make_system's share)."""

    pat: SparsePatterns
    analyses: list
    rows: int
    nodes: int
    A: Any
    L: Any
    L_rows: Any
    L_inv: Any
    real: Any

    @property
    def body_nodes(self) -> bool:
        """Whether any of its analyses keeps bodies as nodes (their roots are then needed)."""
        return any(a.body_nodes for a in self.analyses)


def make_system(patterns: tuple, num_worlds: int, device, real: np.ndarray | None = None,
                share: SparseSystem | None = None) -> SparseSystem:
    """A system from build_patterns' result and one factor's buffers. real: the fixed (W, rows)
    row of each factor row (None: rewritten every step by prepare). share: a system whose matrix
    and factor are not needed while this one's are (the PADMM's, once the projection runs): its
    buffers are used where they are wide enough."""
    pat, analyses, entries = patterns
    rows = max((a.rows for a in analyses), default=0)
    row_entries = max(1, max(len(a.row_entry) for a in analyses))
    real_array = (wp.zeros((num_worlds, rows), dtype=wp.int32, device=device) if real is None
                  else wp.array(np.ascontiguousarray(real, np.int32), dtype=wp.int32, device=device))

    def buffer(width: int, shared):
        if shared is not None and shared.shape[1] >= width:
            return shared
        return wp.zeros((num_worlds, width), dtype=float, device=device)

    return SparseSystem(pat, analyses, rows, analyses[0].nodes,
                        buffer(entries, share and share.A), buffer(entries, share and share.L),
                        buffer(row_entries, share and share.L_rows),
                        buffer(analyses[0].nodes, share and share.L_inv), real_array)


def batch_schedule_cost(analyses) -> int:
    """schedule_cost of a batch's slowest topology (every world of a batch waits on it)."""
    return max(schedule_cost(a) for a in analyses)


def bilateral_factor_rows(row_kind: np.ndarray, row_body_c: np.ndarray, row_body_p: np.ndarray,
                          joint_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The projection's factor rows: each world's bilateral joint rows (linear and angular; its
    first joint_rows[w] rows hold all joint rows), padded to the largest count. Returns (real,
    body_c, body_p), each (W, V): the row of each factor row (-1: padding) and its bodies."""
    W = len(row_kind)
    bilateral = (int(ROW_LINEAR), int(ROW_ANGULAR))
    picked = [np.flatnonzero(np.isin(row_kind[w, :joint_rows[w]], bilateral)) for w in range(W)]
    V = max(1, max(len(p) for p in picked))
    real = np.full((W, V), -1, np.int32)
    body_c = np.full((W, V), -1, np.int32)
    body_p = np.full((W, V), -1, np.int32)
    for w, rows in enumerate(picked):
        real[w, :len(rows)] = rows
        body_c[w, :len(rows)] = row_body_c[w, rows]
        body_p[w, :len(rows)] = row_body_p[w, rows]
    return real, body_c, body_p


def factor(model, shift, mask, bilateral_only: bool = False, system: SparseSystem | None = None) -> None:
    """Factor P D P + diag(shift) (shift (W, R) per row; or the bilateral joint block) of every
    masked world into the system's L (system: the model's PADMM system when None)."""
    system = model.sparse_system if system is None else system
    work = model.work
    wp.launch_tiled(sparse_factor, dim=[model.num_worlds], block_dim=sparse_block(model.device), device=model.device,
                    inputs=[system.pat, mask, shift, int(bilateral_only), work.row_count, model.row_kind,
                            system.real, system.A],
                    outputs=[system.L, system.L_rows, system.L_inv])


def solve(model, rhs, mask, x_out, shared: bool | None = None, system: SparseSystem | None = None) -> None:
    """x_out = (L S L^T)^-1 rhs with the system's stored factors, for every masked world (rows of
    x_out below row_count that the system's factor rows do not stand for are left alone). shared:
    the schedule in shared memory (shared_solve_kernel; None: SOLVE_SHARED on GPUs for batches
    of one topology). system: the model's PADMM system when None."""
    system = model.sparse_system if system is None else system
    work = model.work
    size = -(-system.nodes // VECTOR_STEP) * VECTOR_STEP
    device = wp.get_device(model.device)
    if shared is None:
        shared = (SOLVE_SHARED and device.is_cuda and len(system.analyses) == 1
                  and model.num_worlds >= SOLVE_WORLDS_PER_BLOCK * device.sm_count // 2
                  and 4 * (system.pat.blob_size + SOLVE_WORLDS_PER_BLOCK * size) <= SOLVE_SHARED_BYTES)
    if shared:
        worlds = SOLVE_WORLDS_PER_BLOCK if device.is_cuda else 1
        blocks = -(-model.num_worlds // worlds)
        wp.launch_tiled(shared_solve_kernel(size, worlds, system.pat.blob_size), dim=[blocks],
                        block_dim=sparse_block(model.device) * worlds, device=model.device,
                        inputs=[system.pat, mask, system.L, system.L_rows, system.L_inv, rhs, system.real,
                                work.row_count, model.num_worlds],
                        outputs=[x_out])
        return
    wp.launch_tiled(solve_kernel(size), dim=[model.num_worlds], block_dim=sparse_block(model.device),
                    device=model.device, inputs=[system.pat, mask, system.L, system.L_rows, system.L_inv, rhs,
                                                 system.real, work.row_count],
                    outputs=[x_out])


def matrix(model, system: SparseSystem) -> None:
    """This step's P D P on the system's pattern (system.A), from the rows built by engine.dynamics."""
    work = model.work
    size = -(-system.nodes // VECTOR_STEP) * VECTOR_STEP
    kernel = sparse_matrix
    if STAGE_MATRIX and 4 * STAGE_FLOATS * size <= STAGE_BYTES:
        kernel = staged_matrix_kernel(size)
    wp.launch_tiled(kernel, dim=[model.num_worlds], block_dim=matrix_block(model.device), device=model.device,
                    inputs=[system.pat, work.row_J_c, work.row_J_p, work.row_MJ_c, work.row_MJ_p,
                            work.row_compliance, work.row_precond, model.body_inv_mass, work.sparse_root, system.real],
                    outputs=[system.A])


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
