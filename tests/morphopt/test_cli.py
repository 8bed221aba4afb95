"""The `morphopt` command line: the demo reports measured numbers; bad arguments are refused."""

import json

import pytest

from morphopt.cli import main


def test_demo_fourbar_prints_measurements(capsys):
    """`morphopt demo fourbar` simulates and prints speed, loop closure and energy drift."""
    assert main(["demo", "fourbar", "--worlds", "2", "--seconds", "0.05"]) == 0
    out = capsys.readouterr().out
    assert "world-steps/s" in out and "loop closure" in out and "energy drift" in out


def test_demo_json_measures_a_closed_loop(capsys):
    """The JSON form reports a closed loop and no divergence."""
    assert main(["demo", "sixbar", "--worlds", "2", "--seconds", "0.05", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["scene"] == "sixbar" and result["steps"] == 50
    assert result["max_constraint_violation_m"] < 1e-5 and result["diverged_worlds"] == 0


@pytest.mark.parametrize("argv,message", [(["demo", "fourbar", "--worlds", "0"], "must be > 0"),
                                          (["demo", "fourbar", "--dt", "abc"], "expected a float"),
                                          (["demo", "trebuchet"], "invalid choice")])
def test_bad_arguments_name_the_problem(argv, message, capsys):
    """Invalid CLI arguments exit with status 2 and a message naming the argument."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
