"""USD export and import: round trips, pxr's own validation, identical simulation after a round
trip, DR Legs (a closed-chain biped written by others) standing and hanging, and malformed stages."""

import dataclasses
import json
import math
import os
import pathlib

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdPhysics

from engine import (
    Body,
    GroundPlane,
    Joint,
    JointDrive,
    MechanismSpec,
    Shape,
    SolverConfig,
    TrackedPoint,
    pack_worlds,
    rollout,
)
from morphopt.families import load_family
from morphopt.formats.tree import spanning_tree
from morphopt.formats.usd import read_usd, record_motion, validate_usd, write_usd
from morphopt.linkage.to_spec import to_spec

# DR Legs is benchmark data kept outside the project: $MORPHOPT_ASSETS, else shared/assets beside the checkout.
ASSETS = pathlib.Path(os.environ.get("MORPHOPT_ASSETS", pathlib.Path(__file__).resolve().parents[3] / "shared/assets"))
DR_LEGS = ASSETS / "disneyresearch/dr_legs/usd/dr_legs_with_boxes.usda"


def linkage_spec(name):
    family = load_family(name)
    return to_spec(family.generate(family.space.default()))


def gadget() -> MechanismSpec:
    """Every joint type, limits, drives, armature, reversed declarations and every shape type."""
    q = (0.0, 0.0, math.sin(0.3), math.cos(0.3))
    bodies = [Body("base", 3.0, [0.1, 0.2, 0.3], com=(0.01, 0.0, 0.02), position=(0, 0, 1.0)),
              Body("slider", 0.5, [[0.01, 0.001, 0], [0.001, 0.02, 0], [0, 0, 0.03]], position=(0.3, 0, 1.0),
                   orientation=q, velocity=(0.1, 0, 0), angular_velocity=(0, 0, 0.4)),
              Body("arm", 0.2, [0.001, 0.002, 0.002], position=(0.3, 0.2, 1.0)),
              Body("ball", 0.1, [1e-4] * 3, position=(0.3, 0.4, 1.0)),
              Body("cardan", 0.1, [1e-4] * 3, position=(0.0, 0.0, 0.5)),
              Body("sleeve", 0.1, [1e-4] * 3, position=(0.0, 0.0, 0.2)),
              Body("bolt", 0.1, [1e-4] * 3, position=(0.0, 0.2, 1.0))]
    joints = [Joint("weld", "fixed", None, "base", parent_position=(0, 0, 1.0)),
              Joint("rail", "prismatic", "base", "slider", parent_position=(0.3, 0, 0), axis=(1, 1, 0),
                    limit_lower=-0.1, limit_upper=0.2, damping=0.5, armature=0.01,
                    drive=JointDrive(stiffness=100.0, damping=5.0, target_position=0.05, effort_limit=20.0)),
              Joint("elbow", "revolute", "arm", "slider", parent_position=(0, -0.2, 0), axis=(0, 0, 1),
                    child_orientation=(q[0], q[1], -q[2], q[3]), limit_lower=-1.0, limit_upper=0.5,
                    drive=JointDrive(damping=2.0, target_velocity=1.5, effort_limit=3.0)),
              Joint("socket", "spherical", "arm", "ball", parent_position=(0, 0.2, 0)),
              Joint("cross", "universal", "base", "cardan", parent_position=(0, 0, -0.5), axis=(1, 0, 0),
                    axis2=(0, 1, 0)),
              Joint("tube", "cylindrical", "cardan", "sleeve", parent_position=(0, 0, -0.3), axis=(0, 0, 1)),
              Joint("pin", "revolute", "base", "bolt", parent_position=(0, 0.2, 0), axis=(0, 1, 0)),
              Joint("loop", "inline", "bolt", "arm", parent_position=(0.3, 0, 0), axis=(0, 1, 0))]
    shapes = [Shape("hull", "box", "base", (0.1, 0.2, 0.05), position=(0, 0, 0.1), orientation=q, friction=0.5),
              Shape("knob", "sphere", "ball", 0.03, restitution=0.3, collision_group=2),
              Shape("rod", "capsule", "arm", (0.01, 0.1), orientation=(math.sin(0.5), 0, 0, math.cos(0.5)),
                    collision_group=2),
              Shape("can", "cylinder", "sleeve", (0.04, 0.05), position=(0.01, 0, 0))]
    points = [TrackedPoint("tip", "arm", (0.05, 0.1, 0.0))]
    return MechanismSpec(bodies, joints, points, gravity=(0, 0.5, -9.0), name="gadget", shapes=shapes,
                         ground=GroundPlane(normal=(0, 0.1, 1), offset=-0.2, friction=0.6))


