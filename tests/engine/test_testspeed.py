"""engine.testspeed: the benchmark command prints one JSON object with the promised fields."""

import json

import numpy as np

from engine.testspeed import build_batch, main

FIELDS = ["device", "num_worlds", "steps", "dt", "compile_s", "step_ms_median", "world_steps_per_s",
          "max_constraint_violation_m", "max_constraint_violation_rad", "energy_drift_rel", "padmm_iterations_mean",
          "padmm_iterations_max", "diverged_worlds"]


def test_testspeed_json_for_mixed_batch(capsys):
    """`--scene mixed --json` prints every field; the mixed batch stays closed and finite."""
    assert main(["--scene", "mixed", "--worlds", "4", "--steps", "40", "--dt", "0.001", "--device", "cpu", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    for field in FIELDS:
        assert field in result, field
    assert result["num_worlds"] == 4 and result["steps"] == 40 and result["device"] == "cpu"
    assert result["diverged_worlds"] == 0
    assert 0 < result["max_constraint_violation_m"] < 1e-5
    assert result["energy_drift_rel"] < 1e-2
    assert result["padmm_iterations_max"] >= 1 and result["world_steps_per_s"] > 0


def test_mixed_batch_cycles_through_all_scenes():
    """The mixed batch holds each scene in turn, with its own equilibrium energy."""
    specs, potential_min = build_batch("mixed", 8)
    names = [s.name for s in specs]
    assert names[:4] == ["pendulum", "fourbar", "sixbar", "chain"] and names[4:] == names[:4]
    assert np.all(np.isfinite(potential_min)) and len(set(np.round(potential_min[:4], 9))) == 4
