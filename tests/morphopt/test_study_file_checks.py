"""Every name and number of a study file, and the family it names, checked before any work.

As a user meets them: a misspelled metric, a path_error point the family does not track, numbers
beyond what a run can hold, storage that keeps nothing, family files that fail at import or break
their contract. Each ends the command with exit status 2 and one line on stderr naming the study
file and the key (or the family file), with no traceback, no storage created and stored results
unchanged. The metric names the checks accept are compared with what the evaluation produces.
"""

import hashlib
import inspect
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from morphopt.cli import main
from morphopt.contract import RECORD_EVERY, family_metrics, point_metrics
from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import available_families, load_family
from morphopt.study_spec import load_study_spec

ROOT = pathlib.Path(__file__).resolve().parents[2]
GOOD_SPACE = '''from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Link, Linkage

space = DesignSpace({"r": Float(0.01, 0.05, default=0.02), "x": Float(-1.0, 1.0, default=0.0)})
'''
GOOD_GENERATE = '''

def generate(params, *, crank_speed=6.283185307179586, phase=0.0):
    return Linkage(name="tip", ground={"O": (params["x"], 0.0)}, crank=Crank("O", "T", params["r"], phase=phase,
                   speed=crank_speed), links=[Link("crank", ("O", "T"))], points={"tip": "T"})
'''
FAMILIES = {  # file -> (source, what the one line must say)
    "exits.py": ("import sys\nsys.exit(0)\n", "called sys.exit(0) at import (exits.py, line 2)"),
    "raises.py": (GOOD_SPACE + "raise RuntimeError('calibration table missing')\n" + GOOD_GENERATE,
                  "failed at import: RuntimeError: calibration table missing (raises.py, line 5)"),
    "broken_syntax.py": (GOOD_SPACE + "def generate(params:\n    pass\n", "not valid Python: SyntaxError"),
    "space_five.py": ("space = 5\n\n\ndef generate(params):\n    return None\n",
                      "'space' must be a morphopt.design_space.DesignSpace, got int 5"),
    "returns_text.py": (GOOD_SPACE + "\n\ndef generate(params, **kwargs):\n    return 'a four-bar'\n",
                        "generate(default design) returned str 'a four-bar', expected a morphopt.linkage.Linkage"),
    "not_callable.py": (GOOD_SPACE + "generate = 'tip'\n", "'generate' must be a function, got str 'tip'"),
    "call_fails.py": (GOOD_SPACE + "\n\ndef generate(params, **kwargs):\n    return params['radius']\n",
                      "generate(default design) raised KeyError: 'radius' (call_fails.py, line 8)"),
    "tip.py": (GOOD_SPACE + GOOD_GENERATE, None),
}
# the defects run as real processes (a process costs 2 s of CPU for its imports); the rest through main() here
REAL_PROCESSES = ("family_exits.toml", "family_raises.toml", "typo.toml", "point.toml")


def study_text(name="tiny", family="tip.py", metric="tip_step_height", study="", objective="", simulation="",
               tables="") -> str:
    """A small kinematic study (1 generation of 4 designs) with extra lines for each table."""
    for key, value in (("generations", 1), ("worlds", 4)):
        if f"{key} =" not in study:
            study += f"\n{key} = {value}"
    if "samples =" not in simulation:
        simulation += "\nsamples = 16"
    return "\n".join([f'[study]\nname = "{name}"\nfamily = "{family}"', study, f'[objective]\nmetric = "{metric}"',
                      objective, "[simulation]", simulation, tables, ""])


def folder_state(folder: pathlib.Path) -> dict:
    """Every file of the folder (not the study files' own caches) and its hash."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())
            if p.is_file() and p.suffix != ".pyc"}


def assert_refused(status, out, err, *fragments):
    """Exit 2, one stderr line starting "morphopt" and holding every fragment, nothing on stdout
    but no traceback anywhere."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2, (status, out, err)
    assert "Traceback" not in err and "Traceback" not in out, (out, err)
    assert len(lines) == 1 and lines[0].startswith("morphopt "), err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


@pytest.fixture
def study_folder(tmp_path):
    """A folder with the family files and a study 'tiny' that has stored results."""
    for name, (source, _) in FAMILIES.items():
        (tmp_path / name).write_text(source)
    (tmp_path / "tiny.toml").write_text(study_text())
    assert main(["study", "run", str(tmp_path / "tiny.toml")]) == 0 and (tmp_path / "tiny.sqlite").exists()
    return tmp_path


