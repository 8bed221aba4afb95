"""Sparse direct solver (engine.linalg.sparse_analysis on the host, engine.linalg.sparse on the
device): its factor and solves against NumPy's dense linear algebra on the same matrices, its
symbolic analysis against a numeric factor, and whole steps against the dense Cholesky path.
"""

import dataclasses

import numpy as np
import pytest
import warp as wp

from engine import SolverConfig, Tuning, pack_worlds
from engine.dynamics import delassus
from engine.integrate import bilateral_block
from engine.linalg import sparse, sparse_analysis
from engine.model import ModelArrays, WorkArrays
from engine.pack import MAX_DENSE_ROWS
from engine.rollout import Stepper, rollout
from engine.scenes import make_scene
from engine.scenes_contact import box_stack, fourbar_limits, walker
from engine.spec import MechanismSpec
from morphopt.families import load_family


def random_walkers(count: int, seed: int = 3):
    family = load_family("walker")
    specs = []
    for params in family.space.sample(np.random.default_rng(seed), 4 * count):
        try:
            specs.append(family.build_spec(family.space.validate({**params, "legs_per_side": 1 + len(specs) % 2})))
        except ValueError:
            continue
        if len(specs) == count:
            return specs
    raise AssertionError("not enough walkers could be built")


def with_armature(spec, damping: float = 0.0):
    """The mechanism with an armature (and a damping) on every joint: a dynamics row each."""
    return dataclasses.replace(spec, joints=[dataclasses.replace(j, armature=0.01, damping=damping)
                                             for j in spec.joints])


def standing_delassus(model, device):
    """Step the walkers onto the ground (30 steps: contacts active), then the dense P D P of
    every world's rows built by the dense path's kernel, (W, R, R) on the device."""
    stepper = Stepper(model, model.state(), model.control(), chunk=10)
    for _ in range(3):
        stepper.advance()
    work, W, R = model.work, model.num_worlds, model.max_rows
    assert work.contact_count.numpy().min() > 0
    matrix = wp.zeros((W, R, R), dtype=float, device=device)
    wp.launch(delassus, dim=(W, R, R), device=device, inputs=[work.arrays], outputs=[matrix])
    return matrix


@pytest.mark.parametrize("body_nodes,ordering", [(True, "minimum_degree"), (False, "minimum_degree"),
                                                 (True, "shallow")])
@pytest.mark.parametrize("bilateral_only", [False, True])
def test_factor_and_solve_match_numpy(device, bilateral_only, body_nodes, ordering):
    """Walkers of two topologies standing on the ground (contacts active): (P D P + diag(shift)) x = b
    solved with the sparse factor equals NumPy's dense solve of the matrix the dense path builds,
    with the torso kept as a body node of the factor (quasi-definite, signed pivots) or not, and
    in the elimination order of minimum degree or of the shallowest estimated schedule."""
    one, two = random_walkers(2)  # one and two legs per side
    model = pack_worlds([one, two, one], device=device, dt=2e-3,
                        config=SolverConfig(tuning=Tuning(linear_solver="sparse", sparse_body_nodes=body_nodes,
                                                          sparse_ordering=ordering)))
    if ordering == "shallow":  # the walkers' topologies order with a height weight: shallower trees
        assert all(a.height_weight in sparse_analysis.HEIGHT_WEIGHTS for a in model.sparse_system.analyses)
    assert len(model.sparse_system.analyses) == 2  # one analysis per topology
    torso = one.body_index[one.bodies[0].name]
    assert [a.body_nodes for a in model.sparse_system.analyses] == ([(torso,)] * 2 if body_nodes else [()] * 2)
    assert model.sparse_system.pat.world_pattern.numpy().tolist() == [0, 1, 0]
    work, W, R = model.work, model.num_worlds, model.max_rows
    matrix = standing_delassus(model, device)
    if bilateral_only:
        wp.launch(bilateral_block, dim=(W, R, R), inputs=[model.arrays, work.arrays, matrix], device=device)
    # a shift per row (the PADMM factor caps the joint rows' penalty): 1e-3 to 1e-1, world by world
    shifts = (np.array([1e-3, 1e-2, 1e-1][:W], np.float32)[:, None]
              * np.random.default_rng(1).uniform(0.3, 1.0, (W, R))).astype(np.float32)
    sparse.prepare(model)
    sparse.factor(model, wp.array(shifts, device=device), wp.ones(W, dtype=wp.int32, device=device),
                  bilateral_only=bilateral_only)
    # the factor's copies for the solves: its rows left of the diagonals in row_entry's order, and
    # the reciprocals of its diagonal by position
    system = model.sparse_system
    L, L_rows, L_inv = system.L.numpy(), system.L_rows.numpy(), system.L_inv.numpy()
    for w, p in enumerate(system.pat.world_pattern.numpy()):
        a = system.analyses[p]
        np.testing.assert_array_equal(L_rows[w, :len(a.row_entry)], L[w, a.row_entry])
        np.testing.assert_allclose(L_inv[w, :a.nodes], 1.0 / np.abs(L[w, a.diag]), rtol=1e-6)
    rhs = np.random.default_rng(0).standard_normal((W, R)).astype(np.float32)
    solutions = []
    for shared in (False, True):  # the schedule read from global memory, or from a shared copy
        x = wp.full((W, R), 7.0, dtype=float, device=device)
        sparse.solve(model, wp.array(rhs, device=device), wp.ones(W, dtype=wp.int32, device=device), x, shared=shared)
        solutions.append(x.numpy())
    # both kernels sum in the same order; on a GPU the worlds of the second topology read their
    # schedule from global memory (a block copies its first world's)
    np.testing.assert_array_equal(solutions[0], solutions[1])
    x, matrix, n = solutions[1], matrix.numpy().astype(np.float64), work.row_count.numpy()
    for w in range(W):
        A = matrix[w, :n[w], :n[w]] + np.diag(shifts[w, :n[w]])

        expected = np.linalg.solve(A, rhs[w, :n[w]])
        # float32 factor: error within a few eps times the condition number
        bound = 50 * np.finfo(np.float32).eps * np.linalg.cond(A)
        assert np.abs(x[w, :n[w]] - expected).max() <= bound * np.abs(expected).max()
        assert np.all(x[w, n[w]:] == 0.0)  # rows not in use this step
    masked = wp.full((W, R), 7.0, dtype=float, device=device)
    sparse.solve(model, wp.array(rhs, device=device), wp.array([1, 0, 1], dtype=wp.int32, device=device), masked,
                 shared=True)
    assert np.all(masked.numpy()[1] == 7.0)  # a world out of the mask is left alone
    np.testing.assert_array_equal(masked.numpy()[[0, 2]], x[[0, 2]])


