"""The stress suite (benchmarks/stress.py) at CI sizes on the CPU: every case that holds its
criterion today is asserted here; the runner reports failures and exits non-zero."""

import json

import pytest

from benchmarks import stress

PASSING = ["S1", "S2", "S3", "S4", "S5", "S6", "S7", "S8", "S9", "S10"]


@pytest.mark.parametrize("case_id", PASSING)
def test_stress_case_meets_its_criterion_on_the_cpu(case_id):
    case = next(c for c in stress.CASES if c.id == case_id)
    result = stress.run_case(case, "cpu", full=False)
    assert result["pass"], json.dumps(result["measured"])
    assert result["criterion"] and result["measured"]


def test_freudenstein_oracle_closes_the_loop():
    # the analytic rocker angle puts the coupler at its length for every crank angle
    import numpy as np

    a, b, c, d = 0.2, 0.5, 0.4, 0.5
    theta2 = np.linspace(0.0, 2.0 * np.pi, 50)
    for branch in (1, -1):
        theta4 = stress.freudenstein_rocker(theta2, a, b, c, d, branch)
        B = np.stack([a * np.cos(theta2), a * np.sin(theta2)], axis=1)
        C = np.stack([d + c * np.cos(theta4), c * np.sin(theta4)], axis=1)
        assert np.allclose(np.linalg.norm(C - B, axis=1), b, atol=1e-12)


def test_stress_runner_reports_failures_and_crashes_and_exits_non_zero(monkeypatch, capsys):
    cases = [stress.Case("X1", "fails", "never", lambda device, full: {"measured": {"value": 1}, "pass": False}),
             stress.Case("X2", "crashes", "never", lambda device, full: 1 / 0),
             stress.Case("X3", "passes", "always", lambda device, full: {"measured": {"value": 0}, "pass": True})]
    monkeypatch.setattr(stress, "CASES", cases)
    assert stress.main(["--device", "cpu"]) == 1
    lines = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [(r["case"], r["pass"]) for r in lines] == [("X1", False), ("X2", False), ("X3", True)]
    assert "ZeroDivisionError" in lines[1]["measured"]["error"]
    assert stress.main(["--device", "cpu", "--only", "X3"]) == 0
    with pytest.raises(SystemExit) as exit_info:
        stress.main(["--device", "cpu", "--only", "S42"])
    assert exit_info.value.code == 2


def test_chain_with_densities_hangs_at_its_potential_minimum():
    # released straight down at rest, the chain's energy (the engine's own sum) is its potential minimum
    import numpy as np

    from engine import pack_worlds
    from engine.metrics import compute_metrics
    from engine.scenes import chain

    scene = chain(3, densities=[1.0, 100.0, 1e4], angle=0.0)
    model = pack_worlds([scene.spec], device="cpu")
    state = model.state()
    compute_metrics(model, state)
    assert np.isclose(model.work.energy.numpy()[0], scene.potential_min, rtol=1e-5)
    assert [b.mass for b in scene.spec.bodies] == pytest.approx([0.1, 10.0, 1000.0])
    with pytest.raises(ValueError, match="expected 3 densities"):
        chain(3, densities=[1.0])