# (file name, study text, fragments of the one line) of `morphopt study run`
CLI_CASES = [
    *[(f"family_{name[:-3]}.toml", study_text(family=name), [f"family_{name[:-3]}.toml", "'study.family'",
                                                              str(pathlib.Path(name)), fragment])
      for name, (_, fragment) in FAMILIES.items() if fragment],
    ("typo.toml", study_text(metric="tip_strid"),
     ["typo.toml", "'objective.metric' = 'tip_strid' is not a metric of family", "expected one of: tip_stride"]),
    ("point.toml", study_text(name="point", metric="path_error",
                              objective='direction = "minimize"\npoint = "foot"\ntarget = [[0, 0], [1, 0], [0, 1]]'),
     ["point.toml", "'objective.point' = 'foot' is not a tracked point", "expected one of: tip"]),
    ("memory.toml", study_text(name="memory", study='storage = "sqlite:///:memory:"'),
     ["memory.toml", "'study.storage' = 'sqlite:///:memory:' keeps nothing"]),
    ("short.toml", study_text(name="short", study='mode = "dynamic"', metric="tip_stride",
                              simulation="duration = 1e-9"),
     ["short.toml", "'simulation.duration' = 1e-09 s is shorter than one crank turn (1 s at 6.283 rad/s"]),
]


def test_the_cli_refuses_bad_studies_and_families_before_any_work(study_folder, capsys):
    """Each defect as its own `morphopt study run` (the ones seen as a silent exit 0 or a
    traceback: real processes, several at once): exit 2, one line naming the study file and the
    key or family file, no traceback, and the folder (the stored study 'tiny' included) exactly as
    it was; no database was created for the others."""
    for name, text, _ in CLI_CASES:
        (study_folder / name).write_text(text)
    before = folder_state(study_folder)
    processes = [(subprocess.Popen([sys.executable, "-m", "morphopt.cli", "study", "run", name], cwd=study_folder,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), fragments)
                 for name, _, fragments in CLI_CASES if name in REAL_PROCESSES]
    for name, _, fragments in CLI_CASES:
        if name not in REAL_PROCESSES:
            assert_refused(*run_cli(["study", "run", study_folder / name], capsys), *fragments)
    for process, fragments in processes:
        out, err = process.communicate(timeout=300)
        assert_refused(process.returncode, out, err, *fragments)
    assert folder_state(study_folder) == before


def run_cli(argv, capsys):
    try:
        status = main([str(a) for a in argv])
    except SystemExit as exit_:
        status = exit_.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


FOUR_BAR = dict(family="four_bar", metric="coupler_point_stride")
JANSEN_DYNAMIC = dict(family="jansen_leg", metric="foot_stride", study='mode = "dynamic"')
WALKER = dict(family="walker", metric="walking_speed", study='mode = "dynamic"',
              simulation='dt = 0.005\nduration = 2.0')