def test_analysis_covers_the_numeric_factor():
    """The symbolic pattern holds every non-zero of a numeric Cholesky factor of a random
    symmetric positive definite matrix with the rows' coupling pattern, and the update lists
    rebuild that factor exactly."""
    rng = np.random.default_rng(1)
    bodies = 9
    body_c = rng.integers(0, bodies, 40)
    body_p = np.where(rng.random(40) < 0.3, -1, rng.integers(0, bodies, 40))
    body_c[35:] = -1  # padding rows
    body_p[35:] = -1
    a = sparse_analysis.analyze(body_c, body_p)
    rows = len(body_c)
    assert sorted(a.perm) == list(range(rows))
    share = np.array([[i == j or bool({body_c[i], body_p[i]} & {body_c[j], body_p[j]} - {-1})
                       for j in range(rows)] for i in range(rows)])
    B = rng.standard_normal((rows, rows)) * share
    A = B @ B.T * share + rows * np.eye(rows)  # symmetric, diagonally dominant, on the pattern
    P = A[np.ix_(a.perm, a.perm)]
    L = np.linalg.cholesky(P)
    pattern = np.zeros((rows, rows), bool)
    pattern[a.entry_i, a.entry_j] = True
    assert np.abs(L[~pattern]).max(initial=0.0) < 1e-12
    # the factor rebuilt from the schedule (levels in order, the update lists, the diagonals)
    values = P[a.entry_i, a.entry_j].copy()
    for first, end, diag_end in zip(a.level_first, a.level_end, a.level_diag_end):
        for e in range(first, end):
            u = slice(a.update_begin[e], a.update_end[e])
            values[e] -= np.dot(values[a.update_a[u]], values[a.update_b[u]])
            if e < diag_end:
                values[e] = np.sqrt(values[e])
        for e in range(diag_end, end):
            values[e] /= values[a.diag[a.entry_j[e]]]
    assert np.allclose(values, L[a.entry_i, a.entry_j], atol=1e-12)
    # padding rows stay alone: no entry off the diagonal
    padding = set(np.flatnonzero(np.isin(a.perm, np.arange(35, rows))))
    assert all(i == j for i, j in zip(a.entry_i, a.entry_j) if i in padding or j in padding)


def test_height_weight_shortens_the_elimination_tree():
    """minimum_degree: without a height weight, the greedy order of a plain reference (least degree
    in the elimination graph, lowest index on ties); with one, a chain of 40 rows (each row sharing
    a body with the next), which minimum degree eliminates from one end to the other (40 levels,
    no fill), is taken from both ends and then every other row (as cyclic reduction does): at most
    half the levels for a little fill, and a shorter estimated schedule."""

    def reference(neighbours):
        """Greedy minimum degree on a dict of neighbour sets, eliminated node by node."""
        graph, order = {v: set(n) for v, n in enumerate(neighbours)}, []
        while graph:
            v = min(graph, key=lambda x: (len(graph[x]), x))
            for a in graph[v]:
                graph[a] = (graph[a] | graph[v]) - {a, v}
            del graph[v]
            order.append(v)
        return order

    rng = np.random.default_rng(4)
    for _ in range(5):
        n = 30
        neighbours = [set() for _ in range(n)]
        for i, j in rng.integers(0, n, (45, 2)):
            if i != j:
                neighbours[i].add(int(j))
                neighbours[j].add(int(i))
        assert sparse_analysis.minimum_degree(neighbours) == reference(neighbours)
    rows = 40
    body_c = np.arange(rows)
    body_p = np.arange(1, rows + 1)
    plain = sparse_analysis.analyze(body_c, body_p)
    assert len(plain.level_first) == rows and plain.entries == 2 * rows - 1  # one end to the other, no fill
    for weight in sparse_analysis.HEIGHT_WEIGHTS:
        shallow = sparse_analysis.analyze(body_c, body_p, height_weight=weight)
        assert sorted(shallow.perm) == list(range(rows)) and shallow.height_weight == weight
        assert list(shallow.perm[:2]) == [0, rows - 1]  # both ends first
        assert len(shallow.level_first) <= 10  # from 40 levels
        assert shallow.entries <= 3 * rows  # some fill, bought for the shorter tree
        assert sparse_analysis.schedule_cost(shallow) < sparse_analysis.schedule_cost(plain)
        # the height the order keeps is the elimination tree's level of each node (analyze's levels)
        level = np.zeros(rows, np.int64)
        for first, end in zip(shallow.level_first, shallow.level_diag_end):
            level[shallow.entry_j[first:end]] = np.searchsorted(shallow.level_first, first)
        pos = np.empty(rows, np.int64)
        pos[shallow.perm] = np.arange(rows)
        for j in range(rows):  # a column's parent is the first row below its diagonal
            below = shallow.entry_i[shallow.col_begin[j]:shallow.col_end[j]]
            if len(below):
                assert level[below.min()] > level[j]
    with pytest.raises(ValueError, match="height_weight"):
        sparse_analysis.minimum_degree([set()], height_weight=-1.0)


