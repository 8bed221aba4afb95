"""Studies: spec validation, convergence on a known optimum, resume, and the CLI end to end."""

import math
import pathlib
import textwrap

import pandas as pd
import pytest

from morphopt.cli import main
from morphopt.storage import StudyStorage, read_designs
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec
from toyfamily import TOY_FAMILY



def write(tmp_path, text, name="study.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def toy_study(tmp_path, generations=12, extra=""):
    (tmp_path / "toy.py").write_text(TOY_FAMILY)
    return write(tmp_path, f"""
        [study]
        name = "toy"
        family = "{(tmp_path / 'toy.py').as_posix()}"
        generations = {generations}
        worlds = 8
        seed = 3
        [objective]
        metric = "tip_step_height"
        direction = "maximize"
        [simulation]
        samples = 64
        {extra}
    """)


def test_study_converges_to_the_known_optimum(tmp_path):
    """Maximizing the tip's step height (2 r) drives r to its upper bound 0.05 m (value 0.1 m)."""
    result = run_study(load_study_spec(toy_study(tmp_path)), progress=False)
    assert abs(result.best_params["r"] - 0.05) < 1e-3
    assert abs(result.best_value - 0.1) < 2e-3
    assert result.evaluations == 12 * 8


def test_on_generation_reports_each_stored_generation_with_its_time_and_stages(tmp_path):
    """on_generation sees every generation once, in order, after it is stored (the storage already
    holds it), with the run's seconds and stage seconds so far; the last call's are the result's."""
    spec = load_study_spec(toy_study(tmp_path, generations=3))
    calls = []

    def seen(generation, seconds, stages):
        stored = read_designs(spec.storage_url, spec.name)
        calls.append((generation, seconds, stages, int(stored["generation"].max())))

    result = run_study(spec, progress=False, on_generation=seen)
    assert [c[0] for c in calls] == [0, 1, 2] and [c[3] for c in calls] == [0, 1, 2]
    assert 0.0 < calls[0][1] < calls[1][1] < calls[2][1]
    assert calls[-1][2] == result.stages and calls[0][2]["kinematics"] < calls[-1][2]["kinematics"]


PARETO = """
[[objectives]]
metric = "tip_step_height"
[[objectives]]
metric = "tip_stride"
direction = "minimize"
"""


@pytest.mark.parametrize("optimizer", ['name = "cma"\nrestarts = 3\nrestart_strategy = "bipop"\nsigma0 = 0.6',
                                       'name = "optuna"\nsampler = "tpe"', 'name = "optuna"\nsampler = "nsga2"',
                                       'name = "random"'], ids=["cma bipop", "tpe", "nsga2 pareto", "random"])
def test_resume_gives_the_uninterrupted_result(tmp_path, optimizer):
    """A study stopped after 4 generations and resumed to 10 stores exactly the designs and values of
    a 10-generation run (the optimizer rebuilt from the stored generations)."""
    path = toy_study(tmp_path, generations=10, extra=f"[optimizer]\n{optimizer}")
    if "nsga2" in optimizer:  # several objectives: a Pareto front
        text = path.read_text()
        path.write_text(text[:text.index("[objective]")] + PARETO + text[text.index("[simulation]"):])
    spec = load_study_spec(path)
    full = run_study(spec, progress=False)
    run_study(spec.with_overrides(generations=4), progress=False, fresh=True)  # "interrupted" after 4 generations
    resumed = run_study(spec, resume=True, progress=False)
    assert resumed.best_params == full.best_params and resumed.best_value == full.best_value
    assert resumed.evaluations == full.evaluations == 80
    storage = StudyStorage(spec.storage_url, spec.name)
    archived = [name for name in StudyStorage(spec.storage_url, "").names() if name.startswith("toy.before-")]
    frame, reference = storage.designs(), StudyStorage(spec.storage_url, archived[0]).designs()
    pd.testing.assert_frame_equal(frame, reference, check_exact=True)


@pytest.mark.parametrize("body, message", [
    ("[study]\nname='s'\nfamily='four_bar'\ncolour='red'\n[objective]\nmetric='x'", r"unknown key 'study.colour'"),
    ("[study]\nname='s'\nfamily='four_bar'\nworlds='many'\n[objective]\nmetric='x'", r"'study.worlds' must be int"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[space]\ncrank=[0.12, 0.05]",
     r"'space.crank' has inverted bounds"),
    ("[study]\nname='s'\nfamily='hexapod'\n[objective]\nmetric='x'", r"'study.family': unknown design family"),
    ("[study]\nname='s'\n[objective]\nmetric='x'", r"missing required key 'study.family'"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\ndirection='up'", r"'objective.direction'"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver]\nmax_iteration=50",
     r"unknown key 'solver.max_iteration'; expected a field of engine.SolverConfig"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver]\nmax_iterations=50.5",
     r"'solver.max_iterations' must be int"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver]\nmax_iterations=0",
     r"\[solver\]: .*max_iterations"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver.tuning]\nlinear_solver='qr'",
     r"\[solver\]: .*linear_solver"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver]\nrho=1.0",
     r"unknown key 'solver.rho' \('rho' is a field of engine.Tuning: put it under \[solver.tuning\]\)"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver.tuning]\nrhoo=1.0",
     r"unknown key 'solver.tuning.rhoo'; expected a field of engine.Tuning"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver.tuning]\nrho='big'",
     r"'solver.tuning.rho' must be float"),
    ("[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='x'\n[solver]\ntuning=3",
     r"'solver.tuning' must be a \[solver.tuning\] table"),
])
def test_bad_spec_names_file_and_key(tmp_path, body, message):
    """Every bad spec fails before running, naming the file and the key."""
    path = write(tmp_path, body, name="bad.toml")
    with pytest.raises(ValueError, match=message) as exc:
        load_study_spec(path)
    assert str(path) in str(exc.value)


