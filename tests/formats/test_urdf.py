"""URDF export and import: closed-loop specs survive the round trip, and standard parsers
(yourdfpy, MuJoCo) read the files as the spanning tree at the assembled initial pose."""

import dataclasses
import math
import re
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
import trimesh
import yourdfpy

from engine import Body, GroundPlane, Joint, JointDrive, MechanismSpec, Shape, TrackedPoint
from morphopt.families import load_family
from morphopt.formats.tree import anchor_frames, body_frame, spanning_tree
from morphopt.formats.urdf import EXTENSION_TAG, read_urdf, read_urdf_metadata, write_urdf
from morphopt.linkage.to_spec import to_spec

METADATA = {"family": "four_bar", "params": {"crank": 0.1}, "score": 0.5}


def _quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return (*(math.sin(angle / 2) * axis), math.cos(angle / 2))


def hand_built() -> MechanismSpec:
    """A carriage sliding along world x (PD drive, limits, starting 0.3 m out), an arm hinged on it
    by a joint declared from the arm to the carriage (reversed in the tree), a tool on a driven hinge
    of the carriage, welded to the arm and sprung to it (two loops, one driven and limited), a cap
    welded to the tool (a fixed tree joint), and one shape of every type."""
    elbow_q = _quat((0, 1, 0), 0.4)
    bodies = [Body("carriage", 2.0, [[0.02, 0.001, 0], [0.001, 0.03, 0], [0, 0, 0.04]], com=(0.01, 0, 0.02),
                   position=(0.3, 0.0, 0.1), orientation=_quat((0, 0, 1), 0.2)),
              Body("arm", 0.5, [0.001, 0.01, 0.01], com=(0.1, 0, 0), position=(0.3, 0.0, 0.2), orientation=elbow_q,
                   angular_velocity=(0, 0.5, 0)),
              Body("tool", 0.1, [1e-4, 2e-4, 3e-4], position=(0.5, 0.05, 0.1), orientation=_quat((1, 1, 0), 0.7),
                   velocity=(0.1, 0, 0)),
              Body("cap", 0.05, [1e-5, 1e-5, 2e-5], position=(0.55, 0.05, 0.1))]
    to_carriage = np.linalg.inv(body_frame(MechanismSpec(bodies), "carriage")) @ np.array([0.3, 0.0, 0.2, 1.0])
    joints = [
        Joint("slide", "prismatic", None, "carriage", axis=(1, 0, 0), limit_lower=-0.2, limit_upper=0.8,
              child_position=(0, 0, -0.1), child_orientation=_quat((0, 0, 1), -0.2),
              drive=JointDrive(stiffness=100.0, damping=5.0, target_position=0.5, effort_limit=20.0)),
        Joint("elbow", "revolute", "arm", "carriage", axis=(0, 1, 0), child_position=to_carriage[:3],
              child_orientation=_quat((0, 0, 1), -0.2), limit_lower=-1.0, limit_upper=0.3, armature=0.01,
              damping=0.2, drive=JointDrive(stiffness=3.0, target_position=0.1, target_velocity=0.5)),
        Joint("weld", "fixed", "arm", "tool", parent_position=(0.2, 0.05, 0.0), parent_orientation=_quat((0, 0, 1), 1),
              child_orientation=_quat((1, 0, 0), 0.3)),
        Joint("guard", "revolute", "carriage", "tool", axis=(0, 1, 0), parent_position=to_carriage[:3],
              limit_lower=-0.5, limit_upper=math.inf, drive=JointDrive(damping=1.0, target_velocity=-0.2)),
        Joint("spring", "revolute", "arm", "tool", axis=(0, 0, 1), parent_position=(0.2, 0.05, 0.0), armature=0.001,
              limit_lower=-0.5, limit_upper=0.5, drive=JointDrive(stiffness=2.0, target_position=0.3)),
        Joint("cap_weld", "fixed", "tool", "cap", child_position=(-0.05, 0, 0), child_orientation=_quat((0, 1, 0), 1)),
    ]
    shapes = [Shape("bumper", "box", "carriage", (0.1, 0.05, 0.02), position=(0, 0, -0.05), friction=0.3,
                    restitution=0.2, collision_group=2),
              Shape("rod", "capsule", "arm", (0.01, 0.08), position=(0.1, 0, 0), orientation=_quat((0, 1, 0), 1.5)),
              Shape("drum", "cylinder", "arm", (0.02, 0.01), orientation=_quat((1, 0, 0), 1.5707963)),
              Shape("tip", "sphere", "tool", (0.015,), position=(0.02, 0, 0))]
    return MechanismSpec(bodies, joints, [TrackedPoint("tip", "tool", (0.02, 0, 0))], gravity=(0, 0.5, -9.8),
                         name="machine", shapes=shapes, ground=GroundPlane(offset=-0.1, friction=0.6))


