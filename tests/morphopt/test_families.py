"""Design families as a user meets them: the built-in ones ship in the package and load from any
folder (a ./designs/ folder of the working directory shadows them, explicit paths still work)."""

import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest

from morphopt.families import BUILTIN_DIR, available_families, load_family

ROOT = pathlib.Path(__file__).resolve().parents[2]
BUILTIN = ("four_bar", "jansen_leg", "klann_leg", "walker", "watt_sixbar")


def test_builtin_families_load_from_a_folder_without_designs(tmp_path, monkeypatch):
    """From a folder with no designs/ the built-in families are found in the package itself."""
    monkeypatch.chdir(tmp_path)
    assert set(BUILTIN) <= set(available_families())
    module = load_family("jansen_leg")
    assert pathlib.Path(module.__file__).parent == BUILTIN_DIR
    assert BUILTIN_DIR.parent == pathlib.Path(sys.modules["morphopt"].__file__).resolve().parent


def test_every_builtin_parameter_has_a_unit_and_a_meaning():
    """Each parameter of a built-in family says what it is (help) and its unit ("" for a ratio, a
    count or a choice); a unit or help that is not text is refused when the space is made."""
    from morphopt.design_space import DesignSpace, Float

    for name in BUILTIN:
        for pname, parameter in load_family(name).space.parameters.items():
            assert parameter.help and isinstance(parameter.unit, str), (name, pname)
    assert load_family("jansen_leg").space.parameters["m"].unit == "m"
    assert load_family("walker").space.parameters["crank_speed"].unit == "rad/s"
    assert Float(0.0, 1.0, 0.5, False).unit == ""  # the old positional form still works
    with pytest.raises(ValueError, match="parameter 'x': unit and help must be text"):
        DesignSpace({"x": Float(0.0, 1.0, unit=1.0)})


def test_a_users_designs_folder_comes_first_and_paths_still_work(tmp_path, monkeypatch):
    """./designs/jansen_leg.py shadows the built-in leg, a new family there is listed, and an
    explicit .py path loads whatever the working directory."""
    (tmp_path / "designs").mkdir()
    source = (BUILTIN_DIR / "four_bar.py").read_text()
    (tmp_path / "designs" / "jansen_leg.py").write_text(source)  # a four-bar under Jansen's name
    (tmp_path / "designs" / "my_linkage.py").write_text(source)
    monkeypatch.chdir(tmp_path)
    assert "coupler" in load_family("jansen_leg").space.names
    assert "my_linkage" in available_families() and set(BUILTIN) <= set(available_families())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert "m" in load_family("jansen_leg").space.names  # the built-in one again
    assert "coupler" in load_family(tmp_path / "designs" / "my_linkage.py").space.names


def _backend_is_here() -> bool:
    """Whether this interpreter can build the package without fetching a build backend."""
    try:
        import setuptools
    except ImportError:
        return False
    version = tuple(int(part) for part in setuptools.__version__.split(".")[:2])
    if version >= (70, 1):
        return True  # bdist_wheel is part of setuptools
    try:
        import wheel  # noqa: F401
    except ImportError:
        return False
    return version >= (68, 0)


@pytest.mark.slow
def test_a_non_editable_install_runs_a_study_from_another_folder(tmp_path):
    """`pip install --target` (not editable, no source tree on the path), then from a folder outside
    the repository: `morphopt families` lists the built-in families (in the installed package), and
    `study run` and `study show` of a copy of the quickstart study find jansen_leg and store and
    show its designs."""
    target = tmp_path / "site"
    command = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target), str(ROOT)]
    if _backend_is_here():
        command.append("--no-build-isolation")
    subprocess.run(command, check=True, capture_output=True, text=True, timeout=300)
    assert (target / "morphopt" / "designs" / "jansen_leg.py").is_file()
    work = tmp_path / "work"
    work.mkdir()
    shutil.copy(ROOT / "studies" / "quickstart.toml", work / "quickstart.toml")
    env = {**os.environ, "PYTHONPATH": str(target)}

    def morphopt(*argv):
        return subprocess.run([sys.executable, "-m", "morphopt.cli", *argv], cwd=work, env=env, capture_output=True,
                              text=True, timeout=300)

    where = subprocess.run([sys.executable, "-c", "import morphopt; print(morphopt.__file__)"], cwd=work, env=env,
                           capture_output=True, text=True, check=True).stdout
    assert pathlib.Path(where.strip()).is_relative_to(target), where
    listed = morphopt("families")
    assert listed.returncode == 0, listed.stderr
    assert all(name in listed.stdout for name in BUILTIN) and str(target) in listed.stdout, listed.stdout
    ran = morphopt("study", "run", "quickstart.toml", "--generations", "2", "--worlds", "8")
    assert ran.returncode == 0, ran.stderr[-2000:]
    shown = morphopt("study", "show", "quickstart.toml")
    assert shown.returncode == 0, shown.stderr[-2000:]
    assert "jansen_leg" not in shown.stderr and shown.stdout.strip(), (shown.stdout, shown.stderr)
    from morphopt.storage import read_designs

    assert len(read_designs(f"sqlite:///{work / 'quickstart.sqlite'}", "quickstart")) == 16


