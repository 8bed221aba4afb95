"""What the READMEs state about the shipped files is what the files do (issue 49, item 9), and what
the commands write where they run is ignored by git."""

import pathlib
import re
import shutil
import subprocess
import tomllib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_studies_readme_states_the_quickstart_budget():
    """studies/README.md's "N generations of M designs" for quickstart.toml are the file's numbers."""
    study = tomllib.loads((ROOT / "studies" / "quickstart.toml").read_text())["study"]
    text = (ROOT / "studies" / "README.md").read_text()
    generations, worlds = map(int, re.search(r"over (\d+) generations of (\d+) designs", text).groups())
    assert (generations, worlds) == (study["generations"], study["worlds"])


def test_readme_says_where_the_sweep_figures_land():
    """Every sweep notebook writes to $MORPHOPT_SWEEP_OUT, default 'figures' of the folder it runs
    in, and the README says so (not 'beside them')."""
    for notebook in (ROOT / "studies" / "sweeps").glob("*.py"):
        assert 'os.environ.get("MORPHOPT_SWEEP_OUT", "figures")' in notebook.read_text(), notebook.name
    text = " ".join((ROOT / "README.md").read_text().split())
    assert "`./figures/`, in the folder it runs from" in text and "`figures/` beside them" not in text


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
@pytest.mark.parametrize("path", ["studies/quickstart_export/quickstart_rank1.usda", "my_export/a.urdf", "optuna.db",
                                  "studies/optuna.db", "figures/jansen_2d_maps.png",
                                  "studies/sweeps/figures/walker_best.gif"])
def test_what_commands_write_is_ignored_by_git(path):
    """Export folders, the README's Optuna database and the notebooks' figures are git-ignored."""
    done = subprocess.run(["git", "check-ignore", "--no-index", "-q", path], cwd=ROOT)
    assert done.returncode == 0, f"{path} is not ignored"
