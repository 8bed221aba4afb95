"""URDF export and import of MechanismSpecs, closed kinematic loops included.

write_urdf(spec, path) writes the spanning tree of the spec (morphopt.formats.tree.spanning_tree)
as standard links and joints, and everything URDF cannot say into ONE extension element,
``<morphopt version="1">``, a child of ``<robot>`` that standard parsers (yourdfpy, ROS, MuJoCo)
ignore. read_urdf(path) reads both back, and also reads plain URDFs without the extension.

The standard part (lengths [m], angles [rad], masses [kg], inertia [kg m^2]):
- Body names are link names and joint names are kept. A tree rooted at the world gets a root link
  named "world" (MuJoCo and ROS treat it as the world); a floating base (one body without a world
  joint, e.g. a walker's torso) is the root link itself. A spec with several roots raises.
- Each link's frame sits on its tree joint's child-side anchor frame at the INITIAL state, so the
  URDF zero pose (all q = 0) is the spec's initial, assembled configuration: every loop closes
  there. A floating root link's frame is its body frame.
- <inertial>: mass, origin at the centre of mass, the full inertia tensor in link-frame axes.
- <collision> per spec shape: box, sphere, cylinder; a capsule named N becomes a cylinder named N
  plus spheres "N:end0", "N:end1" (kept exact in the extension). <visual>: the mesh given for the
  body (meshes/<body>.stl beside the URDF, relative filename), else the collision primitives.
- <joint>: revolute ("continuous" without limits), prismatic or fixed; origin and axis at q = 0;
  <limit lower upper> measured from the initial state in the URDF coordinate, an open side written
  as -/+LARGE; effort = the drive's effort limit (LARGE when none or infinite), velocity = LARGE;
  <dynamics damping> = the joint's viscous damping. A tree joint running from the spec's child
  to its parent (TreeJoint.reversed) has its anchors swapped and its coordinate negated.
- <mujoco><compiler .../></mujoco> tells MuJoCo's URDF loader where meshes are and to keep static
  bodies (fusestatic="false") and drop visuals (discardvisual="true").
- MuJoCo welds a root link other than "world" to the world (add a free joint for a floating base)
  and ignores the extension: it simulates the open tree.
Reading: limits with |value| >= LARGE are open; continuous joints are revolute without limits;
mesh collisions are skipped with a warning; floating and planar joints, a second parent of a link
and malformed values raise ValueError naming the file and the element.

The extension (its elements in any order; poses as ``xyz="x y z" rpy="r p y"`` attributes in the
frame named; "inf" allowed only where said):
    <morphopt version="1">
      <mechanism name="..." gravity="gx gy gz"/>                      spec name, gravity [m/s^2]
      <ground normal="nx ny nz" offset="d" friction="f" restitution="e"/>     spec.ground, if any
      <root link="L" xyz rpy/>       world pose of a floating root link's frame (default identity)
      <body link="L" xyz rpy velocity="vx vy vz" angular_velocity="wx wy wz"/>
            the engine body frame in the link frame; initial COM velocity and angular velocity in
            the world frame [m/s], [rad/s]. Body elements in spec order give the body order.
      <tree_joint name="J" reversed="true|false" armature="a">
            one per URDF joint, in spec order (with loop_joint elements: the joint order);
            reversed: the spec's parent is the URDF child; armature [kg m^2] or [kg].
        <anchor xyz rpy/>   the tree parent's anchor frame in the URDF parent link frame, where it
                            differs from the joint origin (a coordinate not 0 at the initial state)
        <drive stiffness damping target_position target_velocity effort_limit/>
                            PD drive; target_position [rad] or [m] from the initial state and
                            target_velocity in the URDF coordinate; effort_limit may be "inf"
      </tree_joint>
      <loop_joint name="J" type="revolute|prismatic|spherical|universal|cylindrical|fixed|inline"
                  parent="L (absent: the world)" child="L" axis axis2 armature damping
                  lower upper (engine coordinate, "-inf"/"inf" allowed)>
        <parent_anchor xyz rpy/>  <child_anchor xyz rpy/>   in the link frames (world if no parent)
        <drive .../>        as above, in the engine coordinate
      </loop_joint>
      <shape name="N" link="L" friction restitution collision_group
             [type="capsule" size="radius half_length" xyz rpy (link frame)]/>   one per shape
      <point name="P" link="L" xyz/>                                  tracked point, link frame
      <metadata>{JSON}</metadata>                                     design metadata
    </morphopt>
"""

