"""MJCF (MuJoCo) export of a MechanismSpec: a body tree plus one equality constraint per loop.

Conventions of the written file (MuJoCo reads it with MjModel.from_xml_path):
- Bodies nest along morphopt.formats.tree.spanning_tree. Every MJCF body frame IS the engine's
  body frame at the initial state (pos and quat relative to the tree parent's body frame; MuJoCo
  quaternions are (w, x, y, z), ours (x, y, z, w)); ``<inertial>`` carries the mass [kg], the centre
  of mass [m] and the full inertia tensor [kg m^2] in that frame. ``<compiler angle="radian">``.
- Tree joints (hinge, slide) sit at the child anchor, axis in the child body frame, with
  ``ref`` = the engine's initial joint coordinate (morphopt.formats.tree.initial_coordinate), so
  MuJoCo's qpos of a joint IS the engine's coordinate and ranges and drive targets are copied as
  they are. A reversed tree joint (the tree runs from the spec's child to its parent) sits at the
  parent anchor with the axis negated, which keeps that sign. Fixed tree joints weld the child to
  its parent (no joint element). Floating roots get a ``<freejoint/>``.
- Loop closures (spanning tree's loops): equality constraints named after the joint, between
  sites on the two bodies ("<joint>/parent", "<joint>/child", ...):
  spherical and inline: one ``connect`` (inline: the parent site is the child anchor's initial
  projection on the parent's axis line; exact for planar linkages, whose tree already holds
  every body in the plane, while a spatial inline closure would be over-constrained); revolute:
  two ``connect`` (at the anchor and CLOSURE_AXIS_LENGTH along the axis; so a revolute closure
  counts as two equality rows); fixed: one ``weld``. Prismatic, cylindrical and universal
  closures have no MuJoCo equality: ValueError naming the joint.
- Equality softness: solref = (time constant, damping ratio) = ``equality_solref``, by default
  (2 timestep, 1): the stiffest MuJoCo accepts without disabling its refsafe flag; solimp =
  EQUALITY_SOLIMP (0.9999: impedance at MuJoCo's maximum, nearly hard, as the engine's rows are).
  Joint limits use the same values (solreflimit, solimplimit); a one-sided limit gets +/- 1e10.
- Drives (JointDrive) become a ``general`` actuator on the joint with gain 1 and bias
  (kp target_position + kd target_velocity, -kp, -kd), so that
  force = ctrl + kp (target_position - q) + kd (target_velocity - qdot) [N m] or [N], clamped
  to +/- effort_limit (forcerange). The targets live in the bias: no ctrl is needed (ctrl is a
  feed-forward effort, like engine Control.joint_effort; 0 in the keyframe). Joint armature and
  viscous damping map to the joint's ``armature`` and ``damping``. The engine wraps a revolute
  drive's position error to (-pi, pi]; MuJoCo does not (the same law while |error| < pi).
- Integrator and step: ``<option integrator timestep>``, by default MJCF_INTEGRATOR ("discrete",
  MuJoCo >= 3.13: the constraints are solved in the metric M + dt D of the implicit damping) at
  MJCF_TIMESTEP (0.1 ms): the stiff crank drives saturate when a crank starts from rest (MuJoCo's
  default state), which MuJoCo clamps explicitly; the measured choice of integrator and step:
  benchmarks/results/README.md, "MJCF export: integrator and step in MuJoCo".
- Initial state: ``<keyframe><key name="initial" qpos qvel ctrl/>``: qpos = the refs (and the
  roots' poses); qvel from the bodies' initial velocities: hinge: relative angular velocity
  about the axis [rad/s]; slide: relative velocity of the anchor along the axis [m/s]; free
  joint: linear velocity of the body frame origin (world frame) then angular velocity in the
  body frame (MuJoCo's convention). Load it with mujoco.mj_resetDataKeyframe(model, data, 0).
- Shapes become geoms of the same type and size (sphere, capsule: radius and half length along
  z, box: half extents, cylinder); the ground plane a plane geom. Geoms never collide on their
  own (contype = conaffinity = 0); the engine's collision pairs (engine.pack.collision_pairs)
  are listed as ``<contact><pair>`` with the engine's friction (geometric mean of the two
  shapes'). MuJoCo has no restitution coefficient: restitution is not written.
- Visual meshes (``meshes``: body -> trimesh.Trimesh in the body frame) are written as binary
  STL files beside the MJCF and attached as mesh geoms in group 1 (contype = conaffinity = 0,
  no mass). Tracked points become sites named after the point.
- Gravity in ``<option gravity>``; design metadata as JSON in
  ``<custom><text name="morphopt_metadata" data=.../></custom>`` (read_metadata reads it back).
"""

