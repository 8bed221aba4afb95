"""Bad input at every public entry point: study TOML files, the command line, design families,
stored optimizer checkpoints, design parameters and imported files.

Every error is a ValueError naming the item and what was expected (the command line: exit status
2, one line on stderr, no traceback); a failed run leaves a study's stored results as they were;
study files are data and a family name never reaches outside designs/.
"""

import hashlib
import json
import math
import pickle
import re
import sqlite3
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from morphopt.cli import main
from morphopt.design_space import Choice, DesignSpace, Float, Int
from morphopt.families import available_families, load_family
from morphopt.optimizers import CMAES, OptunaSampler, RandomSearch
from morphopt import checkpoint
from morphopt.study import run_study
from morphopt.study_spec import SECTIONS, load_study_spec

SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

# --------------------------------------------------------------------------------------------
# A small TOML writer (tomllib only reads), so that hypothesis can derive documents from a valid study.


def toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else toml_string(key)


def toml_string(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + re.sub(r"[\x00-\x1f\x7f]", lambda m: f"\\u{ord(m.group()):04x}", escaped) + '"'


def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return toml_string(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return "{" + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + "}"


def toml_text(data: dict) -> str:
    """TOML for a dict: plain values first, then [tables] and [[arrays of tables]]."""
    lines = [f"{toml_key(k)} = {toml_value(v)}" for k, v in data.items()
             if not isinstance(v, dict) and not (isinstance(v, list) and v and all(isinstance(t, dict) for t in v))]
    for key, value in data.items():
        tables = [value] if isinstance(value, dict) else value if isinstance(value, list) and value and all(
            isinstance(t, dict) for t in value) else []
        for table in tables:
            lines.append(f"[{toml_key(key)}]" if isinstance(value, dict) else f"[[{toml_key(key)}]]")
            lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def valid_study() -> dict:
    """A valid kinematic four-bar study using every section."""
    return {
        "study": {"name": "fuzz", "family": "four_bar", "mode": "kinematic", "seed": 1, "generations": 2, "worlds": 4,
                  "device": "cpu"},
        "objective": {"metric": "coupler_point_stride", "direction": "maximize"},
        "optimizer": {"name": "cma", "sigma0": 0.2, "restarts": 0},
        "simulation": {"samples": 32, "dt": 1e-3, "duration": 1.0},
        "space": {"crank": [0.05, 0.12]},
        "fixed": {"ground": 0.3},
        "constraints": {"transmission_angle_min": [0.2, 3.2]},
    }


identifiers = st.from_regex(r"[a-z][a-z0-9_]{0,11}", fullmatch=True)
scalars = st.one_of(st.booleans(), st.integers(-2**63, 2**63 - 1), st.floats(), st.text(max_size=12))
toml_values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=3)
                           | st.dictionaries(st.text(max_size=6), inner, max_size=3), max_leaves=6)
TYPED = [(section, key, kind) for section, keys in SECTIONS.items() if keys for key, kind in keys.items()]
FOUR_BAR = load_family("four_bar").space.parameters


def wrong_type(kind):
    """TOML values that are not of ``kind`` (an int passes for a float)."""
    others = {str: st.booleans() | st.integers() | st.floats() | st.lists(st.integers(), max_size=2),
              int: st.booleans() | st.floats() | st.text(max_size=5) | st.lists(st.integers(), max_size=2),
              float: st.booleans() | st.text(max_size=5) | st.lists(st.floats(), max_size=2)
              | st.dictionaries(identifiers, st.integers(), max_size=2),
              list: st.booleans() | st.integers() | st.floats() | st.text(max_size=5)}
    return others[kind]


BAD_VALUES = {  # right type, outside what the key allows
    ("study", "worlds"): st.integers(-10, 1), ("study", "generations"): st.integers(-10, 0),
    ("study", "seed"): st.integers(-2**63, -1), ("optimizer", "restarts"): st.integers(-10, -1),
    ("simulation", "samples"): st.integers(-10, 7),
    ("optimizer", "sigma0"): st.floats(1.0 + 1e-9) | st.floats(max_value=0.0) | st.just(math.nan),
    ("simulation", "dt"): st.floats(0.1 + 1e-9) | st.floats(max_value=0.0) | st.just(math.nan),
    ("simulation", "duration"): st.floats(max_value=0.0) | st.sampled_from([math.inf, math.nan]),
    ("simulation", "crank_speed"): st.sampled_from([0.0, math.inf, -math.inf, math.nan]),
    ("study", "mode"): st.text(max_size=10).filter(lambda t: t not in ("kinematic", "dynamic")),
    ("objective", "direction"): st.text(max_size=10).filter(lambda t: t not in ("minimize", "maximize")),
    ("optimizer", "name"): st.text(max_size=10).filter(lambda t: t not in ("cma", "optuna", "random")),
    ("optimizer", "sampler"): st.text(max_size=10).filter(lambda t: t not in ("tpe", "nsga2", "random")),
    ("optimizer", "restart_strategy"): st.text(max_size=10).filter(lambda t: t not in ("ipop", "bipop")),
    ("study", "device"): st.text(max_size=10).filter(lambda t: not re.fullmatch(r"cpu|cuda(:[0-9]+)?", t)),
    ("study", "name"): st.text(max_size=10).filter(lambda t: not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.\-]*", t))
    | st.just("../../elsewhere") | st.just("x" * 201),
    ("study", "family"): identifiers.filter(lambda t: t not in available_families())
    | st.sampled_from(["../four_bar", "designs/four_bar", "os.path", "four_bar.txt", "", "missing.py"]),
    ("objective", "target"): st.just([[0.0, 1.0], [1.0]]) | st.just([1, 2, 3]) | st.just([[0.0, math.nan]] * 3),
}