from __future__ import annotations

import json
import math
import pathlib
import re
import warnings
import xml.etree.ElementTree as ET

import numpy as np

from engine import Body, GroundPlane, Joint, JointDrive, JointType, MechanismSpec, Shape, ShapeType, TrackedPoint
from morphopt.formats.tree import (
    anchor_frames,
    body_frame,
    frame,
    initial_coordinate,
    matrix_to_quat,
    metadata_json,
    spanning_tree,
)

__all__ = ["EXTENSION_TAG", "LARGE", "read_urdf", "read_urdf_metadata", "write_urdf"]

EXTENSION_TAG = "morphopt"  # the extension element, a child of <robot>
EXTENSION_VERSION = "1"
LARGE = 1.0e9  # stands for an open limit, no effort limit and no velocity limit in URDF attributes
WORLD = "world"
_URDF_TYPES = {"revolute": JointType.REVOLUTE, "continuous": JointType.REVOLUTE,
               "prismatic": JointType.PRISMATIC, "fixed": JointType.FIXED}


def _text(values) -> str:
    """Space-separated shortest exact float text (-0.0 written as 0.0)."""
    return " ".join(repr(float(v) + 0.0) for v in np.atleast_1d(np.asarray(values, dtype=float)))


def _rpy_matrix(rpy) -> np.ndarray:
    """Rotation Rz(yaw) Ry(pitch) Rx(roll) of URDF's fixed-axis roll, pitch, yaw [rad]."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _matrix_rpy(R) -> np.ndarray:
    """Roll, pitch, yaw [rad] of a rotation matrix (yaw 0 at gimbal lock)."""
    cos_pitch = math.hypot(R[0, 0], R[1, 0])
    pitch = math.atan2(-R[2, 0], cos_pitch)
    if cos_pitch < 1e-12:
        return np.array([math.atan2(-R[1, 2], R[1, 1]), pitch, 0.0])
    return np.array([math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])])


def _pose(T) -> dict:
    """xyz/rpy attributes of a 4x4 transform."""
    return {"xyz": _text(T[:3, 3]), "rpy": _text(_matrix_rpy(T[:3, :3]))}


def _floats(text, count: int, where: str, *, allow_inf: bool = False) -> np.ndarray:
    """``count`` numbers from an attribute's text; ValueError naming ``where`` when not numbers."""
    try:
        values = np.array([float(v) for v in str(text).split()])
    except ValueError:
        raise ValueError(f"{where}: expected {count} number(s), got {text!r}") from None
    if values.size != count:
        raise ValueError(f"{where}: expected {count} number(s), got {text!r}")
    if np.any(np.isnan(values)) or (not allow_inf and not np.all(np.isfinite(values))):
        raise ValueError(f"{where}: must be {'numbers' if allow_inf else 'finite'}, got {text!r}")
    return values


def _attr(elem, name: str, where: str, default=None, *, count: int = 1, allow_inf: bool = False):
    """A numeric attribute (a float, or an array when count > 1); ``default`` when absent."""
    text = elem.get(name)
    if text is None:
        if default is None:
            raise ValueError(f"{where}: <{elem.tag}> needs the attribute '{name}'")
        return default
    values = _floats(text, count, f"{where}: <{elem.tag}> {name}", allow_inf=allow_inf)
    return float(values[0]) if count == 1 else values


def _pose_of(elem, where: str) -> np.ndarray:
    """4x4 transform of an element's xyz/rpy attributes (identity for None)."""
    T = np.eye(4)
    if elem is not None:
        T[:3, :3] = _rpy_matrix(_attr(elem, "rpy", where, np.zeros(3), count=3))
        T[:3, 3] = _attr(elem, "xyz", where, np.zeros(3), count=3)
    return T


def _relative(A, B) -> np.ndarray:
    """A^-1 B: the 4x4 transform B in the frame A."""
    return np.linalg.solve(A, B)


def _geometry(parent, shape_type: ShapeType, size) -> None:
    geometry = ET.SubElement(parent, "geometry")
    if shape_type == ShapeType.BOX:
        ET.SubElement(geometry, "box", size=_text(2.0 * np.asarray(size[:3])))
    elif shape_type == ShapeType.SPHERE:
        ET.SubElement(geometry, "sphere", radius=_text(size[0]))
    else:
        ET.SubElement(geometry, "cylinder", radius=_text(size[0]), length=_text(2.0 * size[1]))


