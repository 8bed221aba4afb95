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
from engine.model import UNBOUNDED, ContactArrays, ModelArrays, WorkArrays
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
def contact_rows(m: ModelArrays, w: WorkArrays, c: ContactArrays, stabilization: float, restitution_threshold: float,
                 body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector)):
    """Bodies, Jacobian, bias and bounds of the three rows of every contact of c, into w."""
    world, k = wp.tid()
    if k >= c.contact_count[world]:
        return
    a = c.contact_body_a[world, k]
    b = c.contact_body_b[world, k]
    n = c.contact_normal[world, k]
    r_a = c.contact_point_a[world, k] - body_origin(body_q, world, a)
    r_b = c.contact_point_b[world, k] - body_origin(body_q, world, b)
    dt = m.world_dt[world]
    d = c.contact_distance[world, k]
    start = m.contact_row_start[world] + 3 * k
    for component in range(3):
        direction = contact_direction(n, component)
        J_a = twist(direction, wp.cross(r_a, direction))
        J_b = twist(-direction, -wp.cross(r_b, direction))
        if b < 0:
            J_b = wp.spatial_vector()
        row = start + component
        w.row_body_c[world, row] = a
        w.row_body_p[world, row] = b
        w.row_J_c[world, row] = J_a
        w.row_J_p[world, row] = J_b
        w.row_compliance[world, row] = 0.0
        w.row_friction[world, row] = c.contact_friction[world, k]
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
                bias = wp.max(bias, -c.contact_restitution[world, k] * approach)
        w.row_bias[world, row] = bias
        w.row_lo[world, row] = lo
        w.row_hi[world, row] = UNBOUNDED


@wp.kernel
def gather_warmstart(m: ModelArrays, w: WorkArrays, c: ContactArrays, row_lambda_in: wp.array2d(dtype=float),
                     previous_count: wp.array(dtype=wp.int32), previous_key: wp.array2d(dtype=wp.int32),
                     previous_impulse: wp.array2d(dtype=wp.vec3)):
    """Warm-start impulses into w.warm: joint rows from the last step's row_lambda_in; contacts
    matched by key to the last step's (previous_*), projected on this step's normal and tangents;
    new contacts start at zero."""
    world, row = wp.tid()
    start = m.contact_row_start[world]
    value = float(0.0)
    if row < start:
        value = row_lambda_in[world, row]
    elif row < w.row_count[world]:
        k = (row - start) // 3
        key = c.contact_key[world, k]
        for p in range(previous_count[world]):
            if previous_key[world, p] == key:
                value = wp.dot(previous_impulse[world, p], contact_direction(c.contact_normal[world, k],
                                                                             (row - start) % 3))
    w.warm[world, row] = value


@wp.kernel
def store_contacts(m: ModelArrays, c: ContactArrays, row_lambda: wp.array2d(dtype=float),
                   count_out: wp.array(dtype=wp.int32), key_out: wp.array2d(dtype=wp.int32),
                   impulse_out: wp.array2d(dtype=wp.vec3)):
    """Keep this step's contacts and their world-frame impulses [N s] for the next warm start."""
    world, k = wp.tid()
    count = c.contact_count[world]
    if k == 0:
        count_out[world] = count
    if k >= count:
        return
    start = m.contact_row_start[world] + 3 * k
    n = c.contact_normal[world, k]
    impulse = wp.vec3(0.0)
    for component in range(3):
        impulse += row_lambda[world, start + component] * contact_direction(n, component)
    key_out[world, k] = c.contact_key[world, k]
    impulse_out[world, k] = impulse


__all__ = ["contact_rows", "gather_warmstart", "store_contacts"]
