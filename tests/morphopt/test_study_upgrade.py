"""Studies stored by an earlier morphopt resume: their settings held the solver's tuning knobs beside
the user's settings (before engine.Tuning) and a simulation.model key (before the engine planned
itself); both read as what they mean now, while a real change of the study file is still refused."""

import json

import pytest
import sqlalchemy as sa

from morphopt.storage import StudyStorage
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec
from tests.morphopt.toyfamily import toy_study


def _rewrite_settings(spec, change):
    engine = sa.create_engine(spec.storage_url)
    with engine.begin() as connection:
        row = connection.execute(sa.text("SELECT settings FROM studies WHERE name = :n"), {"n": spec.name}).one()
        settings = json.loads(row.settings)
        change(settings)
        connection.execute(sa.text("UPDATE studies SET settings = :s WHERE name = :n"),
                           {"s": json.dumps(settings), "n": spec.name})
    engine.dispose()


def test_a_study_stored_with_flat_solver_knobs_resumes(tmp_path):
    path = toy_study(tmp_path, generations=2, extra="""
        [solver]
        max_iterations = 40
        [solver.tuning]
        rho_update_interval = 8
    """)
    spec = load_study_spec(path)
    run_study(spec, progress=False)

    def older(settings):  # as a study stored before engine.Tuning kept it
        settings["solver"] = {"max_iterations": 40, "rho_update_interval": 8}
        settings["model"] = "maximal"

    _rewrite_settings(spec, older)
    resumed = run_study(load_study_spec(path).with_overrides(generations=3), resume=True, progress=False)
    assert StudyStorage(spec.storage_url, spec.name).info()["generations"] == 3
    assert resumed is not None

    def changed(settings):  # a knob the file does not set: the file changed since the study ran
        settings["solver"] = {"max_iterations": 40, "rho_update_interval": 4}

    _rewrite_settings(spec, changed)
    with pytest.raises(ValueError, match="the study file changed since study 'toy' was run: 'solver'"):
        run_study(load_study_spec(path).with_overrides(generations=4), resume=True, progress=False)
