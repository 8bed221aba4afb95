"""Spatial math: quaternions, rotations, twists as @wp.func for the kernels, and a host section
(NumPy, float64) with the rotations the set-up code shares.

Conventions (see engine.model): quaternions in Warp's (x, y, z, w) order; a twist is a
``wp.spatial_vector`` (v, w) with the linear part first: ``wp.spatial_top`` is the linear
velocity of the centre of mass [m/s] and ``wp.spatial_bottom`` the angular velocity [rad/s],
both in the world frame.
"""

from typing import Any

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only


@wp.func
def twist(linear: wp.vec3, angular: wp.vec3):
    """Pack a (linear, angular) pair into a spatial vector."""
    return wp.spatial_vector(linear[0], linear[1], linear[2], angular[0], angular[1], angular[2])


@wp.func
def quat_integrate(q: wp.quat, omega: wp.vec3, h: float):
    """Rotate q by the world-frame angular velocity omega over time h (exponential map), normalized."""
    angle = wp.length(omega) * h
    if angle < 1.0e-12:
        return q
    axis = omega / wp.length(omega)
    return wp.normalize(wp.quat_from_axis_angle(axis, angle) * q)


@wp.func
def pose_step(X: wp.transform, u: wp.spatial_vector, h: float):
    """The pose X moved by h times the twist u: translation plus h v, rotation exp(h w) q (float32,
    normalized)."""
    return wp.transform(wp.transform_get_translation(X) + h * wp.spatial_top(u),
                        quat_integrate(wp.transform_get_rotation(X), wp.spatial_bottom(u), h))


@wp.func
def two_sum(a: Any, b: Any):
    """Knuth's TwoSum, componentwise: s = fl(a + b) and its rounding error e, with a + b = s + e
    exactly (no ordering of |a| and |b| needed)."""
    s = a + b
    t = s - a
    e = (a - (s - t)) + (b - t)
    return s, e


@wp.func
def quat_increment(q: wp.quat, omega: wp.vec3, h: float):
    """exp(h omega) q - q for the world-frame angular velocity omega: the change of q over h, with
    cos - 1 written as -2 sin^2 so that small rotations keep their digits."""
    speed = wp.length(omega)
    angle = speed * h
    if angle < 1.0e-12:
        return wp.quat(0.0, 0.0, 0.0, 0.0)
    s = wp.sin(0.5 * angle) / speed
    c = wp.sin(0.25 * angle)
    return wp.quat(s * omega[0], s * omega[1], s * omega[2], -2.0 * c * c) * q


@wp.func
def advance_pose(X: wp.transform, low: wp.transform, v: wp.vec3, omega: wp.vec3, h: float):
    """Compensated pose step: the pose X + low (low: the parts float32 X could not hold, its
    rotation a raw quaternion difference) moved by h v and turned by exp(h omega), returned as a
    new (X, low) pair. The rotation's norm is pulled back to 1 by a first-order radial scaling
    (the rotation is unchanged), so that rounding cannot scale the lever arms (left alone: 1e-6
    over 20 s at dt 1 ms)."""
    t, t_low = two_sum(wp.transform_get_translation(X), wp.transform_get_translation(low) + h * v)
    q = wp.transform_get_rotation(X)
    r, r_low = two_sum(q, wp.transform_get_rotation(low) + quat_increment(q, omega, h))
    excess = (wp.dot(r, r) - 1.0) + 2.0 * wp.dot(r, r_low)  # |r + r_low|^2 - 1
    r, r_low = two_sum(r, r_low - (0.5 * excess) * r)
    return wp.transform(t, r), wp.transform(t_low, r_low)


@wp.func
def skew(v: wp.vec3):
    """Cross-product matrix: skew(v) @ x == cross(v, x)."""
    return wp.mat33(0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0)


@wp.func
def world_inertia_inverse(q: wp.quat, inertia_inv_body: wp.mat33):
    """Inverse inertia in the world frame: R I^-1 R^T."""
    r = wp.quat_to_matrix(q)
    return r * inertia_inv_body * wp.transpose(r)


