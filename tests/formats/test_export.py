"""`morphopt export`: the best designs of a study, one folder per design (its meshes included), built
with the study's crank speed, its settings as metadata; --motion only where a format carries it."""

import json
import textwrap
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh
from pxr import Usd

from morphopt.build import LINKAGE_CRANK_SPEED, build_spec
from morphopt.cli import main
from morphopt.families import load_family
from morphopt.formats import FORMATS, export_design
from morphopt.formats.usd import read_usd
from morphopt.storage import StudyStorage
from morphopt.study_spec import load_study_spec


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study")
    path = folder / "legs.toml"
    path.write_text(textwrap.dedent("""
        [study]
        name = "legs"
        family = "jansen_leg"
        mode = "kinematic"
        seed = 2
        generations = 2
        worlds = 8
        [objective]
        metric = "foot_stride"
        direction = "maximize"
        [simulation]
        samples = 90
    """))
    assert main(["study", "run", str(path)]) == 0
    return path


def _best(path, k):
    spec = load_study_spec(path)
    frame = StudyStorage(spec.storage_url, spec.name).designs()
    feasible = frame[frame["failure"] == ""]
    return feasible.sort_values("value", ascending=False).head(k)


@pytest.mark.parametrize("fmt, suffix", [("usd", ".usda"), ("urdf", ".urdf"), ("mjcf", ".xml"), ("svg", ".svg"), ("dxf", ".dxf")])
def test_export_writes_the_best_designs_named_with_their_metadata(study, tmp_path, capsys, fmt, suffix,
                                                                  same_mechanism):
    out = tmp_path / fmt
    assert main(["export", str(study), "--best", "2", "--format", fmt, "--out", str(out)]) == 0
    best = _best(study, 2)
    files = sorted(out.glob(f"*/*{suffix}"))
    assert len(files) == 2
    printed = capsys.readouterr().out
    for rank, row in enumerate(best.itertuples(index=False), start=1):
        name = f"legs_rank{rank}_g{row.generation}_m{row.member}"
        path = out / name / f"{name}{suffix}"
        assert path.is_file() and str(path) in printed
        family = load_family("jansen_leg")
        params = {k: getattr(row, k) for k in family.space.names}
        built = build_spec(family, params, None)  # as the study simulates it: 2 pi rad/s
        if fmt == "usd":
            stage = Usd.Stage.Open(str(path))
            metadata = json.loads(stage.GetRootLayer().customLayerData["morphopt:metadata"])
            same_mechanism(built, read_usd(path))
        elif fmt == "urdf":
            from morphopt.formats.urdf import read_urdf, read_urdf_metadata

            metadata = read_urdf_metadata(path)
            same_mechanism(built, read_urdf(path))
            assert len(list((path.parent / "meshes").glob("*.stl"))) == len(built.bodies)  # the links' bars
        elif fmt == "mjcf":
            import mujoco

            from morphopt.formats.mjcf import read_metadata

            model = mujoco.MjModel.from_xml_path(str(path))
            metadata = read_metadata(model)
            assert model.neq >= 1 and model.nu == 1  # the loop closures and the crank drive
        elif fmt == "svg":
            root = ET.parse(path).getroot()
            metadata = json.loads(next(e for e in root.iter() if e.tag.endswith("metadata")).text)
        else:
            from morphopt.formats.drawing import read_dxf_metadata

            metadata = read_dxf_metadata(path)
        assert metadata["rank"] == rank and metadata["objective"]["foot_stride"] == pytest.approx(row.value)
        assert metadata["params"] == pytest.approx(params)
        assert metadata["simulation"] == {"mode": "kinematic", "dt": 0.001, "duration": 2.0,
                                          "crank_speed": LINKAGE_CRANK_SPEED, "solver": {}}


def test_whole_world_families_export_to_usd_but_not_to_drawings(tmp_path):
    walker = load_family("walker")
    path = export_design(walker, walker.space.default(), "usd", tmp_path, name="walker_default")
    assert path == tmp_path / "walker_default" / "walker_default.usda"
    assert len(read_usd(path).bodies) == len(walker.build_spec(walker.space.default()).bodies)
    with pytest.raises(ValueError, match="design 'walker_default': svg drawings need a planar linkage family"):
        export_design(walker, walker.space.default(), "svg", tmp_path, name="walker_default")


def test_export_of_an_unknown_format_or_an_empty_study_fails_cleanly(tmp_path, capsys):
    with pytest.raises(ValueError, match="unknown format 'step'"):
        export_design(load_family("four_bar"), load_family("four_bar").space.default(), "step", tmp_path, name="x")
    empty = tmp_path / "empty.toml"
    empty.write_text('[study]\nname = "empty"\nfamily = "four_bar"\n[objective]\nmetric = "coupler_point_stride"\n')
    assert main(["export", str(empty), "--format", "usd"]) == 1
    assert "has no stored designs" in capsys.readouterr().out


