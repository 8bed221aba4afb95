"""Compensated summation of the state (engine.integrate, engine.State's body_q_low and body_qd_low)
and float64 position errors of the joints (engine.joints.joint_frames). Oracles: exact float64
arithmetic, a dense NumPy joint residual, and the one-degree-of-freedom motion of parallel cranks
integrated by scipy."""

import math

import numpy as np
import pytest
import warp as wp

from benchmarks.stress import crank_reference, n_fourbar, parallel_linkage_constants
from engine import SolverConfig, pack_worlds, rollout
from engine.joints import JOINT_REVOLUTE, compute_joint_residuals
from engine.spatial import advance_pose, two_sum


@wp.kernel
def _two_sums(a: wp.array(dtype=float), b: wp.array(dtype=float), s: wp.array(dtype=float),
              e: wp.array(dtype=float)):
    i = wp.tid()
    x, y = two_sum(a[i], b[i])
    s[i] = x
    e[i] = y


def test_two_sum_returns_the_exact_rounding_error():
    """s + e equals a + b exactly (float64 holds every float32 sum exactly), whatever the ordering
    and magnitudes of a and b."""
    rng = np.random.default_rng(7)
    a = (rng.normal(size=4000) * 10.0 ** rng.integers(-8, 4, 4000)).astype(np.float32)
    b = (rng.normal(size=4000) * 10.0 ** rng.integers(-8, 4, 4000)).astype(np.float32)
    arrays = [wp.array(x, dtype=float, device="cpu") for x in (a, b)] + [wp.zeros(4000, dtype=float, device="cpu")
                                                                         for _ in range(2)]
    wp.launch(_two_sums, dim=4000, device="cpu", inputs=arrays)
    s, e = arrays[2].numpy().astype(np.float64), arrays[3].numpy().astype(np.float64)
    np.testing.assert_array_equal(s + e, a.astype(np.float64) + b.astype(np.float64))
    assert np.count_nonzero(e) > 1000  # the sums do round


@wp.kernel
def _advance(steps: int, h: float, v: wp.vec3, omega: wp.vec3, compensated: int, X: wp.array(dtype=wp.transform),
             low: wp.array(dtype=wp.transform)):
    pose = X[0]
    rest = low[0]
    for _ in range(steps):
        if compensated != 0:
            pose, rest = advance_pose(pose, rest, v, omega, h)
        else:  # plain float32 sums
            q = wp.transform_get_rotation(pose)
            angle = wp.length(omega) * h
            turn = wp.quat_from_axis_angle(omega / wp.length(omega), angle)
            pose = wp.transform(wp.transform_get_translation(pose) + h * v, wp.normalize(turn * q))
    X[0] = pose
    low[0] = rest


def test_compensated_pose_steps_follow_the_exact_motion_far_from_the_origin():
    """A body 40 m out, moving at 0.37 m/s and turning at 3.1 rad/s about y, 20000 steps of 1 ms:
    compensated steps land within 1e-9 m of the exact sum of the (float32) steps and within 1e-5
    rad of the turn, at unit norm; plain float32 sums drift by more than 1e-5 m (each step's
    3.7e-4 m is rounded to the 3.8e-6 m grid at 40 m)."""
    h, steps = 1e-3, 20000
    v, w = np.array([0.37, 0.0, -0.11]), 3.1
    start = np.array([40.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0])
    errors = {}
    for compensated in (1, 0):
        X = wp.array(start[None].astype(np.float32), dtype=wp.transform, device="cpu")
        low = wp.zeros(1, dtype=wp.transform, device="cpu")
        wp.launch(_advance, dim=1, device="cpu", inputs=[steps, h, wp.vec3(*v), wp.vec3(0.0, w, 0.0), compensated, X,
                                                           low])
        pose = X.numpy()[0].astype(np.float64) + low.numpy()[0]
        step = (np.float32(h) * v.astype(np.float32)).astype(np.float64)  # the float32 increment, exactly
        position = start[:3] + steps * step
        q = pose[3:]
        angle = (2.0 * math.atan2(q[1], q[3])) % (2 * math.pi)
        errors[compensated] = (np.abs(pose[:3] - position).max(), abs(angle - (steps * h * w) % (2 * math.pi)),
                               abs(np.linalg.norm(q) - 1.0))
    assert errors[1][0] < 1e-9 and errors[1][1] < 1e-5 and errors[1][2] < 1e-7, errors
    assert errors[0][0] > 1e-5, errors