def hand_built_open() -> MechanismSpec:
    """hand_built with one-sided limits on the two tree joints (URDF writes the open side as LARGE)."""
    spec = hand_built()
    spec.joints[0] = dataclasses.replace(spec.joints[0], limit_lower=-math.inf)
    spec.joints[1] = dataclasses.replace(spec.joints[1], limit_upper=math.inf)
    return dataclasses.replace(spec)


def family_spec(name: str) -> MechanismSpec:
    family = load_family(name)
    params = family.space.default()
    return family.build_spec(params) if hasattr(family, "build_spec") else to_spec(family.generate(params))


SPECS = {"four_bar": lambda: family_spec("four_bar"), "jansen_leg": lambda: family_spec("jansen_leg"),
         "walker": lambda: family_spec("walker"), "hand_built": hand_built,
         "hand_built_open": hand_built_open}


@pytest.fixture(scope="module", params=list(SPECS))
def exported(request, tmp_path_factory):
    spec = SPECS[request.param]()
    return spec, write_urdf(spec, tmp_path_factory.mktemp(request.param) / f"{request.param}.urdf", metadata=METADATA)


def test_round_trip_gives_the_same_mechanism(exported, same_mechanism):
    """Bodies, joints (loops, drives, limits, armature), shapes, points, gravity, ground, name and body
    order come back; the loop joints and the reversed tree joint too."""
    spec, path = exported
    back = read_urdf(path)
    same_mechanism(spec, back, tol=1e-6)
    assert back.name == spec.name and [b.name for b in back.bodies] == [b.name for b in spec.bodies]
    assert [j.name for j in back.joints] == [j.name for j in spec.joints]
    assert [(j.parent, j.child) for j in back.joints] == [(j.parent, j.child) for j in spec.joints]
    assert [s.name for s in back.shapes] == [s.name for s in spec.shapes]
    for a, b in zip(spec.shapes, back.shapes):
        assert (a.friction, a.restitution, a.collision_group) == (b.friction, b.restitution, b.collision_group)
    for a, b in zip(spec.bodies, back.bodies):  # initial velocities (world frame) and even the body frames
        assert np.allclose(a.velocity, b.velocity, atol=1e-12) and np.allclose(a.angular_velocity,
                                                                                b.angular_velocity, atol=1e-12)
        assert np.allclose(body_frame(spec, a.name), body_frame(back, b.name), atol=1e-9)
    assert (spec.ground is None) == (back.ground is None)
    if spec.ground is not None:
        assert np.allclose(spec.ground.normal, back.ground.normal) and spec.ground.offset == back.ground.offset
        assert spec.ground.friction == back.ground.friction
    assert read_urdf_metadata(path) == METADATA
    assert len(spanning_tree(spec).loops) == len(ET.parse(path).getroot().find(EXTENSION_TAG).findall("loop_joint"))


def test_yourdfpy_reads_the_spanning_tree(exported):
    """yourdfpy validates the file strictly, and its links and joints (names, parent/child, types)
    are exactly the spanning tree of the spec, with a 'world' root link for world-rooted trees."""
    spec, path = exported
    urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    assert urdf.validate(), urdf.errors
    tree = spanning_tree(spec)
    world = ["world"] if not tree.roots else []
    assert sorted(link.name for link in urdf.robot.links) == sorted(world + [b.name for b in spec.bodies])
    assert urdf.base_link == (world + tree.roots)[0]

    def urdf_type(joint):
        kind = joint.type.name.lower()
        return "continuous" if kind == "revolute" and not joint.has_limits else kind

    expected = {tj.joint.name: (tj.parent or "world", tj.child, urdf_type(tj.joint)) for tj in tree.tree.values()}
    assert {j.name: (j.parent, j.child, j.type) for j in urdf.robot.joints} == expected
    if spec.name == "machine":
        assert tree.tree["arm"].reversed and expected["elbow"] == ("carriage", "arm", "revolute")