VALIDATION_CASES = [  # (study keywords, argv after the spec, fragments)
    (dict(FOUR_BAR, study="worlds = 1000000000"), [], ["'study.worlds' must be at most 65536", "memory"]),
    (FOUR_BAR, ["--worlds", "100000"], ["(with worlds=100000)", "'study.worlds' must be at most 65536"]),
    (dict(FOUR_BAR, study="generations = 1000000"), [], ["'study.generations' must be at most 100000"]),
    (FOUR_BAR, ["--generations", "2000", "--worlds", "65536"],
     ["'study.generations' x 'study.worlds' (2000 x 65536) must be at most 1e+08 designs", "row of the study database"]),
    (FOUR_BAR, ["--seed", str(2**32)], ["'study.seed' must be at most 2**32 - 1 = 4294967295", "32-bit"]),
    (dict(FOUR_BAR, study="seed = 18446744073709551615"), [], ["'study.seed' must be at most"]),
    (dict(FOUR_BAR, simulation="samples = 1000000000"), [], ["'simulation.samples' must be at most 100000"]),
    (FOUR_BAR, ["--worlds", "65536"], []),  # 65536 x 16 samples: allowed (checked below: exit 1, nothing stored)
    (dict(FOUR_BAR, simulation="samples = 36000"), ["--worlds", "8192"],
     ["'simulation.samples' x 'study.worlds' (36000 x 8192) must be at most 1e+08", "memory"]),
    (dict(FOUR_BAR, simulation="dt = 1e-300"), [], ["'simulation.dt' must be a time step in [1e-06, 0.1] s"]),
    (dict(FOUR_BAR, simulation="duration = 1e9"), [], ["'simulation.duration' must be a positive number",
                                                        "at most 3600"]),
    (dict(JANSEN_DYNAMIC, simulation="crank_speed = 1e-12"), [],
     ["'simulation.crank_speed' must be 0.01 to 1000 rad/s in magnitude"]),
    (dict(JANSEN_DYNAMIC, simulation="crank_speed = -5000.0"), [], ["'simulation.crank_speed' must be 0.01 to 1000"]),
    (dict(JANSEN_DYNAMIC, simulation="crank_speed = 0.1\nduration = 10.0"), [],
     ["'simulation.duration' = 10 s is shorter than one crank turn (62.83 s at 0.1 rad/s, 'simulation.crank_speed')"]),
    (dict(JANSEN_DYNAMIC, simulation="crank_speed = 100.0"), [],
     ["'simulation.dt' = 0.001 s records a crank turn", "at least 8 records a turn"]),
    (dict(JANSEN_DYNAMIC, simulation="duration = 2000.0\ndt = 1e-4"), [],
     ["'simulation.duration' / 'simulation.dt' (2000 s / 0.0001 s = 2e+07 steps) must be at most 1e+07 steps"]),
    (dict(JANSEN_DYNAMIC, simulation="duration = 60.0"), ["--worlds", "4096"],
     ["recorded world-steps) must be at most 2e+07", "held in memory"]),
    (dict(JANSEN_DYNAMIC, metric="transmission_angle_min"), [],
     ["'objective.metric' = 'transmission_angle_min' is not a metric of family 'jansen_leg' in dynamic mode",
      "torque_rms"]),
    (dict(FOUR_BAR, metric="torque_rms"), [], ["'torque_rms' is not a metric of family 'four_bar' in kinematic mode"]),
    (dict(WALKER, metric="left3_foot_stride"), [],
     ["'objective.metric' = 'left3_foot_stride' is not a metric of every design of the study",
      "legs_per_side=1 has none"]),
    (dict(WALKER, metric="left3_foot_stride", tables="[fixed]\nlegs_per_side = 4"), [], []),
    (dict(WALKER, simulation='dt = 0.005\nduration = 1.0'), [],
     ["'simulation.duration' = 1 s is shorter than one crank turn (1.257 s at 5 rad/s, the design's own crank speed)"]),
    # a key of earlier study files: refused in one line that says what took its place
    (dict(WALKER, simulation='model = "reduced"\ndt = 0.005\nduration = 2.0'), [],
     ["'simulation.model' is no longer a setting: the engine chooses the coordinates of every batch itself"]),
    (dict(FOUR_BAR, tables="[constraints]\ncoupler_point_strid = [0.0, 1.0]"), [],
     ["'constraints.coupler_point_strid' = 'coupler_point_strid' is not a metric"]),
    (dict(FOUR_BAR, tables="[constraints]\npath_error = [0.0, 1.0]"), [],
     ["'constraints.path_error' cannot be constrained"]),
    (dict(FOUR_BAR, objective='point = "coupler_point"'), [],
     ["'objective.point' is read only by metric 'path_error'"]),
    (dict(FOUR_BAR, study='storage = "sqlite://"'), [], ["'study.storage' = 'sqlite://' keeps nothing"]),
    (dict(FOUR_BAR, study='storage = ":memory:"'), [], ["'study.storage' = ':memory:' keeps nothing"]),
    (dict(FOUR_BAR, study='storage = "sqlite+pysqlite:///:memory:?cache=shared"'), [], ["'study.storage'"]),
    (dict(JANSEN_DYNAMIC, tables="[solver.tuning]\nrho_updates = 8"), [],
     ["unknown key 'solver.tuning.rho_updates'; expected a field of engine.Tuning"]),
    (dict(JANSEN_DYNAMIC, tables="[solver]\nrho_update_interval = 8"), [],
     ["unknown key 'solver.rho_update_interval' ('rho_update_interval' is a field of engine.Tuning"]),
    (dict(JANSEN_DYNAMIC, tables="[solver]\nmax_iterations = 30\n[solver.tuning]\nrho_update_interval = 8"), [], []),
]


