"""Sparse direct solver (engine.sparse): its factor and solves against NumPy's dense linear algebra
on the same matrices, and its symbolic analysis against a numeric factor (whole steps against the
dense Cholesky path: tests/engine/test_matrix_free.py).
"""

import numpy as np
import pytest
import warp as wp

from engine import SolverConfig, pack_worlds, sparse
from engine.dynamics import delassus
from engine.integrate import bilateral_block
from engine.rollout import Stepper
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


@pytest.mark.parametrize("bilateral_only", [False, True])
def test_factor_and_solve_match_numpy(device, bilateral_only):
    """Walkers of two topologies standing on the ground (contacts active): (P D P + diag(shift)) x = b
    solved with the sparse factor equals NumPy's dense solve of the matrix the dense path builds."""
    one, two = random_walkers(2)  # one and two legs per side
    model = pack_worlds([one, two, one], device=device, dt=2e-3, config=SolverConfig(linear_solver="sparse"))
    assert len(model.sparse_analyses) == 2  # one analysis per topology
    assert model.sparse.world_pattern.numpy().tolist() == [0, 1, 0]
    stepper = Stepper(model, model.state(), model.control(), chunk=10)
    for _ in range(3):
        stepper.advance()
    work, W, R = model.work, model.num_worlds, model.max_rows
    assert work.contact_count.numpy().min() > 0
    matrix = wp.zeros((W, R, R), dtype=float, device=device)
    wp.launch(delassus, dim=(W, R, R), device=device,
              inputs=[work.row_count, work.row_body_p, work.row_body_c, work.row_J_c, work.row_J_p, work.row_MJ_c,
                      work.row_MJ_p, work.row_compliance, work.row_precond], outputs=[matrix])
    if bilateral_only:
        wp.launch(bilateral_block, dim=(W, R, R), inputs=[model.row_kind, work.row_count, matrix], device=device)
    # a shift per row (the PADMM factor caps the joint rows' penalty): 1e-3 to 1e-1, world by world
    shifts = (np.array([1e-3, 1e-2, 1e-1][:W], np.float32)[:, None]
              * np.random.default_rng(1).uniform(0.3, 1.0, (W, R))).astype(np.float32)
    sparse.prepare(model)
    sparse.factor(model, wp.array(shifts, device=device), wp.ones(W, dtype=wp.int32, device=device),
                  bilateral_only=bilateral_only)
    rhs = np.random.default_rng(0).standard_normal((W, R)).astype(np.float32)
    x = wp.full((W, R), 7.0, dtype=float, device=device)
    sparse.solve(model, wp.array(rhs, device=device), wp.ones(W, dtype=wp.int32, device=device), x)
    x, matrix, n = x.numpy(), matrix.numpy().astype(np.float64), work.row_count.numpy()
    for w in range(W):
        A = matrix[w, :n[w], :n[w]] + np.diag(shifts[w, :n[w]])

        expected = np.linalg.solve(A, rhs[w, :n[w]])
        # float32 factor: error within a few eps times the condition number
        bound = 50 * np.finfo(np.float32).eps * np.linalg.cond(A)
        assert np.abs(x[w, :n[w]] - expected).max() <= bound * np.abs(expected).max()
        assert np.all(x[w, n[w]:] == 0.0)  # rows not in use this step


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
    a = sparse.analyze(body_c, body_p)
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