def test_mujoco_loads_the_tree_at_the_assembled_pose(exported):
    """MuJoCo's own URDF loader accepts the file (no 'multiple parents'); its total mass equals the
    spec's, and at q = 0 every centre of mass is where the spec's initial state puts it (the
    floating root is placed at the origin by MuJoCo: compare relative to it)."""
    spec, path = exported
    model = mujoco.MjModel.from_xml_path(str(path))
    assert math.isclose(model.body_mass.sum(), sum(b.mass for b in spec.bodies), rel_tol=1e-9)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    tree = spanning_tree(spec)
    base = body_frame(spec, tree.roots[0]) if tree.roots else np.eye(4)
    for body in spec.bodies:
        T = np.linalg.inv(base) @ body_frame(spec, body.name)
        assert math.isclose(model.body(body.name).mass[0], body.mass, rel_tol=1e-12)
        assert np.allclose(data.xipos[model.body(body.name).id], T[:3, :3] @ body.com + T[:3, 3], atol=1e-9)


def test_standard_part_alone_describes_the_bodies(exported):
    """Without the extension (what any URDF reader sees) the file still gives every body's mass,
    world centre of mass and world inertia at the initial state, and every tree joint."""
    spec, path = exported
    root = ET.parse(path).getroot()
    root.remove(root.find(EXTENSION_TAG))
    plain_path = path.with_name("plain.urdf")
    ET.ElementTree(root).write(plain_path)
    if spanning_tree(spec).roots:  # a floating root is placed at the world origin without the extension
        return
    plain = read_urdf(plain_path)
    assert not plain.points and plain.ground is None and all(j.drive is None for j in plain.joints)
    assert sorted(j.name for j in plain.joints) == sorted(tj.joint.name for tj in spanning_tree(spec).tree.values())
    for body in spec.bodies:
        other = plain.bodies[plain.body_index[body.name]]
        Ta, Tb = body_frame(spec, body.name), body_frame(plain, body.name)
        assert math.isclose(body.mass, other.mass)
        assert np.allclose(Ta[:3, :3] @ body.com + Ta[:3, 3], Tb[:3, :3] @ other.com + Tb[:3, 3], atol=1e-9)
        assert np.allclose(Ta[:3, :3] @ body.inertia @ Ta[:3, :3].T, Tb[:3, :3] @ other.inertia @ Tb[:3, :3].T,
                           atol=1e-12)


def test_capsules_become_a_cylinder_and_two_spheres_and_limits_are_shifted(tmp_path):
    """The capsule's standard stand-in is a cylinder plus two end spheres; the prismatic joint that
    starts 0.3 m out has its limits and drive target measured from there; the reversed elbow's
    limits are negated; an infinite drive effort is written as a large finite number."""
    path = write_urdf(hand_built(), tmp_path / "machine.urdf")
    root = ET.parse(path).getroot()
    arm = next(link for link in root.findall("link") if link.get("name") == "arm")
    collisions = {c.get("name"): c.find("geometry")[0].tag for c in arm.findall("collision")}
    assert collisions == {"rod": "cylinder", "rod:end0": "sphere", "rod:end1": "sphere", "drum": "cylinder"}
    joints = {j.get("name"): j for j in root.findall("joint")}
    slide, elbow = joints["slide"].find("limit"), joints["elbow"].find("limit")
    assert np.allclose([float(slide.get("lower")), float(slide.get("upper"))], [-0.5, 0.5])
    assert float(slide.get("effort")) == 20.0 and math.isfinite(float(elbow.get("effort")))
    # the elbow starts at q0 = -0.4 rad (the carriage anchor is turned -0.4 about y from the arm's);
    # limits [-1.0, 0.3] are [-0.6, 0.7] from there, and [-0.7, 0.6] in the reversed URDF coordinate
    assert np.allclose([float(elbow.get("lower")), float(elbow.get("upper"))], [-0.7, 0.6])
    assert joints["cap_weld"].get("type") == "fixed" and "weld" not in joints and "spring" not in joints
    extension = root.find(EXTENSION_TAG)
    assert extension.find("loop_joint[@name='spring']/drive") is not None
    assert extension.find("loop_joint[@name='weld']").get("type") == "fixed"
    drive = extension.find("tree_joint[@name='slide']").find("drive")
    assert math.isclose(float(drive.get("target_position")), 0.2)
    assert float(joints["elbow"].find("dynamics").get("damping")) == 0.2


