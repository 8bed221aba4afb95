"""The walker family: a torso on Jansen legs that actually walks, in heterogeneous batches."""

from morphopt.evaluate import evaluate_dynamic
from morphopt.families import load_family


def test_walker_batch_walks_and_rejects_oversized_worlds():
    """A Jansen walker and a larger, faster Klann walker walk forward in one batch (different
    topologies; torso speed > 5 mm/s, torso still upright in roll, feet lifting), while a
    two-legs-per-side design is rejected with a reason."""
    family = load_family("walker")
    base = family.space.default()
    params = [base, {**base, "legs_per_side": 2},
              {**base, "leg_family": "klann_leg", "scale": 3.5, "crank_speed": 7.0}]
    evaluation = evaluate_dynamic(family, params, duration=1.5, dt=1e-3, record_every=10)
    assert evaluation.feasible.tolist() == [True, False, True]
    assert "too large for the dense solver" in evaluation.failures[1]
    for k in (0, 2):
        metrics = evaluation.metrics[k]
        assert metrics["walking_speed"] > 0.005, metrics["walking_speed"]
        assert metrics["heading_drift"] < 0.2  # no sideways fall
        assert metrics["left0_foot_step_height"] > 0.01 and metrics["loop_violation_max"] < 1e-5
        assert metrics["torque_peak"] > 0.0 and metrics["energy_per_distance"] > 0.0
