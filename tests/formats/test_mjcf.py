"""MJCF export: the file loads in MuJoCo, describes the spec's bodies, joints, loops, drives and
shapes, and MuJoCo simulating it tracks our engine's trajectories (the cross-simulator check)."""

import dataclasses
import math

import numpy as np
import pytest

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
from engine.pack import collision_pairs
from engine.scenes import fourbar
from morphopt.families import load_family
from morphopt.formats.mjcf import CLOSURE_AXIS_LENGTH, mjcf_string, read_metadata, write_mjcf
from morphopt.formats.tree import initial_coordinate, matrix_to_quat, quat_to_matrix, spanning_tree
from morphopt.linkage.to_spec import to_spec

mujoco = pytest.importorskip("mujoco", reason="MuJoCo is the independent reference (pip install '.[test]')")

ENGINE_DT, MUJOCO_DT, RECORD = 1e-3, 1e-4, 0.01  # [s]


def jansen_spec() -> MechanismSpec:
    family = load_family("jansen_leg")
    return to_spec(family.generate(family.space.default()))


def passive_fourbar() -> MechanismSpec:
    """engine.scenes.fourbar released at rest: its loop closes with a revolute joint (two connects)."""
    return fourbar(crank_speed=0.0).spec


def _axis_quat(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.array([*(math.sin(angle / 2) * axis), math.cos(angle / 2)])


def floating_spec(armature: float = 0.0, limits: tuple = (-math.inf, math.inf)) -> MechanismSpec:
    """A spinning, drifting pelvis (floating root) with a leg on a reversed, PD-driven hip (initial
    coordinate 0.2 rad) and a foot on a damped, PD-driven prismatic ankle, anchor frames rotated;
    the initial velocities are consistent with the joints. armature: of the hip [kg m^2], and
    five times that [kg] at the ankle; limits: of the hip [rad]."""
    R = quat_to_matrix
    q_pelvis, q_leg, q_foot = _axis_quat((1, 2, 3), 0.4), _axis_quat((0, 1, -1), 0.9), _axis_quat((1, 0, 0), 0.3)
    R_p, R_l, R_f = R(q_pelvis), R(q_leg), R(q_foot)
    hip_world = np.array([0.15, -0.1, 0.9])
    ankle_world = hip_world + R_l @ np.array([0.0, 0.0, -0.4])
    pelvis = Body("pelvis", 5.0, [[0.05, 0.004, 0.0], [0.004, 0.08, 0.002], [0.0, 0.002, 0.06]], com=(0.01, 0.0, 0.02),
                  position=(0.1, -0.2, 1.0), orientation=q_pelvis)
    leg = Body("leg", 1.0, [0.01, 0.012, 0.003], com=(0.0, 0.0, -0.2), position=hip_world, orientation=q_leg)
    foot = Body("foot", 0.5, [0.001, 0.002, 0.0025], com=(0.05, 0.0, 0.0),
                position=ankle_world - np.array([0.0, 0.0, 0.01]), orientation=q_foot)
    q_anchor = _axis_quat((0, 0, 1), 0.5)  # hip anchor frame in the leg frame; axis = its y axis
    hip_axis_world = R_l @ R(q_anchor) @ np.array([0.0, 1.0, 0.0])
    child_anchor_world = R(_axis_quat(hip_axis_world, 0.2)) @ R_l @ R(q_anchor)  # turned 0.2 rad about the axis
    hip = Joint("hip", "revolute", "leg", "pelvis", parent_orientation=q_anchor, axis=(0.0, 1.0, 0.0),
                child_position=R_p.T @ (hip_world - pelvis.position),
                child_orientation=matrix_to_quat(R_p.T @ child_anchor_world), armature=armature,
                limit_lower=limits[0], limit_upper=limits[1],
                drive=JointDrive(stiffness=20.0, damping=0.5, target_position=0.3, target_velocity=0.1))
    ankle = Joint("ankle", "prismatic", "leg", "foot", parent_position=(0.0, 0.0, -0.4),
                  child_position=R_f.T @ (ankle_world - foot.position), child_orientation=matrix_to_quat(R_f.T @ R_l),
                  axis=(0.0, 0.0, -1.0), damping=2.0, armature=5.0 * armature,
                  drive=JointDrive(stiffness=100.0, target_position=0.02))
    slide_world = R_l @ np.array([0.0, 0.0, -1.0])
    # initial twists: the pelvis (v at its COM, w); the hip turning at 1.5 rad/s; the ankle sliding at 0.3 m/s
    w_pelvis, v_pelvis = np.array([0.5, -1.0, 2.0]), np.array([0.3, 0.0, 1.0])

    def com(body):
        return R(body.orientation) @ body.com + body.position

    def velocity_at(v, w, origin, point):
        return v + np.cross(w, point - origin)

    w_leg = w_pelvis - 1.5 * hip_axis_world  # hip coordinate: the pelvis (child) relative to the leg
    v_leg = velocity_at(velocity_at(v_pelvis, w_pelvis, com(pelvis), hip_world), w_leg, hip_world, com(leg))
    v_foot = velocity_at(v_leg, w_leg, com(leg), com(foot)) + 0.3 * slide_world
    for body, v, w in ((pelvis, v_pelvis, w_pelvis), (leg, v_leg, w_leg), (foot, v_foot, w_leg)):
        body.velocity, body.angular_velocity = v, w
    points = [TrackedPoint("toe", "foot", (0.1, 0.02, -0.03)), TrackedPoint("head", "pelvis", (0.0, 0.1, 0.3))]
    spec = MechanismSpec([leg, pelvis, foot], [hip, ankle], points, name="floating")
    assert math.isclose(initial_coordinate(spec, hip), 0.2, abs_tol=1e-12)
    return spec


def mujoco_points(spec: MechanismSpec, xml: str, duration: float) -> np.ndarray:
    """Tracked points (records every RECORD s, P, 3) [m] of MuJoCo from the 'initial' keyframe,
    from the bodies' frames (data.xpos, data.xmat)."""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, p.body) for p in spec.points]
    local = np.array([p.position for p in spec.points])

    def points():
        return data.xpos[ids] + np.einsum("pij,pj->pi", data.xmat[ids].reshape(-1, 3, 3), local)

    records = [points()]
    for _ in range(round(duration / RECORD)):
        for _ in range(round(RECORD / model.opt.timestep)):
            mujoco.mj_step(model, data)
        records.append(points())
    return np.array(records)


