"""Spatial math as @wp.func only: quaternions, rotations, twists.

Conventions (see engine.model): quaternions in Warp's (x, y, z, w) order; a twist is a
``wp.spatial_vector`` (v, w) with the linear part first: ``wp.spatial_top`` is the linear
velocity of the centre of mass [m/s] and ``wp.spatial_bottom`` the angular velocity [rad/s],
both in the world frame.
"""

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
def quat_rotate_vector(q: wp.quat, rotation_vector: wp.vec3):
    """Rotate q by the finite rotation vector (axis * angle) given in the world frame."""
    return quat_integrate(q, rotation_vector, 1.0)


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
    The implicit midpoint rule keeps |I w| and the rotational kinetic energy exactly, which an
    explicit gyroscopic term does not (it feeds energy into a body spinning about its
    intermediate axis). The change, not w1, is returned: the caller adds it to the world-frame
    velocity, so a body turning about a principal axis (d = 0) keeps its velocity bit for bit
    instead of taking the rounding of a rotation to the body frame and back (with float32
    quaternions a steady gain of about one ulp of w per step).
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
def wrap_angle(a: float):
    """Map an angle [rad] to (-pi, pi]."""
    return wp.atan2(wp.sin(a), wp.cos(a))