def test_joint_position_errors_are_summed_in_float64_from_the_compensated_poses():
    """The IFToMM N = 40 four-bar (pivots up to 40 m out) at exactly closed float64 poses, given as
    float32 poses plus their low parts: the revolute joints' position residuals equal a float64
    NumPy evaluation (same float32 anchors) within 1e-10 m; from the float32 poses alone they are
    off by more than 1e-7 m (the 3.8e-6 m float32 grid 40 m out)."""
    spec = n_fourbar(40, 0.3, 1.0)
    model = pack_worlds([spec], device="cpu")
    rotations = np.array([body.orientation for body in spec.bodies], float)
    u, s = rotations[:, :3], rotations[:, 3:]

    def rotate(quat_u, quat_s, vec):
        return vec + 2.0 * np.cross(quat_u, np.cross(quat_u, vec) + quat_s * vec)

    coms = np.array([body.position for body in spec.bodies], float) + rotate(
        u, s, np.array([body.com for body in spec.bodies], float))
    exact = np.concatenate([coms, rotations], axis=1)
    high = exact.astype(np.float32)
    low = (exact - high.astype(np.float64)).astype(np.float32)
    residual = wp.zeros((1, model.max_rows), dtype=float, device="cpu")
    got = {}
    for name, poses, lows, flag in (("exact", high, low, True), ("float32", high, None, False)):
        body_q = wp.array(poses[None], dtype=wp.transform, device="cpu")
        body_q_low = None if lows is None else wp.array(lows[None], dtype=wp.transform, device="cpu")
        compute_joint_residuals(model, body_q, residual, body_q_low, exact=flag)
        got[name] = residual.numpy()[0].astype(np.float64)
    X_p, X_c = model.joint_X_p.numpy()[0].astype(np.float64), model.joint_X_c.numpy()[0].astype(np.float64)
    errors = {"exact": 0.0, "float32": 0.0}
    checked = 0
    for j in range(int(model.joint_count.numpy()[0])):
        if model.joint_type.numpy()[0, j] != JOINT_REVOLUTE:
            continue
        parent, child = model.joint_parent.numpy()[0, j], model.joint_child.numpy()[0, j]
        anchor_c = exact[child, :3] + rotate(exact[child, 3:6][None], exact[child, 6:][None], X_c[j, :3][None])[0]
        anchor_p = X_p[j, :3] if parent < 0 else exact[parent, :3] + rotate(
            exact[parent, 3:6][None], exact[parent, 6:][None], X_p[j, :3][None])[0]
        start = model.joint_row_start.numpy()[0, j]
        for name in errors:
            errors[name] = max(errors[name], np.abs(got[name][start:start + 3] - (anchor_c - anchor_p)).max())
        checked += 1
    assert checked == 81
    assert errors["exact"] < 1e-10 and errors["float32"] > 1e-7, errors


def test_parallel_cranks_keep_their_energy_and_phase_through_flat_passes():
    """IFToMM A02 with 20 four-bars (pivots up to 20 m out), cranks up at 1 m/s, 3 s at dt 1 ms:
    the motion passes the flat configuration (mobility 1 -> 21) twice; the first crank's tip stays
    within 2e-4 m of scipy's one-degree-of-freedom motion and the energy within 5e-5. With float32
    state and joint errors taken between float32 anchors (COM plus lever arm, rounded to the grid of
    positions up to 20 m out) it ended 1.1e-2 m off, having lost 2.6e-4 of its energy."""
    theta0, speed = -0.5 * math.pi, 1.0
    spec = n_fourbar(20, theta0, speed)
    model = pack_worlds([spec], device="cpu", dt=1e-3)
    trace, _ = rollout(model, model.state(), model.control(), 3000, record_every=10)
    reference = crank_reference(theta0, speed, trace.time, *parallel_linkage_constants(spec))
    assert np.sum(np.diff(np.sign(np.sin(reference))) != 0) >= 2  # the flat passes
    expected = np.stack([np.cos(reference), np.zeros_like(reference), -np.sin(reference)], axis=1)
    error = np.linalg.norm(trace.points[:, 0, 0] - expected, axis=1)
    energy = trace.energy[:, 0].astype(np.float64)
    assert error.max() < 2e-4, error.max()
    assert np.abs(energy - energy[0]).max() < 5e-5 * energy[0], np.abs(energy - energy[0]).max() / energy[0]


@pytest.mark.parametrize("compensated", [True, False])
def test_a_lone_crank_keeps_its_phase_for_ten_seconds(compensated):
    """One 1 m, 1 kg crank on a pin turning over under gravity, 10 s at dt 1 ms: within 1e-3 m of
    scipy's motion. With SolverConfig(compensated_state=False), float32 sums of the twist and pose,
    it ends more than 1e-3 m off (3.7e-3 m: each step's velocity change is rounded to the float32
    grid of the velocity itself) and the state's low parts stay zero."""
    theta0, speed = -0.5 * math.pi, 1.0
    spec = n_fourbar(0, theta0, speed)
    model = pack_worlds([spec], device="cpu", dt=1e-3, config=SolverConfig().tuned(compensated_state=compensated))
    trace, final = rollout(model, model.state(), model.control(), 10000, record_every=10)
    reference = crank_reference(theta0, speed, trace.time, *parallel_linkage_constants(spec))
    expected = np.stack([np.cos(reference), np.zeros_like(reference), -np.sin(reference)], axis=1)
    error = np.linalg.norm(trace.points[:, 0, 0] - expected, axis=1)
    lows = np.abs(final.body_q_low.numpy()).max() + np.abs(final.body_qd_low.numpy()).max()
    if compensated:
        assert error.max() < 1e-3 and lows > 0.0, (error.max(), lows)
    else:
        assert error.max() > 1e-3 and lows == 0.0, (error.max(), lows)