def test_cli_runs_shows_plots_and_resumes(tmp_path, capsys):
    """`morphopt study run|show|plot|resume` work end to end on a tiny study."""
    spec = toy_study(tmp_path, generations=3)
    assert main(["study", "run", str(spec), "--worlds", "6"]) == 0
    out = capsys.readouterr().out
    assert "best tip_step_height" in out and "18 designs" in out
    stages = dict(part.rsplit(" ", 2)[:2] for part in out.split("time by stage: ")[1].splitlines()[0].split(", "))
    assert set(stages) == {"ask", "build", "kinematics", "objectives", "tell", "storage"}
    assert all(float(seconds) >= 0.0 for seconds in stages.values())
    assert main(["study", "show", str(spec), "--top", "2"]) == 0
    assert "3/3 generations" in capsys.readouterr().out
    png = tmp_path / "toy.png"
    assert main(["study", "plot", str(spec), "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000
    assert main(["study", "resume", str(spec)]) == 0  # nothing left to do, best design printed again
    assert "best tip_step_height" in capsys.readouterr().out
    assert main(["study", "run", str(tmp_path / "missing.toml")]) == 2
    optuna_url = f"sqlite:///{tmp_path / 'optuna.db'}"
    assert main(["study", "export", str(spec), "--optuna-storage", optuna_url]) == 0
    import optuna

    exported = optuna.load_study(study_name="toy", storage=optuna_url)
    assert len(exported.trials) == 18
    assert abs(exported.best_value - max(t.value for t in exported.trials if t.value is not None)) < 1e-12


def test_quickstart_spec_is_valid():
    """The README's default job parses and names an existing family."""
    spec = load_study_spec(pathlib.Path(__file__).parents[2] / "studies" / "quickstart.toml")
    assert spec.family == "jansen_leg" and spec.mode == "kinematic" and math.isclose(spec.fixed["m"], 0.015)
    assert spec.constraints == {"foot_step_height": [0.02, 1.0]}


def test_path_synthesis_recovers_the_four_bar_that_drew_the_target(tmp_path):
    """studies/four_bar_path.toml: CMA-ES finds the four-bar whose coupler point traced the target
    (crank 0.08 m, point_u 1.2, point_v 0.05 m) to a path error under 1 mm."""
    source = pathlib.Path(__file__).parents[2] / "studies" / "four_bar_path.toml"
    spec = load_study_spec(source).with_overrides(storage=f"sqlite:///{tmp_path / 'path.sqlite'}")
    result = run_study(spec, progress=False)
    assert result.best_value < 1e-3
    assert abs(result.best_params["crank"] - 0.08) < 2e-3 and abs(result.best_params["point_u"] - 1.2) < 0.02


def test_constraints_bound_the_optimum(tmp_path):
    """With the constraint tip_step_height <= 0.06 m, maximizing the step height stops at the
    constraint (r = 0.03 m) and the designs beyond it are stored as failed with the reason."""
    spec = load_study_spec(toy_study(tmp_path, generations=15, extra="[constraints]\ntip_step_height = [0.0, 0.06]"))
    result = run_study(spec, progress=False)
    assert 0.055 < result.best_value <= 0.06 and abs(result.best_params["r"] - 0.03) < 2e-3
    from morphopt.storage import StudyStorage

    failures = StudyStorage(spec.storage_url, spec.name).designs()["failure"]
    assert failures.str.contains("constraint tip_step_height in \\[0, 0.06\\] violated").any()


def multi_study(tmp_path, *, weight, optimizer="name = \"cma\"", generations=20):
    """Toy crank with two conflicting objectives: trace a circle of radius 0.03 m about (0.5, 0)
    (path error ~ |r - 0.03| + |x - 0.5|) and lift the tip high (step height 2 r)."""
    (tmp_path / "toy.py").write_text(TOY_FAMILY)
    circle = [[0.5 + 0.03 * math.cos(t), 0.03 * math.sin(t)] for t in [2 * math.pi * k / 48 for k in range(48)]]
    return write(tmp_path, f"""
        [study]
        name = "multi"
        family = "{(tmp_path / 'toy.py').as_posix()}"
        generations = {generations}
        worlds = 16
        seed = 1
        [optimizer]
        {optimizer}
        [simulation]
        samples = 64
        [[objectives]]
        metric = "path_error"
        direction = "minimize"
        point = "tip"
        target = {circle}
        [[objectives]]
        metric = "tip_step_height"
        direction = "maximize"
        weight = {weight}
    """)


@pytest.mark.parametrize("weight, r_best", [(0.25, 0.03), (1.0, 0.05)])
def test_weighted_objectives_find_the_known_compromise(tmp_path, weight, r_best):
    """score = path_error - weight * step_height: for weight 1/4 the path term wins (r = 0.03 m on
    the target's centre), for weight 1 the step height wins (r at its bound 0.05 m)."""
    spec = load_study_spec(multi_study(tmp_path, weight=weight))
    assert spec.multi_objective and not spec.pareto and spec.direction == "minimize"
    result = run_study(spec, progress=False)
    assert abs(result.best_params["r"] - r_best) < 2e-3, result.best_params
    if weight < 0.5:
        assert abs(result.best_params["x"] - 0.5) < 5e-3
    from morphopt.storage import StudyStorage

    frame = StudyStorage(spec.storage_url, spec.name).designs()
    row = frame.loc[frame["value"].idxmin()]  # the stored value is the weighted score of stored metrics
    assert math.isclose(row["value"], row["metric_path_error"] - weight * row["metric_tip_step_height"], abs_tol=1e-9)


def test_pareto_study_with_nsga2(tmp_path, capsys):
    """Optuna NSGA-II on both objectives: the stored Pareto front is mutually non-dominated,
    dominates every other feasible design it is compared with, and `study show|plot` report it."""
    from morphopt.storage import StudyStorage
    from morphopt.study import pareto_front

    path = multi_study(tmp_path, weight=1.0, optimizer='name = "optuna"\nsampler = "nsga2"', generations=8)
    spec = load_study_spec(path)
    assert spec.pareto
    run_study(spec, progress=False)
    frame = StudyStorage(spec.storage_url, spec.name).designs()
    front = pareto_front(frame, spec)
    feasible = frame[frame["failure"] == ""]
    points = [(e, -h) for e, h in zip(feasible["metric_path_error"], feasible["metric_tip_step_height"])]
    front_points = [(e, -h) for e, h in zip(front["metric_path_error"], front["metric_tip_step_height"])]
    assert 2 <= len(front_points) < len(points)

    def dominates(a, b):
        return a[0] <= b[0] and a[1] <= b[1] and a != b

    for p in front_points:  # no design dominates a front member
        assert not any(dominates(q, p) for q in points)
    for q in points:  # every design off the front is dominated by (or equal to) a front member
        assert q in front_points or any(dominates(p, q) or p == q for p in front_points)
    assert main(["study", "show", str(path), "--top", "3"]) == 0
    assert "Pareto front" in capsys.readouterr().out
    png = tmp_path / "multi.png"
    assert main(["study", "plot", str(path), "--out", str(png)]) == 0 and png.stat().st_size > 10_000


def test_objectives_tables_are_checked(tmp_path):
    path = write(tmp_path, "[study]\nname='s'\nfamily='four_bar'\n[[objectives]]\nmetric='a'\nweight=-1\n", name="bad.toml")
    with pytest.raises(ValueError, match=r"'objectives\[0\].weight' must be a finite number >= 0"):
        load_study_spec(path)
    path = write(tmp_path, "[study]\nname='s'\nfamily='four_bar'\n[objective]\nmetric='a'\n[[objectives]]\nmetric='b'\n",
                 name="both.toml")
    with pytest.raises(ValueError, match="either one"):
        load_study_spec(path)


def test_solver_table_reaches_the_engine(tmp_path, monkeypatch):
    """A dynamic study's [solver] table (and its [solver.tuning] sub-table) becomes the SolverConfig
    of every evaluated batch (and a study without one uses the engine's defaults)."""
    import morphopt.study as study_module
    from engine import SolverConfig, Tuning

    seen = []
    real = study_module.evaluate_dynamic

    def spy(*args, **kwargs):
        seen.append(kwargs.get("config"))
        return real(*args, **kwargs)

    monkeypatch.setattr(study_module, "evaluate_dynamic", spy)
    body = """
        [study]
        name = "{name}"
        family = "four_bar"
        mode = "dynamic"
        generations = 1
        worlds = 2
        [objective]
        metric = "torque_rms"
        direction = "minimize"
        [simulation]
        duration = 1.0  # one crank turn at the default 2 pi rad/s (a study needs one)
        dt = 0.002
        {solver}
    """
    spec = load_study_spec(write(tmp_path, body.format(name="tuned", solver="[solver]\nmax_iterations = 7\n"
                                                       "tolerance = 1e-5\n[solver.tuning]\nlinear_solver = 'dense'"),
                                 "tuned.toml"))
    assert spec.solver == {"max_iterations": 7, "tolerance": 1e-5, "tuning": {"linear_solver": "dense"}}
    run_study(spec, progress=False)
    plain = load_study_spec(write(tmp_path, body.format(name="plain", solver=""), "plain.toml"))
    run_study(plain, progress=False)
    assert seen[0] == SolverConfig(max_iterations=7, tolerance=1e-5, tuning=Tuning(linear_solver="dense"))
    assert seen[1] is None
