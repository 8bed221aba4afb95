"""The design-sweep notebooks (studies/sweeps/*.py, jupytext percent format) run top to bottom on
the CPU at small sizes, the way the README runs them: through a Jupyter kernel started in
studies/sweeps, importing morphopt as installed (nothing puts the source tree on the kernel's
path; in CI the package is a non-editable install), and the figures each one writes exist and
are not empty."""

import pathlib

import jupytext
import nbclient
import pytest

SWEEPS = pathlib.Path(__file__).resolve().parent.parent / "studies" / "sweeps"

# notebook -> the figure files it must write (into $MORPHOPT_SWEEP_OUT)
FIGURES = {
    "four_bar_coupler_sweep": ["four_bar_path_error_map.png", "four_bar_best_worst_curves.png"],
    "jansen_sensitivity": ["jansen_one_at_a_time.png", "jansen_2d_maps.png"],
    "walker_topology_sweep": ["walker_pareto.png", "walker_best.gif"],
    "robust_vs_nominal": ["robust_four_bar.png", "robust_walker.png", "robust_designs.png"],
}


def test_every_notebook_declares_its_figures():
    notebooks = sorted(path.stem for path in SWEEPS.glob("*.py"))
    assert len(notebooks) >= 3, notebooks
    assert sorted(FIGURES) == notebooks


@pytest.mark.parametrize("name", sorted(FIGURES))
def test_notebook_runs_and_writes_its_figures(name, tmp_path, monkeypatch):
    notebook = jupytext.read(SWEEPS / f"{name}.py")
    monkeypatch.setenv("MORPHOPT_SWEEP_SIZE", "small")
    monkeypatch.setenv("MORPHOPT_SWEEP_OUT", str(tmp_path))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.delenv("PYTHONPATH", raising=False)  # the kernel imports the installed morphopt
    client = nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(SWEEPS)}})
    client.execute()  # raises CellExecutionError naming the cell that failed
    for figure in FIGURES[name]:
        path = tmp_path / figure
        assert path.is_file(), f"{name} did not write {figure}"
        assert path.stat().st_size > 1000, f"{name}: {figure} is empty"
