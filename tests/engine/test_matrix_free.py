"""Matrix-free and sparse solver paths: same physics as the dense Cholesky path, and worlds larger than the tile.

Oracles: the dense per-world Cholesky path (a different linear algebra on the same dual problem),
and decoupled copies of a mechanism in one large world, each of which must move exactly like the
mechanism alone in its own small world.
"""

import dataclasses

import numpy as np
import pytest

from engine import SolverConfig, pack_worlds, rollout
from engine.pack import MAX_DENSE_ROWS
from engine.scenes import make_scene
from engine.scenes_contact import box_stack, fourbar_limits, walker
from engine.spec import MechanismSpec

SCENES = {
    "fourbar": lambda: make_scene("fourbar").spec,
    "sixbar": lambda: make_scene("sixbar").spec,
    "fourbar_limits": lambda: fourbar_limits().spec,
    "box_stack": lambda: box_stack(3).spec,
    "walker": lambda: walker().spec,
}


def run(specs, solver, device, steps=400):
    model = pack_worlds(specs, device=device, config=SolverConfig(linear_solver=solver), dt=1e-3)
    trace, _ = rollout(model, model.state(), model.control(), steps, record_every=20)
    return model, trace


@pytest.mark.parametrize("solver", ["matrix_free", "sparse"])
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_large_world_solvers_follow_dense(scene, solver, device):
    spec = SCENES[scene]()
    dense_model, dense = run([spec], "dense", device)
    model, result = run([spec], solver, device)
    assert dense_model.linear_solver == "dense" and model.linear_solver == solver
    assert not result.diverged.any()
    # same trajectory of every tracked point within 0.1 mm over 0.4 s (0.5 mm through the joint
    # limit impacts, where both solvers stop at their own tolerance on a stiff event); the sparse
    # factor solves exactly, like the dense one: equal up to float32 rounding
    tolerance = 5e-4 if scene == "fourbar_limits" else (2e-5 if solver == "sparse" else 1e-4)
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


@pytest.mark.parametrize("choice, solver", [("auto", "sparse"), ("matrix_free", "matrix_free")])
def test_large_world_runs_without_the_dense_tile_and_matches_small_worlds(device, choice, solver):
    single = make_scene("sixbar").spec
    count = 6
    big = copies(single, count)
    assert big.row_count > MAX_DENSE_ROWS
    with pytest.raises(ValueError, match="matrix_free"):
        pack_worlds([big], device=device, config=SolverConfig(linear_solver="dense"))
    model, trace = run([big, single], choice, device, steps=300)  # auto picks the sparse factor for the batch
    assert model.linear_solver == solver
    _, reference = run([single], "dense", device, steps=300)
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
        SolverConfig(linear_solver="lu")
    with pytest.raises(ValueError, match="inner_tolerance_ratio"):
        SolverConfig(inner_tolerance_ratio=1.5)