def test_ranks_never_share_meshes(study, tmp_path):
    """--best 3: each design's folder holds its own meshes, the bars of that design's links (a
    shared meshes/ folder let the last rank's links overwrite the others')."""
    from morphopt.formats import design_meshes

    out = tmp_path / "urdf"
    assert main(["export", str(study), "--best", "3", "--format", "urdf", "--out", str(out)]) == 0
    family = load_family("jansen_leg")
    best = _best(study, 3)
    folders = [out / f"legs_rank{rank}_g{row.generation}_m{row.member}" for rank, row in enumerate(best.itertuples(), 1)]
    assert sorted(out.iterdir()) == sorted(folders)
    for rank, (folder, row) in enumerate(zip(folders, best.itertuples(index=False)), start=1):
        params = {k: getattr(row, k) for k in family.space.names}
        linkage = family.generate(params)
        for body, mesh in design_meshes(linkage, build_spec(family, params, None)).items():
            written = trimesh.load(folder / "meshes" / f"{body}.stl")
            assert np.allclose(written.bounds, mesh.bounds, atol=1e-6), (rank, body)


@pytest.mark.parametrize("fmt", ["urdf", "mjcf", "svg", "dxf"])
def test_motion_is_refused_for_formats_without_time_samples(tmp_path, capsys, fmt):
    """--motion with a format that cannot carry it: one line, exit 2, before any work (the study
    file is not even read, nothing is written)."""
    out = tmp_path / "out"
    assert main(["export", str(tmp_path / "absent.toml"), "--format", fmt, "--motion", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--motion: format '{fmt}' cannot carry a motion" in err
    assert not out.exists()
    with pytest.raises(ValueError, match=f"format '{fmt}' cannot carry a motion"):
        export_design(load_family("four_bar"), {}, fmt, out, name="x", motion_seconds=1.0)


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    """A dynamic study with its own crank speed, time step and [solver] table."""
    path = tmp_path_factory.mktemp("tuned") / "tuned.toml"
    path.write_text(textwrap.dedent("""
        [study]
        name = "tuned"
        family = "jansen_leg"
        mode = "dynamic"
        seed = 2
        generations = 1
        worlds = 4
        [objective]
        metric = "foot_stride"
        direction = "maximize"
        [simulation]
        duration = 1.0
        dt = 0.002
        crank_speed = 9.0
        [solver]
        max_iterations = 9
    """))
    assert main(["study", "run", str(path)]) == 0
    return path


def test_export_motion_uses_the_studys_time_step_and_solver(tuned, tmp_path, monkeypatch):
    """`export --motion` simulates with the study's dt and its [solver] table, and writes the
    motion into the USD file (time samples at the export's frame rate)."""
    import morphopt.formats.usd as usd

    seen = []
    real = usd.record_motion

    def spy(spec, duration, **kwargs):
        seen.append(kwargs)
        return real(spec, duration, **kwargs)

    monkeypatch.setattr(usd, "record_motion", spy)
    out = tmp_path / "out"
    assert main(["export", str(tuned), "--format", "usd", "--motion", "0.1", "--out", str(out)]) == 0
    assert len(seen) == 1 and seen[0]["dt"] == 0.002 and seen[0]["config"].max_iterations == 9
    (exported,) = out.glob("*/*.usda")
    stage = Usd.Stage.Open(str(exported))
    assert stage.GetEndTimeCode() > stage.GetStartTimeCode()  # the motion is there


def test_every_format_drives_the_crank_at_the_studys_speed(tuned, tmp_path):
    """The study optimized at crank_speed 9 rad/s (Jansen's own default is 2): USD, URDF and MJCF
    drive the crank at 9 rad/s, and every file's metadata holds the study's settings."""
    import mujoco

    from morphopt.formats.mjcf import MJCF_TIMESTEP, read_metadata
    from morphopt.formats.urdf import read_urdf, read_urdf_metadata

    settings = {"mode": "dynamic", "dt": 0.002, "duration": 1.0, "crank_speed": 9.0,
                "solver": {"max_iterations": 9}}
    for fmt in ("usd", "urdf", "mjcf"):
        assert main(["export", str(tuned), "--format", fmt, "--out", str(tmp_path / fmt)]) == 0
        (path,) = (tmp_path / fmt).glob(f"*/*{FORMATS[fmt]}")
        if fmt == "mjcf":
            model = mujoco.MjModel.from_xml_path(str(path))
            assert read_metadata(model)["simulation"] == settings
            kd = -model.actuator_biasprm[0, 2]
            assert model.actuator_biasprm[0, 0] == pytest.approx(kd * 9.0) and model.opt.timestep == MJCF_TIMESTEP
            continue
        if fmt == "usd":
            spec, stage = read_usd(path), Usd.Stage.Open(str(path))
            metadata = json.loads(stage.GetRootLayer().customLayerData["morphopt:metadata"])
        else:
            spec, metadata = read_urdf(path), read_urdf_metadata(path)
        assert metadata["simulation"] == settings
        (drive,) = [j.drive for j in spec.joints if j.drive is not None]
        assert abs(drive.target_velocity) == pytest.approx(9.0)