def test_shallow_ordering_keeps_the_shortest_schedule(device):
    """SolverConfig(sparse_ordering="shallow") on walkers of two topologies: each topology's
    analysis is the one of minimum degree or of a height weight with the shortest estimated
    schedule (never longer than minimum degree's, shorter for the walkers), and a batch stepped
    with it moves as the one in minimum-degree order does (a passive six-bar, sparse solver,
    0.2 s: the same motion to float32 rounding)."""
    one, two = random_walkers(2)
    plain = pack_worlds([one, two], device=device, dt=2e-3, config=SolverConfig(tuning=Tuning(linear_solver="sparse")))
    shallow = pack_worlds([one, two], device=device, dt=2e-3,
                          config=SolverConfig(tuning=Tuning(linear_solver="sparse", sparse_ordering="shallow")))
    for a, b in zip(plain.sparse_system.analyses, shallow.sparse_system.analyses):
        assert a.height_weight == 0.0 and a.body_nodes == b.body_nodes
        assert b.height_weight in (0.0, *sparse_analysis.HEIGHT_WEIGHTS)
        assert sparse_analysis.schedule_cost(b) <= sparse_analysis.schedule_cost(a)
    assert all(sparse_analysis.schedule_cost(b) < sparse_analysis.schedule_cost(a)  # every walker topology gains
               for a, b in zip(plain.sparse_system.analyses, shallow.sparse_system.analyses))
    # a topology padded to a batch's larger node count keeps the order chosen for it alone: a chain
    # of 24 rows beside a hub (five rows from each of 12 spokes to body 0) that becomes six nodes
    rows = 60
    hub_c = np.repeat(np.arange(1, 13), 5)
    hub_p = np.zeros_like(hub_c)
    chain_c = np.concatenate([np.arange(1, 25), np.full(36, -1)])
    chain_p = np.concatenate([np.arange(2, 26), np.full(36, -1)])
    _, (hub, chain), _ = sparse_analysis.build_patterns(np.stack([hub_c, chain_c]), np.stack([hub_p, chain_p]),
                                                        device, ordering="shallow")
    assert hub.body_nodes == (0,) and chain.body_nodes == () and chain.nodes == rows + 6
    alone = sparse_analysis.shallowest(chain_c, chain_p, sparse_analysis.choose_body_nodes(chain_c, chain_p),
                                       sparse_analysis.HEIGHT_WEIGHTS)
    assert alone.nodes == rows and chain.height_weight == alone.height_weight > 0.0
    np.testing.assert_array_equal(chain.perm[chain.perm < rows], alone.perm)
    spec = make_scene("sixbar").spec
    ends = []
    for ordering in ("minimum_degree", "shallow"):
        model = pack_worlds([spec] * 2, device=device, dt=1e-3,
                            config=SolverConfig(tuning=Tuning(linear_solver="sparse", step_kernel="staged",
                                                              sparse_ordering=ordering)))
        trace, _ = rollout(model, model.state(), model.control(), 200, record_every=200)
        assert not trace.diverged.any()
        ends.append(trace.points[-1])
    np.testing.assert_allclose(ends[0], ends[1], atol=2e-5)


def test_supernode_blocks_of_the_solves():
    """The solves' supernode blocks against their definition, from a dense elimination tree of the
    factor's pattern: each block a chain of the tree (every member after the first the parent of
    the one before and its only child, with the one before's column pattern = the member and its
    own), at most BLOCK_ROWS members, every position in one block; a block's level one more than
    its child blocks' highest. With one member per block the levels are the factor's own; and the
    schedule's records hold each row's and column's entries outside its block."""
    one, two = random_walkers(2)
    model = pack_worlds([one, two], device="cpu", dt=2e-3, config=SolverConfig(tuning=Tuning(linear_solver="sparse")))
    for a in model.sparse_system.analyses:
        n = a.nodes
        pattern = np.zeros((n, n), bool)
        pattern[a.entry_i, a.entry_j] = True
        below = [np.flatnonzero(pattern[j + 1:, j]) + j + 1 for j in range(n)]
        parent = np.array([b[0] if len(b) else -1 for b in below])
        children = [np.flatnonzero(parent == j) for j in range(n)]
        blocks, level = sparse_analysis.supernodes(a)
        assert sorted(j for b in blocks for j in b) == list(range(n))
        assert max(len(b) for b in blocks) >= 5  # a joint's rows at least
        capped, _ = sparse_analysis.supernodes(a, cap=3)  # chains longer than the cap are split
        assert max(len(b) for b in capped) == 3 and len(capped) > len(blocks)
        assert [j for b in capped for j in b] == sorted(j for b in capped for j in b)
        block_of = {j: k for k, b in enumerate(blocks) for j in b}
        for k, members in enumerate(blocks):
            for prev, j in zip(members, members[1:]):
                assert parent[prev] == j and list(children[j]) == [prev]
                assert list(below[prev]) == [j] + list(below[j])
            first = members[0]  # not mergeable into a child's block
            fits = [c for c in children[first] if list(below[c]) == [first] + list(below[first])]
            assert not (len(children[first]) == 1 and fits
                        and len(blocks[block_of[fits[0]]]) < sparse_analysis.BLOCK_ROWS)
            child_levels = [level[block_of[c]] for j in members for c in children[j] if block_of[c] != k]
            assert level[k] == (max(child_levels) + 1 if child_levels else 0)
        single, single_level = sparse_analysis.supernodes(a, cap=1)
        factor_level = np.zeros(n, int)
        for lv, (first, diag_end) in enumerate(zip(a.level_first, a.level_diag_end)):
            factor_level[a.entry_j[first:diag_end]] = lv
        assert [len(b) for b in single] == [1] * n
        np.testing.assert_array_equal(single_level, factor_level[[b[0] for b in single]])
        records, levels, block_first = sparse_analysis.solve_blocks(a)
        assert sorted(records[:, 0]) == list(range(n)) and len(block_first) == len(blocks)
        for j, T, t, fwd_lo, fwd_hi, bwd_lo, bwd_hi in records:
            members = blocks[block_of[j]]
            assert len(members) == T and members[t] == j
            outside_left = [c for c in np.flatnonzero(pattern[j, :j]) if c not in members]
            assert sorted(a.row_col[fwd_lo:fwd_hi]) == outside_left
            assert list(a.entry_i[bwd_lo:bwd_hi]) == [i for i in below[j] if i not in members]
        for first, count, _, first_block, level_blocks in levels:  # a level's blocks hold its records
            starts = block_first[first_block:first_block + level_blocks]
            assert np.all(records[starts, 2] == 0) and records[starts, 1].sum() == count
            assert starts.min() == first


