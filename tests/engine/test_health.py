"""engine.health: what the engine cannot simulate is refused (impossible inertias) or flagged per
world with a reason (joints that come apart, coordinates too far from the origin for float32, a
solver stopped far from converged), and morphopt's evaluation turns a flag into a failure."""

import dataclasses
import math

import numpy as np
import pytest

from engine import Body, MechanismSpec, SolverConfig, Tuning, pack_worlds, rollout
from engine.health import FAR, JOINTS_OPEN, UNCONVERGED
from engine.scenes import chain, fourbar, shifted


def alternating_chain(ratio: float) -> MechanismSpec:
    return chain(10, densities=[ratio if k % 2 else 1.0 for k in range(10)]).spec


def test_inertia_outside_the_triangle_inequality_is_refused_by_name():
    """diag(1, 1, 5) is no mass distribution (5 > 1 + 1): refused naming the body and the moments;
    so is a rotated full tensor whose principal moments (1, 2, 3.5) break it. A thin disk (0.5,
    0.5, 1), on the boundary, and a slender rod are real bodies and pass."""
    with pytest.raises(ValueError, match=r"body 'arm'.*triangle inequality.*\(1, 1, 5\)"):
        Body("arm", 1.0, (1.0, 1.0, 5.0))
    c, s = math.cos(0.7), math.sin(0.7)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    with pytest.raises(ValueError, match=r"body 'tilted'.*\(1, 2, 3\.5\)"):
        Body("tilted", 1.0, turn @ np.diag([1.0, 2.0, 3.5]) @ turn.T)
    Body("disk", 1.0, (0.5, 0.5, 1.0))
    Body("rod", 1.0, (1e-6, 0.01, 0.01))


def test_mass_ratio_beyond_the_limit_is_flagged_and_a_mild_one_is_not():
    """Two 10-link chains in one batch, links alternating 1:10 and 1:1e8: the 1:1e8 chain opens
    its joints by centimetres within 0.2 s (its PADMM counts as converged: the tolerance is
    relative to the heavy links' impulses) and is flagged with the distance and the mass ratio;
    the 1:10 chain stays closed and is not flagged. Both step kernels."""
    for kernel in ("fused", "staged"):
        model = pack_worlds([alternating_chain(10.0), alternating_chain(1e8)], device="cpu", dt=1e-3,
                            config=SolverConfig(tuning=Tuning(step_kernel=kernel)))
        trace, _ = rollout(model, model.state(), model.control(), 200, record_every=10)
        opened = trace.violation_linear.max(axis=0)
        assert opened[0] < 1e-5 and opened[1] > 2e-2, (kernel, opened)
        assert trace.health.flags.tolist() == [0, JOINTS_OPEN], kernel
        assert trace.health.reason(0) == ""
        reason = trace.health.reason(1)
        assert f"joints came apart by {opened[1]:.3g} m" in reason and "1:1e+08" in reason, reason


def test_four_bar_far_from_the_origin_is_flagged_and_the_same_near_it_is_not():
    """One four-bar at the origin, 1e4 m and 1e5 m away. At 1e5 m float32's spacing (7.8 mm) is
    coarser than the 5 mm joint tolerance: flagged when packed, and its joints do open by
    millimetres; at 1e4 m (spacing 0.98 mm) its error stays under the tolerance, no flag; at the
    origin it stays closed to 1e-6 m."""
    base = fourbar().spec
    model = pack_worlds([base, shifted(base, 1e4), shifted(base, 1e5)], device="cpu", dt=1e-3)
    assert model.health_init.tolist() == [0, 0, FAR]
    trace, _ = rollout(model, model.state(), model.control(), 300, record_every=10)
    opened = trace.violation_linear.max(axis=0)
    assert opened[0] < 1e-6 and opened[1] < 5e-3 and opened[2] > 2e-3, opened
    assert trace.health.flags[0] == 0 and trace.health.flags[1] == 0
    assert trace.health.flags[2] & FAR
    assert "too far from the origin: coordinates reach 1e+05 m" in trace.health.reason(2)
    assert "7.81 mm" in trace.health.reason(2)


def test_unconverged_solver_is_flagged_above_its_threshold():
    """A four-bar whose PADMM may take 2 iterations to an unreachable tolerance stops unconverged
    every step: flagged with the residual and the iterations when the threshold is below the
    residual it stopped at, not flagged at the default threshold (its joints, projected every
    step, stay closed)."""
    loose = SolverConfig(max_iterations=2, tolerance=1e-12, relative_tolerance=0.0)
    runs = {}
    for threshold in (1e-12, loose.health_residual):
        config = dataclasses.replace(loose, health_residual=threshold)
        model = pack_worlds([fourbar().spec], device="cpu", dt=1e-3, config=config)
        runs[threshold], _ = rollout(model, model.state(), model.control(), 50, record_every=10)
    strict, default = runs[1e-12].health, runs[loose.health_residual].health
    assert 0.0 < strict.residual_max[0] < loose.health_residual and strict.residual_iterations[0] == 2
    assert strict.flags[0] == UNCONVERGED
    assert strict.reason(0) == (f"solver did not converge: residual {strict.residual_max[0]:.3g} after 2 "
                                f"iterations (threshold 1e-12)")
    assert default.flags[0] == 0 and default.residual_max[0] == strict.residual_max[0]


def test_evaluation_fails_flagged_worlds_with_their_reason_and_keeps_their_neighbours():
    """Four four-bar designs in one batch through morphopt's evaluate_dynamic; a spec hook moves the
    second 1e5 m away and makes every other body of the third 1e8 times heavier. Those two fail with
    the engine's reasons in maximal coordinates; the first and last get the metrics of the design
    evaluated alone: the far one as too far (its joints opening too); the heavy one's joints come
    apart, its mass ratio named. Unasked, the batch takes the grounded plan (one float64 coordinate
    per world, no joint rows to come apart): the far one still fails as too far, the heavy one runs."""
    from engine import Coordinates
    from morphopt.evaluate import evaluate_dynamic
    from morphopt.families import load_family

    family = load_family("four_bar")
    params = [dict(family.space.default()) for _ in range(4)]
    far, heavy = params[1], params[2]

    def hook(spec, p):
        if p is far:
            return shifted(spec, 1e5)
        if p is heavy:
            for k, body in enumerate(spec.bodies):
                if k % 2:
                    body.mass, body.inertia = body.mass * 1e8, body.inertia * 1e8
        return spec

    for coordinates in ("maximal", None):
        evaluation = evaluate_dynamic(family, params, duration=0.2, record_every=5, spec_hook=hook,
                                      coordinates=coordinates)
        alone = evaluate_dynamic(family, params[:1], duration=0.2, record_every=5, coordinates=coordinates)
        assert evaluation.feasible.tolist() == [True, False, coordinates is None, True]
        for i in (0, 3):
            assert evaluation.metrics[i]["coupler_point_stride"] == alone.metrics[0]["coupler_point_stride"]
            assert evaluation.metrics[i]["torque_peak"] == alone.metrics[0]["torque_peak"]
        failures = evaluation.failures
        assert failures[1].startswith("too far from the origin: coordinates reach 1e+05 m")
        if coordinates == "maximal":
            assert failures[2].startswith("diverged: joints came apart by") and "masses differ" in failures[2]
    assert evaluation.plan.coordinates is Coordinates.GROUNDED
    assert not failures[2], failures