@pytest.mark.parametrize("make", [lambda: linkage_spec("four_bar"), lambda: linkage_spec("jansen_leg"),
                                  lambda: linkage_spec("klann_leg"), gadget,
                                  lambda: load_family("walker").build_spec(load_family("walker").space.default())],
                         ids=["four_bar", "jansen_leg", "klann_leg", "gadget", "walker"])
def test_round_trip_preserves_the_mechanism_and_passes_pxr_validation(tmp_path, make, same_mechanism):
    spec = make()
    path = write_usd(spec, tmp_path / f"{spec.name}.usda", metadata={"params": {"scale": 1.25}, "value": 0.5})
    assert validate_usd(path) == []
    back = read_usd(path)
    same_mechanism(spec, back, 1e-6)
    for a in spec.bodies:  # initial velocities survive too (angular velocity written in deg/s)
        b = back.bodies[back.body_index[a.name]]
        assert np.allclose(a.velocity, b.velocity, atol=1e-6) and np.allclose(a.angular_velocity, b.angular_velocity,
                                                                              atol=1e-6)
    materials = {s.name: (round(s.friction, 6), round(s.restitution, 6), s.collision_group) for s in back.shapes}
    assert materials == {s.name: (round(s.friction, 6), round(s.restitution, 6), s.collision_group) for s in spec.shapes}
    assert (spec.ground is None) == (back.ground is None)
    if spec.ground is not None:
        assert np.allclose(spec.ground.normal, back.ground.normal) and math.isclose(spec.ground.offset,
                                                                                   back.ground.offset, abs_tol=1e-9)
    stage = Usd.Stage.Open(str(path))
    assert json.loads(stage.GetRootLayer().customLayerData["morphopt:metadata"])["params"]["scale"] == 1.25
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == "Z"
    loops = {j.name for j in spanning_tree(spec, any_type=True).loops}
    excluded = {p.GetAttribute("morphopt:name").Get() for p in stage.Traverse()
                if p.IsA(UsdPhysics.Joint) and UsdPhysics.Joint(p).GetExcludeFromArticulationAttr().Get()}
    assert excluded == loops


def test_a_design_exported_and_imported_simulates_identically(tmp_path):
    """The Jansen leg (driven crank, loops) and its USD round trip, side by side in one batch."""
    spec = linkage_spec("jansen_leg")
    back = read_usd(write_usd(spec, tmp_path / "leg.usda"))
    model = pack_worlds([spec, back], device="cpu", config=SolverConfig())
    trace, _ = rollout(model, model.state(), model.control(), steps=300, dt=2e-3, record_every=30)
    order = [back.points.index(next(p for p in back.points if p.name == q.name)) for q in spec.points]
    moved = np.abs(trace.points[-1, 0] - trace.points[0, 0]).max()
    assert moved > 0.01  # the leg did move
    assert np.abs(trace.points[:, 0] - trace.points[:, 1, order]).max() < 1e-5