def run_cli(capsys, *argv):
    """(exit status, stdout, stderr) of `morphopt <argv>` run in this process."""
    from morphopt.cli import main

    status = main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


def test_families_lists_every_builtin_family_with_its_modes(capsys):
    """`morphopt families`: one line per family with its modes and the start of its docstring."""
    status, out, _ = run_cli(capsys, "families")
    assert status == 0
    lines = {line.split()[0]: line for line in out.splitlines() if line.strip()}
    assert "kinematic, dynamic" in lines["jansen_leg"] and "Strandbeest" in lines["jansen_leg"]
    assert "dynamic" in lines["walker"] and "kinematic" not in lines["walker"]
    assert all(name in lines for name in BUILTIN)


def test_families_show_prints_every_parameter_and_the_metrics_with_units(capsys):
    """`morphopt families show jansen_leg`: every parameter with the space's own bounds, default,
    unit and meaning; the metrics of both modes with units and their definitions."""
    from morphopt.contract import DEFINITIONS

    status, out, _ = run_cli(capsys, "families", "show", "jansen_leg")
    assert status == 0
    lines = out.splitlines()
    space = load_family("jansen_leg").space
    for name, parameter in space.parameters.items():
        row = next(line.split(None, 4) for line in lines if line.split()[:1] == [name])
        assert row[1:4] == [f"[{parameter.low:.6g},", f"{parameter.high:.6g}]", f"{parameter.default:.6g}"], row
        assert row[4].startswith("m ") and parameter.help and row[4].endswith(parameter.help)
    assert re.search(r"\n  m +\[0\.012, 0\.018\] +0\.015 +m +crank radius: axle O to crank pin M", out)
    kinematic, dynamic = out.index("metrics, kinematic mode"), out.index("metrics, dynamic mode")
    for metric, key, unit in (("foot_stride", "<point>_stride", "m"), ("foot_stride_full", "<point>_stride_full", "m"),
                              ("transmission_angle_min", "transmission_angle_min", "rad")):
        line = next(line for line in out[kinematic:dynamic].splitlines() if line.split()[:1] == [metric])
        assert line.split()[1] == unit and line.endswith(DEFINITIONS[key].meaning), line
    assert "torque_peak" in out[dynamic:] and "transmission_angle_min" not in out[dynamic:]


def test_families_show_of_an_unknown_family_is_one_line_and_status_2(capsys):
    """A misspelt family: exit status 2, one line on stderr naming it and the families there are."""
    status, out, err = run_cli(capsys, "families", "show", "jansen_legs")
    assert status == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("morphopt families show: unknown design family 'jansen_legs'")
    assert "available: four_bar, jansen_leg" in err


def test_every_derived_metric_is_defined_and_the_readme_lists_the_definitions():
    """Every metric name morphopt.contract derives has one definition, and the README's metric table
    is morphopt.contract.metric_table() verbatim."""
    from morphopt import contract

    names = [*contract.point_metrics(["torso", "torso_up", "foot"], "dynamic"),
             *contract.point_metrics(["foot"], "kinematic"), "path_error"]
    assert all(contract.definition(name, ["torso", "torso_up", "foot"]) for name in names)
    readme = (ROOT / "README.md").read_text()
    begin, end = "<!-- metrics: begin -->\n", "\n<!-- metrics: end -->"
    assert readme[readme.index(begin) + len(begin):readme.index(end)] == contract.metric_table()