@pytest.mark.parametrize("command", [["study", "run"], ["study", "show"], ["export"]])
def test_every_command_refuses_bad_numbers_and_names(tmp_path, capsys, command):
    """Bounds on every number (with the reason), metrics and constraints of the family in the
    study's mode, and storage that keeps something: refused by run, show and export alike (before
    any storage is opened), overrides of the command line included; the limits themselves pass."""
    for k, (keywords, extra, fragments) in enumerate(VALIDATION_CASES):
        if extra and command != ["study", "run"]:
            continue  # only `study run` takes the overrides
        path = tmp_path / f"case{k}.toml"
        path.write_text(study_text(name=f"case{k}", **keywords))
        argv = [*command, path, *extra] + (["--format", "svg"] if command == ["export"] else [])
        if not fragments:  # valid: the command gets past the checks (show/export: nothing stored, exit 1)
            if command != ["study", "run"]:
                status, out, err = run_cli(argv, capsys)
                assert status == 1 and "has no stored designs" in out and not err, (k, out, err)
            else:
                load_study_spec(path).with_overrides(worlds=int(extra[1]) if extra else None)
            continue
        status, out, err = run_cli(argv, capsys)
        assert_refused(status, out, err, str(path), *fragments)
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".toml"] * len(list(tmp_path.iterdir()))


def test_multi_objective_metrics_are_checked_by_index(tmp_path):
    path = tmp_path / "multi.toml"
    path.write_text(textwrap.dedent("""\
        [study]
        name = "multi"
        family = "four_bar"
        [[objectives]]
        metric = "coupler_point_stride"
        [[objectives]]
        metric = "path_error"
        direction = "minimize"
        point = "foot"
        target = [[0, 0], [1, 0], [0, 1]]
    """))
    with pytest.raises(ValueError, match=r"'objectives\[1\].point' = 'foot' is not a tracked point of family "
                                         r"'four_bar' in kinematic mode; expected one of: coupler_point$"):
        load_study_spec(path)


def test_whole_world_families_must_return_worlds(tmp_path):
    """A build_spec that returns something else than an engine.MechanismSpec, or raises: named
    with the family file, the function and the line."""
    family = tmp_path / "world.py"
    for body, fragment in (("return {'bodies': []}", "build_spec(default design) returned dict"),
                           ("return 1 / 0", "build_spec(default design) raised ZeroDivisionError: division by zero "
                                            "(world.py, line 7)")):
        family.write_text("from morphopt.design_space import DesignSpace, Float\n\n"
                          "space = DesignSpace({'a': Float(0.0, 1.0)})\n\n\n"
                          f"def build_spec(params, *, crank_speed=None):\n    {body}\n")
        path = tmp_path / "world.toml"
        path.write_text(study_text(name="world", family="world.py", metric="torque_rms", study='mode = "dynamic"'))
        with pytest.raises(ValueError) as error:
            load_study_spec(path)
        message = str(error.value)
        assert message.startswith(f"{path}: 'study.family': design family {family}") and fragment in message, message


def test_keyboard_interrupt_at_import_still_stops(tmp_path):
    path = tmp_path / "interrupted.py"
    path.write_text("raise KeyboardInterrupt\n")
    with pytest.raises(KeyboardInterrupt):
        load_family(path)


def test_the_projects_studies_and_families_pass():
    """Every study of studies/ loads (as on the README's GPU command line too), and every family
    (the built-in ones, morphopt/designs/) builds its default design in each mode it supports (the
    sweeps load them directly)."""
    for path in sorted((ROOT / "studies").glob("*.toml")):
        spec = load_study_spec(path)
        spec.with_overrides(device="cuda", worlds=4096)
    for name in available_families():
        family = load_family(name)
        space = family.space
        modes = (["kinematic"] if hasattr(family, "generate") else []) + ["dynamic"]
        for mode in modes:
            assert family_metrics(family, space, {}, mode).metrics, (name, mode)


def derived(family, mode, params):
    """The names morphopt.contract accepts for a study fixed at ``params``."""
    from morphopt.design_space import DesignSpace, Float

    free = next(n for n, p in family.space.parameters.items() if isinstance(p, Float))
    space = DesignSpace({free: family.space.parameters[free]})
    fixed = {k: v for k, v in params.items() if k != free}
    return set(family_metrics(family, space, fixed, mode).metrics)


def produced(evaluation) -> list[tuple]:
    """(design, its metric names) of the feasible designs of an evaluation (the first one feasible)."""
    assert not evaluation.failures[0], evaluation.failures[0]
    return [(p, set(m) - {"paths"}) for p, m, f in zip(evaluation.params, evaluation.metrics, evaluation.failures)
            if not f]


@pytest.mark.parametrize("name", ["four_bar", "jansen_leg", "klann_leg", "watt_sixbar"])
def test_kinematic_metric_names_are_what_the_evaluation_produces(name):
    """The derived kinematic names equal the metric keys of evaluate_kinematic's designs (the
    default and random ones that turn)."""
    family = load_family(name)
    designs = [family.space.default(), *family.space.sample(np.random.default_rng(4), 5)]
    evaluation = evaluate_kinematic(family, designs, samples=16)
    for params, metrics in produced(evaluation):
        assert metrics == derived(family, "kinematic", params)
    assert set(evaluation.metrics[0]["paths"]) == set(family.generate(designs[0]).points)


