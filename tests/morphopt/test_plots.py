"""`morphopt study plot` (issue 49, item 5): every shipped study plots, the target curve is drawn on
path-synthesis plots, every axis has a unit, generations are integers."""

import pathlib
import shutil

import matplotlib.pyplot as plt
import pandas as pd
import pytest

from morphopt.cli import main
from morphopt.families import load_family
from morphopt.plots import study_figure
from morphopt.storage import read_designs
from morphopt.study_spec import load_study_spec

STUDIES = pathlib.Path(__file__).parents[2] / "studies"
SHIPPED = sorted(p.name for p in STUDIES.glob("*.toml"))
DYNAMIC = {"jansen_stride.toml", "walker.toml"}


def _axes_have_units(fig) -> None:
    convergence, design = fig.axes[0], fig.axes[1]
    assert convergence.get_xlabel() == "generation"
    ticks = [t for t in convergence.get_xticks() if convergence.get_xlim()[0] <= t <= convergence.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)
    label = convergence.get_ylabel()
    assert "[" in label or label.startswith("score"), label
    if design.axison:
        assert design.get_xlabel().endswith("[m]") and design.get_ylabel().endswith("[m]")


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in DYNAMIC else n for n in SHIPPED])
def test_every_shipped_study_plots(tmp_path, name, capsys):
    """Each studies/*.toml, run for 2 generations of 4 designs, plots to a PNG with units on its axes."""
    spec_path = tmp_path / name
    shutil.copy(STUDIES / name, spec_path)
    assert main(["study", "run", str(spec_path), "--worlds", "4", "--generations", "2"]) in (0, 1)
    png = tmp_path / "plot.png"
    assert main(["study", "plot", str(spec_path), "--out", str(png)]) == 0, capsys.readouterr().err
    assert png.stat().st_size > 10_000
    spec = load_study_spec(spec_path)
    fig = study_figure(read_designs(spec.storage_url, spec.name), spec, load_family(spec.family))
    _axes_have_units(fig)
    plt.close(fig)


def test_path_synthesis_plot_draws_the_target_curve(tmp_path):
    """four_bar_path's plot has the target curve (dashed, closed) beside the coupler point's path."""
    spec = load_study_spec(STUDIES / "four_bar_path.toml")
    family = load_family(spec.family)
    frame = pd.DataFrame([{"generation": 0, "member": 0, "value": 0.01, "failure": "", **family.space.default(),
                           **spec.fixed, "metric_path_error": 0.01}])
    fig = study_figure(frame, spec, family)
    lines = {line.get_label(): line for line in fig.axes[1].get_lines()}
    target = lines["target of coupler_point"]
    x, y = target.get_data()
    assert len(x) == len(spec.objectives[0].target) + 1 and (x[0], y[0]) == (x[-1], y[-1])
    assert target.get_linestyle() == "--" and "path of coupler_point" in lines
    assert fig.axes[0].get_ylabel() == "path_error [m] (minimize)"
    _axes_have_units(fig)
    plt.close(fig)


def test_walker_plot_draws_the_world_side_view(tmp_path):
    """The walker family builds whole worlds (no generate): its best design is drawn from build_spec
    as a side view (x, z) with its tracked points and the ground, not a crash."""
    spec = load_study_spec(STUDIES / "walker.toml")
    family = load_family(spec.family)
    frame = pd.DataFrame([{"generation": g, "member": 0, "value": 0.05 * (g + 1), "failure": "",
                           **family.space.default(), **spec.fixed, "metric_walking_speed": 0.05 * (g + 1)}
                          for g in range(3)])
    fig = study_figure(frame, spec, family)
    design = fig.axes[1]
    labels = {line.get_label() for line in design.get_lines()}
    assert {"torso", "ground"} <= labels
    assert design.get_xlabel() == "x [m]" and design.get_ylabel() == "z [m]"
    assert "side view" in design.get_title() and fig.axes[0].get_ylabel() == "walking_speed [m/s] (maximize)"
    _axes_have_units(fig)
    plt.close(fig)
