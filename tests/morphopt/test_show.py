"""`morphopt study show` and the command line's help (issue 49, item 6): the objective named with its
unit, the member index, the metrics, the failures counted by kind; every subcommand and choice
described in --help."""

import pathlib
import re
import shutil

import pytest

from morphopt.cli import main
from morphopt.report import failure_kind, failure_kinds, metric_label

STUDIES = pathlib.Path(__file__).parents[2] / "studies"


@pytest.mark.parametrize("reason,kind", [
    ("cannot complete a crank turn: dyad 'E' does not close at crank angle 152.0 deg",
     "cannot complete a crank turn: dyad 'E' does not close at crank angle # deg"),
    ("constraint foot_step_height in [0.02, 1] violated: 0.0153", "constraint foot_step_height in [0.02, 1] violated: #"),
    ("fell after 1.23 s: the torso tilted by 50.2 deg (more than 45)",
     "fell after # s: the torso tilted by # deg (more than #)"),
    ("jammed: the drive of joint 'leg_1_crank' stalled at its effort limit (20 N m) from 0.45 s, turning at -0.3 of "
     "its 6.28 rad/s for 0.2 s", "jammed: the drive of joint 'leg_1_crank' stalled at its effort limit (# N m) from # s, "
     "turning at # of its # rad/s for # s"),
    ("too far from the origin: coordinates reach 7e+04 m, where float32 resolves only 3.9 mm",
     "too far from the origin: coordinates reach # m, where float32 resolves only # mm"),
])
def test_failure_kind_drops_the_numbers_that_vary(reason, kind):
    assert failure_kind(reason) == kind


def test_failure_kinds_count_designs_by_kind():
    failures = ["", "x at crank angle 10.0 deg", "x at crank angle 12.0 deg", "constraint a in [0, 1] violated: 2",
                "", "x at crank angle 14.5 deg"]
    assert failure_kinds(failures) == [(3, "x at crank angle # deg"), (1, "constraint a in [0, 1] violated: #")]


def test_metric_labels_carry_units():
    assert metric_label("foot_stride", {"foot"}) == "foot_stride [m]"
    assert metric_label("torque_rms") == "torque_rms [N m]"
    assert metric_label("walking_speed") == "walking_speed [m/s]"
    assert metric_label("transmission_angle_min") == "transmission_angle_min [rad]"
    assert metric_label("heading_drift") == "heading_drift"  # a ratio: no unit


def test_show_names_the_objective_member_metrics_and_failure_kinds(tmp_path, capsys):
    """The quickstart for 2 generations of 16 designs: the objective with its unit, rank, generation
    and member of the best designs, their metrics with units, and failures grouped by kind, their
    counts adding up to the failed designs."""
    spec = tmp_path / "quickstart.toml"
    shutil.copy(STUDIES / "quickstart.toml", spec)
    assert main(["study", "run", str(spec), "--worlds", "16", "--generations", "2"]) == 0
    capsys.readouterr()
    assert main(["study", "show", str(spec), "--top", "3"]) == 0
    out = capsys.readouterr().out
    feasible = int(re.search(r"32 designs, (\d+) feasible", out).group(1))
    assert "objective: foot_stride [m] (maximize)" in out
    header = next(line for line in out.splitlines() if line.lstrip().startswith("rank  generation"))
    assert header.split()[:5] == ["rank", "generation", "member", "foot_stride", "[m]"] and "a [m]" in header
    assert "foot_step_height [m]" in out and "transmission_angle_min [rad]" in out
    kinds = re.findall(r"^\s+(\d+)  (.*)$", out.split("failures: ")[1], re.M)
    assert sum(int(n) for n, _ in kinds) == 32 - feasible
    assert all("crank angle # deg" in kind or kind.startswith("constraint foot_step_height in [0.02, 1]")
               for _, kind in kinds), kinds


def test_help_lists_every_subcommand_and_describes_every_choice(capsys):
    """`morphopt study --help` names run, resume, show, plot and export; `--format` and the demo's
    scene say what each choice is; --verbose is offered."""
    for argv in (["study", "--help"], ["export", "--help"], ["demo", "--help"], ["--help"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 0
    study, export, demo, top = capsys.readouterr().out.split("usage: ")[1:]
    for name in ("run", "resume", "show", "plot", "export"):
        assert re.search(rf"^\s+{name}\s+\w", study, re.M), name
    text = " ".join(export.split())
    assert all(f"{fmt}: " in text for fmt in ("usd", "urdf", "mjcf", "svg", "dxf"))
    text = " ".join(demo.split())
    assert all(f"{scene}: " in text for scene in ("pendulum", "fourbar", "sixbar", "chain", "mixed"))
    assert "--verbose" in demo and "--verbose" in top and "export" in " ".join(top.split())