def test_meshes_are_written_beside_the_urdf_as_visuals(tmp_path):
    """A body's mesh goes to meshes/<body>.stl with a relative filename; yourdfpy loads it and
    MuJoCo still accepts the file."""
    spec = family_spec("four_bar")
    path = write_urdf(spec, tmp_path / "out" / "four_bar.urdf", meshes={"coupler": trimesh.creation.box((0.3, 0.01,
                                                                                                          0.005))})
    assert (tmp_path / "out" / "meshes" / "coupler.stl").is_file()
    urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=True)
    assert urdf.validate() and urdf.validate_filenames()
    assert [v.geometry.mesh.filename for v in urdf.link_map["coupler"].visuals] == ["meshes/coupler.stl"]
    assert len(urdf.scene.geometry) == 1
    mujoco.MjModel.from_xml_path(str(path))
    with pytest.raises(ValueError, match="nowhere"):
        write_urdf(spec, tmp_path / "x.urdf", meshes={"nowhere": trimesh.creation.box()})


PENDULUM = """<?xml version="1.0"?>
<robot name="pendulum">
  <link name="world"/>
  <link name="upper">
    <inertial><origin xyz="0 0 -0.25"/><mass value="2.0"/>
      <inertia ixx="0.05" ixy="0" ixz="0" iyy="0.05" iyz="0" izz="0.001"/></inertial>
    <collision><origin xyz="0 0 -0.25"/><geometry><cylinder radius="0.02" length="0.5"/></geometry></collision>
  </link>
  <link name="lower">
    <inertial><origin xyz="0 0 -0.2" rpy="0 0 1.5707963267948966"/><mass value="1.0"/>
      <inertia ixx="0.02" ixy="0" ixz="0" iyy="0.03" iyz="0" izz="0.015"/></inertial>
    <collision name="bob"><origin xyz="0 0 -0.4"/><geometry><sphere radius="0.05"/></geometry></collision>
  </link>
  <joint name="shoulder" type="revolute">
    <parent link="world"/><child link="upper"/><origin xyz="0 0 1.0"/><axis xyz="0 1 0"/>
    <limit lower="-1.5" upper="1.5" effort="10" velocity="5"/><dynamics damping="0.1"/>
  </joint>
  <joint name="elbow" type="continuous">
    <parent link="upper"/><child link="lower"/><origin xyz="0 0 -0.5" rpy="0 0 1.5707963267948966"/>
    <axis xyz="1 0 0"/>
  </joint>
</robot>
"""


def test_a_plain_urdf_pendulum_imports(tmp_path):
    """A hand-written two-link pendulum: masses, world centres of mass, inertia rotated by the
    inertial rpy, world joint axes and anchors, limits, continuous -> unlimited revolute, damping,
    and collision primitives with their sizes."""
    path = tmp_path / "pendulum.urdf"
    path.write_text(PENDULUM)
    spec = read_urdf(path)
    assert spec.name == "pendulum" and [b.name for b in spec.bodies] == ["upper", "lower"]
    upper, lower = spec.bodies
    assert (upper.mass, lower.mass) == (2.0, 1.0)
    for body, com in ((upper, (0, 0, 0.75)), (lower, (0, 0, 0.3))):
        T = body_frame(spec, body.name)
        assert np.allclose(T[:3, :3] @ body.com + T[:3, 3], com)
    T = body_frame(spec, "lower")  # the link turned 90 deg about z, its inertial 90 deg more: 180 deg
    assert np.allclose(T[:3, :3] @ lower.inertia @ T[:3, :3].T, np.diag([0.02, 0.03, 0.015]), atol=1e-12)
    assert np.allclose(lower.inertia, np.diag([0.03, 0.02, 0.015]), atol=1e-12)  # in the link (body) frame
    shoulder, elbow = spec.joints
    assert shoulder.parent is None and shoulder.child == "upper" and elbow.parent == "upper"
    assert (shoulder.limit_lower, shoulder.limit_upper, shoulder.damping) == (-1.5, 1.5, 0.1)
    assert not elbow.has_limits and elbow.type.name == "REVOLUTE" and shoulder.drive is None
    assert np.allclose(anchor_frames(spec, elbow)[0][:3, :3] @ elbow.axis, (0, 1, 0), atol=1e-12)  # x turned 90 deg
    assert np.allclose((body_frame(spec, "lower") @ np.append(elbow.child_position, 1))[:3], (0, 0, 0.5))
    shapes = {s.name: s for s in spec.shapes}
    assert set(shapes) == {"upper_collision0", "bob"}
    assert shapes["upper_collision0"].type.name == "CYLINDER" and np.allclose(shapes["upper_collision0"].size[:2],
                                                                              (0.02, 0.25))
    assert shapes["bob"].type.name == "SPHERE" and shapes["bob"].body == "lower"


