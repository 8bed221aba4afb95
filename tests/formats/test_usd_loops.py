"""USD loop closures as other importers read them: a planar linkage's loops are PhysicsRevoluteJoints
excluded from the articulation (as DR Legs writes its loops), every joint's coordinate is 0 at the
written state, and Newton (where installed: the bench extra) loads the file with add_usd and steps
it with its MuJoCo and Kamino solvers, the loops closed."""

import math

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdPhysics

from engine import JointType
from morphopt.build import build_spec
from morphopt.families import load_family
from morphopt.formats import export_design
from morphopt.formats.mjcf import MJCF_INTEGRATOR, MJCF_TIMESTEP
from morphopt.formats.tree import anchor_frames, frame, initial_rate, spanning_tree
from morphopt.formats.usd import read_usd, write_usd

LINKAGES = ["four_bar", "jansen_leg", "klann_leg", "watt_sixbar"]


def _world(stage, joint, side: int) -> np.ndarray:
    """World transform (4x4) of a UsdPhysics joint's frame on body0 (side 0) or body1 (side 1)."""
    targets = (joint.GetBody0Rel() if side == 0 else joint.GetBody1Rel()).GetTargets()
    body = np.eye(4)
    if targets:
        body = np.array(UsdGeom.Xformable(stage.GetPrimAtPath(targets[0])).ComputeLocalToWorldTransform(
            Usd.TimeCode.Default())).T
    position = (joint.GetLocalPos0Attr() if side == 0 else joint.GetLocalPos1Attr()).Get()
    rotation = (joint.GetLocalRot0Attr() if side == 0 else joint.GetLocalRot1Attr()).Get()
    im = rotation.GetImaginary()
    return body @ frame(tuple(position), (im[0], im[1], im[2], rotation.GetReal()))


@pytest.mark.parametrize("name", [*LINKAGES, "walker"])
def test_loops_are_revolute_joints_excluded_from_the_articulation(tmp_path, name):
    """Read back with usd-core: every loop closure is a PhysicsRevoluteJoint (no generic PhysicsJoint
    is left) with excludeFromArticulation, between the spec joint's bodies, its X axis on the
    spec's axis; every joint's two frames coincide at the written state (coordinate 0), the tree
    joints carry their initial rates (JointStateAPI) and the scene MuJoCo's stable integrator."""
    family = load_family(name)
    spec = build_spec(family, family.space.default(), None)
    path = export_design(family, family.space.default(), "usd", tmp_path, name=name)
    stage = Usd.Stage.Open(str(path))
    joints = {p.GetAttribute("morphopt:name").Get(): p for p in stage.Traverse() if p.IsA(UsdPhysics.Joint)}
    assert sorted(joints) == sorted(j.name for j in spec.joints)
    assert all(p.GetTypeName() == "PhysicsRevoluteJoint" for p in joints.values())
    loops = spanning_tree(spec, any_type=True).loops
    assert loops and {j.type for j in loops} == {JointType.INLINE}
    for joint in spec.joints:
        usd_joint = UsdPhysics.RevoluteJoint(joints[joint.name])
        assert usd_joint.GetExcludeFromArticulationAttr().Get() == (joint in loops), joint.name
        assert usd_joint.GetAxisAttr().Get() == "X"
        bodies = [str(t.name) for rel in (usd_joint.GetBody0Rel(), usd_joint.GetBody1Rel()) for t in rel.GetTargets()]
        assert bodies == [b for b in (joint.parent, joint.child) if b is not None], joint.name
        frame0, frame1 = _world(stage, usd_joint, 0), _world(stage, usd_joint, 1)
        assert np.allclose(frame0, frame1, atol=1e-6), joint.name  # coincide: coordinate 0
        axis = anchor_frames(spec, joint)[0][:3, :3] @ joint.axis
        assert np.allclose(frame0[:3, 0], axis, atol=1e-6), joint.name
        if joint not in loops:
            velocity = joints[joint.name].GetAttribute("state:angular:physics:velocity").Get()
            assert velocity == pytest.approx(math.degrees(initial_rate(spec, joint)), rel=1e-5, abs=1e-6)
    scene = next(p for p in stage.Traverse() if p.IsA(UsdPhysics.Scene))
    assert scene.GetAttribute("mjc:option:integrator").Get() == MJCF_INTEGRATOR
    assert scene.GetAttribute("mjc:option:timestep").Get() == MJCF_TIMESTEP


