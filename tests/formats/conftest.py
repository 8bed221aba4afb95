"""The oracle of the format round trips: two MechanismSpecs describe the same mechanism when every
body, shape, joint and tracked point agrees in world terms at the initial state.

Formats may choose other frames than the original spec (URDF puts a link's frame on its joint
axis, USD joints name their axis X, Y or Z) and may run a tree joint from the spec's child to its
parent, so the comparison is made in the world frame: masses, centres of mass and inertia tensors
in world axes, joint anchor points and axes in the world, joint limits and drive targets measured
from the initial state, with the sign of the joint coordinate taken into account.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine import JointType, MechanismSpec
from morphopt.formats.tree import anchor_frames, body_frame, frame, initial_coordinate


def _body_world(spec, body):
    T = body_frame(spec, body.name)
    R = T[:3, :3]
    return T[:3, :3] @ body.com + T[:3, 3], R @ body.inertia @ R.T


def _close(a, b, tol, what):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape and np.allclose(a, b, rtol=0.0, atol=tol), f"{what}: {a.tolist()} != {b.tolist()}"


def _interval(lower, upper, q0, sign):
    """Limits measured from the initial state, in the coordinate of sign `sign`."""
    lo, hi = lower - q0, upper - q0
    return (lo, hi) if sign > 0 else (-hi, -lo)


def assert_same_mechanism(a: MechanismSpec, b: MechanismSpec, tol: float = 1e-6, *, shapes: bool = True,
                          points: bool = True) -> None:
    """Assert that b describes the mechanism of a (see the module docstring); names must match."""
    assert sorted(x.name for x in a.bodies) == sorted(x.name for x in b.bodies), "bodies differ"
    for body in a.bodies:
        other = b.bodies[b.body_index[body.name]]
        assert math.isclose(body.mass, other.mass, rel_tol=tol), f"body '{body.name}': mass {body.mass} != {other.mass}"
        com_a, inertia_a = _body_world(a, body)
        com_b, inertia_b = _body_world(b, other)
        _close(com_a, com_b, tol, f"body '{body.name}': world centre of mass")
        _close(inertia_a, inertia_b, tol * max(1.0, np.abs(inertia_a).max()), f"body '{body.name}': world inertia")
    _close(a.gravity, b.gravity, tol, "gravity")
    assert sorted(j.name for j in a.joints) == sorted(j.name for j in b.joints), \
        f"joints differ: {sorted(j.name for j in a.joints)} != {sorted(j.name for j in b.joints)}"
    joints_b = {j.name: j for j in b.joints}
    for ja in a.joints:
        jb = joints_b[ja.name]
        where = f"joint '{ja.name}'"
        assert ja.type == jb.type, f"{where}: type {ja.type.name} != {jb.type.name}"
        assert {ja.parent, ja.child} == {jb.parent, jb.child}, f"{where}: bodies differ"
        swapped = jb.parent != ja.parent
        pa, ca = anchor_frames(a, ja)
        pb, cb = anchor_frames(b, jb)
        if swapped:
            pb, cb = cb, pb
        _close(pa[:3, 3], pb[:3, 3], tol, f"{where}: world anchor on '{ja.parent}'")
        _close(ca[:3, 3], cb[:3, 3], tol, f"{where}: world anchor on '{ja.child}'")
        if ja.type == JointType.FIXED:
            _close(ca[:3, :3] @ pa[:3, :3].T, cb[:3, :3] @ pb[:3, :3].T, tol, f"{where}: relative rotation")
            continue
        if ja.type == JointType.SPHERICAL:
            continue
        axis_a = pa[:3, :3] @ ja.axis
        axis_b = anchor_frames(b, jb)[0][:3, :3] @ jb.axis  # on b's own parent side
        direction = float(axis_a @ axis_b)
        assert abs(abs(direction) - 1.0) < tol, f"{where}: world axis {axis_a.tolist()} vs {axis_b.tolist()}"
        sign = (1.0 if direction > 0 else -1.0) * (-1.0 if swapped else 1.0)  # q_b = sign q_a (about initial)
        if ja.type not in (JointType.REVOLUTE, JointType.PRISMATIC):
            continue
        q0a, q0b = initial_coordinate(a, ja), initial_coordinate(b, jb)
        lim_a = _interval(ja.limit_lower, ja.limit_upper, q0a, sign)
        lim_b = _interval(jb.limit_lower, jb.limit_upper, q0b, 1.0)
        for x, y in zip(lim_a, lim_b):
            assert (math.isinf(x) and x == y) or math.isclose(x, y, abs_tol=tol), f"{where}: limits {lim_a} != {lim_b}"
        assert math.isclose(ja.armature, jb.armature, abs_tol=tol) and math.isclose(ja.damping, jb.damping, abs_tol=tol), \
            f"{where}: armature/damping differ"
        assert (ja.drive is None) == (jb.drive is None), f"{where}: drive present in one only"
        if ja.drive is not None:
            da, db = ja.drive, jb.drive
            assert math.isclose(da.stiffness, db.stiffness, rel_tol=tol) and math.isclose(da.damping, db.damping,
                                                                                         rel_tol=tol), f"{where}: gains"
            assert da.effort_limit == db.effort_limit or math.isclose(da.effort_limit, db.effort_limit, rel_tol=tol)
            assert math.isclose(sign * (da.target_position - q0a), db.target_position - q0b, abs_tol=tol), \
                f"{where}: drive target position"
            assert math.isclose(sign * da.target_velocity, db.target_velocity, abs_tol=tol), \
                f"{where}: drive target velocity"
    if shapes:
        assert sorted(s.name for s in a.shapes) == sorted(s.name for s in b.shapes), "shapes differ"
        shapes_b = {s.name: s for s in b.shapes}
        for sa in a.shapes:
            sb = shapes_b[sa.name]
            assert sa.type == sb.type and sa.body == sb.body, f"shape '{sa.name}' differs"
            _close(sa.size, sb.size, tol, f"shape '{sa.name}': size")
            Ta = body_frame(a, sa.body) @ frame(sa.position, sa.orientation)
            Tb = body_frame(b, sb.body) @ frame(sb.position, sb.orientation)
            _close(Ta[:3, 3], Tb[:3, 3], tol, f"shape '{sa.name}': world position")
            _close(Ta[:3, 2], Tb[:3, 2], tol, f"shape '{sa.name}': world z axis")
            if sa.type == 2:  # boxes: every axis up to sign
                _close(np.abs(Ta[:3, :3]), np.abs(Tb[:3, :3]), tol, f"shape '{sa.name}': world axes")
    if points:
        assert sorted(p.name for p in a.points) == sorted(p.name for p in b.points), "tracked points differ"
        points_b = {p.name: p for p in b.points}
        for pa_ in a.points:
            pb_ = points_b[pa_.name]
            wa = body_frame(a, pa_.body) @ np.append(pa_.position, 1.0)
            wb = body_frame(b, pb_.body) @ np.append(pb_.position, 1.0)
            _close(wa[:3], wb[:3], tol, f"tracked point '{pa_.name}': world position")


@pytest.fixture
def same_mechanism():
    """assert_same_mechanism(a, b, tol=1e-6, *, shapes=True, points=True) as a fixture."""
    return assert_same_mechanism
