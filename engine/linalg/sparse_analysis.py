"""Sparse direct solves of the per-world Delassus matrix, host side: each mechanism topology is
analysed once into the factor's pattern and the schedules that the device kernels
(engine.linalg.sparse) follow.

Why sparse: in maximal coordinates two constraint rows couple only when they act on a common
body, so the preconditioned Delassus matrix P D P of a linkage and its Cholesky factor in a
minimum-degree order are sparse; a solve with it is exact.

Contacts: each collision pair has four candidate slots (engine.collide), so the factor keeps three
rows for every slot of every pair (slots a pair never fills are padding); each step
engine.linalg.sparse.prepare records which compacted row each factor row stands for (-1: unused,
the identity).

Bodies as nodes: a body with many rows couples them all into one dense block of the factor. It
can instead enter as six nodes of its own: with U = P J R (R R^T = M^-1 of those bodies) the
augmented matrix [[A, U], [U^T, -I]] has the Schur complement A + U U^T = P D P and is
quasi-definite, so an L S L^T factor (S = -1 on the body nodes) exists in any order, and its rows
couple only through a star (``choose_body_nodes`` keeps the bodies that shorten the schedule).

``analyze`` gives the elimination order, the elimination tree, the factor's pattern, its levels (a
column's level is one more than its children's highest; a level's columns are computed at once),
the left-looking products and the substitutions' lists; ``supernodes``, ``factor_blocks`` and
``solve_blocks`` schedule dense chains of the tree as blocks; ``matrix_recipe`` says which
Jacobians each matrix entry needs. Worlds of one topology share one analysis (``SparsePatterns``);
only the factor's values are per world (``SparseSystem``). The measurements behind these choices:
benchmarks/results/README.md, "Maximal path: design notes".
"""

import dataclasses
from typing import Any

import numpy as np
import warp as wp

from engine.model import ROW_ANGULAR, ROW_LINEAR

__all__ = ["Analysis", "SparsePatterns", "SparseSystem", "SystemArrays", "analyze", "batch_schedule_cost",
           "bilateral_factor_rows", "build_patterns", "choose_body_nodes", "factor_blocks", "make_system",
           "matrix_recipe", "minimum_degree", "schedule_cost", "shallowest", "solve_blocks", "solve_schedule",
           "supernodes"]


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

    body_nodes: bodies that enter as six nodes each (the module docstring; negative pivots).
    nodes: pad with identity nodes up to this many (every analysis of a batch has as many).
    blocks: add the device's supernode schedules (with_blocks; off for trial analyses whose
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
        # steps are estimated column by column, not by supernode blocks: the body nodes and
        # projection patterns were measured as chosen with this estimate
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
    column by column (its columns' first entries). Returns the records (one per position, in level
    order, BLOCK_RECORD ints: position, block size T, member index t, the forward gather's range in
    row_entry (the block's own entries follow it), the backward's in the column's entries (they
    precede it)), the levels (first record, records, mode: log2 of the lanes sharing a gather,
    forward and backward; first block, blocks) and each block's first record."""
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