def _primitives(shape: Shape, T) -> list[tuple[str, ShapeType, np.ndarray, np.ndarray]]:
    """(name, type, size, pose in the link frame) of a shape's URDF primitives: a capsule becomes a
    cylinder and two end spheres."""
    if shape.type != ShapeType.CAPSULE:
        return [(shape.name, shape.type, shape.size, T)]
    ends = [T @ frame((0.0, 0.0, sign * shape.size[1]), (0.0, 0.0, 0.0, 1.0)) for sign in (-1.0, 1.0)]
    return [(shape.name, ShapeType.CYLINDER, shape.size, T)] + [
        (f"{shape.name}:end{k}", ShapeType.SPHERE, shape.size, end) for k, end in enumerate(ends)]


def _drive(parent, drive: JointDrive, sign: float, offset: float) -> None:
    ET.SubElement(parent, "drive", stiffness=_text(drive.stiffness), damping=_text(drive.damping),
                  target_position=_text(sign * (drive.target_position - offset)),
                  target_velocity=_text(sign * drive.target_velocity), effort_limit=_text(drive.effort_limit))


def write_urdf(spec: MechanismSpec, path, *, metadata: dict | None = None, meshes: dict | None = None) -> pathlib.Path:
    """Write ``spec`` as a URDF file at ``path`` with the <morphopt> extension (module docstring).

    metadata: JSON-able design metadata, stored in the extension (read_urdf_metadata reads it).
    meshes: optional body name -> trimesh.Trimesh in that body's frame [m], written as
    meshes/<body>.stl beside the URDF and used as the body's visual (else its collision shapes).
    Returns the path. Raises ValueError when the spec has several roots (the world and floating
    bodies, or several floating bodies) or a body named "world".
    """
    if spec.ground is not None and spec.ground.relief is not None:  # never dropped silently
        raise ValueError(f"mechanism '{spec.name}': its ground has relief (engine.Relief), which URDF "
                         f"cannot hold; export the spec without it")
    path = pathlib.Path(path)
    meshes = dict(meshes or {})
    if WORLD in spec.body_index:
        raise ValueError(f"mechanism '{spec.name}': the body name '{WORLD}' is reserved for the URDF world link")
    unknown = sorted(set(meshes) - set(spec.body_index))
    if unknown:
        raise ValueError(f"meshes given for bodies that do not exist: {unknown}")
    tree = spanning_tree(spec)
    world_rooted = any(j.parent is None for j in spec.joints)
    if len(tree.roots) > 1 or (world_rooted and tree.roots):
        roots = ([WORLD] if world_rooted else []) + tree.roots
        raise ValueError(f"mechanism '{spec.name}': URDF has one root link, this spec has {len(roots)} roots {roots} "
                         f"(the world and floating bodies, or several floating bodies)")
    # link frames in the world at the initial state; body frames in their link frames
    link = {None: np.eye(4)}
    for name in tree.roots:
        link[name] = body_frame(spec, name)
    for name in tree.order:
        if name in tree.tree:
            parent_anchor, child_anchor = anchor_frames(spec, tree.tree[name].joint)
            link[name] = parent_anchor if tree.tree[name].reversed else child_anchor
    offset = {name: _relative(link[name], body_frame(spec, name)) for name in tree.order}

    robot, stems = ET.Element("robot", name=spec.name), set()
    compiler = {"discardvisual": "true", "fusestatic": "false", "strippath": "true"}
    if meshes:
        compiler["meshdir"] = "meshes"
    ET.SubElement(ET.SubElement(robot, "mujoco"), "compiler", compiler)
    if world_rooted:
        ET.SubElement(robot, "link", name=WORLD)
    for name in tree.order:
        body, O = spec.bodies[spec.body_index[name]], offset[name]
        element = ET.SubElement(robot, "link", name=name)
        inertial = ET.SubElement(element, "inertial")
        ET.SubElement(inertial, "origin", xyz=_text(O[:3, :3] @ body.com + O[:3, 3]), rpy="0.0 0.0 0.0")
        ET.SubElement(inertial, "mass", value=_text(body.mass))
        inertia = O[:3, :3] @ body.inertia @ O[:3, :3].T
        ET.SubElement(inertial, "inertia", {f"i{'xyz'[i]}{'xyz'[j]}": _text(inertia[i, j])
                                            for i in range(3) for j in range(i, 3)})
        primitives = [p for s in spec.shapes if s.body == name
                      for p in _primitives(s, O @ frame(s.position, s.orientation))]
        if name in meshes:
            (path.parent / "meshes").mkdir(parents=True, exist_ok=True)
            stem = re.sub(r"[^A-Za-z0-9_.-]", "_", name)
            while stem in stems:  # two names made alike by the substitution
                stem += "_"
            stems.add(stem)
            filename = f"meshes/{stem}.stl"
            meshes[name].export(str(path.parent / filename))
            visual = ET.SubElement(element, "visual", name=f"{name}_mesh")
            ET.SubElement(visual, "origin", _pose(O))
            ET.SubElement(ET.SubElement(visual, "geometry"), "mesh", filename=filename)
        for kind in ("visual", "collision"):
            if kind == "visual" and name in meshes:
                continue
            for label, shape_type, size, T in primitives:
                primitive = ET.SubElement(element, kind, name=label + ("_visual" if kind == "visual" else ""))
                ET.SubElement(primitive, "origin", _pose(T))
                _geometry(primitive, shape_type, size)

    extension = ET.Element(EXTENSION_TAG, version=EXTENSION_VERSION)
    ET.SubElement(extension, "mechanism", name=spec.name, gravity=_text(spec.gravity))
    if spec.ground is not None:
        g = spec.ground
        ET.SubElement(extension, "ground", normal=_text(g.normal), offset=_text(g.offset), friction=_text(g.friction),
                      restitution=_text(g.restitution))
    for name in tree.roots:
        ET.SubElement(extension, "root", link=name, **_pose(link[name]))
    for body in spec.bodies:
        ET.SubElement(extension, "body", link=body.name, velocity=_text(body.velocity),
                      angular_velocity=_text(body.angular_velocity), **_pose(offset[body.name]))
    tree_joints = {tj.joint.name: tj for tj in tree.tree.values()}
    for name in tree.order:  # the standard joints, in tree order
        if name not in tree.tree:
            continue
        tj = tree.tree[name]
        joint, sign = tj.joint, (-1.0 if tj.reversed else 1.0)
        parent_anchor = anchor_frames(spec, joint)[0]
        kind = joint.type.name.lower()
        if joint.type == JointType.REVOLUTE and not joint.has_limits:
            kind = "continuous"
        element = ET.SubElement(robot, "joint", name=joint.name, type=kind)
        ET.SubElement(element, "parent", link=tj.parent or WORLD)
        ET.SubElement(element, "child", link=name)
        origin = _relative(link[tj.parent], link[name])
        ET.SubElement(element, "origin", _pose(origin))
        if joint.type == JointType.FIXED:
            continue
        ET.SubElement(element, "axis", xyz=_text(link[name][:3, :3].T @ parent_anchor[:3, :3] @ joint.axis))
        q0 = initial_coordinate(spec, joint)
        lower, upper = sorted((sign * (joint.limit_lower - q0), sign * (joint.limit_upper - q0)))
        effort = joint.drive.effort_limit if joint.drive is not None else math.inf
        limit = {"effort": _text(min(effort, LARGE)), "velocity": _text(LARGE)}
        if kind != "continuous":
            limit.update(lower=_text(max(lower, -LARGE)), upper=_text(min(upper, LARGE)))
        ET.SubElement(element, "limit", limit)
        ET.SubElement(element, "dynamics", damping=_text(joint.damping), friction="0.0")
    for joint in spec.joints:  # the extension's joint entries, in spec order
        if joint.name in tree_joints:
            tj = tree_joints[joint.name]
            entry = ET.SubElement(extension, "tree_joint", name=joint.name, reversed=str(tj.reversed).lower(),
                                  armature=_text(joint.armature))
            parent_anchor, child_anchor = anchor_frames(spec, joint)
            near = _relative(link[tj.parent], child_anchor if tj.reversed else parent_anchor)
            if not np.allclose(near, _relative(link[tj.parent], link[tj.child]), rtol=0.0, atol=1e-12):
                ET.SubElement(entry, "anchor", _pose(near))
            if joint.drive is not None:
                _drive(entry, joint.drive, -1.0 if tj.reversed else 1.0, initial_coordinate(spec, joint))
            continue
        entry = ET.SubElement(extension, "loop_joint", name=joint.name, type=joint.type.name.lower(),
                              child=joint.child, axis=_text(joint.axis), axis2=_text(joint.axis2),
                              armature=_text(joint.armature), damping=_text(joint.damping),
                              lower=_text(joint.limit_lower), upper=_text(joint.limit_upper))
        if joint.parent is not None:
            entry.set("parent", joint.parent)
        parent_anchor, child_anchor = anchor_frames(spec, joint)
        ET.SubElement(entry, "parent_anchor", _pose(_relative(link[joint.parent], parent_anchor)))
        ET.SubElement(entry, "child_anchor", _pose(_relative(link[joint.child], child_anchor)))
        if joint.drive is not None:
            _drive(entry, joint.drive, 1.0, 0.0)
    for shape in spec.shapes:
        entry = ET.SubElement(extension, "shape", name=shape.name, link=shape.body, friction=_text(shape.friction),
                              restitution=_text(shape.restitution), collision_group=str(int(shape.collision_group)))
        if shape.type == ShapeType.CAPSULE:
            entry.attrib.update(type="capsule", size=_text(shape.size[:2]),
                                **_pose(offset[shape.body] @ frame(shape.position, shape.orientation)))
    for point in spec.points:
        O = offset[point.body]
        ET.SubElement(extension, "point", name=point.name, link=point.body, xyz=_text(O[:3, :3] @ point.position
                                                                                       + O[:3, 3]))
    ET.SubElement(extension, "metadata").text = metadata_json(metadata)
    robot.append(extension)
    ET.indent(robot)
    path.parent.mkdir(parents=True, exist_ok=True)
    ET.ElementTree(robot).write(path, encoding="utf-8", xml_declaration=True)
    return path


