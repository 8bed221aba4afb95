"""USD (UsdPhysics) export and import of MechanismSpecs.

Export (write_usd): one stage per design, metersPerUnit = kilogramsPerUnit = 1, upAxis Z,
``/<name>`` the default prim holding
- ``PhysicsScene`` with the spec's gravity and MuJoCo's integrator and step that keep the loops
  stable (``mjc:option:integrator``, ``mjc:option:timestep``: morphopt.formats.mjcf; Newton's
  SolverMuJoCo takes the integrator once its custom attributes are registered on the builder);
- ``Bodies/<body>``: Xform with RigidBodyAPI and MassAPI (mass, centre of mass, principal
  moments and axes of the inertia tensor), initial velocity and angular velocity [deg/s, as
  UsdPhysics measures it]; collision shapes as Sphere / Capsule / Cube / Cylinder prims with
  CollisionAPI (friction and restitution through a physics material); visual meshes (a
  ``meshes`` dict of trimesh meshes in body frames) as Mesh prims under ``Visuals``; tracked
  points as Xforms under ``Points`` marked with ``morphopt:trackedPoint``;
- ``Joints/<joint>``: Revolute, Prismatic, Spherical and Fixed joints with body0/body1, local
  frames, limits (degrees for angles, as UsdPhysics wants) and DriveAPI (stiffness and damping
  per degree for angular drives); our joint axis is turned into the joint frame's X axis. Their
  two joint frames coincide at the initial state (a prismatic joint's parent anchor moved along
  the axis onto the child anchor), so every coordinate is 0 there, where importers that build the
  bodies' poses from the joints start (Newton's add_usd); limits and drive position targets are
  written less the initial coordinate. PhysX's JointStateAPI (``state:angular:physics:position``
  0 and ``...:velocity``, deg/s; linear: m, m/s) carries the initial joint velocities to importers
  that read it (Newton with its PhysX schema resolver).
  Universal, cylindrical and inline joints are generic PhysicsJoints whose LimitAPI locks the
  degrees of freedom they remove, with ``morphopt:type`` naming the type for our importer, except
  planar loop closures: an inline joint outside the tree whose two bodies the tree already holds
  in planar motion about its axis (revolute tree joints parallel to it, prismatic ones normal to
  it, fixed ones) is a PhysicsRevoluteJoint about that axis, both joint frames coinciding at the
  initial state (the same motion; its three extra rows repeat what the tree imposes), as DR Legs
  writes its loops: importers that know no generic joint (Newton's add_usd reads it as a joint
  with no degree of freedom, whose closure its MuJoCo solver drops) close these loops.
  Armature and joint damping are ``morphopt:armature`` / ``morphopt:damping``. The joints that
  close loops (outside morphopt.formats.tree.spanning_tree) have excludeFromArticulation, and the
  tree's root carries ArticulationRootAPI;
- ``Ground``: a Plane collider when the spec has a ground plane;
- collision groups: one PhysicsCollisionGroup per non-zero group, filtering itself;
- the design's metadata as JSON in the layer's customLayerData (``morphopt:metadata``);
- optionally the simulated motion (``motion``: times and body poses) as time samples of the
  bodies' transforms, so that the design plays back in a USD viewer.

Import (read_usd): any UsdPhysics stage of rigid bodies (mass properties from MassAPI),
Cube / Sphere / Capsule / Cylinder colliders (a Plane collider on no body is the ground plane),
revolute / prismatic / spherical / fixed joints with limits and drives (and our generic-joint
types), loop joints included, in the stage's units. Anything else with a physics schema (mesh
colliders, D6 joints we cannot name, distance joints, acceleration drives, scaled bodies) is
refused with a message naming the prim, as are missing bodies, bad units and NaN values.
Revolute limits at or beyond +/-180 degrees are read as no limit (such files mean "free").
"""

from __future__ import annotations

import math
import pathlib

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdPhysics, UsdShade, UsdValidation, Vt

from engine import Body, GroundPlane, Joint, JointDrive, JointType, MechanismSpec, Shape, ShapeType, TrackedPoint
from morphopt.formats.mjcf import MJCF_INTEGRATOR, MJCF_TIMESTEP
from morphopt.formats.tree import (
    anchor_frames,
    body_frame,
    initial_coordinate,
    initial_rate,
    matrix_to_quat,
    metadata_json,
    quat_to_matrix,
    spanning_tree,
)

__all__ = ["read_usd", "record_motion", "validate_usd", "write_usd"]

DEG = 180.0 / math.pi
PARALLEL = 1e-9  # |1 - |cos|| (or |cos|) below which two axes count as parallel (or normal)
COINCIDENT = (JointType.REVOLUTE, JointType.PRISMATIC, JointType.FIXED, JointType.SPHERICAL)  # frames equal at start
# Generic-joint types: the degrees of freedom their LimitAPI locks (joint frame: axis = X).
LOCKED = {JointType.UNIVERSAL: ("transX", "transY", "transZ", "rotX"),
          JointType.CYLINDRICAL: ("transY", "transZ", "rotY", "rotZ"),
          JointType.INLINE: ("transY", "transZ")}


def _prim_name(name: str) -> str:
    """A valid prim name for any body/joint/shape name (letters, digits, underscores)."""
    out = "".join(c if c.isalnum() or c == "_" else "_" for c in name)
    return out if out and not out[0].isdigit() else "_" + out


def _align_x(axis) -> np.ndarray:
    """A rotation matrix taking X to ``axis`` (unit)."""
    x = np.asarray(axis, float)
    helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(helper, x)
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def _gf_quat(Gf, q, cls="Quatf"):
    return getattr(Gf, cls)(float(q[3]), float(q[0]), float(q[1]), float(q[2]))


