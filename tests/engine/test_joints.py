"""Joint rows: every Jacobian row is the time derivative of its residual (central differences)."""

import numpy as np
import pytest
import warp as wp

from engine import Body, Joint, JointDrive, JointType, MechanismSpec, pack_worlds
from engine.joints import compute_joint_residuals, compute_joint_rows


def random_quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def quat_mul(a, b):
    av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), [aw * bw - av @ bv]])


def integrate(body_q, body_qd, h):
    """x + h v, exp(h w) q per body (world-frame angular velocity), as the engine does."""
    out = body_q.copy()
    for b in range(body_q.shape[0]):
        out[b, :3] = body_q[b, :3] + h * body_qd[b, :3]
        rot = h * body_qd[b, 3:]
        angle = np.linalg.norm(rot)
        dq = np.concatenate([np.sin(angle / 2) * rot / angle, [np.cos(angle / 2)]]) if angle > 0 else np.array([0, 0, 0, 1.0])
        q = quat_mul(dq, body_q[b, 3:])
        out[b, 3:] = q / np.linalg.norm(q)
    return out


def joint_spec(joint_type, rng, world_parent):
    bodies = [Body(name, 1.0 + rng.random(), np.diag(0.5 + 0.5 * rng.random(3)), com=0.1 * rng.normal(size=3),
                   position=0.3 * rng.normal(size=3), orientation=random_quat(rng)) for name in ("p", "c")]
    drive = JointDrive(stiffness=1.0) if joint_type in (JointType.REVOLUTE, JointType.PRISMATIC) else None
    axis = rng.normal(size=3)
    axis2 = np.cross(axis, rng.normal(size=3))
    joint = Joint("j", joint_type, None if world_parent else "p", "c", parent_position=0.2 * rng.normal(size=3),
                  parent_orientation=random_quat(rng), child_position=0.2 * rng.normal(size=3),
                  child_orientation=random_quat(rng), axis=axis, axis2=axis2, drive=drive)
    if drive is not None:
        # the joint coordinate is defined on the rotational manifold: align the anchor frames up to a
        # rotation about the axis (positions stay random)
        theta = rng.uniform(-2.0, 2.0)
        about_axis = np.concatenate([np.sin(theta / 2) * joint.axis, [np.cos(theta / 2)]])
        parent_q = np.array([0, 0, 0, 1.0]) if world_parent else bodies[0].orientation
        target = quat_mul(quat_mul(parent_q, joint.parent_orientation), about_axis)
        child_inv = joint.child_orientation * np.array([-1, -1, -1, 1.0])
        bodies[1].orientation = quat_mul(target, child_inv)
    return MechanismSpec(bodies, [joint])


@pytest.mark.parametrize("world_parent", [False, True], ids=["body_parent", "world_parent"])
@pytest.mark.parametrize("joint_type", list(JointType), ids=[t.name.lower() for t in JointType])
def test_jacobian_matches_finite_differences(joint_type, world_parent, device):
    """d(phi)/dt along a random twist equals J_c . u_c + J_p . u_p for every row (and the drive row
    matches the derivative of the joint coordinate)."""
    rng = np.random.default_rng(int(joint_type) * 7 + int(world_parent))
    spec = joint_spec(joint_type, rng, world_parent)
    dt = 0.01
    model = pack_worlds([spec], device=device, dt=dt)
    state, control = model.state(), model.control()
    body_q = state.body_q.numpy()[0].astype(np.float64)
    body_qd = rng.normal(size=(2, 6))
    state.body_qd.assign(body_qd[None].astype(np.float32))
    compute_joint_rows(model, state.body_q, state.body_qd, control)
    work = model.work
    n = int(model.row_count.numpy()[0])
    J_c, J_p = work.row_J_c.numpy()[0, :n], work.row_J_p.numpy()[0, :n]
    parent = -1 if world_parent else 0
    rate = J_c @ body_qd[1] + (J_p @ body_qd[0] if parent >= 0 else 0.0)

    h = 1e-3
    residual = wp.zeros((1, model.max_rows), dtype=float, device=device)
    values, coordinates = [], []
    for sign in (1.0, -1.0):
        q = integrate(body_q, body_qd, sign * h)
        compute_joint_residuals(model, wp.array(q[None].astype(np.float32), dtype=wp.transform, device=device), residual)
        values.append(residual.numpy()[0, :n].astype(np.float64))
        compute_joint_rows(model, wp.array(q[None].astype(np.float32), dtype=wp.transform, device=device),
                           state.body_qd, control)
        coordinates.append(-work.row_bias.numpy()[0, n - 1] * dt)  # drive row bias = -q / dt (kp = 1)
    fd = (values[0] - values[1]) / (2 * h)
    bilateral = n - 1 if spec.joints[0].drive is not None else n
    assert np.abs(fd[:bilateral] - rate[:bilateral]).max() < 2e-3 * max(1.0, np.abs(rate).max())
    if spec.joints[0].drive is not None:
        fd_coordinate = (coordinates[0] - coordinates[1]) / (2 * h)
        assert abs(fd_coordinate - rate[n - 1]) < 2e-3 * max(1.0, abs(rate[n - 1]))