@st.composite
def broken_studies(draw, kind: str, bad_key=None):
    """(study dict, the key the error must name) for one defect of valid_study() of ``kind``
    ("bad value": of the key ``bad_key``)."""
    data = valid_study()
    if kind == "unknown key":
        section = draw(st.sampled_from(["study", "objective", "optimizer", "simulation"]))
        key = draw(identifiers.filter(lambda k: k not in SECTIONS[section]))
        data[section][key] = draw(toml_values)
        return data, f"'{section}.{key}'"
    if kind == "unknown section":
        section = draw(identifiers.filter(lambda k: k not in SECTIONS))
        data[section] = draw(st.dictionaries(identifiers, scalars, max_size=2))
        return data, f"[{section}]"
    if kind == "wrong type":
        section, key, expected = draw(st.sampled_from(TYPED))
        data.setdefault(section, {})[key] = draw(wrong_type(expected))
        return data, f"'{section}.{key}'"
    if kind == "bad value":
        section, key = bad_key
        data[section][key] = draw(BAD_VALUES[bad_key])
        if key == "target":
            data["objective"].update(metric="path_error", point="coupler_point")
        return data, f"'{section}.{key}'"
    if kind == "not a table":
        section = draw(st.sampled_from(["study", "objective", "optimizer", "simulation", "space", "constraints"]))
        data[section] = draw(scalars | st.lists(st.integers(), max_size=2))
        return data, f"'{section}'"
    if kind == "space":
        name = draw(st.sampled_from(sorted(FOUR_BAR)))
        low, high = FOUR_BAR[name].low, FOUR_BAR[name].high
        data["space"][name] = draw(st.sampled_from([
            [high, low], [low, low], [low - 1.0, high], [low, high + 1.0], [low], [low, high, high], "wide",
            [low, math.nan], [True, False]]))
        data["fixed"].pop(name, None)
        return data, f"'space.{name}'"
    if kind == "fixed":
        name = draw(st.sampled_from(sorted(FOUR_BAR)) | identifiers.filter(lambda n: n not in FOUR_BAR))
        parameter = FOUR_BAR.get(name, Float(0.0, 1.0))
        data["fixed"][name] = draw(st.floats(parameter.high + 1e-6) | st.floats(max_value=parameter.low - 1e-6)
                                   | st.just(math.nan) | st.text(max_size=4) | st.booleans())
        data["space"].pop(name, None)
        return data, f"'fixed.{name}'"
    if kind == "constraints":
        data["constraints"]["transmission_angle_min"] = draw(st.sampled_from(
            [[1.0, 0.0], [0.0], [0.0, 1.0, 2.0], "low", [math.nan, 1.0], [0.0, math.nan], [False, True]]))
        return data, "'constraints.transmission_angle_min'"
    section, key = draw(st.sampled_from([("study", "name"), ("study", "family"), ("objective", "metric"),
                                         ("objective", None)]))
    if key is None:
        del data["objective"]
        return data, "[objective]"
    del data[section][key]
    return data, f"'{section}.{key}'"


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


def test_the_toml_writer_and_the_valid_study_round_trip(fuzz_dir):
    """The base of the property tests is itself valid: written, read back and loaded unchanged."""
    path = fuzz_dir / "valid.toml"
    path.write_text(toml_text(valid_study()), encoding="utf-8")
    spec = load_study_spec(path)
    assert (spec.name, spec.family, spec.worlds, spec.fixed, spec.space_overrides) == (
        "fuzz", "four_bar", 4, {"ground": 0.3}, {"crank": [0.05, 0.12]})


DEFECTS = [(kind, None) for kind in ("unknown key", "unknown section", "wrong type", "not a table", "space", "fixed",
                                      "constraints", "missing")] + [("bad value", key) for key in BAD_VALUES]