def _np_quat(gq) -> np.ndarray:
    im = gq.GetImaginary()
    return np.array([im[0], im[1], im[2], gq.GetReal()], dtype=float)


def _set_pose(xformable, position, orientation, time=None):

    ops = xformable.GetOrderedXformOps()
    if not ops:
        ops = [xformable.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble),
               xformable.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)]
    when = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    ops[0].Set(Gf.Vec3d(*map(float, position)), when)
    ops[1].Set(_gf_quat(Gf, orientation, "Quatd"), when)


def write_usd(spec: MechanismSpec, path, *, metadata: dict | None = None, meshes: dict | None = None,
              motion: tuple | None = None, fps: float = 60.0, timestep: float = MJCF_TIMESTEP) -> pathlib.Path:
    """Write ``spec`` as a UsdPhysics stage (.usda text or .usd/.usdc binary, by the suffix).

    metadata: JSON-able dict (design parameters, objective values) stored in customLayerData.
    timestep: MuJoCo's step [s] written on the scene (``mjc:option:timestep``) with the integrator
    that keeps the linkages stable (``mjc:option:integrator``: morphopt.formats.mjcf).
    meshes: optional {body name: trimesh.Trimesh in the body frame [m]} visual meshes.
    motion: optional (times (T,) [s], poses (T, B, 7) body-frame position + quaternion xyzw per
    body in spec order), e.g. from record_motion(); written as time samples at ``fps``.
    Returns the path written.
    """
    if spec.ground is not None and spec.ground.relief is not None:  # never dropped silently
        raise ValueError(f"mechanism '{spec.name}': its ground has relief (engine.Relief), which USD "
                         f"cannot hold; export the spec without it")
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root_path = Sdf.Path("/" + _prim_name(spec.name))
    root = UsdGeom.Xform.Define(stage, root_path)
    stage.SetDefaultPrim(root.GetPrim())
    layer_data = {"morphopt:spec_name": spec.name}
    if metadata is not None:
        layer_data["morphopt:metadata"] = metadata_json(metadata)
    stage.GetRootLayer().customLayerData = layer_data

    scene = UsdPhysics.Scene.Define(stage, root_path.AppendChild("PhysicsScene"))
    g = np.asarray(spec.gravity, float)
    magnitude = float(np.linalg.norm(g))
    scene.CreateGravityMagnitudeAttr(magnitude)
    scene.CreateGravityDirectionAttr(Gf.Vec3f(*(g / magnitude if magnitude > 0 else (0.0, 0.0, -1.0))))
    scene_prim = scene.GetPrim()
    scene_prim.CreateAttribute("mjc:option:integrator", Sdf.ValueTypeNames.Token).Set(MJCF_INTEGRATOR)
    scene_prim.CreateAttribute("mjc:option:timestep", Sdf.ValueTypeNames.Double).Set(float(timestep))

    tree = spanning_tree(spec, any_type=True)
    bodies_path = root_path.AppendChild("Bodies")
    UsdGeom.Scope.Define(stage, bodies_path)
    body_paths, materials = {}, {}
    names = {}
    for body in spec.bodies:
        prim_name = _prim_name(body.name)
        if prim_name in names:
            raise ValueError(f"body '{body.name}': its prim name '{prim_name}' collides with body '{names[prim_name]}'")
        names[prim_name] = body.name
        xform = UsdGeom.Xform.Define(stage, bodies_path.AppendChild(prim_name))
        prim = xform.GetPrim()
        body_paths[body.name] = prim.GetPath()
        _set_pose(xform, body.position, body.orientation)
        rigid = UsdPhysics.RigidBodyAPI.Apply(prim)
        rigid.CreateVelocityAttr(Gf.Vec3f(*map(float, body.velocity)))
        rigid.CreateAngularVelocityAttr(Gf.Vec3f(*map(float, np.asarray(body.angular_velocity) * DEG)))
        mass = UsdPhysics.MassAPI.Apply(prim)
        mass.CreateMassAttr(float(body.mass))
        mass.CreateCenterOfMassAttr(Gf.Vec3f(*map(float, body.com)))
        moments, axes = np.linalg.eigh(body.inertia)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1.0
        mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*map(float, moments)))
        mass.CreatePrincipalAxesAttr(_gf_quat(Gf, matrix_to_quat(axes)))
        prim.CreateAttribute("morphopt:name", Sdf.ValueTypeNames.String).Set(body.name)
    if tree.roots:
        UsdPhysics.ArticulationRootAPI.Apply(stage.GetPrimAtPath(body_paths[tree.roots[0]]))
    else:
        UsdPhysics.ArticulationRootAPI.Apply(root.GetPrim())

    for shape in spec.shapes:
        shape_path = body_paths[shape.body].AppendChild("Collisions").AppendChild(_prim_name(shape.name))
        radius, second, third = (float(v) for v in shape.size)
        if shape.type == ShapeType.SPHERE:
            geom = UsdGeom.Sphere.Define(stage, shape_path)
            geom.CreateRadiusAttr(radius)
        elif shape.type == ShapeType.CAPSULE:
            geom = UsdGeom.Capsule.Define(stage, shape_path)
            geom.CreateRadiusAttr(radius)
            geom.CreateHeightAttr(2.0 * second)
            geom.CreateAxisAttr(UsdGeom.Tokens.z)
        elif shape.type == ShapeType.CYLINDER:
            geom = UsdGeom.Cylinder.Define(stage, shape_path)
            geom.CreateRadiusAttr(radius)
            geom.CreateHeightAttr(2.0 * second)
            geom.CreateAxisAttr(UsdGeom.Tokens.z)
        else:
            geom = UsdGeom.Cube.Define(stage, shape_path)
            geom.CreateSizeAttr(2.0)
        _set_pose(geom, shape.position, shape.orientation)
        if shape.type == ShapeType.BOX:
            geom.AddScaleOp().Set(Gf.Vec3f(radius, second, third))
        prim = geom.GetPrim()
        UsdPhysics.CollisionAPI.Apply(prim)
        prim.CreateAttribute("morphopt:name", Sdf.ValueTypeNames.String).Set(shape.name)
        key = (shape.friction, shape.restitution)
        if key not in materials:
            material = UsdShade.Material.Define(stage, root_path.AppendChild("Materials").AppendChild(
                f"material_{len(materials)}"))
            api = UsdPhysics.MaterialAPI.Apply(material.GetPrim())
            api.CreateStaticFrictionAttr(float(shape.friction))
            api.CreateDynamicFrictionAttr(float(shape.friction))
            api.CreateRestitutionAttr(float(shape.restitution))
            materials[key] = material
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(materials[key], UsdShade.Tokens.weakerThanDescendants, "physics")
    groups = sorted({s.collision_group for s in spec.shapes if s.collision_group})
    for group in groups:
        collision_group = UsdPhysics.CollisionGroup.Define(
            stage, root_path.AppendChild("CollisionGroups").AppendChild(f"group_{group}"))
        collection = collision_group.GetCollidersCollectionAPI()
        for shape in spec.shapes:
            if shape.collision_group == group:
                collection.CreateIncludesRel().AddTarget(
                    body_paths[shape.body].AppendChild("Collisions").AppendChild(_prim_name(shape.name)))
        collision_group.CreateFilteredGroupsRel().AddTarget(collision_group.GetPath())
        collision_group.GetPrim().CreateAttribute("morphopt:group", Sdf.ValueTypeNames.Int).Set(int(group))

    for name, mesh in (meshes or {}).items():
        if name not in body_paths:
            raise ValueError(f"meshes: no body named '{name}'")
        usd_mesh = UsdGeom.Mesh.Define(stage, body_paths[name].AppendChild("Visuals").AppendChild("mesh"))
        usd_mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(mesh.vertices, dtype=np.float32)))
        faces = np.asarray(mesh.faces, dtype=np.int32)
        usd_mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
        usd_mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
        usd_mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)

    for point in spec.points:
        xform = UsdGeom.Xform.Define(stage, body_paths[point.body].AppendChild("Points").AppendChild(
            _prim_name(point.name)))
        xform.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, point.position)))
        xform.GetPrim().CreateAttribute("morphopt:trackedPoint", Sdf.ValueTypeNames.String).Set(point.name)

    if spec.ground is not None:
        plane = UsdGeom.Plane.Define(stage, root_path.AppendChild("Ground"))
        plane.CreateAxisAttr(UsdGeom.Tokens.z)
        normal = np.asarray(spec.ground.normal, float)
        _set_pose(plane, normal * spec.ground.offset, matrix_to_quat(_align_x(normal) @ _align_x((0, 0, 1)).T))
        UsdPhysics.CollisionAPI.Apply(plane.GetPrim())
        api = UsdPhysics.MaterialAPI.Apply(plane.GetPrim())
        api.CreateStaticFrictionAttr(float(spec.ground.friction))
        api.CreateDynamicFrictionAttr(float(spec.ground.friction))
        api.CreateRestitutionAttr(float(spec.ground.restitution))

    joints_path = root_path.AppendChild("Joints")
    UsdGeom.Scope.Define(stage, joints_path)
    loops = {j.name for j in tree.loops}
    for joint in spec.joints:
        _write_joint(stage, joints_path.AppendChild(_prim_name(joint.name)), spec, joint, body_paths,
                     joint.name in loops, joint.name in loops and _planar_closure(spec, tree, joint))

    if motion is not None:
        times, poses = motion
        poses = np.asarray(poses, float)
        stage.SetTimeCodesPerSecond(fps)
        stage.SetStartTimeCode(float(times[0]) * fps)
        stage.SetEndTimeCode(float(times[-1]) * fps)
        for b, body in enumerate(spec.bodies):
            xform = UsdGeom.Xform(stage.GetPrimAtPath(body_paths[body.name]))
            for t, pose in zip(times, poses[:, b]):
                _set_pose(xform, pose[:3], pose[3:], time=float(t) * fps)
    stage.GetRootLayer().Save()
    return path


