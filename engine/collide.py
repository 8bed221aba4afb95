"""Collision detection per world: candidate contacts for every static shape pair, then compaction.

Pairs are fixed at pack time (engine.pack): every shape against the world's ground plane, and
every two shapes of different bodies of the same world that are not joined by a joint and do not
share a non-zero collision group. Pair (a, b) has shape a of lower or equal type than shape b
(sphere < capsule < box < cylinder); b = -1 is the ground plane. Pair p owns candidate slots
4p .. 4p + 3 (the slot is the contact's key for warm starting); a contact's normal points from b
to a, its distance is negative when the shapes overlap [m]. Supported: every primitive against
the plane; sphere-sphere, sphere-capsule, capsule-capsule, sphere-box, capsule-box, box-box (SAT
face normal, corners over the other box's face both ways, the 4 deepest kept); cylinders collide
with the ground plane only.

compact_contacts then keeps, per world and in slot order (deterministic), the candidates closer
than the margin, up to the world's contact capacity, and counts the ones it had to drop.
"""

import warp as wp

from engine.model import Candidates, ContactArrays, ShapeArrays
from engine.spec import ShapeType

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

SPHERE = wp.constant(int(ShapeType.SPHERE))
CAPSULE = wp.constant(int(ShapeType.CAPSULE))
BOX = wp.constant(int(ShapeType.BOX))
CYLINDER = wp.constant(int(ShapeType.CYLINDER))
PAIR_SLOTS = wp.constant(4)  # candidate slots per pair (the most any pair emits)

# contacts a pair can produce, by (type a, type b); against the plane by type a
PLANE_CONTACTS = {ShapeType.SPHERE: 1, ShapeType.CAPSULE: 2, ShapeType.BOX: 4, ShapeType.CYLINDER: 4}
PAIR_CONTACTS = {
    (ShapeType.SPHERE, ShapeType.SPHERE): 1, (ShapeType.SPHERE, ShapeType.CAPSULE): 1,
    (ShapeType.CAPSULE, ShapeType.CAPSULE): 2, (ShapeType.SPHERE, ShapeType.BOX): 1,
    (ShapeType.CAPSULE, ShapeType.BOX): 2, (ShapeType.BOX, ShapeType.BOX): 4,
}


@wp.func
def emit(c: Candidates, world: int, slot: int, point_a: wp.vec3, point_b: wp.vec3, normal: wp.vec3, distance: float):
    """Write one contact candidate into ``slot`` of ``world`` and mark it valid."""
    c.valid[world, slot] = 1
    c.point_a[world, slot] = point_a
    c.point_b[world, slot] = point_b
    c.normal[world, slot] = normal
    c.distance[world, slot] = distance


@wp.func
def emit_spheres(c: Candidates, world: int, slot: int, center_a: wp.vec3, radius_a: float, center_b: wp.vec3,
                 radius_b: float):
    """Contact between two spheres (also the closest points of segments); normal from b to a."""
    delta = center_a - center_b
    length = wp.length(delta)
    normal = wp.vec3(0.0, 0.0, 1.0)
    if length > 1.0e-9:
        normal = delta / length
    emit(c, world, slot, center_a - radius_a * normal, center_b + radius_b * normal, normal,
         length - radius_a - radius_b)


@wp.func
def closest_on_segment(p0: wp.vec3, p1: wp.vec3, q: wp.vec3):
    """Closest point to q on the segment p0-p1."""
    d = p1 - p0
    t = wp.clamp(wp.dot(q - p0, d) / wp.max(wp.dot(d, d), 1.0e-12), 0.0, 1.0)
    return p0 + t * d