def test_motion_plays_back_as_time_samples(tmp_path):
    spec = linkage_spec("four_bar")
    times, poses = record_motion(spec, 0.2, dt=2e-3, fps=50.0)
    assert poses.shape == (len(times), len(spec.bodies), 7) and len(times) == 11
    path = write_usd(spec, tmp_path / "moving.usda", motion=(times, poses), fps=50.0)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetEndTimeCode() == pytest.approx(10.0)
    crank = next(p for p in stage.Traverse() if p.HasAPI(UsdPhysics.RigidBodyAPI))
    xform = UsdGeom.Xformable(crank)
    first = np.array(xform.ComputeLocalToWorldTransform(0.0)).T
    last = np.array(xform.ComputeLocalToWorldTransform(10.0)).T
    assert np.allclose(first[:3, 3], poses[0, 0, :3], atol=1e-6) and np.allclose(last[:3, 3], poses[-1, 0, :3],
                                                                                 atol=1e-6)
    assert not np.allclose(first, last)  # the crank turned


@pytest.fixture(scope="module")
def dr_legs_path():
    if not DR_LEGS.is_file():
        pytest.skip(f"the DR Legs asset is not on this machine ({DR_LEGS.name}); it is benchmark data kept outside "
                    f"the project")
    return DR_LEGS


def test_dr_legs_imports_with_its_loops(dr_legs_path):
    spec = read_usd(dr_legs_path)
    assert len(spec.bodies) == 31 and len(spec.joints) == 36 and all(j.type.name == "REVOLUTE" for j in spec.joints)
    assert sum(j.drive is not None for j in spec.joints) == 12
    assert len(spanning_tree(spec).loops) == 6  # 36 joints - 30 tree joints of 31 bodies on a floating pelvis
    assert sorted(s.type.name for s in spec.shapes) == ["BOX", "BOX", "BOX"]
    drive = next(j.drive for j in spec.joints if j.drive is not None)
    assert drive.stiffness == pytest.approx(50.0, rel=1e-6)  # 0.8727 N m per degree in the file


def test_dr_legs_stands_on_its_pd_drives_for_two_seconds(dr_legs_path):
    """Floating pelvis on the ground plane (feet 1.3 mm above it), the file's PD drives holding
    zero: after 2 s the pelvis is still at standing height and every joint holds to 1e-4 m."""
    spec = read_usd(dr_legs_path, origin=(0.0, 0.0, 0.265))
    spec = dataclasses.replace(spec, ground=GroundPlane(), points=[TrackedPoint("pelvis", "pelvis"),
                                                                  TrackedPoint("nose", "pelvis", (0.1, 0.0, 0.0))])
    model = pack_worlds([spec], device="cpu", config=SolverConfig())
    trace, _ = rollout(model, model.state(), model.control(), steps=400, dt=5e-3, record_every=20)
    assert not trace.diverged.any()
    height = trace.points[:, 0, 0, 2]
    assert np.all(np.abs(height - height[0]) < 0.03), height
    nose = trace.points[:, 0, 1] - trace.points[:, 0, 0]
    assert np.abs(nose[:, 2]).max() < 0.1 * 0.2  # the pelvis tilts by less than ~11 degrees
    assert trace.violation_linear.max() < 1e-4


def test_dr_legs_hangs_passively_from_a_welded_pelvis(dr_legs_path):
    spec = read_usd(dr_legs_path, origin=(0.0, 0.0, 0.5))
    pelvis = spec.bodies[spec.body_index["pelvis"]]
    joints = [dataclasses.replace(j, drive=None) for j in spec.joints]
    joints.append(Joint("weld", "fixed", None, "pelvis", parent_position=pelvis.position,
                        parent_orientation=pelvis.orientation))
    spec = dataclasses.replace(spec, joints=joints, points=[TrackedPoint("foot", "foot_l")])
    model = pack_worlds([spec], device="cpu", config=SolverConfig())
    trace, _ = rollout(model, model.state(), model.control(), steps=200, dt=1e-2, record_every=10)
    assert not trace.diverged.any() and np.all(np.isfinite(trace.points))
    assert trace.violation_linear.max() < 1e-4
    assert np.linalg.norm(trace.points[-1, 0, 0] - trace.points[0, 0, 0]) < 0.5  # hangs, does not fly off