def _tree_path(tree, body: str | None) -> list:
    """The tree joints from ``body`` up to its root (the world or a floating root), nearest first."""
    out = []
    while body is not None and body in tree.tree:
        edge = tree.tree[body]
        out.append(edge)
        body = edge.parent
    return out


def _planar_closure(spec: MechanismSpec, tree, joint: Joint) -> bool:
    """Whether an inline loop closure's bodies are held by the tree in planar motion about its axis
    (module doc): written as a revolute joint."""
    if joint.type != JointType.INLINE:
        return False
    up, down = _tree_path(tree, joint.parent), _tree_path(tree, joint.child)
    shared = {id(e) for e in up} & {id(e) for e in down}
    parent_frame, child_frame = anchor_frames(spec, joint)
    n = parent_frame[:3, :3] @ joint.axis
    if abs(abs(float(n @ (child_frame[:3, :3] @ joint.axis))) - 1.0) > PARALLEL:
        return False
    for edge in up + down:
        if id(edge) in shared or edge.joint.type == JointType.FIXED:
            continue
        axis = anchor_frames(spec, edge.joint)[0][:3, :3] @ edge.joint.axis
        if edge.joint.type == JointType.REVOLUTE and abs(abs(float(n @ axis)) - 1.0) <= PARALLEL:
            continue
        if edge.joint.type == JointType.PRISMATIC and abs(float(n @ axis)) <= PARALLEL:
            continue
        return False
    return True