MALFORMED = [  # (what, text to replace, replacement, message)
    ("missing child", '<child link="lower"/>', '<child link="nolink"/>', "joint 'elbow': child link 'nolink'"),
    ("missing parent", '<parent link="upper"/>', '<parent link="nolink"/>', "joint 'elbow': parent link 'nolink'"),
    ("NaN mass", '<mass value="2.0"/>', '<mass value="nan"/>', "link 'upper'"),
    ("non-numeric origin", '<origin xyz="0 0 1.0"/>', '<origin xyz="0 zero 1.0"/>', "joint 'shoulder'"),
    ("non-numeric limit", 'upper="1.5"', 'upper="high"', "joint 'shoulder'"),
    ("two parents", "</robot>", ('<joint name="extra" type="fixed"><parent link="world"/><child link="lower"/>'
                                 "</joint></robot>"), "link 'lower' has two parent joints, 'elbow' and 'extra'"),
    ("floating joint", 'type="continuous"', 'type="floating"', "joint 'elbow': floating"),
    ("planar joint", 'type="revolute"', 'type="planar"', "joint 'shoulder': planar"),
    ("unknown joint type", 'type="revolute"', 'type="hinge"', "joint 'shoulder': unknown joint type"),
    ("no inertial", '<mass value="1.0"/>', "", "link 'lower'"),
    ("not XML", "</robot>", "", "not well-formed"),
]


@pytest.mark.parametrize("what, old, new, message", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_urdf_raises_naming_the_file_and_element(tmp_path, what, old, new, message):
    """Each defect raises ValueError naming the file and the link or joint at fault."""
    path = tmp_path / "bad.urdf"
    assert old in PENDULUM
    path.write_text(PENDULUM.replace(old, new, 1))
    with pytest.raises(ValueError, match=re.escape(message)) as error:
        read_urdf(path)
    assert str(path) in str(error.value)


def test_unknown_extension_joint_type_and_bad_extension_numbers_raise(tmp_path):
    """An unknown loop joint type, a NaN in a loop anchor or a missing link raises naming the loop joint."""
    path = write_urdf(family_spec("four_bar"), tmp_path / "four_bar.urdf")
    text = path.read_text()
    path.write_text(text.replace('type="inline"', 'type="hinge"'))
    with pytest.raises(ValueError, match=r"loop_joint 'D_rocker': unknown joint type 'hinge'"):
        read_urdf(path)
    path.write_text(re.sub(r'<parent_anchor xyz="[^"]*"', '<parent_anchor xyz="nan 0 0"', text))
    with pytest.raises(ValueError, match=r"loop_joint 'D_rocker'.*parent_anchor"):
        read_urdf(path)
    path.write_text(text.replace('child="rocker"', 'child="nolink"'))
    with pytest.raises(ValueError, match=r"loop_joint 'D_rocker': child link 'nolink' does not exist"):
        read_urdf(path)


def test_several_roots_are_refused_on_export(tmp_path):
    """URDF has one root link: a world-jointed arm plus a free ball, or two free bodies, raise; so does
    a body named 'world' (the world link's name)."""
    arm, ball = Body("arm", 1.0, [1, 1, 1]), Body("ball", 1.0, [1, 1, 1])
    with pytest.raises(ValueError, match="roots"):
        write_urdf(MechanismSpec([arm, ball], [Joint("hinge", "revolute", None, "arm")]), tmp_path / "a.urdf")
    with pytest.raises(ValueError, match="roots"):
        write_urdf(MechanismSpec([arm, ball]), tmp_path / "b.urdf")
    with pytest.raises(ValueError, match="'world' is reserved"):
        write_urdf(MechanismSpec([Body("world", 1.0, [1, 1, 1])]), tmp_path / "c.urdf")


def test_imported_four_bar_simulates_like_the_original(tmp_path):
    """Both worlds in one batch: the coupler point of the imported four-bar follows the original's
    path over 200 steps of 1 ms to 1e-6 m."""
    from engine import pack_worlds, rollout

    spec = family_spec("four_bar")
    back = read_urdf(write_urdf(spec, tmp_path / "four_bar.urdf"))
    model = pack_worlds([spec, back], device="cpu")
    trace, _ = rollout(model, model.state(), model.control(), steps=200, dt=1e-3, record_every=20)
    points = np.asarray(trace.points)
    assert np.ptp(points[:, 0, 0, 0]) > 0.01  # it moved
    assert np.abs(points[:, 0] - points[:, 1]).max() < 1e-6