@wp.func
def segment_segment(p0: wp.vec3, p1: wp.vec3, q0: wp.vec3, q1: wp.vec3):
    """Closest points (on p, on q) of two segments."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    c = wp.dot(d1, r)
    b = wp.dot(d1, d2)
    denom = a * e - b * b
    s = float(0.0)
    if denom > 1.0e-12 * a * e:
        s = wp.clamp((b * f - c * e) / denom, 0.0, 1.0)
    t = (b * s + f) / wp.max(e, 1.0e-12)
    if t < 0.0:
        t = 0.0
        s = wp.clamp(-c / wp.max(a, 1.0e-12), 0.0, 1.0)
    elif t > 1.0:
        t = 1.0
        s = wp.clamp((b - c) / wp.max(a, 1.0e-12), 0.0, 1.0)
    return p0 + s * d1, q0 + t * d2


@wp.func
def point_box(p: wp.vec3, X_box: wp.transform, half: wp.vec3):
    """Signed distance of p to a box, outward normal at the closest feature, closest surface point."""
    local = wp.transform_point(wp.transform_inverse(X_box), p)
    clamped = wp.vec3(wp.clamp(local[0], -half[0], half[0]), wp.clamp(local[1], -half[1], half[1]),
                      wp.clamp(local[2], -half[2], half[2]))
    delta = local - clamped
    distance = wp.length(delta)
    normal_local = wp.vec3(0.0, 0.0, 1.0)
    surface = clamped
    if distance > 1.0e-9:
        normal_local = delta / distance
    else:  # inside: leave through the nearest face
        best = float(-1.0e30)
        for k in range(3):
            gap = wp.abs(local[k]) - half[k]
            if gap > best:
                best = gap
                normal_local = wp.vec3(0.0)
                normal_local[k] = wp.sign(local[k])
        distance = best
        surface = local
        for k in range(3):
            if normal_local[k] != 0.0:
                surface[k] = normal_local[k] * half[k]
    q = wp.transform_get_rotation(X_box)
    return distance, wp.quat_rotate(q, normal_local), wp.transform_point(X_box, surface)


@wp.func
def box_corner(X: wp.transform, half: wp.vec3, k: int):
    """World position of corner ``k`` (bits 0, 1, 2 pick +x, +y, +z) of a box with half-extents ``half`` at pose X."""
    sx = float(1.0) if (k & 1) != 0 else float(-1.0)
    sy = float(1.0) if (k & 2) != 0 else float(-1.0)
    sz = float(1.0) if (k & 4) != 0 else float(-1.0)
    return wp.transform_point(X, wp.vec3(sx * half[0], sy * half[1], sz * half[2]))


@wp.func
def plane_distance(p: wp.vec3, normal: wp.vec3, offset: float):
    """Signed distance of p above the plane normal . x = offset (unit normal)."""
    return wp.dot(normal, p) - offset


@wp.func
def keep_deepest(c: Candidates, world: int, base: int, point_a: wp.vec3, point_b: wp.vec3, normal: wp.vec3,
                 distance: float):
    """Insert a candidate into the pair's 4 slots, replacing the shallowest when they are full; a
    candidate within 0.5 mm of a kept one (the same corner seen from both boxes) merges into it."""
    worst = int(-1)
    worst_distance = float(-1.0e30)
    for k in range(PAIR_SLOTS):
        slot = base + k
        if c.valid[world, slot] != 0 and wp.length(c.point_a[world, slot] - point_a) < 5.0e-4:
            if distance < c.distance[world, slot]:
                emit(c, world, slot, point_a, point_b, normal, distance)
            return
    for k in range(PAIR_SLOTS):
        slot = base + k
        if c.valid[world, slot] == 0:
            emit(c, world, slot, point_a, point_b, normal, distance)
            return
        if c.distance[world, slot] > worst_distance:
            worst_distance = c.distance[world, slot]
            worst = slot
    if distance < worst_distance:
        emit(c, world, worst, point_a, point_b, normal, distance)


@wp.func
def box_projection(q: wp.quat, half: wp.vec3, u: wp.vec3):
    """Half the extent of a box along the unit vector u."""
    return (half[0] * wp.abs(wp.dot(u, wp.quat_rotate(q, wp.vec3(1.0, 0.0, 0.0))))
            + half[1] * wp.abs(wp.dot(u, wp.quat_rotate(q, wp.vec3(0.0, 1.0, 0.0))))
            + half[2] * wp.abs(wp.dot(u, wp.quat_rotate(q, wp.vec3(0.0, 0.0, 1.0)))))


@wp.func
def within_face(X: wp.transform, half: wp.vec3, n: wp.vec3, p: wp.vec3):
    """True when p projects, along n, into the box's face whose normal is closest to n."""
    local = wp.transform_point(wp.transform_inverse(X), p)
    n_local = wp.quat_rotate_inv(wp.transform_get_rotation(X), n)
    axis = int(0)
    for k in range(1, 3):
        if wp.abs(n_local[k]) > wp.abs(n_local[axis]):
            axis = k
    inside = True
    for k in range(3):
        if k != axis and wp.abs(local[k]) > half[k] * 1.001 + 1.0e-5:
            inside = False
    return inside