def _joint_frames(spec: MechanismSpec, joint: Joint, coincident: bool) -> tuple:
    """(localPos0, localRot0, localPos1, localRot1, offset) of a joint, the joint frames' X axis on
    the joint axis. coincident: the child frame is the parent's at the initial state (and a sliding
    joint's parent anchor moves along the axis onto the child anchor's projection), so the written
    coordinate is 0 there and offset [rad or m] is the engine's initial coordinate (limits and drive
    targets are written less offset); else each frame follows its anchor frame and offset is 0."""
    align = _align_x(joint.axis)
    frame0 = quat_to_matrix(joint.parent_orientation) @ align  # in the parent body frame
    position0 = np.asarray(joint.parent_position, float)
    if not coincident:
        child = quat_to_matrix(joint.child_orientation) @ align
        if joint.type == JointType.UNIVERSAL:  # axis2 (child anchor frame) becomes the child frame's Y axis
            M = _align_x(joint.axis2)
            child = quat_to_matrix(joint.child_orientation) @ np.stack([M[:, 1], M[:, 0], -M[:, 2]], axis=1)
        return position0, matrix_to_quat(frame0), joint.child_position, matrix_to_quat(child), 0.0
    world0 = body_frame(spec, joint.parent)[:3, :3] @ frame0
    frame1 = body_frame(spec, joint.child)[:3, :3].T @ world0
    if joint.type in (JointType.PRISMATIC, JointType.INLINE):
        parent_anchor, child_anchor = (T[:3, 3] for T in anchor_frames(spec, joint))
        position0 = position0 + float(world0[:, 0] @ (child_anchor - parent_anchor)) * frame0[:, 0]
    return (position0, matrix_to_quat(frame0), joint.child_position, matrix_to_quat(frame1),
            initial_coordinate(spec, joint))


def _write_joint(stage, path, spec: MechanismSpec, joint: Joint, body_paths: dict, loop: bool, planar: bool) -> None:
    kind = joint.type
    if planar:  # a planar inline loop closure: a revolute joint (module doc)
        usd_joint = UsdPhysics.RevoluteJoint.Define(stage, path)
    elif kind == JointType.REVOLUTE:
        usd_joint = UsdPhysics.RevoluteJoint.Define(stage, path)
    elif kind == JointType.PRISMATIC:
        usd_joint = UsdPhysics.PrismaticJoint.Define(stage, path)
    elif kind == JointType.SPHERICAL:
        usd_joint = UsdPhysics.SphericalJoint.Define(stage, path)
    elif kind == JointType.FIXED:
        usd_joint = UsdPhysics.FixedJoint.Define(stage, path)
    else:
        usd_joint = UsdPhysics.Joint.Define(stage, path)
        for dof in LOCKED[kind]:
            limit = UsdPhysics.LimitAPI.Apply(usd_joint.GetPrim(), dof)
            limit.CreateLowAttr(1.0)
            limit.CreateHighAttr(-1.0)  # low > high: locked
    prim = usd_joint.GetPrim()
    prim.CreateAttribute("morphopt:type", Sdf.ValueTypeNames.Token).Set(kind.name.lower())
    prim.CreateAttribute("morphopt:name", Sdf.ValueTypeNames.String).Set(joint.name)
    if joint.parent is not None:
        usd_joint.CreateBody0Rel().SetTargets([body_paths[joint.parent]])
    usd_joint.CreateBody1Rel().SetTargets([body_paths[joint.child]])
    position0, rot0, position1, rot1, offset = _joint_frames(spec, joint, planar or kind in COINCIDENT)
    usd_joint.CreateLocalPos0Attr(Gf.Vec3f(*map(float, position0)))
    usd_joint.CreateLocalRot0Attr(_gf_quat(Gf, rot0))
    usd_joint.CreateLocalPos1Attr(Gf.Vec3f(*map(float, position1)))
    usd_joint.CreateLocalRot1Attr(_gf_quat(Gf, rot1))
    if loop:
        usd_joint.CreateExcludeFromArticulationAttr(True)
    if planar or kind == JointType.SPHERICAL:
        usd_joint.CreateAxisAttr(UsdPhysics.Tokens.x)
    elif kind in (JointType.REVOLUTE, JointType.PRISMATIC):
        usd_joint.CreateAxisAttr(UsdPhysics.Tokens.x)
        scale = DEG if kind == JointType.REVOLUTE else 1.0
        usd_joint.CreateLowerLimitAttr(float((joint.limit_lower - offset) * scale))
        usd_joint.CreateUpperLimitAttr(float((joint.limit_upper - offset) * scale))
        instance = "angular" if kind == JointType.REVOLUTE else "linear"  # PhysX's JointStateAPI
        prim.AddAppliedSchema(f"PhysicsJointStateAPI:{instance}")
        prim.CreateAttribute(f"state:{instance}:physics:position", Sdf.ValueTypeNames.Float).Set(0.0)
        prim.CreateAttribute(f"state:{instance}:physics:velocity", Sdf.ValueTypeNames.Float).Set(
            float(initial_rate(spec, joint) * scale))
        if joint.armature:
            prim.CreateAttribute("morphopt:armature", Sdf.ValueTypeNames.Double).Set(float(joint.armature))
        if joint.damping:
            prim.CreateAttribute("morphopt:damping", Sdf.ValueTypeNames.Double).Set(float(joint.damping))
        if joint.drive is not None:
            drive = UsdPhysics.DriveAPI.Apply(prim, instance)
            d = joint.drive
            drive.CreateTypeAttr(UsdPhysics.Tokens.force)
            drive.CreateStiffnessAttr(float(d.stiffness / scale))
            drive.CreateDampingAttr(float(d.damping / scale))
            drive.CreateTargetPositionAttr(float((d.target_position - offset) * scale))
            drive.CreateTargetVelocityAttr(float(d.target_velocity * scale))
            drive.CreateMaxForceAttr(float(d.effort_limit))


