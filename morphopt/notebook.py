"""Helpers for the design-sweep notebooks: animations of tracked-point paths and stored studies as tables.

``animate_paths`` turns the paths of one design (``Evaluation.metrics[i]["paths"]``: point name ->
(N, 2) array [m]) into a GIF or MP4 of the points moving over one crank turn; ``animate_design``
evaluates one design of a linkage family kinematically and animates it; ``load_study`` reads the
designs a study stored, as ``morphopt study show`` does, into a pandas DataFrame.
"""

from __future__ import annotations

import pathlib
import shutil
from collections.abc import Mapping, Sequence

import numpy as np

__all__ = ["animate_design", "animate_paths", "load_study"]


def _checked_paths(paths: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The paths as float arrays (N, 2) of one common N; ValueError naming the first bad one."""
    if not paths:
        raise ValueError("animate_paths: no paths to animate")
    out, length = {}, None
    for name, values in paths.items():
        array = np.asarray(values, dtype=float)
        if array.ndim != 2 or array.shape[1] != 2 or len(array) == 0:
            raise ValueError(f"animate_paths: path '{name}' must be an (N, 2) array, got shape {array.shape}")
        if length is not None and len(array) != length:
            raise ValueError(f"animate_paths: path '{name}' has {len(array)} samples, the others {length}")
        if not np.isfinite(array).all():
            raise ValueError(f"animate_paths: path '{name}' holds non-finite values")
        length = len(array)
        out[str(name)] = array
    return out


def _ffmpeg(configured: str) -> str | None:
    """The ffmpeg program: matplotlib's configured one when it runs here, else the one the
    imageio-ffmpeg package ships, else None."""
    found = shutil.which(configured)
    if found:
        return found
    try:
        import imageio_ffmpeg
    except ImportError:
        return None
    try:
        return imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError:  # the package without a binary for this platform
        return None


def _writer(path: pathlib.Path, fps: int):
    """The matplotlib writer for the file's suffix (.gif: Pillow, .mp4: FFmpeg)."""
    from matplotlib import animation, rcParams

    suffix = path.suffix.lower()
    if suffix == ".gif":
        return animation.PillowWriter(fps=fps)
    if suffix == ".mp4":
        program = _ffmpeg(rcParams["animation.ffmpeg_path"])
        if program is None:
            raise RuntimeError(f"cannot write {path}: MP4 needs ffmpeg, which is not installed (install ffmpeg or "
                               f"pip install 'morphopt[notebook]', or save a .gif instead)")
        rcParams["animation.ffmpeg_path"] = program
        # H.264 in a yuv420p stream (what browsers and notebook front ends play)
        return animation.FFMpegWriter(fps=fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p"])
    raise ValueError(f"cannot write {path}: expected a file name ending in .gif or .mp4")


def animate_paths(paths: Mapping[str, np.ndarray], path, *, fps: int = 20, title: str | None = None,
                  chain: Sequence[str] | None = None, closed: bool = False, units: str = "m") -> pathlib.Path:
    """Animate tracked points moving along their paths and save the animation; returns its path.

    paths: point name -> (N, 2) positions [m] over one crank turn (all of the same N), as in
    ``Evaluation.metrics[i]["paths"]``; the animation has one frame per sample (N frames).
    Every full path is drawn faintly, the current points as dots. chain: point names joined by
    a line in that order in every frame (a bar between consecutive points, e.g. the points along
    a leg); None joins nothing, since unrelated points (a torso and its feet) have no bar between
    them. closed=True draws each faint path back to its start (a crank turn's closed curve; leave
    it off for the paths of a walker, which travel). A file name ending in .gif is written with
    Pillow, one ending in .mp4 with ffmpeg as H.264 (the system's ffmpeg, else the one of the
    imageio-ffmpeg package: ``pip install 'morphopt[notebook]'``; RuntimeError when there is
    neither), ValueError for any other suffix.
    """
    import matplotlib.pyplot as plt
    from matplotlib import animation

    path = pathlib.Path(path)
    writer = _writer(path, fps)
    curves = _checked_paths(paths)
    chain = list(chain or [])
    unknown = [name for name in chain if name not in curves]
    if unknown:
        raise ValueError(f"animate_paths: chain names unknown point(s) {unknown}; the points are {list(curves)}")
    frames = len(next(iter(curves.values())))
    everything = np.concatenate(list(curves.values()))
    low, high = everything.min(axis=0), everything.max(axis=0)
    margin = 0.08 * max(float((high - low).max()), 1e-6)

    figure, axes = plt.subplots(figsize=(6.0, 4.5), dpi=80)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    dots = {}
    for k, (name, curve) in enumerate(curves.items()):
        colour = colours[k % len(colours)]
        trace = np.vstack([curve, curve[:1]]) if closed else curve
        axes.plot(trace[:, 0], trace[:, 1], color=colour, alpha=0.3, linewidth=1.0)
        dots[name], = axes.plot([], [], "o", color=colour, markersize=6, label=name)
    bars, = axes.plot([], [], "-", color="0.2", linewidth=2.0)
    axes.set_xlim(low[0] - margin, high[0] + margin)
    axes.set_ylim(low[1] - margin, high[1] + margin)
    axes.set_aspect("equal")
    axes.set_xlabel(f"x [{units}]")
    axes.set_ylabel(f"height [{units}]")
    if len(curves) <= 10:
        axes.legend(loc="upper right", fontsize="small")
    heading = axes.set_title(title or "")
    figure.tight_layout()

    def draw(frame: int):
        for name, dot in dots.items():
            dot.set_data([curves[name][frame, 0]], [curves[name][frame, 1]])
        if chain:
            joined = np.array([curves[name][frame] for name in chain])
            bars.set_data(joined[:, 0], joined[:, 1])
        heading.set_text(f"{title + ': ' if title else ''}sample {frame + 1}/{frames}")
        return [*dots.values(), bars, heading]

    movie = animation.FuncAnimation(figure, draw, frames=frames, interval=1000.0 / fps, blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        movie.save(str(path), writer=writer)
    finally:
        plt.close(figure)
    return path


def animate_design(family, params: Mapping, path, *, samples: int = 120, device: str = "cpu", fps: int = 20,
                   title: str | None = None) -> pathlib.Path:
    """Evaluate one design of a linkage family kinematically (``samples`` crank angles over one
    turn, on ``device``) and animate its tracked points with ``animate_paths``; returns the file.

    family: a family module (see ``morphopt.families.load_family``) or its name. Raises ValueError
    with the failure reason when the design cannot be generated or cannot complete a crank turn.
    """
    from morphopt.evaluate import evaluate_kinematic
    from morphopt.families import load_family

    if isinstance(family, (str, pathlib.PurePath)):
        family = load_family(family)
    evaluation = evaluate_kinematic(family, [dict(params)], samples=samples, device=device)
    if evaluation.failures[0]:
        raise ValueError(f"design cannot be animated: {evaluation.failures[0]}")
    paths = evaluation.metrics[0]["paths"]
    name = getattr(family, "__name__", "design").removeprefix("morphopt_family_")
    return animate_paths(paths, path, fps=fps, title=title or name,
                         chain=list(paths) if len(paths) > 1 else None, closed=True)


def load_study(study_file):
    """The designs a study stored, as a pandas DataFrame: one row per evaluated design with its
    generation, member, value (the objective, None when failed), failure reason ("" when
    feasible), one column per parameter and one ``metric_<name>`` column per scalar metric.

    study_file: the study's TOML spec (its [study] storage, by default <name>.sqlite beside the
    spec, holds the results). Raises ValueError naming the file when the spec is invalid or when
    nothing is stored for the study yet (run it first: ``morphopt study run <spec>``).
    """
    from morphopt.storage import read_designs
    from morphopt.study_spec import load_study_spec

    spec = load_study_spec(study_file)
    url = spec.storage_url
    frame = read_designs(url, spec.name)
    if frame.empty:
        raise ValueError(f"{study_file}: study '{spec.name}' has no stored designs in {url} "
                         f"(run it first: morphopt study run {study_file})")
    return frame