def test_factor_blocks_and_shifted_diagonals():
    """The factor's schedule by blocks: each level's slots are the entries of its blocks' columns
    (diagonal and below), every entry once over all levels, most products first, each with its
    products less those with its own block's earlier columns (the last ones of its list); the
    rows below each block once; the shifted diagonals: every position but the body nodes', at its
    diagonal entry."""
    rng = np.random.default_rng(4)
    body_c = rng.integers(0, 6, 30)
    body_p = np.where(rng.random(30) < 0.3, -1, rng.integers(0, 6, 30))
    body_c[27:] = -1  # padding rows
    body_p[27:] = -1
    a = sparse_analysis.analyze(body_c, body_p, body_nodes=[int(np.bincount(body_c[:27]).argmax())], nodes=40)
    blocks, level = sparse_analysis.supernodes(a)
    assert len(a.factor_plan) == level.max() + 1 and max(len(b) for b in blocks) > 1
    block_of = {j: k for k, b in enumerate(blocks) for j in b}
    seen = []
    for lv, (first, end, _, _, _, row_first, row_end) in enumerate(a.factor_plan):
        slots = a.factor_slots[first:end]
        columns = [j for k in np.flatnonzero(level == lv) for j in blocks[k]]
        assert sorted(slots[:, 0]) == sorted(e for e in range(a.entries) if a.entry_j[e] in columns)
        assert np.all(np.diff(slots[:, 2] - slots[:, 1]) <= 0)
        for e, begin, stop in slots:
            members = blocks[block_of[a.entry_j[e]]]
            own = members[:members.index(a.entry_j[e])]
            assert begin == a.update_begin[e] and stop == a.update_end[e] - len(own)
            assert list(a.entry_j[a.update_b[stop:a.update_end[e]]]) == own
        below = a.factor_rows[row_first:row_end]
        expected = [(a.block_records[:, 0].tolist().index(b[0]), r) for k in np.flatnonzero(level == lv)
                    for b in [blocks[k]] for r in range(a.col_end[b[-1]] - a.col_begin[b[-1]])]
        assert sorted(map(tuple, below)) == sorted(expected)
        seen += list(slots[:, 0])
    assert sorted(seen) == list(range(a.entries))
    shifted = sparse_analysis.shifted_diagonals(a)
    # body nodes are the node ids rows .. rows + 5 (one body); rows and padding nodes (up to 40) get the shift
    is_body = (a.perm >= a.rows) & (a.perm < a.rows + 6)
    assert is_body.sum() == 6 and a.nodes == 40 and (a.perm >= a.rows + 6).sum() == 40 - a.rows - 6
    expected = np.full(a.entries, -1)
    for e in np.flatnonzero(a.entry_i == a.entry_j):
        if not is_body[a.entry_i[e]]:
            expected[e] = a.entry_i[e]
    np.testing.assert_array_equal(shifted, expected)


def test_body_nodes_factor_the_augmented_system():
    """With bodies kept as nodes, the schedule factors the quasi-definite system
    K = [[A_R, U], [U^T, -I]] (A_R: the rows' coupling through the other bodies, U: the rows on the
    body nodes) as L S L^T with S = -1 on the body nodes, and solving K [x; y] = [b; 0] gives
    (A_R + U U^T) x = b: checked against NumPy on a random matrix with the rows' pattern."""
    rng = np.random.default_rng(4)
    bodies, rows = 7, 36
    body_c = rng.integers(0, bodies, rows)
    body_p = np.where(rng.random(rows) < 0.3, -1, rng.integers(0, bodies, rows))
    body_c[:14] = 0  # body 0 is a hub: 14 of the rows act on it
    body_c[33:] = -1  # padding rows
    body_p[33:] = -1
    hubs = (0, 3)
    a = sparse_analysis.analyze(body_c, body_p, hubs, nodes=rows + 6 * len(hubs) + 2)  # and two padding nodes
    n = a.nodes
    assert sorted(a.perm) == list(range(n)) and a.rows == rows
    on = [set(np.flatnonzero((body_c == b) | (body_p == b))) for b in range(bodies)]
    share = np.array([[i == j or any(i in on[b] and j in on[b] for b in range(bodies) if b not in hubs)
                       for j in range(rows)] for i in range(rows)])
    B = rng.standard_normal((rows, rows)) * share
    A_R = B @ B.T * share + rows * np.eye(rows)
    U = np.zeros((rows, 6 * len(hubs)))
    for k, b in enumerate(hubs):
        U[sorted(on[b]), 6 * k:6 * k + 6] = rng.standard_normal((len(on[b]), 6))
    K = np.eye(n)
    K[:rows, :rows] = A_R
    K[:rows, rows:rows + U.shape[1]] = U
    K[rows:rows + U.shape[1], :rows] = U.T
    K[rows:rows + U.shape[1], rows:rows + U.shape[1]] = -np.eye(U.shape[1])
    Kp = K[np.ix_(a.perm, a.perm)]
    pattern = np.zeros((n, n), bool)
    pattern[a.entry_i, a.entry_j] = True
    lower = np.tril(Kp, -1) != 0
    assert not np.any(lower & ~pattern)  # the pattern holds the matrix
    # rebuild the factor from the schedule: signed products, signed pivots
    values = Kp[a.entry_i, a.entry_j].copy()
    negative = (a.perm >= rows) & (a.perm < rows + U.shape[1])
    for first, end, diag_end in zip(a.level_first, a.level_end, a.level_diag_end):
        for e in range(first, end):
            for u in range(a.update_begin[e], a.update_end[e]):
                ia, ib = a.update_a[u], a.update_b[u]
                values[e] -= -values[-1 - ia] * values[ib] if ia < 0 else values[ia] * values[ib]
            if e < diag_end:
                values[e] = -np.sqrt(-values[e]) if negative[a.entry_j[e]] else np.sqrt(values[e])
        for e in range(diag_end, end):
            values[e] /= values[a.diag[a.entry_j[e]]]
    L = np.zeros((n, n))
    L[a.entry_i, a.entry_j] = values
    d = np.diag(L).copy()
    assert np.all((d < 0) == negative)
    L[np.diag_indices(n)] = np.abs(d)
    assert np.allclose(L @ np.diag(np.sign(d)) @ L.T, Kp, atol=1e-9)
    b = rng.standard_normal(rows)
    rhs = np.zeros(n)
    rhs[:rows] = b
    x = np.linalg.solve(L.T, np.sign(d) * np.linalg.solve(L, rhs[a.perm]))
    solution = np.empty(n)
    solution[a.perm] = x
    assert np.allclose(solution[:rows], np.linalg.solve(A_R + U @ U.T, b), atol=1e-9)


