"""morphopt.notebook: animations have one frame per sample, infeasible designs are refused with
their reason, and load_study returns exactly the designs a study stored."""

import textwrap

import numpy as np
import pytest
from PIL import Image

from morphopt.families import load_family
from morphopt.notebook import animate_design, animate_paths, load_study
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec


def _frames(path) -> int:
    with Image.open(path) as image:
        return image.n_frames


def test_animate_paths_writes_one_frame_per_sample(tmp_path):
    """Two points on circles: a GIF with 24 frames, one per sample."""
    angles = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    circle = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    paths = {"a": 0.1 * circle, "b": 0.2 * circle + 0.05}
    out = animate_paths(paths, tmp_path / "sub" / "circles.gif", fps=10, title="circles", chain=["a", "b"])
    assert out == tmp_path / "sub" / "circles.gif"
    assert out.stat().st_size > 1000
    assert _frames(out) == 24


def test_animate_paths_writes_an_mp4_with_one_frame_per_sample(tmp_path):
    """18 samples at 12 frames/s: ffmpeg's own count of the H.264 file is 18 frames, 1.5 s."""
    import imageio_ffmpeg

    angles = np.linspace(0.0, 2.0 * np.pi, 18, endpoint=False)
    out = animate_paths({"a": np.stack([np.cos(angles), np.sin(angles)], axis=1)}, tmp_path / "circle.mp4", fps=12)
    assert out.read_bytes()[4:8] == b"ftyp"  # an MP4 container
    frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(out))
    assert frames == 18
    assert seconds == pytest.approx(1.5, abs=0.1)


def test_animate_paths_without_ffmpeg_names_the_way_out(tmp_path, monkeypatch):
    """No ffmpeg anywhere: a RuntimeError that says how to get one, and no file."""
    import morphopt.notebook as notebook

    monkeypatch.setattr(notebook, "_ffmpeg", lambda configured: None)
    with pytest.raises(RuntimeError, match=r"MP4 needs ffmpeg.*morphopt\[notebook\]"):
        animate_paths({"a": np.zeros((4, 2))}, tmp_path / "x.mp4")
    assert not (tmp_path / "x.mp4").exists()


def test_animate_paths_refuses_bad_input(tmp_path):
    """Mismatched lengths, unknown chain points and unknown suffixes are named."""
    with pytest.raises(ValueError, match="'b' has 5 samples"):
        animate_paths({"a": np.zeros((4, 2)), "b": np.zeros((5, 2))}, tmp_path / "x.gif")
    with pytest.raises(ValueError, match="unknown point"):
        animate_paths({"a": np.zeros((4, 2))}, tmp_path / "x.gif", chain=["a", "nope"])
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        animate_paths({"a": np.zeros((4, 2))}, tmp_path / "x.avi")


def test_animate_design_writes_a_gif_of_the_crank_turn(tmp_path):
    """A Jansen leg over 30 crank angles: 30 frames."""
    family = load_family("jansen_leg")
    out = animate_design(family, family.space.default(), tmp_path / "jansen.gif", samples=30)
    assert out.stat().st_size > 1000
    assert _frames(out) == 30


def test_animate_design_refuses_an_infeasible_design_with_its_reason(tmp_path):
    """A four-bar whose coupler and rocker cannot reach across the ground link cannot turn its crank."""
    family = load_family("four_bar")
    params = {**family.space.default(), "crank": 0.15, "ground": 0.45, "coupler": 0.15, "rocker": 0.10}
    with pytest.raises(ValueError, match="cannot complete a crank turn: dyad 'C' does not close"):
        animate_design(family, params, tmp_path / "never.gif", samples=30)
    assert not (tmp_path / "never.gif").exists()


def _tiny_study(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(textwrap.dedent("""
        [study]
        name = "tiny"
        family = "four_bar"
        mode = "kinematic"
        generations = 1
        worlds = 6
        seed = 1
        [objective]
        metric = "coupler_point_stride"
        direction = "maximize"
        [simulation]
        samples = 32
    """))
    return path


def test_load_study_returns_the_stored_designs(tmp_path):
    """One generation of six designs: six rows whose parameters and values are the stored ones."""
    path = _tiny_study(tmp_path)
    with pytest.raises(ValueError, match="tiny.toml.*no stored designs"):
        load_study(path)
    result = run_study(load_study_spec(path), progress=False)
    frame = load_study(path)
    assert len(frame) == 6
    assert frame["generation"].tolist() == [0] * 6
    assert sorted(frame["member"]) == list(range(6))
    assert {"crank", "coupler", "value", "failure", "metric_coupler_point_stride"} <= set(frame.columns)
    feasible = frame[frame["failure"] == ""]
    assert len(feasible) >= 1
    assert feasible["value"].max() == pytest.approx(result.best_value)
    best = feasible.loc[feasible["value"].idxmax()]
    assert best["crank"] == pytest.approx(result.best_params["crank"])