@pytest.mark.parametrize("kind, bad_key", DEFECTS, ids=[k if b is None else ".".join(b) for k, b in DEFECTS])
@settings(SETTINGS, max_examples=15)
@given(data=st.data())
def test_one_defect_in_a_study_file_is_named(fuzz_dir, kind, bad_key, data):
    """A valid study with one defect (unknown key or section, wrong type, value out of range,
    inverted or out-of-family bounds, unknown family, missing key) raises ValueError that starts
    with the file's path and names the key; never another exception."""
    data, key = data.draw(broken_studies(kind, bad_key))
    path = fuzz_dir / "broken.toml"
    path.write_text(toml_text(data), encoding="utf-8")
    with pytest.raises(ValueError) as error:
        load_study_spec(path)
    message = str(error.value)
    assert message.startswith(str(path)), message
    assert key in message, (key, message)


@pytest.mark.parametrize("section", ["study", "objective", "optimizer", "simulation", "space", "fixed",
                                     "constraints"])
@settings(SETTINGS, max_examples=25)
@given(data=st.data())
def test_any_value_anywhere_loads_or_is_named(fuzz_dir, section, data):
    """Any TOML value under any key (known or not) of a valid study either loads or raises
    ValueError starting with the file's path and naming the section; never another exception."""
    known = [*(SECTIONS[section] or ()), *FOUR_BAR, "transmission_angle_min"]
    key = data.draw(st.sampled_from(known) | st.text(max_size=8), label="key")
    value = data.draw(toml_values | st.lists(st.lists(st.floats(), max_size=3), max_size=4), label="value")
    data = valid_study()
    data[section][key] = value
    path = fuzz_dir / "any.toml"
    path.write_text(toml_text(data), encoding="utf-8")
    try:
        spec = load_study_spec(path)
    except ValueError as error:
        message = str(error)
        assert message.startswith(str(path)), message
        assert section in message, (section, message)
    else:
        assert spec.name == "fuzz" and spec.family == "four_bar"


@SETTINGS
@given(st.text(max_size=200).map(str.encode) | st.binary(max_size=200))
def test_garbage_files_raise_naming_the_file(fuzz_dir, content):
    """Random text, or random bytes (mostly not UTF-8), is refused with a ValueError naming the file."""
    path = fuzz_dir / "garbage.toml"
    path.write_bytes(content)
    with pytest.raises(ValueError) as error:
        load_study_spec(path)
    assert str(error.value).startswith(str(path))


# --------------------------------------------------------------------------------------------
# The command line: exit status 2, one line on stderr naming the item, no traceback.


def run_cli(argv, capsys) -> tuple[int, str]:
    """main(argv) in-process: (exit status, stderr), whether argparse exits or main returns."""
    try:
        status = main([str(a) for a in argv])
    except SystemExit as exit_:
        status = exit_.code
    return status, capsys.readouterr().err


def assert_one_line_error(status, err, fragment):
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2, (status, err)
    assert "Traceback" not in err
    assert len(lines) == 1 and lines[0].startswith("morphopt"), err
    assert fragment in lines[0], (fragment, lines[0])


@pytest.fixture
def study_files(tmp_path):
    """A valid (never run) study, and broken ones."""
    files = {"ok": toml_text(valid_study()), "bad_toml": "[study\nname = 'x'\n",
             "unknown_key": toml_text({**valid_study(), "study": {**valid_study()["study"], "colour": "red"}}),
             "hexapod": toml_text({**valid_study(), "study": {**valid_study()["study"], "family": "hexapod"}}),
             "escape": toml_text({**valid_study(), "study": {**valid_study()["study"], "family": "../designs/x"}})}
    paths = {}
    for name, text in files.items():
        paths[name] = tmp_path / f"{name}.toml"
        paths[name].write_text(text)
    paths["missing"], paths["folder"] = tmp_path / "missing.toml", tmp_path
    return paths


CLI_CASES = [
    (["study", "run", "{missing}"], "no such study file"),
    (["study", "run", "{bad_toml}"], "not valid TOML"),
    (["study", "show", "{unknown_key}"], "unknown key 'study.colour'"),
    (["study", "show", "{folder}"], "cannot read the study file"),
    (["study", "run", "{hexapod}"], "'study.family': unknown design family 'hexapod'"),
    (["study", "run", "{escape}"], "'study.family': design family '../designs/x'"),
    (["study", "run", "{ok}", "--worlds", "0"], "argument --worlds: must be > 0, got 0"),
    (["study", "run", "{ok}", "--worlds", "many"], "argument --worlds: expected an int, got 'many'"),
    (["study", "run", "{ok}", "--worlds", "1"], "'study.worlds' must be an integer >= 2"),
    (["study", "run", "{ok}", "--seed", "-1"], "'study.seed' must be an integer >= 0"),
    (["study", "run", "{ok}", "--device", "gpu"], "'study.device' must be 'cpu', 'cuda' or 'cuda:N'"),
    (["study", "run", "{ok}", "--device", "cuda:99"], "'study.device' 'cuda:99' is not available"),
    (["study", "resume", "{ok}"], "has nothing to resume"),
    (["study", "show", "{ok}", "--top", "-2"], "argument --top: must be > 0"),
    (["study", "fly", "{ok}"], "invalid choice: 'fly'"),
    (["export", "{ok}", "--format", "obj"], "argument --format: invalid choice: 'obj'"),
    (["export", "{ok}"], "the following arguments are required: --format"),
    (["demo", "fourbar", "--device", "gpu"], "--device 'gpu'"),
    (["demo", "fourbar", "--dt", "-1"], "argument --dt: must be > 0"),
]