def _parse(path: pathlib.Path) -> ET.Element:
    try:
        robot = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"{path}: not well-formed XML: {exc}") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc}") from None
    if robot.tag != "robot":
        raise ValueError(f"{path}: the root element is <{robot.tag}>, not <robot>")
    return robot


def _extension(robot, path) -> ET.Element | None:
    found = robot.findall(EXTENSION_TAG)
    if len(found) > 1:
        raise ValueError(f"{path}: more than one <{EXTENSION_TAG}> element")
    if found and found[0].get("version") != EXTENSION_VERSION:
        raise ValueError(f"{path}: <{EXTENSION_TAG}> version {found[0].get('version')!r} is not {EXTENSION_VERSION}")
    return found[0] if found else None


def read_urdf_metadata(path) -> dict:
    """The design metadata stored by write_urdf ({} when the file has none)."""
    path = pathlib.Path(path)
    extension = _extension(_parse(path), path)
    element = None if extension is None else extension.find("metadata")
    if element is None or not (element.text or "").strip():
        return {}
    try:
        return json.loads(element.text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: <{EXTENSION_TAG}> metadata is not JSON: {exc}") from None


def _named(elements, path, what: str) -> dict:
    """name -> element, refusing missing and duplicate names."""
    found = {}
    for element in elements:
        name = element.get("name") or element.get("link")
        if not name:
            raise ValueError(f"{path}: a <{element.tag}> without a name")
        if name in found:
            raise ValueError(f"{path}: duplicate {what} '{name}'")
        found[name] = element
    return found


def _drive_of(element, where: str, sign: float, offset: float) -> JointDrive | None:
    if element is None:
        return None
    return JointDrive(stiffness=_attr(element, "stiffness", where, 0.0), damping=_attr(element, "damping", where, 0.0),
                      target_position=offset + sign * _attr(element, "target_position", where, 0.0),
                      target_velocity=sign * _attr(element, "target_velocity", where, 0.0),
                      effort_limit=_attr(element, "effort_limit", where, math.inf, allow_inf=True))


def _link_ref(element, role: str, links: dict, where: str, *, optional: bool = False) -> str | None:
    name = element.get(role) if element.find(role) is None else element.find(role).get("link")
    if name is None and optional:
        return None
    if name is None or name not in links:
        raise ValueError(f"{where}: {role} link {name!r} does not exist")
    return name


def _geometry_shape(element, where: str):
    """(ShapeType, size) of a <geometry>; None for meshes (warned)."""
    geometry = element.find("geometry")
    primitive = None if geometry is None or len(geometry) == 0 else geometry[0]
    if primitive is None:
        raise ValueError(f"{where}: <{element.tag}> has no geometry")
    if primitive.tag == "box":
        return ShapeType.BOX, 0.5 * _attr(primitive, "size", where, count=3)
    if primitive.tag == "sphere":
        return ShapeType.SPHERE, [_attr(primitive, "radius", where)]
    if primitive.tag == "cylinder":
        return ShapeType.CYLINDER, [_attr(primitive, "radius", where), 0.5 * _attr(primitive, "length", where)]
    if primitive.tag == "mesh":
        warnings.warn(f"{where}: mesh collision geometry is not supported by the engine; skipped", stacklevel=3)
        return None
    raise ValueError(f"{where}: unknown geometry <{primitive.tag}>")


def _checked(where: str, make, *args, **kwargs):
    """make(*args, **kwargs); the engine's ValueError re-raised with the file and element prepended."""
    try:
        return make(*args, **kwargs)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _anchor(role: str, T) -> dict:
    """Joint keyword arguments of an anchor frame (4x4 in the body frame)."""
    return {f"{role}_position": T[:3, 3], f"{role}_orientation": matrix_to_quat(T[:3, :3])}


def _tree(robot, path) -> tuple[dict, dict, list[str]]:
    """Links and joints by name, and the link order from the single root; checks the references."""
    links = _named(robot.findall("link"), path, "link")
    joints = _named(robot.findall("joint"), path, "joint")
    parent_of: dict[str, str] = {}
    for name, element in joints.items():
        where = f"{path}: joint '{name}'"
        kind = element.get("type")
        if kind in ("floating", "planar"):
            raise ValueError(f"{where}: {kind} joints are not supported (the engine has no such joint)")
        if kind not in _URDF_TYPES:
            raise ValueError(f"{where}: unknown joint type {kind!r}")
        parent, child = _link_ref(element, "parent", links, where), _link_ref(element, "child", links, where)
        if child == WORLD or parent == child:
            raise ValueError(f"{where}: invalid child link '{child}'")
        if child in parent_of:
            raise ValueError(f"{path}: link '{child}' has two parent joints, '{parent_of[child]}' and '{name}' "
                             f"(close kinematic loops in the <{EXTENSION_TAG}> extension)")
        parent_of[child] = name
    roots = [name for name in links if name not in parent_of]
    if len(roots) != 1:
        raise ValueError(f"{path}: a URDF needs exactly one root link, found {roots or 'none (a cycle)'}")
    order = [roots[0]]
    for parent in order:  # grows while iterating: breadth first
        order += [e.find("child").get("link") for e in joints.values() if e.find("parent").get("link") == parent]
    if len(order) != len(links):
        raise ValueError(f"{path}: links not connected to the root '{roots[0]}': "
                         f"{sorted(set(links) - set(order))} (a cycle of joints)")
    return links, joints, order


def _body(name: str, element, extra, link_T, where: str) -> tuple[Body, np.ndarray]:
    """The Body of a link (link_T: its world frame at q = 0) and its body frame in the link frame."""
    offset = _pose_of(extra, where)
    inertial = element.find("inertial")
    if inertial is None or inertial.find("mass") is None or inertial.find("inertia") is None:
        raise ValueError(f"{where}: no <inertial> with <mass> and <inertia> (the engine needs every body to have mass)")
    T = _relative(offset, _pose_of(inertial.find("origin"), where))
    i = {k: _attr(inertial.find("inertia"), k, where) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
    tensor = np.array([[i["ixx"], i["ixy"], i["ixz"]], [i["ixy"], i["iyy"], i["iyz"]], [i["ixz"], i["iyz"], i["izz"]]])
    B = link_T @ offset
    zero = np.zeros(3)
    velocity = zero if extra is None else _attr(extra, "velocity", where, zero, count=3)
    spin = zero if extra is None else _attr(extra, "angular_velocity", where, zero, count=3)
    body = _checked(where, Body, name, _attr(inertial.find("mass"), "value", where), T[:3, :3] @ tensor @ T[:3, :3].T,
                    com=T[:3, 3], position=B[:3, 3], orientation=matrix_to_quat(B[:3, :3]), velocity=velocity,
                    angular_velocity=spin)
    return body, offset


def read_urdf(path) -> MechanismSpec:
    """Read a URDF file (with or without the <morphopt> extension) as a MechanismSpec.

    Links become bodies (a root link named "world" is the world), joints keep their names.
    Raises ValueError naming the file and the link or joint when the file is malformed: a joint
    referring to a missing link, non-numeric or NaN values, a link with two parents, a floating,
    planar or unknown joint type, an unknown extension joint type, a link without <inertial>.
    """
    path = pathlib.Path(path)
    robot = _parse(path)
    extension = _extension(robot, path)

    def ext(tag: str) -> list:
        return [] if extension is None else extension.findall(tag)

    links, urdf_joints, order = _tree(robot, path)
    root_pose = {e.get("link"): e for e in ext("root")}
    link = {None: np.eye(4), order[0]: _pose_of(root_pose.get(order[0]), f"{path}: <{EXTENSION_TAG}> root")}
    for name in order:  # link frames at q = 0, parents first
        for element in urdf_joints.values():
            if element.find("child").get("link") == name:
                link[name] = link[element.find("parent").get("link")] @ _pose_of(
                    element.find("origin"), f"{path}: joint '{element.get('name')}': origin")

    body_ext = _named(ext("body"), path, "extension body")
    for name in body_ext:
        if name not in links or name == WORLD:
            raise ValueError(f"{path}: <{EXTENSION_TAG}> body: link '{name}' does not exist")
    names = list(body_ext) + [n for n in order if n not in body_ext and n != WORLD]
    offset, bodies = {None: np.eye(4), WORLD: np.eye(4)}, []
    for name in names:
        body, offset[name] = _body(name, links[name], body_ext.get(name), link[name], f"{path}: link '{name}'")
        bodies.append(body)
    body_spec = MechanismSpec(bodies)

    def in_body(name, T):  # a link-frame transform in the body frame
        return _relative(offset[name], T)

    joint_ext = _named(ext("tree_joint"), path, "extension tree_joint")
    joints = {}
    for name, element in urdf_joints.items():
        where = f"{path}: joint '{name}'"
        extra = joint_ext.get(name)
        kind = _URDF_TYPES[element.get("type")]
        parent, child = element.find("parent").get("link"), element.find("child").get("link")
        far = link[child]
        anchor = None if extra is None else extra.find("anchor")
        near = link[parent] @ _pose_of(element.find("origin") if anchor is None else anchor, where)
        axis = np.array([1.0, 0.0, 0.0])
        if element.find("axis") is not None:
            axis = _attr(element.find("axis"), "xyz", where, axis, count=3)
        if kind != JointType.FIXED and np.linalg.norm(axis) < 1e-12:
            raise ValueError(f"{where}: the axis is zero")
        reverse = extra is not None and extra.get("reversed", "false") == "true"
        if reverse and parent == WORLD:
            raise ValueError(f"{where}: a reversed joint cannot have the world as its spec child")
        (p_name, p_anchor), (c_name, c_anchor) = ((child, far), (parent, near)) if reverse else ((parent, near),
                                                                                               (child, far))
        anchors = {**_anchor("parent", in_body(p_name, _relative(link[p_name], p_anchor))),
                   **_anchor("child", in_body(c_name, _relative(link[c_name], c_anchor)))}
        axis = p_anchor[:3, :3].T @ far[:3, :3] @ (axis / max(np.linalg.norm(axis), 1e-300))
        p_body, sign = (None if p_name == WORLD else p_name), (-1.0 if reverse else 1.0)
        q0 = initial_coordinate(body_spec, _checked(where, Joint, name, kind, p_body, c_name, axis=axis, **anchors))
        lower, upper, damping = -math.inf, math.inf, 0.0
        limit = element.find("limit")
        if kind != JointType.FIXED and element.get("type") != "continuous" and limit is not None:
            lo, hi = _attr(limit, "lower", where, 0.0), _attr(limit, "upper", where, 0.0)
            if lo > hi:
                raise ValueError(f"{where}: limit lower {lo} is above upper {hi}")
            lo, hi = (-math.inf if lo <= -LARGE else lo), (math.inf if hi >= LARGE else hi)
            lower, upper = sorted((q0 + sign * lo, q0 + sign * hi))
        if kind != JointType.FIXED and element.find("dynamics") is not None:
            damping = _attr(element.find("dynamics"), "damping", where, 0.0)
        joints[name] = _checked(where, Joint, name, kind, p_body, c_name, axis=axis, damping=damping,
                                armature=0.0 if extra is None else _attr(extra, "armature", where, 0.0),
                                drive=None if extra is None else _drive_of(extra.find("drive"), where, sign, q0),
                                limit_lower=lower, limit_upper=upper, **anchors)
    for name in joint_ext:
        if name not in urdf_joints:
            raise ValueError(f"{path}: <{EXTENSION_TAG}> tree_joint '{name}': no URDF joint of that name")
    for element in ext("loop_joint"):
        name = element.get("name")
        where = f"{path}: <{EXTENSION_TAG}> loop_joint '{name}'"
        if not name or name in joints:
            raise ValueError(f"{where}: a missing or duplicate joint name")
        kind = element.get("type", "")
        if kind.upper() not in JointType.__members__:
            raise ValueError(f"{where}: unknown joint type {kind!r}")
        parent = _link_ref(element, "parent", links, where, optional=True)
        child = _link_ref(element, "child", links, where)
        joints[name] = _checked(
            where, Joint, name, kind, None if parent in (None, WORLD) else parent, child,
            axis=_attr(element, "axis", where, count=3), armature=_attr(element, "armature", where, 0.0),
            axis2=_attr(element, "axis2", where, np.array([0.0, 1.0, 0.0]), count=3),
            damping=_attr(element, "damping", where, 0.0), drive=_drive_of(element.find("drive"), where, 1.0, 0.0),
            limit_lower=_attr(element, "lower", where, -math.inf, allow_inf=True),
            limit_upper=_attr(element, "upper", where, math.inf, allow_inf=True),
            **_anchor("parent", in_body(parent, _pose_of(element.find("parent_anchor"), where))),
            **_anchor("child", in_body(child, _pose_of(element.find("child_anchor"), where))))
    ranked = [e.get("name") for e in (extension if extension is not None else []) if e.tag.endswith("_joint")]
    ordered = [joints[n] for n in ranked if n in joints] + [j for n, j in joints.items() if n not in ranked]

    # shapes: URDF collisions with friction etc. from the extension, capsules exact from the extension
    shape_ext = _named(ext("shape"), path, "extension shape")
    capsules = {n: e for n, e in shape_ext.items() if e.get("type") == "capsule"}
    found = []
    for name in names:
        stand_ins = {c + s for c, e in capsules.items() if e.get("link") == name for s in ("", ":end0", ":end1")}
        for k, element in enumerate(links[name].findall("collision")):
            label = element.get("name") or f"{name}_collision{k}"
            where = f"{path}: link '{name}': collision '{label}'"
            if label in stand_ins and (label in capsules or label not in shape_ext):
                continue
            geometry = _geometry_shape(element, where)
            if geometry is not None:
                found.append((label, geometry[0], name, geometry[1], in_body(name, _pose_of(element.find("origin"),
                                                                                             where))))
    for label, element in capsules.items():
        where = f"{path}: <{EXTENSION_TAG}> shape '{label}'"
        body = _link_ref(element, "link", links, where)
        found.append((label, ShapeType.CAPSULE, body, _attr(element, "size", where, count=2),
                      in_body(body, _pose_of(element, where))))
    rank = {n: k for k, n in enumerate(shape_ext)}
    shapes = []
    for label, kind, body, size, T in sorted(found, key=lambda s: rank.get(s[0], len(rank))):
        where = f"{path}: shape '{label}'"
        extra = shape_ext.get(label)
        if extra is not None and extra.get("link") != body:
            raise ValueError(f"{where}: the extension puts it on link {extra.get('link')!r}, the URDF on '{body}'")
        props = {} if extra is None else {
            "friction": _attr(extra, "friction", where, 0.8), "restitution": _attr(extra, "restitution", where, 0.0),
            "collision_group": int(_attr(extra, "collision_group", where, 0.0))}
        shapes.append(_checked(where, Shape, label, kind, body, size, position=T[:3, 3],
                               orientation=matrix_to_quat(T[:3, :3]), **props))

    points = []
    for element in ext("point"):
        where = f"{path}: <{EXTENSION_TAG}> point '{element.get('name')}'"
        body = _link_ref(element, "link", links, where)
        points.append(_checked(where, TrackedPoint, element.get("name"), body,
                               in_body(body, _pose_of(element, where))[:3, 3]))
    mechanism = None if extension is None else extension.find("mechanism")
    where = f"{path}: <{EXTENSION_TAG}> mechanism"
    gravity = np.array([0.0, 0.0, -9.81])
    if mechanism is not None:
        gravity = _attr(mechanism, "gravity", where, gravity, count=3)
    name = (robot.get("name") if mechanism is None else mechanism.get("name", robot.get("name"))) or "mechanism"
    g = None if extension is None else extension.find("ground")
    where = f"{path}: <{EXTENSION_TAG}> ground"
    ground = None if g is None else _checked(
        where, GroundPlane, normal=_attr(g, "normal", where, np.array([0.0, 0.0, 1.0]), count=3),
        offset=_attr(g, "offset", where, 0.0), friction=_attr(g, "friction", where, 0.8),
        restitution=_attr(g, "restitution", where, 0.0))
    return _checked(str(path), MechanismSpec, bodies, ordered, points, gravity=gravity, name=name, shapes=shapes,
                    ground=ground)