def _stage_with(tmp_path, edit):
    """A valid exported four-bar, edited by ``edit(stage)``, saved under a new name."""
    path = write_usd(linkage_spec("four_bar"), tmp_path / "ok.usda")
    stage = Usd.Stage.Open(str(path))
    edit(stage)
    out = tmp_path / "bad.usda"
    stage.GetRootLayer().Export(str(out))
    return out


def _joint_prim(stage):
    return next(p for p in stage.Traverse() if p.IsA(UsdPhysics.Joint))


def _body_prim(stage):
    return next(p for p in stage.Traverse() if p.HasAPI(UsdPhysics.RigidBodyAPI))


@pytest.mark.parametrize("edit, message", [
    (lambda st: UsdPhysics.Joint(_joint_prim(st)).GetBody1Rel().SetTargets([Sdf.Path("/four_bar/Bodies/nothing")]),
     r"joint /four_bar/Joints/\w+: physics:body1 points to /four_bar/Bodies/nothing, which is not a rigid body"),
    (lambda st: UsdGeom.SetStageMetersPerUnit(st, 0.0), r"metersPerUnit must be a positive number"),
    (lambda st: UsdPhysics.MassAPI(_body_prim(st)).GetMassAttr().Set(float("nan")), r"body /four_bar/Bodies/\w+: "),
    (lambda st: UsdPhysics.CollisionAPI.Apply(UsdGeom.Mesh.Define(st, "/four_bar/Bodies/crank/hull").GetPrim()),
     r"collider /four_bar/Bodies/crank/hull: unsupported collider type Mesh"),
    (lambda st: UsdPhysics.DistanceJoint.Define(st, "/four_bar/Joints/spring"),
     r"joint /four_bar/Joints/spring: unsupported joint type PhysicsDistanceJoint"),
    (lambda st: _joint_prim(st).GetAttribute("physics:localPos0").Set((float("nan"), 0.0, 0.0)),
     r"joint /four_bar/Joints/\w+: physics:localPos0: must be finite"),
])
def test_malformed_stages_are_refused_naming_the_prim(tmp_path, edit, message):
    path = _stage_with(tmp_path, edit)
    with pytest.raises(ValueError, match=message) as exc:
        read_usd(path)
    assert str(path) in str(exc.value)


def test_a_world_joint_written_with_body0_only_reads_as_the_same_joint(tmp_path, same_mechanism):
    """UsdPhysics lets either side be the world: the driven crank joint written with its body in
    body0 (and the world in body1, so the drive's target is negated to turn the same way) imports
    as the same joint."""
    spec = linkage_spec("four_bar")
    driven = next(j for j in spec.joints if j.drive is not None and j.parent is None)

    def flip(stage):
        prim = next(p for p in stage.Traverse() if p.IsA(UsdPhysics.Joint)
                    and p.GetAttribute("morphopt:name").Get() == driven.name)
        joint = UsdPhysics.Joint(prim)
        joint.GetBody0Rel().SetTargets(joint.GetBody1Rel().GetTargets())
        joint.GetBody1Rel().ClearTargets(True)
        pos0, pos1 = joint.GetLocalPos0Attr().Get(), joint.GetLocalPos1Attr().Get()
        rot0, rot1 = joint.GetLocalRot0Attr().Get(), joint.GetLocalRot1Attr().Get()
        joint.GetLocalPos0Attr().Set(pos1)
        joint.GetLocalPos1Attr().Set(pos0)
        joint.GetLocalRot0Attr().Set(rot1)
        joint.GetLocalRot1Attr().Set(rot0)
        target = prim.GetAttribute("drive:angular:physics:targetVelocity")
        target.Set(-target.Get())

    back = read_usd(_stage_with(tmp_path, flip))
    assert driven.drive.target_velocity != 0.0
    same_mechanism(spec, back)