def engine_points(spec: MechanismSpec, duration: float, dt: float = ENGINE_DT) -> np.ndarray:
    """Tracked points (records every RECORD s, P, 3) [m] of our engine on the CPU, time step dt [s]."""
    config = SolverConfig(tolerance=1e-7, relative_tolerance=1e-6, max_iterations=200)
    model = pack_worlds([spec], device="cpu", config=config)
    trace, _ = rollout(model, model.state(), model.control(), round(duration / dt), dt=dt,
                       record_every=round(RECORD / dt))
    assert not trace.diverged.any()
    return trace.points[:, 0, :len(spec.points)]


def tracking_error(spec: MechanismSpec, duration: float = 2.0, *, integrator: str = "discrete",
                   engine_dt: float = ENGINE_DT) -> float:
    """Largest distance [m] between MuJoCo's (dt 0.1 ms) and our engine's tracked points over
    ``duration``. MuJoCo's "discrete" integrator (MuJoCo >= 3.13) solves the constraints in the
    metric M + dt D of the implicit velocity update: with "implicitfast" the Jansen crank's stiff
    drive (kd 50 N m s/rad on a crank of ~1e-7 kg m^2) destabilizes MuJoCo after 1.4 s."""
    xml = mjcf_string(spec, timestep=MUJOCO_DT, integrator=integrator)
    reference, ours = mujoco_points(spec, xml, duration), engine_points(spec, duration, engine_dt)
    assert reference.shape == ours.shape
    return float(np.linalg.norm(reference - ours, axis=-1).max())


def test_passive_fourbar_tracks_the_engine_in_mujoco():
    """Acceptance: the passive four-bar falling from rest under gravity (loop closed by a
    revolute joint -> two connects) follows our engine's trajectory within 1 mm for 2 s
    (measured: 0.027 mm)."""
    error = tracking_error(passive_fourbar())
    assert error < 1e-3, error


def test_driven_jansen_leg_tracks_the_engine_in_mujoco():
    """Acceptance: the Jansen leg with its crank velocity drive (kd 50 N m s/rad, started at crank
    speed from the keyframe, loops closed by inline joints -> connects) follows our engine's foot
    path within 1 mm for 2 s (measured: 0.055 mm, most of it our engine's 1 ms step)."""
    error = tracking_error(jansen_spec())
    assert error < 1e-3, error


def test_floating_base_reversed_drive_and_slide_track_the_engine():
    """A free root with its MuJoCo free-joint velocity convention, a reversed PD-driven hinge
    (target in the engine's coordinate) and a damped, PD-driven slide: MuJoCo follows our engine
    within 1 mm for 1 s (measured: 0.30 mm against MuJoCo's RK4, which at 0.1 ms is exact to
    1e-11 m here; our engine's error is first order in its step, 0.59 mm at 1 ms, from the
    implicit PD drives). No armature here: the engine's armature rows disagree with MuJoCo's
    joint-space armature on a moving base (the mapping is checked structurally below)."""
    error = tracking_error(floating_spec(), duration=1.0, integrator="RK4", engine_dt=5e-4)
    assert error < 1e-3, error