def record_motion(spec: MechanismSpec, duration: float, *, dt: float = 1e-3, fps: float = 60.0, config=None,
                  device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Simulate ``spec`` alone for ``duration`` [s] and return (times (T,), poses (T, B, 7)): each
    body frame's world position and quaternion (x, y, z, w) at ``fps`` frames per second."""
    from engine import SolverConfig, pack_worlds, rollout

    model = pack_worlds([spec], device=device, config=config or SolverConfig())
    state, control = model.state(), model.control()
    per_frame = max(1, round(1.0 / (fps * dt)))
    frames = round(duration / (per_frame * dt))
    coms = np.array([b.com for b in spec.bodies])
    times, poses = [], []
    for k in range(frames + 1):
        if k:
            _, state = rollout(model, state, control, steps=per_frame, dt=dt, record_every=per_frame)
        q = state.body_q.numpy()[0, : len(spec.bodies)]  # COM position, body orientation
        frame_poses = np.empty((len(spec.bodies), 7))
        for b in range(len(spec.bodies)):
            R = quat_to_matrix(q[b, 3:])
            frame_poses[b, :3] = q[b, :3] - R @ coms[b]
            frame_poses[b, 3:] = q[b, 3:]
        times.append(k * per_frame * dt)
        poses.append(frame_poses)
    return np.array(times), np.array(poses)


# ---------------------------------------------------------------------------------------------
# Import


def _finite(values, what: str):
    array = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what}: must be finite, got {array.tolist()}")
    return array


def _world_matrix(prim, cache) -> np.ndarray:
    """A prim's local-to-world 4x4 matrix as a NumPy array acting on column vectors."""
    return np.array(cache.GetLocalToWorldTransform(prim), dtype=float).T