from __future__ import annotations

import json
import math
import pathlib
import xml.etree.ElementTree as ET

import numpy as np

from engine import JointType, MechanismSpec, ShapeType
from engine.pack import collision_pairs
from morphopt.formats.tree import (
    SpanningTree,
    TreeJoint,
    anchor_frames,
    body_frame,
    body_twist,
    frame,
    initial_coordinate,
    matrix_to_quat,
    metadata_json,
    quat_to_matrix,
    spanning_tree,
)

__all__ = ["CLOSURE_AXIS_LENGTH", "EQUALITY_SOLIMP", "METADATA_NAME", "MJCF_INTEGRATOR", "MJCF_TIMESTEP",
           "initial_keyframe", "mjcf_string", "read_metadata", "write_mjcf"]

METADATA_NAME = "morphopt_metadata"
EQUALITY_SOLIMP = (0.9999, 0.9999, 0.001, 0.5, 2.0)  # dmin, dmax, width [m], midpoint, power
CLOSURE_AXIS_LENGTH = 0.1  # [m] distance of a revolute closure's second connect along the axis
FAR_LIMIT = 1e10  # stands for an infinite side of a one-sided joint limit [rad] or [m]
INTEGRATORS = ("Euler", "RK4", "implicit", "implicitfast", "discrete")
MJCF_INTEGRATOR = "discrete"  # stable for every built-in family (module doc); needs MuJoCo >= 3.13
MJCF_TIMESTEP = 1e-4  # [s] the largest measured step that keeps their loops within 0.1 mm
GEOM_TYPES = {ShapeType.SPHERE: "sphere", ShapeType.CAPSULE: "capsule", ShapeType.BOX: "box",
              ShapeType.CYLINDER: "cylinder"}
GEOM_SIZE_COUNT = {ShapeType.SPHERE: 1, ShapeType.CAPSULE: 2, ShapeType.BOX: 3, ShapeType.CYLINDER: 2}
FRICTION_TAIL = (0.005, 0.0001)  # MuJoCo's torsional and rolling friction (the engine has none of note)


def _num(values) -> str:
    """Space-separated shortest round-trip decimal strings of the numbers (-0.0 written as 0.0)."""
    return " ".join(repr(float(v) + 0.0) for v in np.atleast_1d(np.asarray(values, dtype=float)))


def _wxyz(quat_xyzw) -> np.ndarray:
    """Quaternion (x, y, z, w) -> MuJoCo's (w, x, y, z)."""
    x, y, z, w = np.asarray(quat_xyzw, dtype=float)
    return np.array([w, x, y, z])


def _pose(element: ET.Element, T: np.ndarray) -> None:
    """Set pos and quat of an element from a 4x4 transform relative to its parent frame."""
    element.set("pos", _num(T[:3, 3]))
    element.set("quat", _num(_wxyz(matrix_to_quat(T[:3, :3]))))


def _check_loop(joint) -> None:
    """Raise ValueError naming the joint when a loop closure has no MJCF equality or carries
    what only a tree joint can hold (drive, armature, damping, limits)."""
    if joint.type in (JointType.PRISMATIC, JointType.CYLINDRICAL, JointType.UNIVERSAL):
        raise ValueError(f"joint '{joint.name}': a {joint.type.name.lower()} joint closes a loop, and MJCF has no "
                         f"equality constraint for it (only revolute, spherical, inline and fixed closures)")
    if joint.drive is not None or joint.armature > 0.0 or joint.damping > 0.0 or joint.has_limits:
        raise ValueError(f"joint '{joint.name}': closes a loop, so it becomes an MJCF equality constraint, "
                         f"which cannot carry a drive, armature, damping or limits")


def _tree_joint_frame(spec: MechanismSpec, edge: TreeJoint) -> tuple[np.ndarray, np.ndarray]:
    """Position [m] and unit axis of a tree joint in the MJCF child body's frame (see module doc)."""
    joint = edge.joint
    if edge.reversed:
        return joint.parent_position, -(quat_to_matrix(joint.parent_orientation) @ joint.axis)
    return joint.child_position, quat_to_matrix(joint.child_orientation) @ joint.axis


def _dfs(tree: SpanningTree) -> list[tuple[str, TreeJoint | None]]:
    """Bodies in MJCF order (depth first, as MuJoCo numbers them), each with its tree joint
    (None for a floating root): first the world's subtrees, then each floating root's."""
    out = []

    def visit(edge: TreeJoint | None, name: str):
        out.append((name, edge))
        for child in tree.children(name):
            visit(child, child.child)

    for edge in tree.children(None):
        visit(edge, edge.child)
    for root in tree.roots:
        visit(None, root)
    return out