@wp.func
def box_box(c: Candidates, world: int, base: int, Xa: wp.transform, ha: wp.vec3, Xb: wp.transform, hb: wp.vec3,
            margin: float):
    """Box-box manifold: the face axis of least penetration (SAT over the 6 face normals) is the
    normal; corners of each box that lie over the other box's face and within the margin of its
    supporting plane become contacts (the 4 deepest kept). Edge-edge touching is not detected."""
    qa = wp.transform_get_rotation(Xa)
    qb = wp.transform_get_rotation(Xb)
    ca = wp.transform_get_translation(Xa)
    cb = wp.transform_get_translation(Xb)
    best = float(-1.0e30)
    n = wp.vec3(0.0, 0.0, 1.0)
    for k in range(6):
        e = wp.vec3(0.0)
        e[k % 3] = 1.0
        u = wp.quat_rotate(qa, e)
        if k >= 3:
            u = wp.quat_rotate(qb, e)
        separation = wp.abs(wp.dot(u, ca - cb)) - box_projection(qa, ha, u) - box_projection(qb, hb, u)
        if separation > best:
            best = separation
            n = u
    if wp.dot(n, ca - cb) < 0.0:
        n = -n  # from b to a
    plane_b = wp.dot(n, cb) + box_projection(qb, hb, n)  # b's supporting plane facing a
    plane_a = wp.dot(n, ca) - box_projection(qa, ha, n)  # a's supporting plane facing b
    for k in range(8):
        corner = box_corner(Xa, ha, k)
        d = wp.dot(n, corner) - plane_b
        if d < margin and within_face(Xb, hb, n, corner):
            keep_deepest(c, world, base, corner, corner - d * n, n, d)
    for k in range(8):
        corner = box_corner(Xb, hb, k)
        d = plane_a - wp.dot(n, corner)
        if d < margin and within_face(Xa, ha, n, corner):
            keep_deepest(c, world, base, corner + d * n, corner, n, d)


@wp.func
def plane_point(ta: int, Xa: wp.transform, size_a: wp.vec3, n: wp.vec3, k: int):
    """Candidate k of a shape (type ta, pose Xa) against a plane of normal n: a sphere's lowest point
    (k 0), a capsule's end k's lowest point (k 0, 1), a box's corner k (0-7), a cylinder's rim point
    k % 4 (a quarter turn apart, starting at the one lowest along n) of cap k // 4 (0-7)."""
    pa = wp.transform_get_translation(Xa)
    axis_a = wp.quat_rotate(wp.transform_get_rotation(Xa), wp.vec3(0.0, 0.0, 1.0))
    if ta == SPHERE:
        return pa - size_a[0] * n
    if ta == CAPSULE:
        return pa + (2.0 * float(k) - 1.0) * size_a[1] * axis_a - size_a[0] * n
    if ta == BOX:
        return box_corner(Xa, size_a, k)
    radial = -n - wp.dot(-n, axis_a) * axis_a
    if wp.length(radial) < 1.0e-6:
        radial = wp.cross(axis_a, wp.vec3(1.0, 0.0, 0.0))
        if wp.length(radial) < 1.0e-6:
            radial = wp.cross(axis_a, wp.vec3(0.0, 1.0, 0.0))
    u = wp.normalize(radial)
    v = wp.cross(axis_a, u)
    center = pa + (2.0 * float(k / 4) - 1.0) * size_a[1] * axis_a
    angle = 0.5 * wp.pi * float(k % 4)
    return center + size_a[0] * (wp.cos(angle) * u + wp.sin(angle) * v)