@pytest.mark.parametrize("argv, fragment", CLI_CASES, ids=[" ".join(a).replace("{", "").replace("}", "")
                                                             for a, _ in CLI_CASES])
def test_cli_bad_input_exits_2_with_one_line(study_files, capsys, argv, fragment):
    """Every kind of bad input ends the command with status 2 and one stderr line naming the item."""
    status, err = run_cli([a.format(**study_files) for a in argv], capsys)
    assert_one_line_error(status, err, fragment)


def test_cli_as_a_process_exits_2_without_traceback(study_files):
    """The installed entry point behaves the same in a real process (exit status, one line)."""
    for argv, fragment in ((["study", "run", str(study_files["bad_toml"])], "not valid TOML"),
                           (["export", str(study_files["ok"]), "--format", "obj"], "invalid choice: 'obj'")):
        result = subprocess.run([sys.executable, "-m", "morphopt.cli", *argv], capture_output=True, text=True, check=False,
                                timeout=120)
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert result.returncode == 2 and "Traceback" not in result.stderr
        assert len(lines) == 1 and fragment in lines[0], result.stderr


def test_read_only_commands_create_no_database(study_files, capsys):
    """`study show` of a study never run says so and leaves no database file behind."""
    assert main(["study", "show", str(study_files["ok"])]) == 1
    assert "has no stored designs" in capsys.readouterr().out
    assert not (study_files["ok"].parent / "fuzz.sqlite").exists()


# --------------------------------------------------------------------------------------------
# A failed run leaves the stored results untouched.


def tiny_study(tmp_path, **changes) -> dict:
    """One generation of four four-bars that all turn (ground, coupler and rocker fixed: Grashof)."""
    data = valid_study()
    data["study"].update(name="tiny", generations=1, worlds=4)
    data["simulation"] = {"samples": 16}
    data["fixed"] = {"ground": 0.3, "coupler": 0.3, "rocker": 0.25}
    del data["constraints"]
    for section, values in changes.items():
        data[section] = {**data.get(section, {}), **values}
    return data


def snapshot(database) -> tuple:
    """Every stored row of both tables, and the file's hash."""
    with sqlite3.connect(database) as connection:
        designs = connection.execute("SELECT * FROM designs ORDER BY study, generation, member").fetchall()
        checkpoints = connection.execute("SELECT * FROM checkpoints ORDER BY study").fetchall()
    connection.close()
    return designs, checkpoints, hashlib.sha256(database.read_bytes()).hexdigest()


def test_failed_runs_leave_stored_results_untouched(tmp_path, capsys, monkeypatch):
    """After a 1-generation study, an invalid spec, an unavailable device, a resume with another
    space or optimizer, a crash in the first generation of a --fresh run and a damaged checkpoint
    all fail and leave every stored row (and the database file) as it was."""
    path = tmp_path / "tiny.toml"
    path.write_text(toml_text(tiny_study(tmp_path)))
    assert run_study(load_study_spec(path), progress=False).best_params is not None
    database = tmp_path / "tiny.sqlite"
    before = snapshot(database)
    assert len(before[0]) == 4 and len(before[1]) == 1
    capsys.readouterr()

    failures = [  # (spec changes, argv after the spec, what the error names)
        ({}, ["run", "--worlds", "1"], "'study.worlds'"),
        ({}, ["run", "--device", "cuda:99"], "'study.device'"),
        ({"study": {"colour": "red"}}, ["run"], "unknown key 'study.colour'"),
        ({"space": {"crank": [0.06, 0.08]}}, ["resume"], "another design space"),
        ({"optimizer": {"name": "random"}}, ["resume"], "the spec asks for optimizer 'random'"),
    ]
    for changes, argv, fragment in failures:
        path.write_text(toml_text(tiny_study(tmp_path, **changes)))
        status, err = run_cli(["study", argv[0], path, *argv[1:]], capsys)
        assert_one_line_error(status, err, fragment)
        assert snapshot(database) == before, (changes, argv)

    path.write_text(toml_text(tiny_study(tmp_path)))
    status, err = run_cli(["export", path, "--format", "urdf", "--out", path], capsys)  # --out is a file
    assert_one_line_error(status, err, str(path))
    status, err = run_cli(["study", "export", path, "--optuna-storage", "nowhere://x"], capsys)
    assert_one_line_error(status, err, "cannot open the Optuna storage 'nowhere://x'")
    assert snapshot(database) == before

    def crash(*args, **kwargs):
        raise RuntimeError("the evaluation crashed")

    monkeypatch.setattr("morphopt.study.evaluate_kinematic", crash)
    with pytest.raises(RuntimeError, match="the evaluation crashed"):
        run_study(load_study_spec(path), progress=False, fresh=True)  # it would move the results aside
    assert snapshot(database)[:2] == before[:2]  # the lease was taken and given back; no design moved
    monkeypatch.undo()

    with sqlite3.connect(database) as connection:
        connection.execute("UPDATE checkpoints SET state = ?", (b"not a checkpoint",))
    connection.close()
    damaged = snapshot(database)
    status, err = run_cli(["study", "resume", path], capsys)
    assert_one_line_error(status, err, f"study 'tiny' in sqlite:///{database}: the optimizer checkpoint is not in")
    assert snapshot(database) == damaged