# dependent steps a level of columns costs besides its sums, per phase (factor, forward, backward):
# its loads of level bounds and records, the factor's division pass, and barriers
LEVEL_STEPS = (8, 5, 5)
BLOCK_ROWS = 32  # most members of a supernode (supernodes): its rows' products take a lane each
BLOCK_RECORD = 7  # ints per position in the solves' supernode schedule (solve_blocks)
BLOCK_LEVEL = 5  # ints per level of it
FACTOR_LEVEL = 7  # ints per level of the factor's schedule by blocks (factor_blocks)
TOGETHER_BIT = wp.constant(9)  # of a level's mode in factor_blocks' plan: the warp factors its blocks together
# dependent steps a warp barrier costs in blocks_together's estimate (measured against 5 and never:
# benchmarks/results/README.md, "Maximal path: design notes")
BARRIER_STEPS = 1
SOLVES_PER_FACTOR = 4  # solves per factor in a step (PADMM iterations between penalty updates, projections)
BODY_NODE_ROWS = 12  # a body acted on by fewer rows never gains from nodes of its own (six of them)
# candidate bodies (most rows first) tried per topology, and the share of the plain schedule's
# estimated cost below which the chosen set is used: the estimate favours body nodes, so the set
# must save a fifth (benchmarks/results/README.md, "Maximal path: design notes")
BODY_NODE_TRIES = 16
BODY_NODE_MISSES = 4  # ... ending early after this many in a row that did not shorten it
BODY_NODE_GAIN = 0.8
# height weights that Tuning.sparse_ordering="shallow" tries besides plain minimum degree (their
# estimates: benchmarks/results/README.md, "Engine design notes (moved from the code)")
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
    where it saves a fifth or more (1 - BODY_NODE_GAIN)."""
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
    per item plus log2(g) + 1 for its sum (benchmarks/results/README.md, "Maximal path: design
    notes")."""
    lengths = np.asarray(lengths, np.int64)
    if len(lengths) == 0:
        return (0, 0) if with_cost else 0
    best, best_cost = 0, None
    for shift in (0, 5):  # one lane or the whole warp per item (groups of 2 to 16 measured slower)
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
    records, firsts, row, entry, size = blob_layout(levels, nodes, row_entries, entries)
    blob = np.zeros(size, np.int32)
    blob[:a.block_levels.size] = a.block_levels.reshape(-1)
    blob[records:records + a.block_records.size] = a.block_records.reshape(-1)
    blob[firsts:firsts + len(a.block_first)] = a.block_first
    blob[row:row + len(a.row_col)] = a.row_col
    blob[entry:entry + a.entries] = a.entry_i
    return blob


def blob_layout(levels: int, nodes: int, row_entries: int, entries: int) -> tuple[int, int, int, int, int]:
    """Offsets in a solve schedule (solve_schedule) of the records, the blocks' first records,
    row_col and entry_i, and its size (the levels start at 0)."""
    records = BLOCK_LEVEL * levels
    firsts = records + BLOCK_RECORD * nodes
    row = firsts + nodes
    entry = row + row_entries
    return records, firsts, row, entry, entry + entries


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
    row unused this step or of a padding node), RECIPE_ROW_BODY (a row and a body node: bit 2 set
    when the row is at entry_j's position, bit 3 when it acts on the body as its parent, bits 4-6
    the node's component, bits 8 up the body)."""
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
    shortest estimated schedule (shallowest; Tuning.sparse_ordering).
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
    s.blob_diag, s.blob_block, s.blob_row, s.blob_entry, s.blob_size = blob_layout(levels, nodes, row_entries, entries)
    return s, analyses, entries


@wp.struct
class SystemArrays:
    """A SparseSystem's per-world buffers (documented there), as one kernel argument."""

    real: wp.array2d(dtype=wp.int32)
    A: wp.array2d(dtype=float)
    L: wp.array2d(dtype=float)
    L_rows: wp.array2d(dtype=float)
    L_inv: wp.array2d(dtype=float)


@dataclasses.dataclass
class SparseSystem:
    """A batch's factor schedules (one per topology) and the per-world buffers of one factor:
    pat and analyses from build_patterns, rows (factor rows per world), nodes (positions per
    world), A and L (W, entries) the matrix on the pattern and its factor, L_rows (W, entries left
    of the diagonals) the factor's rows for the forward substitution, L_inv (W, nodes) the
    reciprocals 1 / |L_jj| of its diagonal by position, real (W, rows) the row of this step each
    factor row stands for (-1: unused); ``arrays`` (SystemArrays) groups the buffers for the
    kernels. A model has the PADMM's system (all rows, contact slots included: real rewritten every
    step where the batch has contacts, else fixed at packing) and, where
    Tuning.sparse_projection_pattern chooses it, the projection's (the bilateral joint rows alone,
    real fixed at packing; it uses the PADMM's buffers where they are wide enough)."""

    pat: SparsePatterns
    analyses: list
    rows: int
    nodes: int
    A: Any
    L: Any
    L_rows: Any
    L_inv: Any
    real: Any
    arrays: SystemArrays = dataclasses.field(init=False, repr=False)

    def __post_init__(self):
        self.arrays = SystemArrays()
        for name in SystemArrays.vars:
            setattr(self.arrays, name, getattr(self, name))

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

