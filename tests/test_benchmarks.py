"""The walker benchmarks run end to end at tiny sizes and report what they promise."""

import json

import numpy as np

from benchmarks import walker_precision, walker_steps


def test_walker_steps_reports_a_finite_batch_of_three_leg_walkers(tmp_path, capsys):
    assert walker_steps.main(["--device", "cpu", "--worlds", "2", "--warmup", "10", "--steps", "10",
                              "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "walker_steps_cpu.json").read_text())
    assert result == json.loads(capsys.readouterr().out)
    assert result["worlds"] == 2 and result["legs_per_side"] == 3 and result["linear_solver"] == "matrix_free"
    assert result["rows"] > 128 and result["nan_worlds"] == 0
    assert result["ms_per_step"] > 0 and result["padmm_iterations_mean"] >= 1
    assert result["cr_iterations_per_step"] >= result["padmm_iterations_mean"]  # at least one CR iteration each
    assert set(result["stage_ms"]) == {"kinematics", "collision", "dual_problem", "padmm", "integrate", "projection"}


def test_walker_precision_compares_settings_with_the_reference(tmp_path):
    assert walker_precision.main(["--device", "cpu", "--worlds", "2", "--duration", "0.04", "--only", "default",
                                  "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "walker_precision_cpu.json").read_text())
    rows = {r["setting"]: r for r in report["settings"]}
    assert set(rows) == {"reference", "default"}
    assert rows["reference"]["speed_error_median"] == 0.0  # the reference against itself
    assert np.isfinite(rows["default"]["speed_error_median"]) and rows["default"]["diverged"] == 0
    assert rows["default"]["joint_separation_max"] < 1e-3
    assert (tmp_path / "walker_precision_cpu.png").stat().st_size > 1000