# --------------------------------------------------------------------------------------------
# Stored optimizer state: JSON and float64 arrays only, and a rebuilt optimizer continues exactly.


OPTIMIZER_NAMES = ["cma", "cma bipop", "optuna tpe", "optuna nsga2", "random"]
SPACE = DesignSpace({"a": Float(0.0, 1.0), "b": Float(0.1, 10.0, log=True), "n": Int(1, 5),
                     "c": Choice(("x", "y", "z"))})
FACTORIES = [
    lambda: CMAES(SPACE, popsize=6, seed=3, restarts=1),
    lambda: CMAES(SPACE, popsize=6, seed=3, restarts=2, restart_strategy="bipop"),
    lambda: OptunaSampler(SPACE, sampler="tpe", seed=3),
    lambda: OptunaSampler(SPACE, sampler="nsga2", seed=3, directions=["minimize", "minimize"]),
    lambda: RandomSearch(SPACE, seed=3),
]


def drive(optimizer, generations: int, pareto: bool) -> list:
    """Ask and tell ``generations`` batches of 6 (a failure among them); returns the optimizer log."""
    log = []
    for generation in range(generations):
        asked = optimizer.ask(6)
        values = np.array([p["a"] + math.log(p["b"]) + p["n"] + (p["c"] == "y") for p in asked])
        values[generation % 6] = math.inf  # a failed design
        told = np.column_stack([values, values, -values]) if pareto else values[:, None]
        if pareto:
            optimizer.tell(asked, values.tolist(), told[:, 1:])
        else:
            optimizer.tell(asked, values.tolist())
        log.append((generation, checkpoint.designs_digest(asked), told))
        optimizer.asked_so_far = [*getattr(optimizer, "asked_so_far", []), asked]
    return log


@pytest.mark.parametrize("index", range(5), ids=OPTIMIZER_NAMES)
def test_every_optimizer_is_rebuilt_exactly_from_its_log_and_checkpoint(index):
    """An optimizer rebuilt from its seed by replaying the stored log matches the checkpoint's summary
    bit for bit and asks exactly what the original asks next; a log or checkpoint that was altered is
    refused with a message naming the storage."""
    pareto = OPTIMIZER_NAMES[index] == "optuna nsga2"
    original = FACTORIES[index]()
    log = drive(original, 12, pareto)  # CMA-ES with restarts restarts within 12 generations of 6
    blob = checkpoint.encode({"optimizer": "x", "space": checkpoint.space_description(SPACE)},
                             checkpoint.summary(original))
    header, arrays = checkpoint.decode(blob, "study 's' in db")
    assert header["space"] == checkpoint.space_description(SPACE) and header["version"] == checkpoint.VERSION
    rebuilt = FACTORIES[index]()
    checkpoint.replay(rebuilt, log, "study 's' in db")
    checkpoint.check_summary(rebuilt, arrays, "study 's' in db")
    assert rebuilt.evaluations == original.evaluations == 72 and rebuilt.best_value == original.best_value
    if getattr(rebuilt, "takes_stored_designs", False):  # TPE and random: the stored designs, then the states
        quick = FACTORIES[index]()
        checkpoint.replay(quick, log, "study 's' in db", original.asked_so_far)
        checkpoint.restore_random_states(quick, arrays, "study 's' in db")
        checkpoint.check_summary(quick, arrays, "study 's' in db")
        assert quick.ask(6) == rebuilt.ask(6) == original.ask(6)
    else:
        assert rebuilt.ask(6) == original.ask(6)
    changed = [(g, d, t.copy()) for g, d, t in log]
    changed[5][2][2, :] = -1e3  # one told value differs
    with pytest.raises(ValueError, match=r"^study 's' in db: the optimizer rebuilt from the stored"):
        fresh = FACTORIES[index]()
        checkpoint.replay(fresh, changed, "study 's' in db")
        checkpoint.check_summary(fresh, arrays, "study 's' in db")
    with pytest.raises(ValueError, match=r"asks for other designs in generation 0"):
        checkpoint.replay(FACTORIES[index](), [(0, "0" * 64, log[0][2])], "study 's' in db")


