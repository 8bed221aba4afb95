"""engine.point_positions: every world's tracked points from any plan's State, checked against the
points computed in NumPy from the State's own body poses and against the rollout's record of the
same state."""

import numpy as np
import pytest

import engine
from engine.scenes import fourbar, sixbar
from engine.spatial import quat_matrix
from morphopt.families import load_family


def _numpy_points(model, state) -> np.ndarray:
    """The points of each world's spec from state.body_q (W, B, 7: the centre-of-mass frames),
    computed on the host: a point at p in the body frame is at c + R (p - com)."""
    poses = state.body_q.numpy()
    out = np.zeros((model.num_worlds, max(len(s.points) for s in model.specs), 3))
    for w, spec in enumerate(model.specs):
        index = spec.body_index
        for k, point in enumerate(spec.points):
            pose = poses[w, index[point.body]]
            com = np.asarray(spec.bodies[index[point.body]].com)
            out[w, k] = pose[:3] + quat_matrix(pose[3:]) @ (np.asarray(point.position) - com)
    return out


def _walker():
    family = load_family("walker")
    return family.build_spec(family.space.default())


@pytest.mark.parametrize("coordinates", ["maximal", "tree"])
def test_points_of_a_linkage_follow_its_bodies_in_maximal_and_tree_coordinates(coordinates):
    specs = [fourbar().spec, sixbar().spec, fourbar(crank=0.12).spec]
    model = engine.pack(specs, "cpu", coordinates=coordinates, dt=1e-3)
    state = model.state()
    start = engine.point_positions(model, state)
    assert start.shape == (3, 1, 3)
    np.testing.assert_allclose(start, _numpy_points(model, state), atol=1e-6)
    trace, final = engine.rollout(model, state, None if coordinates == "tree" else model.control(), 40,
                                  record_every=20)
    moved = engine.point_positions(model, final)
    assert np.linalg.norm(moved - start, axis=-1).min() > 1e-3  # the linkages swung under gravity
    np.testing.assert_allclose(moved, _numpy_points(model, final), atol=1e-6)
    np.testing.assert_allclose(moved, trace.points[-1], atol=1e-6)


def test_points_of_a_walker_on_the_tabulated_plan_and_of_a_grouped_batch():
    walker = _walker()
    model = engine.pack([walker], "cpu", dt=5e-3, contact_capacity=None)
    assert model.plan.coordinates == engine.Coordinates.TABULATED
    trace, final = engine.rollout(model, model.state(), None, 20, record_every=10)
    points = engine.point_positions(model, final)
    assert points.shape == (1, len(walker.points), 3)
    np.testing.assert_allclose(points, trace.points[-1], atol=1e-6)

    mixed = engine.pack([walker, fourbar().spec], "cpu", dt=5e-3)  # worlds of two plans: run in groups
    assert mixed.plan.coordinates == engine.Coordinates.MIXED
    state = mixed.state()
    points = engine.point_positions(mixed, state)
    assert points.shape == (2, len(walker.points), 3)
    np.testing.assert_allclose(points[1, :1], _numpy_points(engine.pack([fourbar().spec], "cpu"),
                                                            engine.pack([fourbar().spec], "cpu").state())[0],
                               atol=1e-6)
    assert np.all(points[1, 1:] == 0.0)  # past the four-bar's one point