@pytest.mark.parametrize("make", [passive_fourbar, jansen_spec, lambda: floating_spec(0.01, (-1.0, math.inf))])
def test_written_file_loads_with_the_spec_contents(tmp_path, make):
    """MuJoCo loads the written file: one body per spec body, the same total mass, one joint per
    non-fixed tree joint (plus a free joint per floating root), one connect per loop closure (two
    for a revolute closure), one actuator per drive, gravity, and the metadata reads back."""
    spec = make()
    metadata = {"family": spec.name, "params": {"a": np.float64(0.038), "note": 'quotes " & <tags>'}}
    path = write_mjcf(spec, tmp_path / "mech.xml", metadata=metadata)
    model = mujoco.MjModel.from_xml_path(str(path))
    tree = spanning_tree(spec)
    assert model.nbody == len(spec.bodies) + 1  # + the world body
    assert math.isclose(model.body_mass.sum(), sum(b.mass for b in spec.bodies), rel_tol=1e-9)
    assert model.njnt == sum(t.joint.type.name != "FIXED" for t in tree.tree.values()) + len(tree.roots)
    expected = sum(2 if j.type.name == "REVOLUTE" else 1 for j in tree.loops)
    assert model.neq == expected and (model.eq_type == mujoco.mjtEq.mjEQ_CONNECT).all()
    assert model.nu == sum(j.drive is not None for j in spec.joints)
    assert np.allclose(model.opt.gravity, spec.gravity)
    assert read_metadata(model) == metadata
    body = spec.bodies[0]
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body.name)
    assert np.allclose(model.body_ipos[index], body.com) and math.isclose(model.body_mass[index], body.mass)
    for joint in spec.joints:
        if joint in tree.loops:
            continue
        index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint.name)
        dof = model.jnt_dofadr[index]
        assert math.isclose(model.dof_armature[dof], joint.armature) and math.isclose(model.dof_damping[dof],
                                                                                        joint.damping)
        if joint.has_limits:  # qpos is the engine's coordinate, also across a reversed joint
            assert model.jnt_limited[index] and np.allclose(model.jnt_range[index], [joint.limit_lower, 1e10])


def test_keyframe_reproduces_the_initial_body_velocities():
    """The 'initial' keyframe gives every body the spec's initial pose, centre-of-mass velocity and
    angular velocity (free-joint and reversed-joint velocity conventions included)."""
    for spec in (floating_spec(), jansen_spec()):
        model = mujoco.MjModel.from_xml_string(mjcf_string(spec))
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, 0)
        mujoco.mj_forward(model, data)
        twist = np.zeros(6)
        for body in spec.bodies:
            index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body.name)
            assert np.allclose(data.xpos[index], body.position) and np.allclose(
                data.xmat[index].reshape(3, 3), quat_to_matrix(body.orientation))
            mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, index, twist, 0)  # (w, v at xpos)
            R = quat_to_matrix(body.orientation)
            v_com = twist[3:] + np.cross(twist[:3], R @ body.com)
            assert np.allclose(twist[:3], body.angular_velocity, atol=1e-9), body.name
            assert np.allclose(v_com, body.velocity, atol=1e-9), body.name


def test_drive_becomes_a_bias_actuator_with_the_effort_limit():
    """The crank's velocity drive is a general actuator: force = kd (target_velocity - qdot),
    clamped at the effort limit; no control input is needed."""
    spec = jansen_spec()
    drive = next(j for j in spec.joints if j.drive is not None)
    model = mujoco.MjModel.from_xml_string(mjcf_string(spec))
    assert np.allclose(model.actuator_biasprm[0, :3], [drive.drive.damping * drive.drive.target_velocity, 0.0,
                                                       -drive.drive.damping])
    assert model.actuator_forcelimited[0] and np.allclose(model.actuator_forcerange[0], [-50.0, 50.0])
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    data.qvel[0] = drive.drive.target_velocity - 0.01
    mujoco.mj_forward(model, data)
    assert math.isclose(data.actuator_force[0], drive.drive.damping * 0.01, rel_tol=1e-9)