class _Exploit:
    def __init__(self, call, args):
        self.call, self.args = call, args

    def __reduce__(self):
        return self.call, self.args


def hostile_pickles(tmp_path) -> dict:
    """Pickled checkpoints an attacker could store: each would write a file or run a command if it
    were unpickled (a memmap opened for writing, a .pth line, os.system, eval, a NEWOBJ of memmap)."""
    site = tmp_path / "site-packages"
    site.mkdir(exist_ok=True)
    target = str(tmp_path / "mm.bin").encode()
    memmap = (b"\x80\x04cnumpy\nmemmap\n(X" + len(target).to_bytes(4, "little") + target
              + b"cnumpy\nuint8\nX\x02\x00\x00\x00w+K\x00K\x10t\x81.")
    return {
        "memmap NEWOBJ": memmap,
        "pth": pickle.dumps(_Exploit(eval, (f"open({str(site / 'evil.pth')!r}, 'w').write('import os')",))),
        "os.system": pickle.dumps(_Exploit(__import__("os").system, (f"touch {tmp_path / 'ran'}",))),
        "builtins.eval": pickle.dumps(_Exploit(eval, (f"open({str(tmp_path / 'ran')!r}, 'w')",))),
        "pathlib touch": pickle.dumps(_Exploit(__import__("pathlib").Path.touch, (tmp_path / "ran",))),
    }


def tree(folder) -> dict:
    """Every file under ``folder`` with its hash."""
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_hostile_pickled_checkpoints_are_never_unpickled(tmp_path):
    """Every hostile pickle is refused by the checkpoint reader with one line that says why, and
    nothing on disk changes (the pickle is never parsed)."""
    blobs = hostile_pickles(tmp_path)
    probe = tmp_path / "probe"
    probe.mkdir()
    pickle.loads(hostile_pickles(probe)["memmap NEWOBJ"])  # the attack is real: unpickled, it writes a file
    assert (probe / "mm.bin").stat().st_size == 16
    before = tree(tmp_path)
    for name, blob in blobs.items():
        with pytest.raises(checkpoint.CheckpointError, match=r"^study 'x' in db: .* never unpickles") as error:
            checkpoint.decode(blob, "study 'x' in db")
        assert "\n" not in str(error.value), name
    assert tree(tmp_path) == before


def checkpoint_blob(header_text: bytes, data: bytes = b"", length=None) -> bytes:
    length = len(header_text) if length is None else length
    return checkpoint.MAGIC + length.to_bytes(8, "little") + header_text + data


@pytest.mark.parametrize("blob, reason", [
    (b"", "not in morphopt's checkpoint format"),
    (b"not a checkpoint", "not in morphopt's checkpoint format"),
    (checkpoint_blob(b"{}", length=1 << 40), "truncated or damaged"),
    (checkpoint_blob(b"{not json"), "header is not JSON"),
    (checkpoint_blob(b"[" * 100000 + b"]" * 100000), "header is not JSON"),
    (checkpoint_blob(b'{"version": 2, "arrays": []}'), "format version 2"),
    (checkpoint_blob(b'{"version": 1, "arrays": [["a", 0, [4]]]}', b"\x00" * 16), "arrays are damaged"),
    (checkpoint_blob(b'{"version": 1, "arrays": [["a", -2, [1]]]}', b"\x00" * 16), "arrays are damaged"),
    (checkpoint_blob(b'{"version": 1, "arrays": [["a", 0, "x"]]}', b"\x00" * 8), "arrays are damaged"),
    (checkpoint_blob(b'{"version": 1, "arrays": []}', b"\x00" * 5), "truncated"),
    (None, "not a byte string"),
])
def test_damaged_checkpoints_are_named(blob, reason):
    """Damaged, truncated, deeply nested or future-version checkpoints: one line naming the storage."""
    with pytest.raises(checkpoint.CheckpointError, match=r"^study 'x' in db: the optimizer checkpoint") as error:
        checkpoint.decode(blob, "study 'x' in db")
    assert reason in str(error.value)