@pytest.mark.parametrize("cap", [None, 2])
@pytest.mark.parametrize("together", [False, True])
def test_factor_kernel_with_body_node_blocks(device, monkeypatch, together, cap):
    """The device factor (sparse_factor) on a quasi-definite matrix with two hubs kept as body
    nodes, whose six nodes make supernode blocks with rows below them, against NumPy's signed
    factor of the same matrix: blocks factored a lane per block and a lane per row below, or by
    the warp column by column (blocks_together forced either way), and with the blocks capped at
    two members (BLOCK_ROWS: chains split into several blocks); its copies for the solves too."""
    rng = np.random.default_rng(4)
    bodies, rows = 7, 36
    body_c = rng.integers(0, bodies, rows)
    body_p = np.where(rng.random(rows) < 0.3, -1, rng.integers(0, bodies, rows))
    body_c[:14] = 0  # two hubs
    body_p[14:24] = 3
    hubs = (0, 3)
    monkeypatch.setattr(sparse_analysis, "blocks_together", lambda records, firsts: together)
    monkeypatch.setattr(sparse_analysis, "choose_body_nodes", lambda c, p: sparse_analysis.analyze(c, p, hubs))
    if cap is not None:
        monkeypatch.setattr(sparse_analysis, "BLOCK_ROWS", cap)
    pat, (a,), entries = sparse_analysis.build_patterns(body_c[None], body_p[None], device)
    n = a.nodes
    blocks, _ = sparse_analysis.supernodes(a)
    assert max(len(b) for b in blocks) == (cap or 6)
    body = a.node_body()[0]
    below = {tuple(b): len(a.entry_i[a.col_begin[b[-1]]:a.col_end[b[-1]]]) for b in blocks}
    assert any(len(b) > 1 and body[b[0]] >= 0 and below[tuple(b)] > 0 for b in blocks)  # a body block with rows below
    # the augmented matrix on the pattern: rows coupled through the other bodies, U on the body nodes, -I
    on = [set(np.flatnonzero((body_c == b) | (body_p == b))) for b in range(bodies)]
    share = np.array([[i == j or any(i in on[b] and j in on[b] for b in range(bodies) if b not in hubs)
                       for j in range(rows)] for i in range(rows)])
    B = rng.standard_normal((rows, rows)) * share
    K = np.eye(n)
    K[:rows, :rows] = B @ B.T * share + rows * np.eye(rows)
    for k, b in enumerate(hubs):
        U = rng.standard_normal((len(on[b]), 6))
        K[np.ix_(sorted(on[b]), range(rows + 6 * k, rows + 6 * k + 6))] = U
        K[np.ix_(range(rows + 6 * k, rows + 6 * k + 6), sorted(on[b]))] = U.T
        K[range(rows + 6 * k, rows + 6 * k + 6), range(rows + 6 * k, rows + 6 * k + 6)] = -1.0
    Kp = K[np.ix_(a.perm, a.perm)]
    negative = body >= 0
    # NumPy's signed factor: L S L^T = Kp, L_jj > 0, S = -1 on the body nodes
    L = np.zeros((n, n))
    for j in range(n):
        s = np.where(negative[:j], -1.0, 1.0)
        pivot = Kp[j, j] - np.sum(L[j, :j] ** 2 * s)
        L[j, j] = np.sqrt(-pivot if negative[j] else pivot)
        L[j + 1:, j] = (Kp[j + 1:, j] - L[j + 1:, :j] @ (s * L[j, :j])) / (-L[j, j] if negative[j] else L[j, j])
    expected = np.where(a.entry_i == a.entry_j, np.where(negative[a.entry_j], -1.0, 1.0), 1.0) * L[a.entry_i, a.entry_j]
    A = wp.array(Kp[a.entry_i, a.entry_j][None].astype(np.float32), device=device)
    out = [wp.zeros((1, width), dtype=float, device=device) for width in (entries, max(1, len(a.row_entry)), n)]
    buffers = sparse_analysis.SystemArrays()
    buffers.real, buffers.A = wp.array(np.arange(rows, dtype=np.int32)[None], device=device), A
    buffers.L, buffers.L_rows, buffers.L_inv = out
    wp.launch_tiled(sparse.sparse_factor, dim=[1], block_dim=sparse.sparse_block(device), device=device,
                    inputs=[pat, buffers, wp.ones(1, dtype=wp.int32, device=device),
                            wp.zeros((1, rows), dtype=float, device=device), 0,
                            wp.array([rows], dtype=wp.int32, device=device),
                            wp.zeros((1, rows), dtype=wp.int32, device=device)])
    L_out = out[0].numpy()[0, :a.entries]
    np.testing.assert_allclose(L_out, expected, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(out[1].numpy()[0, :len(a.row_entry)], L_out[a.row_entry])
    np.testing.assert_allclose(out[2].numpy()[0], 1.0 / np.abs(L_out[a.diag]), rtol=1e-6)


def test_choose_body_nodes_shortens_a_hub():
    """A hub body acted on by many rows is kept as a node where the schedule gets shorter; a
    chain of light bodies keeps none."""
    spokes = 12
    body_c = np.repeat(np.arange(1, spokes + 1), 5)  # five rows from each spoke to the hub (body 0)
    body_p = np.zeros_like(body_c)
    a = sparse_analysis.choose_body_nodes(body_c, body_p)
    plain = sparse_analysis.analyze(body_c, body_p)
    assert a.body_nodes == (0,)
    assert sparse_analysis.schedule_cost(a) < sparse_analysis.schedule_cost(plain)
    assert a.entries < plain.entries
    chain_c = np.repeat(np.arange(1, 9), 5)
    chain_p = np.repeat(np.arange(0, 8), 5)
    assert sparse_analysis.choose_body_nodes(chain_c, chain_p).body_nodes == ()


def test_choose_body_nodes_stops_after_misses(monkeypatch):
    """The greedy search goes on past bodies that do not shorten the schedule, up to
    BODY_NODE_MISSES of them in a row: a body that helps, tried after three that do not, is kept;
    with one miss allowed it is never tried. (The analyses are stand-ins with set costs: the
    search's control flow is under test, not the estimate.)"""
    rows = {0: 60, 201: 30, 202: 29, 203: 28, 100: 20, 300: 5}  # the try order: most rows first
    body_c = np.concatenate([np.full(n, b) for b, n in rows.items()])
    body_p = np.full(len(body_c), -1)
    tried = []

    def stand_in(row_body_c, row_body_p, body_nodes=(), nodes=None, blocks=True):
        tried.append(tuple(body_nodes))
        cost = 1000 - 500 * (0 in body_nodes) - 100 * (100 in body_nodes) + 10 * sum(b > 200 for b in body_nodes)
        arrays = {f.name: np.zeros(0) for f in dataclasses.fields(sparse_analysis.Analysis) if f.type is np.ndarray}
        return sparse_analysis.Analysis(**arrays, factor_steps=cost, solve_steps=0, body_nodes=tuple(body_nodes))

    monkeypatch.setattr(sparse_analysis, "analyze", stand_in)
    monkeypatch.setattr(sparse_analysis, "BODY_NODE_MISSES", 4)
    assert sparse_analysis.choose_body_nodes(body_c, body_p).body_nodes == (0, 100)
    assert [t[-1] for t in tried[1:]] == [0, 201, 202, 203, 100]  # body 300 has too few rows to try
    tried.clear()
    monkeypatch.setattr(sparse_analysis, "BODY_NODE_MISSES", 1)
    assert sparse_analysis.choose_body_nodes(body_c, body_p).body_nodes == (0,)
    assert [t[-1] for t in tried[1:]] == [0, 201]  # stopped after the first miss


@pytest.mark.parametrize("body_nodes", [True, False])
def test_projection_pattern_solves_the_bilateral_block(device, body_nodes):
    """The projection's own system (engine.linalg.sparse_analysis.bilateral_factor_rows: each
    world's bilateral joint rows alone) factors and solves P D P's bilateral block plus a shift per
    row, as NumPy's dense solve of that block of the matrix the dense path builds; the rows it does
    not stand for (drives, contacts) are left alone below the row count and zeroed above it."""
    one, two = random_walkers(2)
    model = pack_worlds([one, two, one], device=device, dt=2e-3,
                        config=SolverConfig(tuning=Tuning(linear_solver="sparse", sparse_body_nodes=body_nodes,
                                                          sparse_projection_pattern="always")))
    system = model.sparse_projection
    assert system is not None and system is not model.sparse_system
    assert system.L is model.sparse_system.L  # the PADMM's buffers, free while the projection runs
    kind = model.row_kind.numpy()
    start = model.contact_row_start.numpy()
    real = system.real.numpy()
    for w in range(model.num_worlds):  # exactly the bilateral joint rows, in row order, then padding
        picked = np.flatnonzero(kind[w, :start[w]] <= 1)
        assert real[w, :len(picked)].tolist() == picked.tolist() and np.all(real[w, len(picked):] == -1)
        assert len(picked) < start[w]  # the walkers' crank drives are joint rows left out
    assert system.nodes < model.sparse_system.nodes
    work, W, R = model.work, model.num_worlds, model.max_rows
    matrix = standing_delassus(model, device)
    shifts = (np.array([1e-3, 1e-2, 1e-1], np.float32)[:, None]
              * np.random.default_rng(2).uniform(0.3, 1.0, (W, R))).astype(np.float32)
    sparse.matrix(model, system)
    sparse.factor(model, wp.array(shifts, device=device), wp.ones(W, dtype=wp.int32, device=device), system=system)
    rhs = np.random.default_rng(4).standard_normal((W, R)).astype(np.float32)
    solutions = []
    for shared in (False, True):  # the schedule read from global memory, or from a shared copy
        x = wp.full((W, R), 7.0, dtype=float, device=device)
        sparse.solve(model, wp.array(rhs, device=device), wp.ones(W, dtype=wp.int32, device=device), x,
                     shared=shared, system=system)
        solutions.append(x.numpy())
    np.testing.assert_array_equal(solutions[0], solutions[1])
    x, matrix, n = solutions[0], matrix.numpy().astype(np.float64), work.row_count.numpy()
    for w in range(W):
        b = np.flatnonzero(kind[w, :n[w]] <= 1)
        A = matrix[w][np.ix_(b, b)] + np.diag(shifts[w, b])
        expected = np.linalg.solve(A, rhs[w, b])
        bound = 50 * np.finfo(np.float32).eps * np.linalg.cond(A)
        assert np.abs(x[w, b] - expected).max() <= bound * np.abs(expected).max()
        others = np.setdiff1d(np.arange(n[w]), b)
        assert len(others) > 0 and np.all(x[w, others] == 7.0)
        assert np.all(x[w, n[w]:] == 0.0)


def test_projection_pattern_choice(device):
    """"auto" gives the projection a pattern of its own where its estimated schedule is the
    shorter one (a four-bar with an armature on every joint: 20 bilateral of 24 rows), not for
    walkers (their drives are a few of many rows, and the torso as a node serves the PADMM's
    pattern best); never without rows besides the bilateral ones or without projection
    iterations; "always" and "never" (True and False) force it."""
    spec = make_scene("fourbar").spec
    armature = with_armature(spec)

    def pattern(specs, config=SolverConfig(), **knobs):
        model = pack_worlds(specs, device=device, dt=1e-3, config=config.tuned(linear_solver="sparse", **knobs))
        return model.sparse_projection

    assert pattern([armature]) is not None
    assert pattern([armature], SolverConfig(position_iterations=0)) is None
    assert pattern([spec]) is None  # only bilateral rows: the PADMM factor serves
    assert pattern(random_walkers(2)) is None
    assert pattern(random_walkers(2), sparse_projection_pattern="always") is not None
    assert pattern(random_walkers(2), sparse_projection_pattern=True) is not None
    assert pattern([armature], sparse_projection_pattern=False) is None
    with pytest.raises(ValueError, match="sparse_projection_pattern"):
        SolverConfig(tuning=Tuning(sparse_projection_pattern="sometimes"))


def test_projection_pattern_steps_like_the_padmm_pattern(device):
    """Whole steps of a batch of a four-bar and a six-bar with an armature and damping on every
    joint, a plain four-bar (no rows besides its joints') and a walker on the ground: projecting
    on the bilateral rows' own pattern moves the linkages as on the PADMM's pattern (the same
    matrix, the other rows made identity; worlds are independent: float32 rounding apart), and
    every world keeps its loops as closed."""
    specs = [with_armature(make_scene("fourbar").spec, 0.05), with_armature(make_scene("sixbar").spec, 0.05),
             make_scene("fourbar").spec, random_walkers(1)[0]]
    traces = []
    for choice in ("always", "never"):
        model = pack_worlds(specs, device=device, dt=1e-3,
                            config=SolverConfig(tuning=Tuning(linear_solver="sparse",
                                                              sparse_projection_pattern=choice)))
        assert (model.sparse_projection is not None) == (choice == "always")
        trace, _ = rollout(model, model.state(), model.control(), 400, record_every=20)
        assert not trace.diverged.any()
        traces.append(trace)
    own, padmm = traces
    linkages = slice(0, 3)  # the worlds of the two four-bars and the six-bar
    assert np.ptp(own.points[:, linkages]) > 0.3  # they move
    assert np.abs(own.points[:, linkages] - padmm.points[:, linkages]).max() < 1e-5
    assert own.violation_linear.max() < max(2e-7, 2.0 * padmm.violation_linear.max())


@pytest.mark.parametrize("staged", [False, True])
def test_matrix_recipe_builds_the_augmented_matrix_of_numpy(staged):
    """engine.linalg.sparse.sparse_matrix, which follows matrix_recipe, and its variant with the rows
    staged in shared memory (staged_matrix_kernel), against the augmented matrix
    [[P (J M^-1 J^T + R) P without the nodes' share, P J R_b], [., -I]] formed in NumPy from the
    same Jacobians: a hub body 300 with 60 rows (kept as six nodes: bodies above 255 use the
    recipe's high bits), a second hub 411, leaves in a chain, rows on the world frame, and rows
    unused this step (the identity)."""
    rng = np.random.default_rng(7)
    body_c, body_p = [], []
    for leaf in range(20):
        body_c += [leaf] * 3
        body_p += [300] * 3
        if leaf:
            body_c.append(leaf)
            body_p.append(leaf - 1)
    body_c += [411, 411, 411, 5, 6]
    body_p += [300, 2, -1, 411, -1]
    rbc, rbp = np.array([body_c], np.int32), np.array([body_p], np.int32)
    pat, (analysis,), entries = sparse_analysis.build_patterns(rbc, rbp, "cpu")
    assert 300 in analysis.body_nodes
    rows, bodies = rbc.shape[1], 412
    unused = rng.random(rows) < 0.15
    real = np.where(unused, -1, np.arange(rows)).astype(np.int32)[None, :]
    J_c, J_p, MJ_c, MJ_p = (rng.normal(size=(rows, 6)).astype(np.float32) for _ in range(4))
    compliance = rng.random(rows).astype(np.float32)
    precond = (0.5 + rng.random(rows)).astype(np.float32)
    inv_mass = (0.5 + rng.random(bodies)).astype(np.float32)
    root = rng.normal(size=(bodies, 3, 3)).astype(np.float32)

    def arr(x, dtype=float):
        return wp.array(x[None], dtype=dtype, device="cpu")

    A = wp.zeros((1, entries), dtype=float, device="cpu")
    size = -(-analysis.nodes // sparse.VECTOR_STEP) * sparse.VECTOR_STEP
    kernel = sparse.staged_matrix_kernel(size) if staged else sparse.sparse_matrix
    buffers, m, w = sparse_analysis.SystemArrays(), ModelArrays(), WorkArrays()  # only the arrays the kernel reads
    buffers.real, buffers.A = wp.array(real, dtype=wp.int32, device="cpu"), A
    w.row_J_c, w.row_J_p, w.row_MJ_c, w.row_MJ_p = (arr(x, wp.spatial_vector) for x in (J_c, J_p, MJ_c, MJ_p))
    w.row_compliance, w.row_precond, w.sparse_root = arr(compliance), arr(precond), arr(root, wp.mat33)
    m.body_inv_mass = arr(inv_mass)
    wp.launch_tiled(kernel, dim=[1], block_dim=1, device="cpu", inputs=[pat, buffers, m, w])
    node_row = analysis.node_row()
    node_body, node_comp = analysis.node_body()
    nodes = set(analysis.body_nodes)
    sides = {0: (body_c, J_c, MJ_c), 1: (body_p, J_p, MJ_p)}
    expected = np.zeros(entries)
    for e in range(analysis.entries):
        pi, pj = analysis.entry_i[e], analysis.entry_j[e]
        ri, rj = node_row[pi], node_row[pj]
        if ri >= 0 and rj >= 0:
            i, j = real[0, ri], real[0, rj]
            if i < 0 or j < 0:
                expected[e] = 1.0 if pi == pj else 0.0
                continue
            d = sum(float(sides[si][1][i] @ sides[sj][2][j]) for si in (0, 1) for sj in (0, 1)
                    if sides[si][0][i] >= 0 and sides[si][0][i] == sides[sj][0][j] and sides[si][0][i] not in nodes)
            expected[e] = precond[i] * precond[j] * (d + (compliance[i] if i == j else 0.0))
        elif ri >= 0 or rj >= 0:
            r, position = (ri, pj) if ri >= 0 else (rj, pi)
            i, b, c = real[0, r], node_body[position], node_comp[position]
            if i < 0 or b not in (body_c[i], body_p[i]):
                continue
            J = (J_c if body_c[i] == b else J_p)[i]
            expected[e] = precond[i] * (J[c] * np.sqrt(inv_mass[b]) if c < 3 else J[3:] @ root[b][:, c - 3])
        else:
            expected[e] = -1.0 if pi == pj else 0.0
    np.testing.assert_allclose(A.numpy()[0, :analysis.entries], expected[:analysis.entries], rtol=2e-5, atol=2e-6)
    assert (np.abs(expected) > 0).sum() > analysis.entries // 4


# Whole steps against the dense Cholesky path (a different linear algebra on the same dual
# problem), and decoupled copies of a mechanism in one world larger than the dense tile, each of
# which must move exactly like the mechanism alone in its own small world.
LARGE_WORLD_SCENES = {
    "fourbar": lambda: make_scene("fourbar").spec,
    "sixbar": lambda: make_scene("sixbar").spec,
    "fourbar_limits": lambda: fourbar_limits().spec,
    "box_stack": lambda: box_stack(3).spec,
    "walker": lambda: walker().spec,
}


def run_solver(specs, solver, device, steps=400):
    model = pack_worlds(specs, device=device, config=SolverConfig(tuning=Tuning(linear_solver=solver)), dt=1e-3)
    trace, _ = rollout(model, model.state(), model.control(), steps, record_every=20)
    return model, trace


@pytest.mark.parametrize("scene", sorted(LARGE_WORLD_SCENES))
def test_sparse_steps_follow_dense(scene, device):
    spec = LARGE_WORLD_SCENES[scene]()
    dense_model, dense = run_solver([spec], "dense", device)
    model, result = run_solver([spec], "sparse", device)
    assert dense_model.linear_solver == "dense" and model.linear_solver == "sparse"
    assert not result.diverged.any()
    # same trajectory of every tracked point over 0.4 s (0.5 mm through the joint limit impacts,
    # where both solvers stop at their own tolerance on a stiff event); the sparse factor solves
    # exactly, like the dense one: elsewhere equal up to float32 rounding
    tolerance = 5e-4 if scene == "fourbar_limits" else 2e-5
    assert np.abs(dense.points - result.points).max() < tolerance
    # loops stay closed as tightly as with the dense factor
    assert result.violation_linear.max() < max(1e-6, 2.0 * dense.violation_linear.max())


def copies(spec: MechanismSpec, count: int, spacing: float = 1.0) -> MechanismSpec:
    """``count`` disconnected copies of a (shape-free) mechanism in one world, spaced along y."""
    bodies, joints, points = [], [], []
    for k in range(count):
        shift = np.array([0.0, spacing * k, 0.0])
        rename = {b.name: f"{b.name}_{k}" for b in spec.bodies}
        for b in spec.bodies:
            bodies.append(dataclasses.replace(b, name=rename[b.name], position=np.asarray(b.position) + shift))
        for j in spec.joints:
            parent_position = np.asarray(j.parent_position) + (shift if j.parent is None else 0.0)
            joints.append(dataclasses.replace(j, name=f"{j.name}_{k}", parent=rename.get(j.parent),
                                              child=rename[j.child], parent_position=parent_position))
        for p in spec.points:
            points.append(dataclasses.replace(p, name=f"{p.name}_{k}", body=rename[p.body]))
    return MechanismSpec(bodies, joints, points, gravity=spec.gravity, name=f"{spec.name}_x{count}")


def test_large_world_runs_without_the_dense_tile_and_matches_small_worlds(device):
    single = make_scene("sixbar").spec
    count = 6
    big = copies(single, count)
    assert big.row_count > MAX_DENSE_ROWS
    with pytest.raises(ValueError, match="linear_solver='sparse'"):
        pack_worlds([big], device=device, config=SolverConfig(tuning=Tuning(linear_solver="dense")))
    model, trace = run_solver([big, single], "auto", device, steps=300)  # auto picks the sparse factor
    assert model.linear_solver == "sparse"
    _, reference = run_solver([single], "dense", device, steps=300)
    assert not trace.diverged.any()
    points = len(single.points)
    for k in range(count):
        # copy k moves like the lone mechanism (shifted by k m along y)
        shifted = trace.points[:, 0, k * points:(k + 1) * points] - np.array([0.0, float(k), 0.0])
        assert np.abs(shifted - reference.points[:, 0]).max() < 2e-4
    assert trace.violation_linear[:, 0].max() < 1e-5
    # the small world of the same batch is unaffected by sharing it with a large one
    assert np.abs(trace.points[:, 1, :points] - reference.points[:, 0]).max() < 2e-4


def test_solver_choice_is_validated():
    with pytest.raises(ValueError, match="linear_solver"):
        SolverConfig(tuning=Tuning(linear_solver="lu"))