def test_spatial_inline_closures_stay_generic_joints(tmp_path):
    """An inline loop closure whose bodies the tree does not hold in a plane about its axis (a rail
    across it) is no revolute joint: a generic joint locking transY and transZ, read back as inline."""
    from tests.formats.test_usd import gadget

    spec = gadget()
    stage = Usd.Stage.Open(str(write_usd(spec, tmp_path / "gadget.usda")))
    loop = next(p for p in stage.Traverse() if p.IsA(UsdPhysics.Joint) and p.GetName() == "loop")
    assert loop.GetTypeName() == "PhysicsJoint" and loop.GetAttribute("morphopt:type").Get() == "inline"
    assert next(j for j in read_usd(tmp_path / "gadget.usda").joints if j.name == "loop").type == JointType.INLINE


# --- Newton (the bench extra) ---------------------------------------------------------------------

def _newton():
    return pytest.importorskip("newton", reason="Newton is not installed (pip install '.[bench]'); it reads the "
                                                "USD export with ModelBuilder.add_usd")


def _loop_error(model, state) -> float:
    """Largest distance [m] between the two anchors of a joint outside the articulation."""
    body_q = state.body_q.numpy()
    parent, child = model.joint_parent.numpy(), model.joint_child.numpy()
    X_p, X_c = model.joint_X_p.numpy(), model.joint_X_c.numpy()
    loops = np.flatnonzero(model.joint_articulation.numpy() < 0)
    assert len(loops)

    def point(transform, local):
        position, (x, y, z, w) = transform[:3], transform[3:7]
        u = np.array([x, y, z])
        return position + local + 2.0 * np.cross(u, np.cross(u, local) + w * local)

    world = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    return max(float(np.linalg.norm(point(body_q[parent[j]] if parent[j] >= 0 else world, X_p[j][:3])
                                     - point(body_q[child[j]], X_c[j][:3]))) for j in loops)


def _newton_run(newton, path, solver: str, seconds: float, dt: float) -> tuple[float, float]:
    """(largest loop opening [m], crank speed / drive target at the end) of ``seconds`` stepped by
    Newton from the state add_usd builds (coordinates 0: the written, assembled state; at rest)."""
    import warp as wp

    device = "cuda" if wp.is_cuda_available() else "cpu"
    builder = newton.ModelBuilder(up_axis=newton.Axis.Z)
    cls = newton.solvers.SolverMuJoCo if solver == "mujoco" else newton.solvers.SolverKamino
    cls.register_custom_attributes(builder)  # the scene's mjc:option:integrator for MuJoCo
    builder.add_usd(str(path))
    model = builder.finalize(device=device)
    if solver == "mujoco":
        assert int(model.mujoco.integrator.numpy()[0]) == 4  # "discrete", from the file
        engine = cls(model, use_mujoco_cpu=device == "cpu")
    else:
        engine = cls(model=model)
    state, next_state, control = model.state(), model.state(), model.control()
    newton.eval_fk(model, model.joint_q, model.joint_qd, state)
    worst = _loop_error(model, state)
    assert worst < 1e-5  # the written state is assembled
    for step in range(round(seconds / dt)):
        state.clear_forces()
        engine.step(state, next_state, control, None, dt)
        state, next_state = next_state, state
        if step % 20 == 0:
            assert np.isfinite(state.body_q.numpy()).all(), f"{solver}: NaN at {step * dt:.3f} s"
            worst = max(worst, _loop_error(model, state))
    newton.eval_ik(model, state, model.joint_q, model.joint_qd)
    driven = int(np.argmax(model.joint_target_kd.numpy()))  # the crank's dof
    return worst, float(model.joint_qd.numpy()[driven]) / float(model.joint_target_qd.numpy()[driven])


@pytest.mark.slow
@pytest.mark.parametrize("name", LINKAGES)
@pytest.mark.parametrize("solver, seconds, dt, tolerance", [("mujoco", 1.0, 1e-3, 2e-3), ("kamino", 0.3, 1e-3, 5e-4)])
def test_newton_steps_the_usd_with_its_loops_closed(tmp_path, name, solver, seconds, dt, tolerance):
    """Newton's add_usd reads the loops as joints to close (not joints without a degree of freedom)
    and the crank's velocity drive; its MuJoCo solver (loops as two connects each, MuJoCo's default
    softness, the file's "discrete" integrator) and Kamino keep them closed while the crank turns
    from rest. Measured on the CPU (Newton 1.8): MuJoCo 0.16-0.94 mm over 2 s, Kamino 0.043 mm
    (Jansen, 1 s)."""
    newton = _newton()
    family = load_family(name)
    path = export_design(family, family.space.default(), "usd", tmp_path, name=name)
    worst, speed = _newton_run(newton, path, solver, seconds, dt)
    assert worst < tolerance, f"{solver}: a loop opened by {worst:.3g} m"
    assert speed == pytest.approx(1.0, abs=0.05)  # the drive turns the crank at the study's speed