def test_closures_of_every_supported_type_and_meshes(tmp_path):
    """A body chain closed to the world by a spherical, a fixed and an inline joint gives a
    connect, a weld and a connect whose sites coincide at the initial state; shapes become geoms
    with the engine's collision pairs and friction; meshes become visual STL geoms in group 1."""
    trimesh = pytest.importorskip("trimesh")
    bodies = [Body(f"b{k}", 1.0, [0.01, 0.01, 0.01], position=(0.2 * k, 0.0, 1.0)) for k in range(4)]
    joints = [Joint("j1", "revolute", None, "b1", parent_position=(0.2, 0, 1)),
              Joint("j0", "revolute", "b1", "b0", parent_position=(-0.2, 0, 0), axis=(0, 1, 0)),
              Joint("j2", "prismatic", "b1", "b2", parent_position=(0.2, 0, 0), axis=(1, 0, 0)),
              Joint("j3", "fixed", "b2", "b3", parent_position=(0.2, 0, 0)),
              Joint("ball", "spherical", None, "b0", parent_position=(0, 0, 1)),
              Joint("weld", "fixed", None, "b3", parent_position=(0.6, 0, 1)),
              Joint("line", "inline", None, "b2", parent_position=(0.4, 0, 0.7), axis=(0, 0, 1))]
    shapes = [Shape("ball_shape", "sphere", "b0", 0.05, friction=0.5), Shape("rod", "capsule", "b2", (0.02, 0.1)),
              Shape("block", "box", "b3", (0.05, 0.04, 0.03), position=(0, 0, 0.01)),
              Shape("can", "cylinder", "b1", (0.03, 0.05))]
    spec = MechanismSpec(bodies, joints, shapes=shapes, ground=GroundPlane(offset=-0.5, friction=0.9))
    meshes = {"b1": trimesh.creation.box(extents=(0.1, 0.02, 0.02))}
    path = write_mjcf(spec, tmp_path / "closures.xml", meshes=meshes)
    assert (tmp_path / "closures_b1.stl").is_file()
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    loops = spanning_tree(spec).loops
    assert sorted(j.type.name for j in loops) == ["FIXED", "INLINE", "SPHERICAL"]
    kinds = {model.equality(k).name: int(model.eq_type[k]) for k in range(model.neq)}
    assert kinds == {j.name: mujoco.mjtEq.mjEQ_WELD if j.type.name == "FIXED" else mujoco.mjtEq.mjEQ_CONNECT
                     for j in loops}
    for name in kinds:
        site1, site2 = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"{name}/{s}") for s in ("parent", "child"))
        assert np.allclose(data.site_xpos[site1], data.site_xpos[site2])
    assert model.npair == len(collision_pairs(spec))
    geoms = {model.geom(k).name: k for k in range(model.ngeom)}
    assert np.allclose(model.geom_size[geoms["rod"]][:2], [0.02, 0.1])
    assert np.allclose(model.geom_size[geoms["block"]], [0.05, 0.04, 0.03])
    pair = next(k for k in range(model.npair) if {int(model.pair_geom1[k]), int(model.pair_geom2[k])}
                == {geoms["ball_shape"], geoms["ground_plane"]})
    assert math.isclose(model.pair_friction[pair][0], math.sqrt(0.5 * 0.9))
    assert np.allclose(data.geom_xpos[geoms["ground_plane"]], [0, 0, -0.5])
    visual = geoms["b1/visual"]
    assert model.geom_group[visual] == 1 and model.geom_contype[visual] == 0 and model.geom_conaffinity[visual] == 0


def test_revolute_closure_uses_two_connects_along_the_axis():
    """A revolute loop closure is held by two connects, the second CLOSURE_AXIS_LENGTH along the axis."""
    model = mujoco.MjModel.from_xml_string(mjcf_string(passive_fourbar()))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    names = [model.equality(k).name for k in range(model.neq)]
    assert len(names) == 2 and names[1] == f"{names[0]}/axis"

    def site(name):
        return data.site_xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)]

    loop = names[0]
    assert np.allclose(site(f"{loop}/parent_axis"), site(f"{loop}/child_axis"))
    assert math.isclose(np.linalg.norm(site(f"{loop}/parent_axis") - site(f"{loop}/parent")), CLOSURE_AXIS_LENGTH)


def test_unsupported_input_is_refused_by_name():
    """A cylindrical loop closure, a driven loop closure, a body named 'world' and an unknown
    integrator raise ValueError naming them."""
    bodies = [Body("a", 1.0, [1, 1, 1]), Body("b", 1.0, [1, 1, 1])]
    joints = [Joint("ja", "revolute", None, "a"), Joint("ab", "revolute", "a", "b"),
              Joint("slider", "cylindrical", None, "b")]
    with pytest.raises(ValueError, match="joint 'slider'"):
        mjcf_string(MechanismSpec(bodies, joints))
    driven = [dataclasses.replace(j, drive=JointDrive(damping=1.0), type="revolute") for j in joints]
    with pytest.raises(ValueError, match="joint 'ab': closes a loop"):  # world joints enter the tree first
        mjcf_string(MechanismSpec(bodies, driven))
    with pytest.raises(ValueError, match="body 'world'"):
        mjcf_string(MechanismSpec([Body("world", 1.0, [1, 1, 1])]))
    with pytest.raises(ValueError, match="integrator"):
        mjcf_string(MechanismSpec(bodies[:1]), integrator="verlet")
