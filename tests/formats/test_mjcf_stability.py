"""Exported MJCF is stable in MuJoCo: 5 s from MuJoCo's default state (qpos0, at rest: the crank
drive starts saturated) and from the exported keyframe (at crank speed), finite and with the
loops closed, for every built-in family's default design and the best design of every shipped
study (studies/*.toml, run for two generations of 16 designs)."""

import pathlib
import shutil

import numpy as np
import pytest

from morphopt.cli import main
from morphopt.families import load_family
from morphopt.formats import export_design
from morphopt.study_spec import load_study_spec

mujoco = pytest.importorskip("mujoco", reason="MuJoCo loads the exported MJCF (pip install '.[test]')")

SECONDS = 5.0
LOOP_TOLERANCE = 1e-3  # [m] largest distance between a closure's two sites (measured: below 1.3e-4 m)
STUDIES = sorted((pathlib.Path(__file__).resolve().parents[2] / "studies").glob("*.toml"))
FAMILIES = ["four_bar", "jansen_leg", "klann_leg", "watt_sixbar", "walker"]
SLOW = {"walker", "jansen_stride"}  # 3-6 s of MuJoCo each, or a dynamic study with its kernels to compile


def _slow(names):
    return [pytest.param(n, marks=pytest.mark.slow) if getattr(n, "stem", n) in SLOW else n for n in names]


def simulate(path, keyframe: bool) -> float:
    """Step the MJCF file SECONDS from MuJoCo's default state or its keyframe; the largest loop
    opening [m] (connect constraints' site distance). Fails on NaN or MuJoCo's instability warning."""
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    if keyframe:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    connects = [k for k in range(model.neq) if model.eq_type[k] == mujoco.mjtEq.mjEQ_CONNECT]
    assert connects, "no loop closure to check"
    sites = model.eq_obj1id[connects], model.eq_obj2id[connects]
    worst = 0.0
    for step in range(round(SECONDS / model.opt.timestep)):
        mujoco.mj_step(model, data)
        if step % 10 == 0:
            assert data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number == 0, \
                f"MuJoCo reset an unstable simulation at {data.time:.4f} s"
            worst = max(worst, float(np.linalg.norm(data.site_xpos[sites[0]] - data.site_xpos[sites[1]], axis=1).max()))
    assert np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()
    return worst


def check(path) -> None:
    for keyframe in (False, True):
        worst = simulate(path, keyframe)
        assert worst < LOOP_TOLERANCE, f"{path.name} from the {'keyframe' if keyframe else 'default state'}: " \
                                       f"a loop opened by {worst:.3g} m"


@pytest.mark.parametrize("name", _slow(FAMILIES))
def test_default_design_of_every_family_is_stable(tmp_path, name):
    family = load_family(name)
    check(export_design(family, family.space.default(), "mjcf", tmp_path, name=name))


@pytest.mark.parametrize("study", _slow(STUDIES), ids=lambda p: p.stem)
def test_best_design_of_every_shipped_study_is_stable(tmp_path, study):
    copy = tmp_path / study.name
    shutil.copy(study, copy)
    spec = load_study_spec(copy)
    assert main(["study", "run", str(copy), "--generations", "2", "--worlds", "16", "--device", "cpu"]) == 0
    assert main(["export", str(copy), "--format", "mjcf", "--out", str(tmp_path / "out")]) == 0
    (path,) = (tmp_path / "out").glob("*/*.xml")
    assert path.parent.name.startswith(f"{spec.name}_rank1_")
    check(path)
