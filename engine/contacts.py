"""Contact rows: one normal and two tangent rows per contact, warm-started by contact key.

For contact k of a world, rows contact_row_start + 3k (normal n, from body b to body a), +1 and
+2 (tangents t1, t2 = normal_basis(n)). Row velocity = relative velocity of the contact points
along the row direction (a minus b). The normal row asks for
    v_n+ >= -d / dt                              (separated by d > 0: may close the gap, no more)
    v_n+ >= contact_stabilization * (-d) / dt    (penetrating by -d: pushed out over a few steps)
    v_n+ >= -e v_n-                              (Newton restitution when the contact closes this
                                                  step at more than restitution_threshold)
and the triplet of impulses lies in the Coulomb cone |lambda_t| <= mu lambda_n (projection in
engine.padmm, with the De Saxce correction). Friction combines per pair by the geometric mean,
restitution by the maximum (engine.collide).
"""

import warp as wp

from engine.joints import body_twist, normal_basis
from engine.model import UNBOUNDED
from engine.spatial import twist

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only


@wp.func
def contact_direction(n: wp.vec3, component: int):
    """Row direction: the normal (0) or a tangent (1, 2)."""
    if component == 0:
        return n
    return normal_basis(n, component - 1)


@wp.func
def body_origin(body_q: wp.array2d(dtype=wp.transform), world: int, body: int):
    """Position of the body's frame origin; the world origin for the ground (body < 0)."""
    if body < 0:
        return wp.vec3(0.0)
    return wp.transform_get_translation(body_q[world, body])


@wp.kernel
def contact_rows(
    # model
    contact_row_start: wp.array(dtype=wp.int32),
    world_dt: wp.array(dtype=float),
    stabilization: float,
    restitution_threshold: float,
    # in
    body_q: wp.array2d(dtype=wp.transform),
    body_qd: wp.array2d(dtype=wp.spatial_vector),
    contact_count: wp.array(dtype=wp.int32),
    contact_body_a: wp.array2d(dtype=wp.int32),
    contact_body_b: wp.array2d(dtype=wp.int32),
    contact_point_a: wp.array2d(dtype=wp.vec3),
    contact_point_b: wp.array2d(dtype=wp.vec3),
    contact_normal: wp.array2d(dtype=wp.vec3),
    contact_distance: wp.array2d(dtype=float),
    contact_friction: wp.array2d(dtype=float),
    contact_restitution: wp.array2d(dtype=float),
    # out
    row_body_c_out: wp.array2d(dtype=wp.int32),
    row_body_p_out: wp.array2d(dtype=wp.int32),
    row_J_c_out: wp.array2d(dtype=wp.spatial_vector),
    row_J_p_out: wp.array2d(dtype=wp.spatial_vector),
    row_bias_out: wp.array2d(dtype=float),
    row_compliance_out: wp.array2d(dtype=float),
    row_lo_out: wp.array2d(dtype=float),
    row_hi_out: wp.array2d(dtype=float),
    row_friction_out: wp.array2d(dtype=float),
):
    """Jacobian, bias and bounds of the three rows of every contact."""
    world, k = wp.tid()
    if k >= contact_count[world]:
        return
    a = contact_body_a[world, k]
    b = contact_body_b[world, k]
    n = contact_normal[world, k]
    r_a = contact_point_a[world, k] - body_origin(body_q, world, a)
    r_b = contact_point_b[world, k] - body_origin(body_q, world, b)
    dt = world_dt[world]
    d = contact_distance[world, k]
    start = contact_row_start[world] + 3 * k
    for component in range(3):
        direction = contact_direction(n, component)
        J_a = twist(direction, wp.cross(r_a, direction))
        J_b = twist(-direction, -wp.cross(r_b, direction))
        if b < 0:
            J_b = wp.spatial_vector()
        row = start + component
        row_body_c_out[world, row] = a
        row_body_p_out[world, row] = b
        row_J_c_out[world, row] = J_a
        row_J_p_out[world, row] = J_b
        row_compliance_out[world, row] = 0.0
        row_friction_out[world, row] = contact_friction[world, k]
        bias = float(0.0)
        lo = -UNBOUNDED
        if component == 0:
            lo = 0.0
            approach = wp.dot(J_a, body_twist(body_qd, world, a)) + wp.dot(J_b, body_twist(body_qd, world, b))
            if d > 0.0:
                bias = -d / dt
            else:
                bias = stabilization * (-d) / dt
            if approach < -restitution_threshold and d + dt * approach < 0.0:
                bias = wp.max(bias, -contact_restitution[world, k] * approach)
        row_bias_out[world, row] = bias
        row_lo_out[world, row] = lo
        row_hi_out[world, row] = UNBOUNDED


@wp.kernel
def gather_warmstart(
    contact_row_start: wp.array(dtype=wp.int32),
    row_count: wp.array(dtype=wp.int32),
    row_lambda_in: wp.array2d(dtype=float),
    contact_key: wp.array2d(dtype=wp.int32),
    contact_normal: wp.array2d(dtype=wp.vec3),
    previous_count: wp.array(dtype=wp.int32),
    previous_key: wp.array2d(dtype=wp.int32),
    previous_impulse: wp.array2d(dtype=wp.vec3),
    # out
    warm_out: wp.array2d(dtype=float),
):
    """Warm-start impulses: joint rows from the last step; contacts matched by key, projected on
    this step's normal and tangents; new contacts start at zero."""
    world, row = wp.tid()
    start = contact_row_start[world]
    value = float(0.0)
    if row < start:
        value = row_lambda_in[world, row]
    elif row < row_count[world]:
        k = (row - start) // 3
        key = contact_key[world, k]
        for p in range(previous_count[world]):
            if previous_key[world, p] == key:
                value = wp.dot(previous_impulse[world, p], contact_direction(contact_normal[world, k], (row - start) % 3))
    warm_out[world, row] = value


@wp.kernel
def store_contacts(
    contact_row_start: wp.array(dtype=wp.int32),
    contact_count: wp.array(dtype=wp.int32),
    contact_key: wp.array2d(dtype=wp.int32),
    contact_normal: wp.array2d(dtype=wp.vec3),
    row_lambda: wp.array2d(dtype=float),
    # out
    count_out: wp.array(dtype=wp.int32),
    key_out: wp.array2d(dtype=wp.int32),
    impulse_out: wp.array2d(dtype=wp.vec3),
):
    """Keep this step's contacts and their world-frame impulses [N s] for the next warm start."""
    world, k = wp.tid()
    count = contact_count[world]
    if k == 0:
        count_out[world] = count
    if k >= count:
        return
    start = contact_row_start[world] + 3 * k
    n = contact_normal[world, k]
    impulse = wp.vec3(0.0)
    for component in range(3):
        impulse += row_lambda[world, start + component] * contact_direction(n, component)
    key_out[world, k] = contact_key[world, k]
    impulse_out[world, k] = impulse


__all__ = ["contact_rows", "gather_warmstart", "store_contacts"]