def _rigid(matrix, what: str):
    """Position and rotation of a 4x4 transform without scale or shear (else ValueError)."""
    R = matrix[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
        raise ValueError(f"{what}: scaled or sheared transforms are not supported on rigid bodies")
    return matrix[:3, 3].copy(), R


def read_usd(path, *, origin=(0.0, 0.0, 0.0), name: str | None = None) -> MechanismSpec:
    """Read a UsdPhysics stage into a MechanismSpec (SI units, Z up); see the module docstring.

    origin: a translation [m] added to every body (e.g. to stand a robot on the ground plane).
    Raises ValueError naming the file and the prim for anything it cannot represent.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such USD file")
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:  # USD's own reader errors: malformed or foreign files
        raise ValueError(f"{path}: not a readable USD stage ({_usd_reason(exc)})") from None
    if stage is None:
        raise ValueError(f"{path}: not a readable USD stage")
    try:
        return _read_stage(stage, path, np.asarray(origin, float), name)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    except Tf.ErrorException as exc:
        raise ValueError(f"{path}: {_usd_reason(exc)}") from None


def _usd_reason(exc) -> str:
    """The message of USD's first error, without its source location."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    first = lines[0] if lines else type(exc).__name__
    return first.rsplit(" : ", 1)[-1].strip("'")


def _read_stage(stage, path, origin, name) -> MechanismSpec:
    meters = UsdGeom.GetStageMetersPerUnit(stage)
    kilograms = UsdPhysics.GetStageKilogramsPerUnit(stage)
    for unit, value in (("metersPerUnit", meters), ("kilogramsPerUnit", kilograms)):
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"stage {unit} must be a positive number, got {value}")
    up = UsdGeom.GetStageUpAxis(stage)
    if up not in ("Z", "Y"):
        raise ValueError(f"stage upAxis must be Y or Z, got {up!r}")
    to_z = np.eye(4)
    if up == "Y":  # (x, y, z)_Y-up -> (x, -z, y)_Z-up: a rotation of +90 degrees about X
        to_z[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    units = np.diag([meters, meters, meters, 1.0])
    cache = UsdGeom.XformCache()
    layer = stage.GetRootLayer().customLayerData or {}
    spec_name = name or layer.get("morphopt:spec_name") or (stage.GetDefaultPrim().GetName()
                                                            if stage.GetDefaultPrim() else path.stem)
    gravity = np.array([0.0, 0.0, -9.81])
    bodies, shapes, joints, points = [], [], [], []
    body_of_path, poses, ground = {}, {}, None
    group_of_shape = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdPhysics.Scene):
            scene = UsdPhysics.Scene(prim)
            direction = np.array(scene.GetGravityDirectionAttr().Get() or (0.0, 0.0, 0.0), float)
            magnitude = scene.GetGravityMagnitudeAttr().Get()
            if np.linalg.norm(direction) < 1e-12:
                direction = np.array([0.0, 0.0, -1.0]) if up == "Z" else np.array([0.0, -1.0, 0.0])
            if magnitude is None or magnitude < -1e30 or not math.isfinite(magnitude):
                magnitude = 9.81 / meters  # UsdPhysics: -inf means earth gravity in stage units
            gravity = to_z[:3, :3] @ (direction / np.linalg.norm(direction)) * magnitude * meters
        if prim.IsA(UsdPhysics.CollisionGroup):
            group = UsdPhysics.CollisionGroup(prim)
            filtered = group.GetFilteredGroupsRel().GetTargets()
            if prim.GetPath() in filtered:
                number = prim.GetAttribute("morphopt:group").Get() if prim.HasAttribute("morphopt:group") else None
                number = int(number) if number else 1 + len(set(group_of_shape.values()))
                query = group.GetCollidersCollectionAPI().ComputeMembershipQuery()
                for target in Usd.CollectionAPI.ComputeIncludedPaths(query, stage):
                    group_of_shape[target] = number
        if not prim.HasAPI(UsdPhysics.RigidBodyAPI):
            continue
        where = f"body {prim.GetPath()}"
        if not prim.IsA(UsdGeom.Xformable):
            raise ValueError(f"{where}: a rigid body must be an Xformable prim")
        body_name = prim.GetAttribute("morphopt:name").Get() if prim.HasAttribute("morphopt:name") else prim.GetName()
        matrix = to_z @ units @ _world_matrix(prim, cache)
        matrix[:3, :3] /= meters
        position, R = _rigid(matrix, where)
        position = position + origin
        mass_api = UsdPhysics.MassAPI(prim)
        mass = mass_api.GetMassAttr().Get() if prim.HasAPI(UsdPhysics.MassAPI) else None
        if mass is None or mass <= 0.0:
            raise ValueError(f"{where}: needs a positive physics:mass (MassAPI); densities from colliders are "
                             f"not supported")
        mass = float(_finite(mass, f"{where}: physics:mass")) * kilograms
        com = _finite(mass_api.GetCenterOfMassAttr().Get() or (0.0, 0.0, 0.0), f"{where}: physics:centerOfMass")
        moments = _finite(mass_api.GetDiagonalInertiaAttr().Get() or (0.0, 0.0, 0.0),
                          f"{where}: physics:diagonalInertia") * kilograms * meters**2
        if np.any(moments <= 0.0):
            raise ValueError(f"{where}: physics:diagonalInertia must be positive, got {moments.tolist()}")
        axes_q = mass_api.GetPrincipalAxesAttr().Get()
        axes = quat_to_matrix(_finite(_np_quat(axes_q), f"{where}: physics:principalAxes")) if axes_q else np.eye(3)
        velocity = np.asarray(UsdPhysics.RigidBodyAPI(prim).GetVelocityAttr().Get() or (0.0, 0.0, 0.0), float)
        omega = np.asarray(UsdPhysics.RigidBodyAPI(prim).GetAngularVelocityAttr().Get() or (0.0, 0.0, 0.0), float)
        try:
            body = Body(body_name, mass, axes @ np.diag(moments) @ axes.T, com=com * meters, position=position,
                        orientation=matrix_to_quat(R), velocity=to_z[:3, :3] @ velocity * meters,
                        angular_velocity=to_z[:3, :3] @ omega / DEG)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        if body_name in {b.name for b in bodies}:
            raise ValueError(f"{where}: a second body named '{body_name}'")
        bodies.append(body)
        body_of_path[prim.GetPath()] = body_name
        poses[body_name] = (position, R)
    for prim in stage.Traverse():
        if prim.HasAPI(UsdPhysics.CollisionAPI):
            owner = prim
            while owner and owner.GetPath() not in body_of_path and owner.GetPath() != Sdf.Path.absoluteRootPath:
                owner = owner.GetParent()
            body_name = body_of_path.get(owner.GetPath()) if owner else None
            if prim.IsA(UsdGeom.Plane) and body_name is None:
                matrix = to_z @ units @ _world_matrix(prim, cache)
                axis = {"X": 0, "Y": 1, "Z": 2}[UsdGeom.Plane(prim).GetAxisAttr().Get()]
                normal = matrix[:3, axis] / np.linalg.norm(matrix[:3, axis])
                friction = prim.GetAttribute("physics:dynamicFriction").Get() \
                    if prim.HasAttribute("physics:dynamicFriction") else 0.8
                restitution = prim.GetAttribute("physics:restitution").Get() \
                    if prim.HasAttribute("physics:restitution") else 0.0
                ground = GroundPlane(normal, float(normal @ matrix[:3, 3]), friction=friction, restitution=restitution)
                continue
            if body_name is None:
                raise ValueError(f"collider {prim.GetPath()}: static colliders other than a ground plane are not "
                                 f"supported")
            shapes.append(_read_shape(prim, body_name, poses[body_name], to_z @ units, cache, group_of_shape,
                                      meters, origin))
        if prim.HasAttribute("morphopt:trackedPoint"):
            owner = prim.GetParent()
            while owner and owner.GetPath() not in body_of_path and owner.GetPath() != Sdf.Path.absoluteRootPath:
                owner = owner.GetParent()
            if owner.GetPath() not in body_of_path:
                raise ValueError(f"tracked point {prim.GetPath()}: not under a rigid body")
            body_name = body_of_path[owner.GetPath()]
            world = (to_z @ units @ _world_matrix(prim, cache))[:3, 3] + origin
            position, R = poses[body_name]
            points.append(TrackedPoint(prim.GetAttribute("morphopt:trackedPoint").Get(), body_name,
                                       R.T @ (world - position)))
        if prim.IsA(UsdPhysics.Joint):
            joint = _read_joint(prim, body_of_path, poses, meters, to_z, origin, cache)
            if joint is not None:
                joints.append(joint)
        elif prim.GetTypeName().startswith("Physics") and prim.GetTypeName() not in (
                "PhysicsScene", "PhysicsCollisionGroup"):
            raise ValueError(f"prim {prim.GetPath()}: unsupported physics prim type {prim.GetTypeName()}")
    if not bodies:
        raise ValueError("no rigid bodies (PhysicsRigidBodyAPI) on the stage")
    return MechanismSpec(bodies, joints, points, gravity=gravity, name=spec_name, shapes=shapes, ground=ground)


