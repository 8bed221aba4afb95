"""Batched evaluation: kinematic and dynamic paths agree, failures carry reasons, batches carry on."""

import numpy as np

from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import load_family


def test_kinematic_batch_reports_failures_with_reasons_and_keeps_the_rest():
    """Jansen's leg, an out-of-range design and a leg that cannot close: the good one gets its
    flat-stance stride (~49 mm of its 68 mm foot travel), the others fail with a reason."""
    family = load_family("jansen_leg")
    good = family.space.default()
    broken = {**good, "m": good["m"] * 1.2, "j": good["j"] * 0.8, "b": good["b"] * 0.8}  # locks mid-turn
    outside = {**good, "m": 1.0}  # a 1 m crank is outside the design space
    evaluation = evaluate_kinematic(family, [good, outside, broken])
    assert evaluation.feasible.tolist() == [True, False, False]
    assert 0.045 < evaluation.metrics[0]["foot_stride"] < 0.052
    assert "'m' = 1.0 is outside" in evaluation.failures[1]
    assert "does not close at crank angle" in evaluation.failures[2]


def test_dynamic_evaluation_matches_kinematic_paths():
    """Driven at 2 pi rad/s for 1.5 s, the simulated coupler-point and foot paths over the last turn
    have the kinematic stride and step height (1 mm), and the crank torque is reported."""
    for name, point in (("four_bar", "coupler_point"), ("jansen_leg", "foot")):
        family = load_family(name)
        params = [family.space.default()]
        kinematic = evaluate_kinematic(family, params).metrics[0]
        dynamic = evaluate_dynamic(family, params, duration=1.5, record_every=5).metrics[0]
        for metric in (f"{point}_stride", f"{point}_step_height"):
            assert abs(dynamic[metric] - kinematic[metric]) < 1e-3, (name, metric)
        assert dynamic["torque_peak"] > 0 and np.isfinite(dynamic["torque_rms"])
        assert dynamic["loop_violation_max"] < 1e-5


def test_torn_mechanisms_fail_as_diverged():
    """A design whose joints come apart by more than loop_tolerance fails with the distance in its
    reason (a torn mechanism can stay finite and score absurdly well); the same design passes
    under a tolerance above its real loop error."""
    family = load_family("four_bar")
    params = [family.space.default()]
    ok = evaluate_dynamic(family, params, duration=0.2, record_every=5)
    assert ok.feasible.all()
    error = ok.metrics[0]["loop_violation_max"]
    assert 0.0 < error < 1e-5
    strict = evaluate_dynamic(family, params, duration=0.2, record_every=5, loop_tolerance=0.5 * error)
    assert not strict.feasible.any()
    assert "diverged: joints came apart by" in strict.failures[0] and "m tolerance" in strict.failures[0]