def test_assembled_joint_has_zero_residual(device):
    """A revolute joint whose anchors coincide and whose axes align has phi = 0 on every row."""
    bodies = [Body("a", 1.0, (0.1, 0.1, 0.1), position=(0.0, 0.0, 0.0)), Body("b", 1.0, (0.1, 0.1, 0.1), position=(1.0, 0, 0))]
    joint = Joint("hinge", "revolute", "a", "b", parent_position=(0.5, 0, 0), child_position=(-0.5, 0, 0), axis=(0, 1, 0))
    model = pack_worlds([MechanismSpec(bodies, [joint])], device=device)
    residual = wp.zeros((1, model.max_rows), dtype=float, device=device)
    compute_joint_residuals(model, model.state().body_q, residual)
    assert np.abs(residual.numpy()[0, :5]).max() < 1e-7


def test_joint_kernels_by_part_give_the_rows_of_whole_joints():
    """A thread per part of a joint (the GPU's layout, engine.joints.joint_parts) writes exactly
    the rows of a thread per joint (the CPU's): every joint type, drives, limits and armature rows,
    with the worlds' joint counts differing."""
    import dataclasses

    from engine import joints as J

    rng = np.random.default_rng(5)
    specs = []
    for k, joint_type in enumerate(JointType):
        spec = joint_spec(joint_type, rng, world_parent=k % 2 == 0)
        extra = {}
        if joint_type in (JointType.REVOLUTE, JointType.PRISMATIC):  # the types with a coordinate
            extra = dict(limit_lower=-0.3, limit_upper=0.2, armature=0.01 * k, damping=0.02)
        joint = dataclasses.replace(spec.joints[0], **extra)
        specs.append(dataclasses.replace(spec, joints=[dataclasses.replace(joint, name=f"j{n}")
                                                       for n in range(1 + k % 3)]))
    model = pack_worlds(specs, device="cpu")
    state, control = model.state(), model.control()
    state.body_qd.assign(rng.normal(size=(len(specs), model.max_bodies, 6)).astype(np.float32))
    outputs = {}
    for parts in (1, int(J.JOINT_PARTS)):
        work = model.work
        for name in ("row_J_c", "row_J_p", "row_bias", "row_compliance", "row_lo", "row_hi", "row_residual"):
            getattr(work, name).fill_(7.0)  # rows nobody writes keep it in both runs
        original = J.joint_parts
        J.joint_parts = lambda device, parts=parts: parts
        try:
            compute_joint_rows(model, state.body_q, state.body_qd, control)
            rows = {name: getattr(work, name).numpy().copy() for name in
                    ("row_J_c", "row_J_p", "row_bias", "row_compliance", "row_lo", "row_hi", "row_residual")}
        finally:
            J.joint_parts = original
        outputs[parts] = rows
    for name, whole in outputs[1].items():
        np.testing.assert_array_equal(outputs[int(J.JOINT_PARTS)][name], whole, err_msg=name)
    assert np.abs(outputs[1]["row_residual"]).max() > 1e-3  # random poses: the joints are far from assembled
    assert (outputs[1]["row_compliance"] != 7.0).sum() > len(specs) * 3  # rows were written