@wp.func
def plane_point_count(ta: int):
    """How many candidates plane_point has for a shape of type ta."""
    if ta == SPHERE:
        return 1
    if ta == CAPSULE:
        return 2
    return 8


@wp.func
def shape_against_plane(c: Candidates, world: int, base: int, ta: int, Xa: wp.transform, size_a: wp.vec3,
                        n: wp.vec3, off: float, margin: float):
    """Candidate contacts of one shape (type ta, pose Xa) against the plane n . x = off, into the
    pair's slots base .. base + 3 (cleared by the caller): a sphere's lowest point, a capsule's two
    ends', a box's or a cylinder's rim's 4 deepest points within the margin (plane_point)."""
    for k in range(plane_point_count(ta)):
        point = plane_point(ta, Xa, size_a, n, k)
        d = plane_distance(point, n, off)
        if ta == SPHERE or ta == CAPSULE:
            emit(c, world, base + k, point, point - d * n, n, d)
        elif d < margin:
            keep_deepest(c, world, base, point, point - d * n, n, d)


@wp.kernel
def generate_candidates(shapes: ShapeArrays, margin: float, body_q: wp.array2d(dtype=wp.transform), c: Candidates):
    """Candidate contacts of one shape pair."""
    world, pair = wp.tid()
    if pair >= shapes.pair_count[world]:
        return
    base = pair * PAIR_SLOTS
    for k in range(PAIR_SLOTS):
        c.valid[world, base + k] = 0
    sa = shapes.pair_shape_a[world, pair]
    sb = shapes.pair_shape_b[world, pair]
    ta = shapes.shape_type[world, sa]
    Xa = body_q[world, shapes.shape_body[world, sa]] * shapes.shape_X[world, sa]
    size_a = shapes.shape_size[world, sa]
    pa = wp.transform_get_translation(Xa)
    axis_a = wp.quat_rotate(wp.transform_get_rotation(Xa), wp.vec3(0.0, 0.0, 1.0))
    if sb < 0:  # against the ground plane
        shape_against_plane(c, world, base, ta, Xa, size_a, shapes.ground_normal[world], shapes.ground_offset[world],
                            margin)
        return
    tb = shapes.shape_type[world, sb]
    Xb = body_q[world, shapes.shape_body[world, sb]] * shapes.shape_X[world, sb]
    size_b = shapes.shape_size[world, sb]
    pb = wp.transform_get_translation(Xb)
    axis_b = wp.quat_rotate(wp.transform_get_rotation(Xb), wp.vec3(0.0, 0.0, 1.0))
    if ta == SPHERE and tb == SPHERE:
        emit_spheres(c, world, base, pa, size_a[0], pb, size_b[0])
    elif ta == SPHERE and tb == CAPSULE:
        q = closest_on_segment(pb - size_b[1] * axis_b, pb + size_b[1] * axis_b, pa)
        emit_spheres(c, world, base, pa, size_a[0], q, size_b[0])
    elif ta == CAPSULE and tb == CAPSULE:
        a0 = pa - size_a[1] * axis_a
        a1 = pa + size_a[1] * axis_a
        b0 = pb - size_b[1] * axis_b
        b1 = pb + size_b[1] * axis_b
        p, q = segment_segment(a0, a1, b0, b1)
        emit_spheres(c, world, base, p, size_a[0], q, size_b[0])
        # nearly parallel segments touch along a line: add the farthest endpoint pairing
        if wp.abs(wp.dot(axis_a, axis_b)) > 0.99:
            e0 = closest_on_segment(b0, b1, a0)
            e1 = closest_on_segment(b0, b1, a1)
            if wp.length(a0 - p) > wp.length(a1 - p):
                emit_spheres(c, world, base + 1, a0, size_a[0], e0, size_b[0])
            else:
                emit_spheres(c, world, base + 1, a1, size_a[0], e1, size_b[0])
    elif ta == SPHERE and tb == BOX:
        d, n, q = point_box(pa, Xb, size_b)
        emit(c, world, base, pa - size_a[0] * n, q, n, d - size_a[0])
    elif ta == CAPSULE and tb == BOX:
        for k in range(2):
            p = pa + (2.0 * float(k) - 1.0) * size_a[1] * axis_a
            for _it in range(4):  # alternate projections: segment point <-> box point
                d, n, q = point_box(p, Xb, size_b)
                p = closest_on_segment(pa - size_a[1] * axis_a, pa + size_a[1] * axis_a, q)
            d, n, q = point_box(p, Xb, size_b)
            emit(c, world, base + k, p - size_a[0] * n, q, n, d - size_a[0])
    elif ta == BOX and tb == BOX:
        box_box(c, world, base, Xa, size_a, Xb, size_b, margin)