@wp.func
def gyroscopic_implicit_midpoint(omega: wp.vec3, inertia: wp.mat33, h: float):
    """Change of the body-frame angular velocity over a torque-free step of Euler's equations.

    Solves I d + h * wm x (I wm) = 0 for d = w1 - w0 with wm = w0 + d / 2 by three Newton steps.
    The implicit midpoint rule keeps |I w| and the rotational kinetic energy exactly (an explicit
    gyroscopic term feeds energy into a body spinning about its intermediate axis). The change,
    not w1, is returned, so that a body turning about a principal axis (d = 0) keeps its
    world-frame velocity bit for bit instead of the rounding of a round trip to the body frame.
    """
    d = wp.vec3(0.0)
    for _it in range(3):
        wm = omega + 0.5 * d
        lm = inertia * wm
        f = inertia * d + h * wp.cross(wm, lm)
        jac = inertia + 0.5 * h * (skew(wm) * inertia - skew(lm))
        d = d - wp.inverse(jac) * f
    return d


@wp.func
def relative_rotation(q_parent: wp.quat, q_child: wp.quat):
    """Child frame orientation relative to the parent frame, on the w >= 0 hemisphere."""
    q_rel = wp.quat_inverse(q_parent) * q_child
    if q_rel[3] < 0.0:
        q_rel = wp.quat(-q_rel[0], -q_rel[1], -q_rel[2], -q_rel[3])
    return q_rel


@wp.func
def hinge_angle(q_parent: wp.quat, q_child: wp.quat, axis: wp.vec3):
    """The angle [rad] of the child frame about ``axis`` (in the parent frame) relative to the parent."""
    q_rel = relative_rotation(q_parent, q_child)
    return 2.0 * wp.atan2(wp.dot(wp.vec3(q_rel[0], q_rel[1], q_rel[2]), axis), q_rel[3])


@wp.func
def spring_tension(coef: wp.vec4, gap: wp.vec3, relative_velocity: wp.vec3):
    """A spring-damper's unit direction n from its first point to its second (gap: second - first)
    and its tension T = k (L - L0) + c dL/dt (coef: k, c, L0, tension only), positive pulling the
    points together; T = 0 without a direction (L < 1e-9 m) and, tension-only, while slack or
    pushing."""
    length = wp.length(gap)
    stretch = length - coef[2]
    tension_only = coef[3] != 0.0
    if length < 1.0e-9 or (tension_only and stretch < 0.0):
        return wp.vec3(), 0.0
    n = gap / length
    tension = coef[0] * stretch + coef[1] * wp.dot(n, relative_velocity)
    if tension_only:
        tension = wp.max(tension, 0.0)
    return n, tension


@wp.func
def wrap_angle(a: float):
    """Map an angle [rad] to (-pi, pi]."""
    return wp.atan2(wp.sin(a), wp.cos(a))


# -- host side (NumPy, float64) ------------------------------------------------------------------
# the layouts' bit-for-bit tests (tests/engine/test_tabulated_paths.py) rely on these exact formulas


def cross(a, b) -> np.ndarray:
    """a x b over the last axis of arrays (broadcast); np.cross's arithmetic, without its overhead."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two float64 3-vectors: np.cross's arithmetic in Python floats (the same bits, checked
    on 200,000 random pairs) at a thirtieth of its cost on single vectors (the tree plan's set-up
    takes one per loop row and joint); other dtypes go to np.cross."""
    if a.dtype != np.float64 or b.dtype != np.float64:
        return np.cross(a, b)
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def rotate(quat, vec) -> np.ndarray:
    """vec (..., 3) rotated by the unit quaternion quat (..., 4), (x, y, z, w)."""
    u, s = quat[..., :3], quat[..., 3:]
    return vec + 2.0 * cross(u, cross(u, vec) + s * vec)


def quat_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