# --------------------------------------------------------------------------------------------
# Families load only from designs/ or an explicit .py path; study files are data.

MARKED_FAMILY = '''
import pathlib
pathlib.Path(__file__).with_suffix(".ran").touch()  # shows that this module was executed
from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Link, Linkage

space = DesignSpace({"r": Float(0.01, 0.05), "x": Float(-1.0, 1.0)})


def generate(params, *, crank_speed=6.283185307179586, phase=0.0):
    return Linkage(name="marked", ground={"O": (params["x"], 0.0)},
                   crank=Crank("O", "T", params["r"], phase=phase, speed=crank_speed),
                   links=[Link("crank", ("O", "T"))], points={"tip": "T"})
'''


@pytest.mark.parametrize("name", ["../outside", "designs/../outside", "a/b", "os.path", "four_bar; import os",
                                  "four_bar.txt", "", " four_bar", None, 3])
def test_family_names_never_leave_designs(tmp_path, monkeypatch, name):
    """A family is a plain identifier in designs/ or a .py path: anything else is refused,
    naming it, and nothing is executed (here ../outside.py exists beside designs/)."""
    (tmp_path / "designs").mkdir()
    (tmp_path / "outside.py").write_text(MARKED_FAMILY)
    monkeypatch.chdir(tmp_path)  # designs/ of the working directory is searched first
    with pytest.raises(ValueError, match="design family") as error:
        load_family(name)
    assert (repr(name) if not isinstance(name, str) or not name else f"'{name}'") in str(error.value)
    assert not (tmp_path / "outside.ran").exists()


def test_explicit_family_paths_are_relative_to_the_study_file(tmp_path, monkeypatch):
    """A study reaches a family outside designs/ only through a path to a .py file, taken from the
    spec's folder whatever the working directory; the same module as a name is refused."""
    (tmp_path / "outside.py").write_text(MARKED_FAMILY)
    monkeypatch.chdir(tmp_path.parent)
    data = valid_study()
    del data["space"], data["fixed"]
    data["objective"]["metric"] = "tip_stride"  # the family tracks "tip"
    data["study"]["family"] = "outside"
    path = tmp_path / "s.toml"
    path.write_text(toml_text(data))
    with pytest.raises(ValueError, match=r"'study.family': unknown design family 'outside'"):
        load_study_spec(path)
    data["study"]["family"] = "../outside"
    path.write_text(toml_text(data))
    with pytest.raises(ValueError, match=r"'study.family': design family '../outside'"):
        load_study_spec(path)
    assert not (tmp_path / "outside.ran").exists()
    data["study"]["family"] = "outside.py"
    path.write_text(toml_text(data))
    spec = load_study_spec(path)
    assert spec.family == str((tmp_path / "outside.py").resolve()) and (tmp_path / "outside.ran").exists()


def test_study_files_are_data_never_code(tmp_path, monkeypatch):
    """Python in a study file is never run: as a file it is not TOML, as values it is text."""
    monkeypatch.chdir(tmp_path)
    marker = tmp_path / "ran"
    code = f"import pathlib\npathlib.Path({str(marker)!r}).touch()\n"
    path = tmp_path / "code.toml"
    path.write_text(code)
    with pytest.raises(ValueError, match="not valid TOML"):
        load_study_spec(path)
    call = f"__import__('pathlib').Path({str(marker)!r}).touch()"
    data = valid_study()
    data["study"]["name"] = call
    path.write_text(toml_text(data))
    with pytest.raises(ValueError, match="'study.name' must be"):
        load_study_spec(path)
    for section in ("objective", "constraints"):
        data = valid_study()
        if section == "objective":
            data["objective"]["metric"] = call
        else:
            data["constraints"] = {call: [0.0, 1.0]}
        path.write_text(toml_text(data))
        with pytest.raises(ValueError, match="is not a metric of family 'four_bar'"):  # a name, never run
            load_study_spec(path)
    assert not marker.exists()


# --------------------------------------------------------------------------------------------
# Design parameters outside their bounds.


@SETTINGS
@given(st.floats(allow_nan=True).filter(lambda v: not 0.04 <= v <= 0.15) | st.booleans() | st.text(max_size=4))
def test_design_parameters_outside_bounds_name_parameter_bound_and_value(value):
    """A value outside a parameter's range (or not a number) raises ValueError naming the
    parameter, its bounds and the value."""
    space = load_family("four_bar").space
    with pytest.raises(ValueError) as error:
        space.validate({**space.default(), "crank": value})
    message = str(error.value)
    assert "'crank'" in message and repr(value) in message and "[0.04, 0.15]" in message


