"""Design families as a user meets them: the built-in ones ship in the package and load from any
folder (a ./designs/ folder of the working directory shadows them, explicit paths still work)."""

import os
import pathlib
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
    the repository: `study run` and `study show` of a copy of the quickstart study find jansen_leg
    and store and show its designs."""
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
    ran = morphopt("study", "run", "quickstart.toml", "--generations", "2", "--worlds", "8")
    assert ran.returncode == 0, ran.stderr[-2000:]
    shown = morphopt("study", "show", "quickstart.toml")
    assert shown.returncode == 0, shown.stderr[-2000:]
    assert "jansen_leg" not in shown.stderr and shown.stdout.strip(), (shown.stdout, shown.stderr)
    from morphopt.storage import read_designs

    assert len(read_designs(f"sqlite:///{work / 'quickstart.sqlite'}", "quickstart")) == 16