def initial_keyframe(spec: MechanismSpec, tree: SpanningTree | None = None) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo (qpos, qvel) of the spec's initial state, in the written model's joint order.

    hinge qpos [rad] = initial_coordinate, qvel [rad/s] = axis . (w_child - w_parent); slide
    qpos [m], qvel [m/s] = axis . relative velocity of the anchor; free joint qpos = origin [m]
    and quaternion (w, x, y, z), qvel = origin velocity (world) [m/s], angular velocity (body
    frame) [rad/s].
    """
    tree = tree or spanning_tree(spec)
    qpos, qvel = [], []
    for name, edge in _dfs(tree):
        T = body_frame(spec, name)
        if edge is None:
            velocity, omega = body_twist(spec, name, T[:3, 3])
            qpos += [*T[:3, 3], *_wxyz(matrix_to_quat(T[:3, :3]))]
            qvel += [*velocity, *(T[:3, :3].T @ omega)]
            continue
        if edge.joint.type == JointType.FIXED:
            continue
        position, axis = _tree_joint_frame(spec, edge)
        anchor, axis_world = T[:3, :3] @ position + T[:3, 3], T[:3, :3] @ axis
        v_child, w_child = body_twist(spec, name, anchor)
        v_parent, w_parent = body_twist(spec, edge.parent, anchor)
        relative = w_child - w_parent if edge.joint.type == JointType.REVOLUTE else v_child - v_parent
        qpos.append(initial_coordinate(spec, edge.joint))
        qvel.append(float(axis_world @ relative))
    return np.asarray(qpos, dtype=float), np.asarray(qvel, dtype=float)


def _add_site(parent: ET.Element, name: str, position, orientation=None) -> None:
    site = ET.SubElement(parent, "site", name=name, pos=_num(position), size="0.002", group="3")
    if orientation is not None:
        site.set("quat", _num(_wxyz(orientation)))


def _add_joint(body: ET.Element, spec: MechanismSpec, edge: TreeJoint, actuators: ET.Element,
               solref: str, solimp: str) -> None:
    """The MJCF joint (and actuator) of a revolute or prismatic tree joint."""
    joint = edge.joint
    position, axis = _tree_joint_frame(spec, edge)
    element = ET.SubElement(body, "joint", name=joint.name, type="hinge" if joint.type == JointType.REVOLUTE
                            else "slide", pos=_num(position), axis=_num(axis),
                            ref=_num(initial_coordinate(spec, joint)))
    if joint.armature > 0.0:
        element.set("armature", _num(joint.armature))
    if joint.damping > 0.0:
        element.set("damping", _num(joint.damping))
    if joint.has_limits:
        lower = joint.limit_lower if math.isfinite(joint.limit_lower) else -FAR_LIMIT
        upper = joint.limit_upper if math.isfinite(joint.limit_upper) else FAR_LIMIT
        element.attrib.update(limited="true", range=_num((lower, upper)), solreflimit=solref, solimplimit=solimp)
    drive = joint.drive
    if drive is not None:
        bias = (drive.stiffness * drive.target_position + drive.damping * drive.target_velocity,
                -drive.stiffness, -drive.damping)
        actuator = ET.SubElement(actuators, "general", name=joint.name, joint=joint.name, gainprm="1",
                                 biasprm=_num(bias), biastype="affine", ctrllimited="false")
        if math.isfinite(drive.effort_limit):
            actuator.attrib.update(forcelimited="true", forcerange=_num((-drive.effort_limit, drive.effort_limit)))


def _add_loop(spec: MechanismSpec, joint, bodies: dict, equality: ET.Element, solref: str, solimp: str) -> None:
    """Sites on both bodies and the equality constraint(s) closing one loop (see module doc)."""
    parent, child = bodies[joint.parent], bodies[joint.child]
    p_pos, c_pos = joint.parent_position, joint.child_position
    attrs = {"solref": solref, "solimp": solimp}
    if joint.type == JointType.FIXED:
        _add_site(parent, f"{joint.name}/parent", p_pos, joint.parent_orientation)
        _add_site(child, f"{joint.name}/child", c_pos, joint.child_orientation)
        ET.SubElement(equality, "weld", name=joint.name, site1=f"{joint.name}/parent", site2=f"{joint.name}/child",
                      **attrs)
        return
    axis_parent = quat_to_matrix(joint.parent_orientation) @ joint.axis  # in the parent body frame
    if joint.type == JointType.INLINE:  # the child anchor's initial projection on the parent's axis line
        frame_p, frame_c = anchor_frames(spec, joint)
        along = float((frame_p[:3, :3] @ joint.axis) @ (frame_c[:3, 3] - frame_p[:3, 3]))
        p_pos = p_pos + along * axis_parent
    _add_site(parent, f"{joint.name}/parent", p_pos)
    _add_site(child, f"{joint.name}/child", c_pos)
    ET.SubElement(equality, "connect", name=joint.name, site1=f"{joint.name}/parent", site2=f"{joint.name}/child",
                  **attrs)
    if joint.type == JointType.REVOLUTE:
        axis_child = quat_to_matrix(joint.child_orientation) @ joint.axis
        _add_site(parent, f"{joint.name}/parent_axis", p_pos + CLOSURE_AXIS_LENGTH * axis_parent)
        _add_site(child, f"{joint.name}/child_axis", c_pos + CLOSURE_AXIS_LENGTH * axis_child)
        ET.SubElement(equality, "connect", name=f"{joint.name}/axis", site1=f"{joint.name}/parent_axis",
                      site2=f"{joint.name}/child_axis", **attrs)


def _build(spec: MechanismSpec, *, metadata: dict | None, mesh_files: dict[str, str], timestep: float,
           integrator: str, equality_solref, equality_solimp) -> ET.Element:
    """The MJCF element tree of ``spec`` (mesh_files: body -> STL file name beside the MJCF)."""
    if not (timestep > 0.0 and math.isfinite(timestep)):
        raise ValueError(f"timestep must be positive and finite [s], got {timestep!r}")
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS)}, got {integrator!r}")
    if spec.ground is not None and spec.ground.relief is not None:  # never dropped silently
        raise ValueError(f"mechanism '{spec.name}': its ground has relief (engine.Relief), which MJCF "
                         f"cannot hold; export the spec without it")
    if "world" in spec.body_index:
        raise ValueError("body 'world': the name is reserved in MJCF, rename the body")
    for name in mesh_files:
        if name not in spec.body_index:
            raise ValueError(f"meshes: body '{name}' does not exist")
    tree = spanning_tree(spec)
    for joint in tree.loops:
        _check_loop(joint)
    solref = _num(equality_solref if equality_solref is not None else (2.0 * timestep, 1.0))
    solimp = _num(equality_solimp)

    root = ET.Element("mujoco", model=spec.name)
    ET.SubElement(root, "compiler", angle="radian", inertiafromgeom="false", autolimits="true")
    ET.SubElement(root, "option", timestep=_num(timestep), integrator=integrator, gravity=_num(spec.gravity))
    if metadata is not None:
        custom = ET.SubElement(root, "custom")
        ET.SubElement(custom, "text", name=METADATA_NAME, data=metadata_json(metadata))
    if mesh_files:
        asset = ET.SubElement(root, "asset")
        for name, file in mesh_files.items():
            ET.SubElement(asset, "mesh", name=f"{name}/visual", file=file, inertia="shell")
    worldbody = ET.SubElement(root, "worldbody")
    actuators, equality = ET.Element("actuator"), ET.Element("equality")
    bodies: dict = {None: worldbody}
    for name, edge in _dfs(tree):
        parent_name = None if edge is None else edge.parent
        body = ET.SubElement(bodies[parent_name], "body", name=name)
        _pose(body, np.linalg.inv(body_frame(spec, parent_name)) @ body_frame(spec, name))
        bodies[name] = body
        data = spec.bodies[spec.body_index[name]]
        inertia = data.inertia
        ET.SubElement(body, "inertial", pos=_num(data.com), mass=_num(data.mass), fullinertia=_num(
            (inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2])))
        if edge is None:
            ET.SubElement(body, "freejoint", name=f"{name}/free")
        elif edge.joint.type != JointType.FIXED:
            _add_joint(body, spec, edge, actuators, solref, solimp)
        if name in mesh_files:
            ET.SubElement(body, "geom", name=f"{name}/visual", type="mesh", mesh=f"{name}/visual", contype="0",
                          conaffinity="0", group="1", mass="0")
    for shape in spec.shapes:
        geom = ET.SubElement(bodies[shape.body], "geom", name=shape.name, type=GEOM_TYPES[shape.type],
                             size=_num(shape.size[:GEOM_SIZE_COUNT[shape.type]]), contype="0", conaffinity="0",
                             friction=_num((shape.friction, *FRICTION_TAIL)))
        _pose(geom, frame(shape.position, shape.orientation))
    contact = ET.Element("contact")
    if spec.ground is not None:
        plane = ET.SubElement(worldbody, "geom", name="ground_plane", type="plane", size="0 0 1", contype="0",
                              conaffinity="0", friction=_num((spec.ground.friction, *FRICTION_TAIL)))
        normal = spec.ground.normal
        z = np.array([0.0, 0.0, 1.0])
        axis, cosine = np.cross(z, normal), float(z @ normal)
        sine = float(np.linalg.norm(axis))
        angle = math.atan2(sine, cosine)
        axis = axis / sine if sine > 1e-12 else np.array([1.0, 0.0, 0.0])
        plane.attrib.update(pos=_num(spec.ground.offset * normal),
                            quat=_num((math.cos(angle / 2), *(math.sin(angle / 2) * axis))))
    for a, b in collision_pairs(spec):
        first = spec.shapes[a]
        other = spec.ground if b < 0 else spec.shapes[b]
        mu = math.sqrt(first.friction * other.friction)
        ET.SubElement(contact, "pair", geom1=first.name, geom2="ground_plane" if b < 0 else other.name, condim="3",
                      friction=_num((mu, mu, *FRICTION_TAIL, FRICTION_TAIL[1])))
    for point in spec.points:
        _add_site(bodies[point.body], point.name, point.position)
    for joint in tree.loops:
        _add_loop(spec, joint, bodies, equality, solref, solimp)
    for element in (contact, equality, actuators):
        if len(element):
            root.append(element)
    qpos, qvel = initial_keyframe(spec, tree)
    keyframe = ET.SubElement(root, "keyframe")
    key = ET.SubElement(keyframe, "key", name="initial")
    if len(qpos):
        key.attrib.update(qpos=_num(qpos), qvel=_num(qvel))
    if len(actuators):
        key.set("ctrl", _num(np.zeros(len(actuators))))
    return root


def mjcf_string(spec: MechanismSpec, *, metadata: dict | None = None, timestep: float = MJCF_TIMESTEP,
                integrator: str = MJCF_INTEGRATOR, equality_solref=None,
                equality_solimp=EQUALITY_SOLIMP) -> str:
    """The MJCF of ``spec`` as a string, without visual meshes (see the module doc).

    timestep [s]; integrator: "Euler", "RK4", "implicit", "implicitfast" or "discrete"; equality_solref:
    (time constant [s], damping ratio) of loop closures and joint limits, default (2 timestep, 1);
    equality_solimp: MuJoCo's five impedance numbers. Raises ValueError naming the joint (or
    body) that MJCF cannot describe.
    """
    root = _build(spec, metadata=metadata, mesh_files={}, timestep=timestep, integrator=integrator,
                  equality_solref=equality_solref, equality_solimp=equality_solimp)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def write_mjcf(spec: MechanismSpec, path, *, metadata: dict | None = None, meshes: dict | None = None,
               timestep: float = MJCF_TIMESTEP, integrator: str = MJCF_INTEGRATOR, equality_solref=None,
               equality_solimp=EQUALITY_SOLIMP) -> pathlib.Path:
    """Write the MJCF of ``spec`` to ``path`` and return the path.

    meshes: body name -> trimesh.Trimesh in that body's frame [m], written as binary STL files
    "<stem>_<body>.stl" beside the MJCF (visual geoms only). Other arguments as mjcf_string.
    """
    path = pathlib.Path(path)
    meshes = dict(meshes or {})
    for name in meshes:
        if name not in spec.body_index:
            raise ValueError(f"meshes: body '{name}' does not exist")
    mesh_files = {}
    for name in meshes:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        mesh_files[name] = f"{path.stem}_{safe}.stl"
    root = _build(spec, metadata=metadata, mesh_files=mesh_files, timestep=timestep, integrator=integrator,
                  equality_solref=equality_solref, equality_solimp=equality_solimp)
    path.parent.mkdir(parents=True, exist_ok=True)
    for name, mesh in meshes.items():
        mesh.export(path.parent / mesh_files[name], file_type="stl")
    ET.indent(root)
    path.write_text(ET.tostring(root, encoding="unicode") + "\n")
    return path


def read_metadata(model) -> dict | None:
    """The design metadata of a loaded mujoco.MjModel written by write_mjcf (None when absent)."""
    import mujoco

    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, METADATA_NAME)
    if index < 0:
        return None
    start, size = int(model.text_adr[index]), int(model.text_size[index])
    return json.loads(bytes(model.text_data[start:start + size]).split(b"\0")[0].decode())