@pytest.mark.parametrize("params, fragment", [
    ({"legs": 2.5}, "'legs' = 2.5 is outside integers in [2, 6]"),
    ({"legs": True}, "'legs' = True is outside integers in [2, 6]"),
    ({"kind": "wheel"}, "'kind' = 'wheel' is outside the choices ['jansen', 'klann']"),
    ({"wings": 2}, "unknown design parameter(s) ['wings']"),
    (None, "design parameter 'kind' is missing"),
])
def test_int_choice_unknown_and_missing_parameters_are_named(params, fragment):
    """Integers, choices, unknown and missing parameters are refused by name."""
    space = DesignSpace({"length": Float(0.1, 0.5), "legs": Int(2, 6), "kind": Choice(("jansen", "klann"))})
    given_params = {"length": 0.2, "legs": 4} if params is None else {**space.default(), **params}
    with pytest.raises(ValueError, match=re.escape(fragment)):
        space.validate(given_params)


# --------------------------------------------------------------------------------------------
# Imported files that are not what they claim to be.


@pytest.mark.parametrize("content, fragment", [
    (b"", "not well-formed XML"), (b"\x00\xff\xfe\x89PNG", "not well-formed XML"),
    (b"<html><body/></html>", "the root element is <html>, not <robot>"),
    (b'<robot name="r"><link name="a"/><joint name="j" type="revolute"><parent link="a"/></joint></robot>',
     "joint 'j'"),
    (None, "cannot read"),
])
def test_urdf_files_that_are_not_urdf_are_named(tmp_path, content, fragment):
    """read_urdf: an empty, binary, foreign or broken file (or a folder) raises ValueError naming the file."""
    from morphopt.formats.urdf import read_urdf

    path = tmp_path / "robot.urdf"
    if content is None:
        path.mkdir()
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError, match=re.escape(fragment)) as error:
        read_urdf(path)
    assert str(error.value).startswith(str(path))


def test_urdf_metadata_that_is_not_json_is_named(tmp_path):
    """read_urdf_metadata: metadata that is not JSON raises ValueError naming the file."""
    from morphopt.formats.urdf import EXTENSION_TAG, EXTENSION_VERSION, read_urdf_metadata

    path = tmp_path / "m.urdf"
    path.write_text(f'<robot name="r"><{EXTENSION_TAG} version="{EXTENSION_VERSION}"><metadata>{{not json'
                    f"</metadata></{EXTENSION_TAG}></robot>")
    with pytest.raises(ValueError, match="metadata is not JSON") as error:
        read_urdf_metadata(path)
    assert str(error.value).startswith(str(path))


@pytest.mark.parametrize("name, content, fragment", [
    ("garbage.usda", "this is not a stage {{{", "not a readable USD stage"),
    ("empty.usda", "", "not a readable USD stage"),
    ("binary.usd", "\x00\x01PXR-USDC", "not a readable USD stage"),
    ("missing.usda", None, "no such USD file"),
    ("bodiless.usda", "#usda 1.0\n", "no rigid bodies"),
])
def test_usd_files_that_are_not_stages_are_named(tmp_path, name, content, fragment):
    """read_usd: a garbage, empty or missing file, or a stage without bodies, raises ValueError naming the file."""
    from morphopt.formats.usd import read_usd

    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    with pytest.raises(ValueError, match=re.escape(fragment)) as error:
        read_usd(path)
    assert str(error.value).startswith(str(path))


def test_the_toml_writer_escapes_what_toml_requires():
    """The TOML writer escapes what TOML requires (quotes, backslashes, control characters)."""
    import tomllib

    data = {"t": {"k": 'a"b\\c\x00\x7f\n\u00e9\U0001f600', "f": [1.5, -0.0, 1e-300, math.inf], "q w": {"": True}}}
    loaded = tomllib.loads(toml_text(data))
    assert json.dumps(loaded, sort_keys=True) == json.dumps(data, sort_keys=True)


@pytest.mark.parametrize("mode, space, fragment", [
    ("kinematic", {}, "'study.mode' must be 'dynamic' for family 'walker'"),
    ("dynamic", {"leg_family": ["jansen_leg", "klann_leg"]}, "'space.leg_family' cannot narrow a choice among"),
    ("dynamic", {"legs_per_side": [1.5, 3]}, "'space.legs_per_side' must be [low, high] (integers)"),
])
def test_whole_world_families_need_dynamic_mode_and_integer_or_choice_rules(tmp_path, mode, space, fragment):
    """A whole-world family (the walker) cannot be evaluated kinematically; its integer and choice
    parameters cannot be narrowed like reals. Each mistake is named before anything runs."""
    data = valid_study()
    data["study"].update(family="walker", mode=mode)
    data["space"], data["fixed"] = space, {}
    path = tmp_path / "walker.toml"
    path.write_text(toml_text(data))
    with pytest.raises(ValueError, match=re.escape(fragment)) as error:
        load_study_spec(path)
    assert str(error.value).startswith(str(path))