def _read_shape(prim, body_name, pose, to_world, cache, group_of_shape, meters, origin) -> Shape:

    where = f"collider {prim.GetPath()}"
    matrix = to_world @ _world_matrix(prim, cache)
    scale = np.linalg.norm(matrix[:3, :3], axis=0) / meters
    R = matrix[:3, :3] / (scale * meters)
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5):
        raise ValueError(f"{where}: sheared collider transforms are not supported")
    body_position, body_R = pose
    position = body_R.T @ (matrix[:3, 3] + origin - body_position)
    name = prim.GetAttribute("morphopt:name").Get() if prim.HasAttribute("morphopt:name") else \
        f"{body_name}/{prim.GetName()}"
    axis_turn = np.eye(3)
    if prim.IsA(UsdGeom.Cube):
        size = 0.5 * UsdGeom.Cube(prim).GetSizeAttr().Get() * scale * meters
        kind = ShapeType.BOX
    elif prim.IsA(UsdGeom.Sphere):
        if not np.allclose(scale, scale[0], rtol=1e-6):
            raise ValueError(f"{where}: a non-uniformly scaled sphere is not a sphere")
        size, kind = [UsdGeom.Sphere(prim).GetRadiusAttr().Get() * scale[0] * meters], ShapeType.SPHERE
    elif prim.IsA(UsdGeom.Capsule) or prim.IsA(UsdGeom.Cylinder):
        geom = UsdGeom.Capsule(prim) if prim.IsA(UsdGeom.Capsule) else UsdGeom.Cylinder(prim)
        axis = {"X": 0, "Y": 1, "Z": 2}[geom.GetAxisAttr().Get()]
        if axis != 2:  # our capsules and cylinders run along local z
            axis_turn = np.roll(np.eye(3), 2 - axis, axis=1) if axis == 0 else np.array(
                [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        radial = [s for k, s in enumerate(scale) if k != axis]
        if not np.isclose(radial[0], radial[1], rtol=1e-6):
            raise ValueError(f"{where}: a capsule or cylinder scaled unevenly across its axis")
        size = [geom.GetRadiusAttr().Get() * radial[0] * meters, 0.5 * geom.GetHeightAttr().Get() * scale[axis] * meters]
        kind = ShapeType.CAPSULE if prim.IsA(UsdGeom.Capsule) else ShapeType.CYLINDER
    else:
        approximation = ""
        if prim.HasAPI(UsdPhysics.MeshCollisionAPI):
            approximation = f" (approximation {UsdPhysics.MeshCollisionAPI(prim).GetApproximationAttr().Get()})"
        raise ValueError(f"{where}: unsupported collider type {prim.GetTypeName()}{approximation}; "
                         f"use Cube, Sphere, Capsule or Cylinder")
    orientation = matrix_to_quat(body_R.T @ R @ axis_turn)
    friction, restitution = 0.8, 0.0
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial("physics")
    if material and material.GetPrim().HasAPI(UsdPhysics.MaterialAPI):
        api = UsdPhysics.MaterialAPI(material.GetPrim())
        friction = api.GetDynamicFrictionAttr().Get() if api.GetDynamicFrictionAttr().HasAuthoredValue() else friction
        restitution = api.GetRestitutionAttr().Get() if api.GetRestitutionAttr().HasAuthoredValue() else restitution
    try:
        return Shape(name, kind, body_name, np.asarray(size, float), position, orientation, friction=friction,
                     restitution=restitution, collision_group=group_of_shape.get(prim.GetPath(), 0))
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _read_joint(prim, body_of_path, poses, meters, to_z, origin, cache):

    where = f"joint {prim.GetPath()}"
    joint = UsdPhysics.Joint(prim)
    if not joint.GetJointEnabledAttr().Get():
        return None  # disabled on purpose by the file
    typename = prim.GetAttribute("morphopt:type").Get() if prim.HasAttribute("morphopt:type") else None
    if prim.IsA(UsdPhysics.RevoluteJoint) and typename == "inline":  # a planar loop closure (module doc)
        kind = JointType.INLINE
    elif prim.IsA(UsdPhysics.RevoluteJoint):
        kind = JointType.REVOLUTE
    elif prim.IsA(UsdPhysics.PrismaticJoint):
        kind = JointType.PRISMATIC
    elif prim.IsA(UsdPhysics.SphericalJoint):
        kind = JointType.SPHERICAL
    elif prim.IsA(UsdPhysics.FixedJoint):
        kind = JointType.FIXED
    elif typename in ("universal", "cylindrical", "inline"):
        kind = JointType[typename.upper()]
    else:
        raise ValueError(f"{where}: unsupported joint type {prim.GetTypeName()}"
                         + (" (a generic D6 joint)" if prim.GetTypeName() == "PhysicsJoint" else ""))
    name = prim.GetAttribute("morphopt:name").Get() if prim.HasAttribute("morphopt:name") else prim.GetName()
    ends = []
    for rel in (joint.GetBody0Rel(), joint.GetBody1Rel()):
        targets = rel.GetTargets()
        if len(targets) > 1:
            raise ValueError(f"{where}: {rel.GetName()} has {len(targets)} targets")
        if targets and targets[0] not in body_of_path:
            raise ValueError(f"{where}: {rel.GetName()} points to {targets[0]}, which is not a rigid body on the stage")
        ends.append(body_of_path[targets[0]] if targets else None)
    parent, child = ends
    positions = [_finite(joint.GetLocalPos0Attr().Get() or (0, 0, 0), f"{where}: physics:localPos0") * meters,
                 _finite(joint.GetLocalPos1Attr().Get() or (0, 0, 0), f"{where}: physics:localPos1") * meters]
    rotations = []
    for attr in (joint.GetLocalRot0Attr(), joint.GetLocalRot1Attr()):
        value = attr.Get()
        rotations.append(_finite(_np_quat(value), f"{where}: {attr.GetName()}") if value is not None
                         else np.array([0.0, 0.0, 0.0, 1.0]))
    swapped = child is None
    if swapped:  # only body0: swap the sides so that the world is the parent (the coordinate changes sign)
        if parent is None:
            raise ValueError(f"{where}: joins no rigid body (body0 and body1 are empty)")
        parent, child = None, parent
        positions.reverse()
        rotations.reverse()
    if parent is None:  # the world-side anchor is in stage coordinates
        world = to_z[:3, :3]
        positions[0] = world @ positions[0] + origin
        rotations[0] = matrix_to_quat(world @ quat_to_matrix(rotations[0]))
    axis_token = "X"
    if kind in (JointType.REVOLUTE, JointType.PRISMATIC, JointType.SPHERICAL) or prim.IsA(UsdPhysics.RevoluteJoint):
        axis_token = prim.GetAttribute("physics:axis").Get() or "X"
    axis = np.eye(3)[{"X": 0, "Y": 1, "Z": 2}[axis_token]]
    axis2 = np.array([0.0, 1.0, 0.0])  # universal joints: the child frame's Y axis (the parent's X is the axis)
    lower, upper, drive, armature, damping = -math.inf, math.inf, None, 0.0, 0.0
    if kind in (JointType.REVOLUTE, JointType.PRISMATIC):
        angular = kind == JointType.REVOLUTE
        scale = 1.0 / DEG if angular else meters
        lo = prim.GetAttribute("physics:lowerLimit").Get()
        hi = prim.GetAttribute("physics:upperLimit").Get()
        if lo is not None and math.isfinite(lo) and not (angular and lo <= -180.0):
            lower = float(lo) * scale
        if hi is not None and math.isfinite(hi) and not (angular and hi >= 180.0):
            upper = float(hi) * scale
        if any(v is not None and math.isnan(v) for v in (lo, hi)):
            raise ValueError(f"{where}: NaN joint limit")
        instance = "angular" if angular else "linear"
        if prim.HasAPI(UsdPhysics.DriveAPI, instance):
            api = UsdPhysics.DriveAPI(prim, instance)
            if (api.GetTypeAttr().Get() or "force") != "force":
                raise ValueError(f"{where}: drive type '{api.GetTypeAttr().Get()}' is not supported (only 'force')")
            per = DEG if angular else 1.0 / meters
            max_force = api.GetMaxForceAttr().Get()
            values = {"stiffness": (api.GetStiffnessAttr().Get() or 0.0) * per,
                      "damping": (api.GetDampingAttr().Get() or 0.0) * per,
                      "target_position": (api.GetTargetPositionAttr().Get() or 0.0) * scale,
                      "target_velocity": (api.GetTargetVelocityAttr().Get() or 0.0) * scale}
            if any(not math.isfinite(v) for v in values.values()):
                raise ValueError(f"{where}: drive values must be finite, got {values}")
            effort = math.inf if max_force is None or max_force < 0 or not math.isfinite(max_force) else max_force
            drive = JointDrive(effort_limit=effort, **values) if effort > 0 else None
        if prim.HasAttribute("morphopt:armature"):
            armature = float(prim.GetAttribute("morphopt:armature").Get())
        if prim.HasAttribute("morphopt:damping"):
            damping = float(prim.GetAttribute("morphopt:damping").Get())
    if swapped:
        lower, upper = -upper, -lower
        if drive is not None:
            drive.target_position, drive.target_velocity = -drive.target_position, -drive.target_velocity
    try:
        return Joint(name, kind, parent, child, parent_position=positions[0], parent_orientation=rotations[0],
                     child_position=positions[1], child_orientation=rotations[1], axis=axis, axis2=axis2,
                     armature=armature, damping=damping, drive=drive, limit_lower=lower, limit_upper=upper)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def validate_usd(path) -> list[str]:
    """pxr's own validation of a stage (the UsdPhysics, UsdGeom, UsdShade and core validators):
    one line per error or warning found, empty when the stage is clean."""

    registry = UsdValidation.ValidationRegistry()
    validators = [v for v in registry.GetOrLoadAllValidators()
                  if v.GetMetadata().name.split(":")[0] in ("usdPhysicsValidators", "usdGeomValidators",
                                                          "usdShadeValidators", "usdValidation")]
    context = UsdValidation.ValidationContext(validators)
    stage = Usd.Stage.Open(str(path))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in context.Validate(stage)]
