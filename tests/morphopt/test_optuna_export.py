"""`morphopt study export --optuna-storage` (issue 49, item 7): in seconds for 1,920 designs, and a
second export adds only what is new."""

import time

import numpy as np
import optuna
import pandas as pd
import pytest

from morphopt.cli import main
from morphopt.design_space import DesignSpace, Float, Int
from morphopt.storage import export_to_optuna
from toyfamily import toy_study

optuna.logging.set_verbosity(optuna.logging.WARNING)


def test_export_twice_adds_no_duplicates_and_a_resumed_study_adds_its_new_designs(tmp_path, capsys):
    """Export, export again (nothing new: 0 written, the count of those already there), resume the
    study for one more generation, export: only its 6 designs are added."""
    spec = toy_study(tmp_path, worlds=6)
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    assert main(["study", "run", str(spec)]) == 0
    assert main(["study", "export", str(spec), "--optuna-storage", url]) == 0
    assert "exported 18 trials of 'toy'" in capsys.readouterr().out
    assert main(["study", "export", str(spec), "--optuna-storage", url]) == 0
    assert "exported 0 trials of 'toy'" in capsys.readouterr().out.replace("18 designs were there already", "")
    assert len(optuna.load_study(study_name="toy", storage=url).trials) == 18
    assert main(["study", "resume", str(spec), "--generations", "4"]) == 0
    assert main(["study", "export", str(spec), "--optuna-storage", url]) == 0
    assert "exported 6 trials of 'toy' to" in capsys.readouterr().out
    trials = optuna.load_study(study_name="toy", storage=url).trials
    keys = [(t.user_attrs["generation"], t.user_attrs["member"]) for t in trials]
    assert len(trials) == 24 and len(set(keys)) == 24 and [t.number for t in trials] == list(range(24))
    assert sorted(keys) == [(g, m) for g in range(4) for m in range(6)]


def test_export_of_1920_designs_takes_seconds_and_keeps_every_field(tmp_path):
    """1,920 designs (a 30 x 64 study, every fifth failed) in one transaction: values, states,
    parameters and attributes as Optuna reads them back."""
    space = DesignSpace({"a": Float(0.0, 1.0), "b": Float(1e-3, 1.0, log=True), "n": Int(1, 5)})
    rng = np.random.default_rng(0)
    rows = [{"generation": g, "member": m, "value": float(rng.random()) if m % 5 else np.nan,
             "failure": "" if m % 5 else "cannot close at crank angle 1.2 rad",
             "a": float(rng.random()), "b": float(10 ** rng.uniform(-3, 0)), "n": int(rng.integers(1, 6))}
            for g in range(30) for m in range(64)]
    frame = pd.DataFrame(rows)
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    start = time.perf_counter()
    assert export_to_optuna(frame, study_name="big", space=space, direction="maximize", storage=url) == (1920, 0)
    seconds = time.perf_counter() - start
    assert seconds < 20.0  # 67 s before (add_trials); about 2-4 s on a 2-core machine
    study = optuna.load_study(study_name="big", storage=url)
    trials = study.trials
    assert len(trials) == 1920 and [t.number for t in trials] == list(range(1920))
    for trial, row in zip(trials, rows):
        assert trial.user_attrs == {"generation": row["generation"], "member": row["member"], "failure": row["failure"]}
        assert trial.params == {"a": row["a"], "b": row["b"], "n": row["n"]}
        if row["failure"]:
            assert trial.state == optuna.trial.TrialState.FAIL and trial.value is None
        else:
            assert trial.state == optuna.trial.TrialState.COMPLETE and trial.value == row["value"]
    assert study.best_value == max(r["value"] for r in rows if not r["failure"])
    assert export_to_optuna(frame, study_name="big", space=space, direction="maximize", storage=url) == (0, 1920)


def test_export_into_a_study_of_the_other_direction_is_refused(tmp_path):
    """An Optuna study of the same name that minimizes is not mixed with a maximized study."""
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    optuna.create_study(study_name="toy", storage=url, direction="minimize")
    frame = pd.DataFrame([{"generation": 0, "member": 0, "value": 1.0, "failure": "", "a": 0.5}])
    with pytest.raises(ValueError, match="is to minimize; this study's value is to maximize"):
        export_to_optuna(frame, study_name="toy", space=DesignSpace({"a": Float(0.0, 1.0)}), direction="maximize",
                         storage=url)