def test_dynamic_metric_names_are_what_the_evaluation_produces():
    """The derived dynamic names equal the metric keys of evaluate_dynamic: a linkage made a world,
    and walkers of two topologies in the engine's own plan (tabulated) and in maximal coordinates,
    a few steps each; the record interval the duration checks assume is evaluate_dynamic's."""
    assert inspect.signature(evaluate_dynamic).parameters["record_every"].default == RECORD_EVERY
    jansen = load_family("jansen_leg")
    evaluation = evaluate_dynamic(jansen, [jansen.space.default()], duration=0.02, dt=1e-3)
    assert [m for _, m in produced(evaluation)] == [derived(jansen, "dynamic", jansen.space.default())]
    walker = load_family("walker")
    designs = [{**walker.space.default(), "legs_per_side": 1},
               {**walker.space.default(), "legs_per_side": 2, "leg_family": "klann_leg"}]
    for coordinates in (None, "maximal"):
        evaluation = evaluate_dynamic(walker, designs, duration=0.02, dt=2e-3, coordinates=coordinates)
        assert evaluation.plan.coordinates.value == (coordinates or "tabulated")
        assert len(produced(evaluation)) == 2, evaluation.failures
        for params, metrics in produced(evaluation):
            assert metrics == derived(walker, "dynamic", params), coordinates
    assert "torso_tilt_max" in point_metrics(["torso", "torso_up"], "dynamic")
    assert "torso_tilt_max" not in point_metrics(["torso"], "dynamic")


@pytest.mark.parametrize("table, error", [
    ('[cluster]\naddress = "local"\nworkers = 2\nshard_timeout = 30.0\n', None),
    ('[cluster]\nworkers = -1\n', "'cluster.workers' must be an integer in 0 .. 4096"),
    ('[cluster]\nshard_timeout = -5.0\n', "'cluster.shard_timeout' must be 0"),
    ('[cluster]\naddress = " auto"\n', "'cluster.address' must be 'local', 'auto' or a Ray address"),
    ('[cluster]\nnodes = 3\n', "unknown key 'cluster.nodes'"),
    ('[cluster]\ngpus_per_worker = 0.0\n', "'cluster.gpus_per_worker' must be a share of a GPU in"),
    ('[cluster]\ngpus_per_worker = 1.5\n', "'cluster.gpus_per_worker' must be a share of a GPU in"),
    ('[cluster]\ngpus_per_worker = nan\n', "'cluster.gpus_per_worker' must be a share of a GPU in"),
    ('[cluster]\ngpus_per_worker = 0.00001\n', "'cluster.gpus_per_worker' must be a share of a GPU in"),  # finer than Ray places
])
def test_the_cluster_table_is_read_and_checked(tmp_path, table, error):
    text = (ROOT / "studies" / "quickstart.toml").read_text() + "\n" + table
    path = tmp_path / "q.toml"
    path.write_text(text)
    if error is None:
        spec = load_study_spec(path)
        assert (spec.cluster, spec.workers, spec.shard_timeout) == ("local", 2, 30.0)
        return
    with pytest.raises(ValueError, match=error.replace(".", r"\.").replace("(", r"\(")):
        load_study_spec(path)


def test_a_cuda_study_takes_a_share_of_a_gpu_per_worker_from_the_file_or_the_command_line(tmp_path):
    from morphopt.cli import _study_spec, build_parser

    path = tmp_path / "q.toml"
    path.write_text((ROOT / "studies" / "quickstart.toml").read_text().replace('device = "cpu"', 'device = "cuda"')
                    + '\n[cluster]\naddress = "local"\ngpus_per_worker = 0.5\n')
    spec = load_study_spec(path)
    assert (spec.device, spec.gpus_per_worker) == ("cuda", 0.5)
    assert spec.with_overrides(gpus_per_worker=0.25).gpus_per_worker == 0.25
    assert spec.with_overrides(device="cpu").gpus_per_worker == 0.5  # kept, unused: a CPU worker takes cores
    args = build_parser().parse_args(["study", "run", str(path), "--gpus-per-worker", "0.25", "--workers", "4"])
    assert (_study_spec(args).gpus_per_worker, _study_spec(args).workers) == (0.25, 4)
