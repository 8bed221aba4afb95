"""A slowly driven linkage built by morphopt.linkage.to_spec, stepped on the reduced plans (grounded,
chosen by default, and tree),
stays on its kinematics: every node's position at the crank angle the step reached, against
morphopt.linkage.solve_at (the planar position solver, float64, independent of the engine)."""

import dataclasses
import math

import numpy as np
import pytest

import engine
from morphopt.families import load_family
from morphopt.linkage.kinematics import solve_at
from morphopt.linkage.to_spec import to_spec


def _with_every_node(linkage):
    """The linkage with a tracked point on every moving node (the crank's tip first)."""
    nodes = [linkage.crank.tip] + [d.node for d in linkage.dyads]
    extra = {f"node_{n}": n for n in nodes if n not in linkage.points.values()}
    return dataclasses.replace(linkage, points={**linkage.points, **extra})


@pytest.mark.parametrize("coordinates", [None, "tree"])
@pytest.mark.parametrize("name", ["jansen_leg", "klann_leg", "four_bar"])
def test_a_slowly_driven_linkage_follows_its_kinematics_on_the_reduced_plans(name, coordinates):
    family = load_family(name)
    speed = 0.5  # [rad/s]: slow, a quarter turn in 3 s
    linkage = _with_every_node(family.generate(family.space.default(), crank_speed=speed))
    spec = to_spec(linkage)
    model = engine.pack([spec], "cpu", dt=1e-3, coordinates=coordinates)
    assert model.plan.coordinates == (engine.Coordinates.GROUNDED if coordinates is None else engine.Coordinates.TREE)
    state = model.state()
    crank = linkage.crank
    centre = np.asarray(linkage.ground[crank.center])
    worst = 0.0
    for _ in range(6):
        engine.rollout(model, state, None, 500, record_every=500)
        points = engine.point_positions(model, state)[0]  # (P, 3), world (x, 0, y) of the plane's (x, y)
        names = [p.name for p in spec.points]
        tip = points[names.index(next(k for k, v in linkage.points.items() if v == crank.tip))]
        angle = math.atan2(tip[2] - centre[1], tip[0] - centre[0])
        solution = solve_at([linkage], np.array([[angle]]))[0]
        assert solution.feasible
        for point_name, node in linkage.points.items():
            expected = solution.nodes[node][0]
            got = points[names.index(point_name)]
            assert abs(got[1]) < 1e-9  # in the plane
            worst = max(worst, float(np.hypot(got[0] - expected[0], got[2] - expected[1])))
    turned = math.atan2(tip[2] - centre[1], tip[0] - centre[0]) - crank.phase
    assert abs(math.remainder(turned - 3.0 * speed, 2 * math.pi)) < 0.05  # the drive kept its speed
    assert worst < 1e-6, worst
