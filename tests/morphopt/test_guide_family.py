"""The README's guide to writing a design family works as written: its example module, saved next
to a study file, loads as a family, evaluates, and runs a one-generation study end to end."""

import pathlib
import re

import numpy as np

from morphopt.cli import main
from morphopt.evaluate import evaluate_kinematic
from morphopt.families import load_family

README = pathlib.Path(__file__).resolve().parents[2] / "README.md"


def guide_family_source() -> str:
    text = README.read_text()
    block = re.search(r"<!-- guide-family: begin -->\s*```python\n(.*?)```\s*<!-- guide-family: end -->", text, re.DOTALL)
    assert block, "README: the guide's family example (between the guide-family markers) is missing"
    return block.group(1)


def test_guide_family_evaluates_its_arm_tip(tmp_path):
    path = tmp_path / "rocker_arm.py"
    path.write_text(guide_family_source())
    family = load_family(str(path))
    params = [family.space.default(), {**family.space.default(), "coupler": 0.15, "rocker": 0.10, "crank": 0.08}]
    evaluation = evaluate_kinematic(family, params, samples=90)
    # the default design turns; the second cannot close (0.2 m ground, 0.15 + 0.10 against 0.08 + 0.2)
    assert evaluation.failures[0] == "" and evaluation.failures[1] != ""
    tip = evaluation.metrics[0]["paths"]["tip"]
    # T stays on the rocker's line at rocker + arm from its ground pivot D = (0.2, 0)
    assert np.allclose(np.hypot(tip[:, 0] - 0.20, tip[:, 1]), 0.25, atol=1e-5)
    assert evaluation.metrics[0]["tip_step_height"] > 0.01


def test_guide_family_runs_a_one_generation_study(tmp_path, capsys):
    (tmp_path / "rocker_arm.py").write_text(guide_family_source())
    study = tmp_path / "rocker_arm_lift.toml"
    study.write_text('[study]\nname = "rocker_arm_lift"\nfamily = "rocker_arm.py"\ngenerations = 1\nworlds = 8\n'
                     '[objective]\nmetric = "tip_step_height"\ndirection = "maximize"\n[simulation]\nsamples = 90\n')
    assert main(["study", "run", str(study)]) == 0
    from morphopt.notebook import load_study

    frame = load_study(study)
    assert len(frame) == 8 and set(frame["generation"]) == {0}
    feasible = frame[frame["failure"] == ""]
    assert len(feasible) >= 1
    assert (feasible["metric_tip_step_height"] > 0.0).all()
