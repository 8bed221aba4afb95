"""`morphopt export`: the best designs of a study, one file per design and format, with metadata."""

import json
import textwrap
import xml.etree.ElementTree as ET

import pytest
from pxr import Usd

from morphopt.cli import main
from morphopt.families import load_family
from morphopt.formats import export_design
from morphopt.formats.usd import read_usd
from morphopt.linkage.to_spec import to_spec
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
    files = sorted(out.glob(f"*{suffix}"))
    assert len(files) == 2
    printed = capsys.readouterr().out
    for rank, row in enumerate(best.itertuples(index=False), start=1):
        path = out / f"legs_rank{rank}_g{row.generation}_m{row.member}{suffix}"
        assert path.is_file() and str(path) in printed
        family = load_family("jansen_leg")
        params = {k: getattr(row, k) for k in family.space.names}
        if fmt == "usd":
            stage = Usd.Stage.Open(str(path))
            metadata = json.loads(stage.GetRootLayer().customLayerData["morphopt:metadata"])
            same_mechanism(to_spec(family.generate(params)), read_usd(path))
        elif fmt == "urdf":
            from morphopt.formats.urdf import read_urdf, read_urdf_metadata

            metadata = read_urdf_metadata(path)
            same_mechanism(to_spec(family.generate(params)), read_urdf(path))
            assert (out / "meshes").is_dir()  # the links' bars as visual meshes
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


def test_whole_world_families_export_to_usd_but_not_to_drawings(tmp_path):
    walker = load_family("walker")
    path = export_design(walker, walker.space.default(), "usd", tmp_path, name="walker_default")
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


def test_export_motion_uses_the_studys_time_step_and_solver(tmp_path, monkeypatch):
    """`export --motion` simulates with the study's dt and its [solver] table, and writes the
    motion into the USD file (time samples at the export's frame rate)."""
    import morphopt.formats.usd as usd

    path = tmp_path / "tuned.toml"
    path.write_text(textwrap.dedent("""
        [study]
        name = "tuned"
        family = "jansen_leg"
        seed = 2
        generations = 1
        worlds = 8
        [objective]
        metric = "foot_stride"
        direction = "maximize"
        [simulation]
        samples = 36
        dt = 0.002
        [solver]
        max_iterations = 9
    """))
    assert main(["study", "run", str(path)]) == 0
    seen = []
    real = usd.record_motion

    def spy(spec, duration, **kwargs):
        seen.append(kwargs)
        return real(spec, duration, **kwargs)

    monkeypatch.setattr(usd, "record_motion", spy)
    out = tmp_path / "out"
    assert main(["export", str(path), "--format", "usd", "--motion", "0.1", "--out", str(out)]) == 0
    assert len(seen) == 1 and seen[0]["dt"] == 0.002 and seen[0]["config"].max_iterations == 9
    (exported,) = out.glob("*.usda")
    stage = Usd.Stage.Open(str(exported))
    assert stage.GetEndTimeCode() > stage.GetStartTimeCode()  # the motion is there