@wp.kernel
def compact_contacts(shapes: ShapeArrays, contact_row_start: wp.array(dtype=wp.int32), contact_capacity: int,
                     margin: float, c: Candidates, row_count_out: wp.array(dtype=wp.int32), out: ContactArrays):
    """Per world, in slot order: keep candidates closer than the margin, up to the capacity, into
    ``out``; this step's row count into row_count_out."""
    world = wp.tid()
    count = int(0)
    dropped = int(0)
    for pair in range(shapes.pair_count[world]):
        base = pair * PAIR_SLOTS
        sa = shapes.pair_shape_a[world, pair]
        sb = shapes.pair_shape_b[world, pair]
        mu = float(0.0)
        e = float(0.0)
        body_b = int(-1)
        if sb < 0:
            mu = wp.sqrt(shapes.shape_friction[world, sa] * shapes.ground_friction[world])
            e = wp.max(shapes.shape_restitution[world, sa], shapes.ground_restitution[world])
        else:
            mu = wp.sqrt(shapes.shape_friction[world, sa] * shapes.shape_friction[world, sb])
            e = wp.max(shapes.shape_restitution[world, sa], shapes.shape_restitution[world, sb])
            body_b = shapes.shape_body[world, sb]
        for k in range(PAIR_SLOTS):
            slot = base + k
            if c.valid[world, slot] != 0:
                if c.distance[world, slot] < margin:
                    if count < contact_capacity:
                        out.contact_key[world, count] = slot
                        out.contact_body_a[world, count] = shapes.shape_body[world, sa]
                        out.contact_body_b[world, count] = body_b
                        out.contact_point_a[world, count] = c.point_a[world, slot]
                        out.contact_point_b[world, count] = c.point_b[world, slot]
                        out.contact_normal[world, count] = c.normal[world, slot]
                        out.contact_distance[world, count] = c.distance[world, slot]
                        out.contact_friction[world, count] = mu
                        out.contact_restitution[world, count] = e
                        count += 1
                    else:
                        dropped += 1
    out.contact_count[world] = count
    out.contact_dropped[world] = dropped
    row_count_out[world] = contact_row_start[world] + 3 * count


__all__ = ["Candidates", "PAIR_CONTACTS", "PLANE_CONTACTS", "compact_contacts", "generate_candidates"]
