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


def test_batched_kinematic_evaluation_matches_the_numpy_reference():
    """evaluate_kinematic (families called once with parameter arrays, compiled kernels, the batch
    split over the CPU cores) gives the NumPy reference's feasibility, failure reasons, paths,
    stride, step height and transmission angle (1e-9) for 160 random designs of each family."""
    from morphopt.linkage import solve_cycles
    from morphopt.metrics import stride_and_step_height

    rng = np.random.default_rng(11)
    for name in ("jansen_leg", "klann_leg", "four_bar", "watt_sixbar"):
        family = load_family(name)
        params = family.space.sample(rng, 160)
        evaluation = evaluate_kinematic(family, params, samples=90)
        reference = solve_cycles([family.generate(p) for p in params], samples=90)
        assert evaluation.feasible.tolist() == [s.feasible for s in reference], name
        assert 0 < evaluation.feasible.sum(), name
        for metrics, failure, solution, p in zip(evaluation.metrics, evaluation.failures, reference, params):
            if not solution.feasible:
                assert failure == solution.reason
                continue
            linkage = family.generate(p)
            for point in linkage.points:
                path = solution.point(point, linkage)
                assert np.abs(metrics["paths"][point] - path).max() < 1e-9
                stride, height = stride_and_step_height(path)
                assert abs(metrics[f"{point}_stride"] - stride) < 1e-9
                assert abs(metrics[f"{point}_step_height"] - height) < 1e-9
            assert abs(metrics["transmission_angle_min"] - solution.transmission_angle_min) < 1e-9


def test_families_that_need_floats_are_generated_design_by_design():
    """A family whose generate works only on floats (math functions, float()) and one that quietly
    ignores its parameter arrays both fall back to one generate call per design and give the same
    results as the NumPy-written four-bar; a NaN or string parameter fails with its name."""
    import math
    import types

    from morphopt.linkage import Linkage

    four_bar = load_family("four_bar")

    def floats_only(params, **kwargs):
        assert all(isinstance(v, float) for v in params.values())
        return four_bar.generate({k: float(v) for k, v in params.items()}, **kwargs)

    frozen = four_bar.generate(four_bar.space.default())

    def ignores_arrays(params, **kwargs):
        if np.ndim(params["crank"]) > 0:
            return frozen  # wrong for every design but the default: must be caught
        return four_bar.generate(params, **kwargs)

    rng = np.random.default_rng(2)
    params = four_bar.space.sample(rng, 130)
    expected = evaluate_kinematic(four_bar, params, samples=60)
    for generate in (floats_only, ignores_arrays):
        family = types.SimpleNamespace(space=four_bar.space, generate=generate)
        evaluation = evaluate_kinematic(family, params, samples=60)
        assert evaluation.failures == expected.failures
        for got, want in zip(evaluation.metrics, expected.metrics):
            if want:
                assert abs(got["coupler_point_stride"] - want["coupler_point_stride"]) < 1e-12
    assert isinstance(frozen, Linkage) and math.isfinite(frozen.crank.radius)
    bad = [{**params[0], "rocker": float("nan")}, {**params[0], "crank": "long"}, params[1]]
    evaluation = evaluate_kinematic(four_bar, bad, samples=60)
    assert "'rocker' = nan is outside" in evaluation.failures[0]
    assert "'crank' = 'long' is outside" in evaluation.failures[1]
    assert evaluation.failures[2] == expected.failures[1]
