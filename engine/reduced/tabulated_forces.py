"""Force elements and a Control in the tabulated plan: wrenches on the base and the sub-chains' links
mapped to the step's generalized forces.

An entity is the world (-1), the base (0) or link k of sub-chain g (1 + g MAX_LINKS + k). A wrench
(force F at the world point x, torque T) on an entity adds F and (x - p) x F + T to the base's
generalized force (p: the base's centre of mass) and, on a link, F . (e + w' x (x - c)) + T . w' to
its sub-chain's coordinate, with e and w' the link's centre-of-mass velocity and angular velocity
per unit driving rate and c its centre of mass. The step adds them to its bias forces before the
free velocity, at the pose and rates its velocity products use (Moreau-Jean: the midpoint, rates
extrapolated), so forces act where they do in the maximal and tree plans. Force slots follow
chains.pack_force_slots, with frames relative to the entity's centre of mass and table frame.
"""

import numpy as np
import warp as wp

from engine.model import FORCE_BODY_WRENCH, FORCE_JOINT_SPRING, FORCE_LINEAR_SPRING
from engine.reduced.chain_layout import _transform
from engine.reduced.chains import pack_force_slots
from engine.reduced.tabulated_kernel import (MAX_LINKS, TabulatedState, TabulatedWorlds, link_read, plane,
                                             table_index, table_read, vecnv)
from engine.spatial import hinge_angle, quat_matrix, spring_tension, wrap_angle
from engine.spec import JointType

__all__ = ["TabulatedForces", "applied_forces", "pack_forces", "spring_energy"]


@wp.struct
class TabulatedForces:
    """Every world's force slots (F padded; chains.pack_force_slots's fields, entries as above) and
    where a Control acts: control_body (W, B) each spec body's entity; control_joint (W, J, 2) each
    revolute spec joint's child and parent entities (-1 for other joints' both), control_frame
    (W, J) its parent anchor frame relative to the parent entity (in the world for -1) and
    control_axis (W, J) its axis in that frame."""

    force_count: wp.array(dtype=wp.int32)
    force_kind: wp.array2d(dtype=wp.int32)
    force_entry: wp.array3d(dtype=wp.int32)
    force_frame: wp.array3d(dtype=wp.transform)
    force_vec: wp.array3d(dtype=wp.vec3)
    force_coef: wp.array2d(dtype=wp.vec4)
    control_body: wp.array2d(dtype=wp.int32)
    control_joint: wp.array3d(dtype=wp.int32)
    control_frame: wp.array2d(dtype=wp.transform)
    control_axis: wp.array2d(dtype=wp.vec3)


def pack_forces(layouts: list, max_bodies: int, max_joints: int, device, control: bool = False) -> TabulatedForces:
    """The batch's TabulatedForces from its TabulatedLayouts: the force slots of the specs that have
    any, and where a Control acts only when ``control`` (else 1 x 1 placeholders: a walker study's
    batch, which steps without a Control, spends no host time on its joints' frames)."""
    W = len(layouts)
    F = max(1, max(len(lay.spec.forces) for lay in layouts))
    B, J = (max_bodies, max_joints) if control else (1, 1)
    identity = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    h = {"force_count": np.zeros(W, np.int32), "force_kind": np.zeros((W, F), np.int32),
         "force_entry": np.full((W, F, 2), -1, np.int32), "force_frame": np.tile(identity, (W, F, 2, 1)),
         "force_vec": np.zeros((W, F, 2, 3)), "force_coef": np.zeros((W, F, 4)),
         "control_body": np.full((W, B), -1, np.int32), "control_joint": np.full((W, J, 2), -1, np.int32),
         "control_frame": np.tile(identity, (W, J, 1)), "control_axis": np.zeros((W, J, 3))}
    for w, lay in enumerate(layouts):
        spec = lay.spec
        if not spec.forces and not control:
            continue
        index = spec.body_index

        def entity(b):  # (entity, C: body frame -> its entity's table frame, centre of mass in the body frame)
            g, k, frame = lay.bodies[b]
            return (0 if g < 0 else 1 + g * int(MAX_LINKS) + k), quat_matrix(frame), spec.bodies[b].com

        def side(name, R, p):
            if name is None:
                return -1, _transform(R, p)
            e, C, com = entity(index[name])
            return e, _transform(C @ R, C @ (np.asarray(p, float) - com))

        pack_force_slots(h, w, spec, side)
        if not control:
            continue
        entities = [entity(b) for b in range(len(spec.bodies))]
        h["control_body"][w, :len(entities)] = [e for e, _, _ in entities]
        for j, joint in enumerate(spec.joints):
            if joint.type == JointType.REVOLUTE:
                h["control_joint"][w, j] = [-1 if name is None else entities[index[name]][0]
                                            for name in (joint.child, joint.parent)]
                h["control_frame"][w, j] = side(joint.parent, quat_matrix(joint.parent_orientation),
                                                joint.parent_position)[1]
                h["control_axis"][w, j] = joint.axis
    out = TabulatedForces()
    types = {"force_frame": wp.transform, "force_vec": wp.vec3, "force_coef": wp.vec4, "control_frame": wp.transform,
             "control_axis": wp.vec3}
    for name, value in h.items():
        dtype = types.get(name, wp.int32)
        setattr(out, name, wp.array(value.astype(np.int32 if dtype == wp.int32 else np.float32), dtype=dtype,
                                    device=device))
    return out


@wp.func
def entity_at(worlds: TabulatedWorlds, state: TabulatedState, w: int, e: int, p: wp.vec3, q: wp.quat, R: wp.mat33,
              axis: wp.vec3, u: vecnv, half: float):
    """Entity e's centre of mass, orientation (its table frame), velocity and angular velocity at the
    base pose (p, q; R its matrix) and velocities u, the sub-chains' angles advanced by half times
    their rates in the state (as chain_columns advances them); and its velocity e1 and angular
    velocity w1 per unit driving rate (the world: at rest at the origin)."""
    v = wp.vec3(u[0], u[1], u[2])
    om = wp.vec3(u[3], u[4], u[5])
    if e < 0:  # the world: at rest
        return wp.vec3(), wp.quat_identity(), wp.vec3(), wp.vec3(), wp.vec3(), wp.vec3()
    if e == 0:
        return p, q, v, om, wp.vec3(), wp.vec3()
    g = (e - 1) / MAX_LINKS
    k = (e - 1) - g * MAX_LINKS
    rate = u[6 + g]
    t = worlds.group_table[w, g]
    s = worlds.group_scale[w, g]
    i0, i1, f = table_index(state.coord[w, g] + half * state.coord_rate[w, g], worlds.samples)
    c0 = link_read(worlds.links0, t, i0, i1, f, k)
    c1 = table_read(worlds.links1, t, i0, i1, f, k)
    d = R * (worlds.group_origin[w, g] + wp.vec3(s * c0[0], 0.0, s * c0[1]))
    e1 = plane(R, c1) * s
    w1 = axis * c1[2]
    turn = wp.quat_from_axis_angle(wp.vec3(0.0, -1.0, 0.0), c0[2])
    return p + d, q * turn, v + wp.cross(om, d) + e1 * rate, om + w1 * rate, e1, w1


@wp.func
def side_frame(X: wp.transform, e: int, c: wp.vec3, q: wp.quat):
    """A frame X relative to entity e (centre of mass c, orientation q) in the world (the world's: X)."""
    if e < 0:
        return X
    return wp.transform_multiply(wp.transform(c, q), X)


@wp.func
def push(gen: vecnv, e: int, p: wp.vec3, c: wp.vec3, e1: wp.vec3, w1: wp.vec3, F: wp.vec3, x: wp.vec3, T: wp.vec3):
    """gen plus the generalized force of F at x and T on entity e (centre of mass c, per-rate
    velocities e1, w1); the world (-1) takes nothing."""
    if e < 0:
        return gen
    tb = wp.cross(x - p, F) + T
    for i in range(3):
        gen[i] += F[i]
        gen[3 + i] += tb[i]
    if e > 0:
        g = (e - 1) / MAX_LINKS
        gen[6 + g] += wp.dot(F, e1 + wp.cross(w1, x - c)) + wp.dot(T, w1)
    return gen


@wp.func
def applied_forces(worlds: TabulatedWorlds, state: TabulatedState, fo: TabulatedForces, w: int, p: wp.vec3,
                   q: wp.quat, u: vecnv, half: float, forces: int, controlled: int,
                   body_f: wp.array2d(dtype=wp.spatial_vector), joint_effort: wp.array2d(dtype=float)):
    """The generalized forces of world w's force slots (forces != 0) and of a Control's body_f and
    joint_effort (controlled != 0) at the base pose (p, q), velocities u and angles advanced by half
    times their rates: a spring-damper's tension k (L - L0) + c dL/dt along its points' line
    (tension_only: never a push), a joint element's torque about the joint's world axis on its child
    and the opposite on its parent (a spring's angle from the two anchor frames, as the maximal plan
    measures it), a body wrench or body_f at the centre of mass."""
    R = wp.quat_to_matrix(q)
    axis = -(R * wp.vec3(0.0, 1.0, 0.0))
    gen = vecnv()
    zero = wp.vec3()
    if forces != 0:
        for f in range(fo.force_count[w]):
            kind = fo.force_kind[w, f]
            ea = fo.force_entry[w, f, 0]
            eb = fo.force_entry[w, f, 1]
            ca, qa, va, oa, a1, aw = entity_at(worlds, state, w, ea, p, q, R, axis, u, half)
            cb, qb, vb, ob, b1, bw = entity_at(worlds, state, w, eb, p, q, R, axis, u, half)
            Xa = side_frame(fo.force_frame[w, f, 0], ea, ca, qa)
            Xb = side_frame(fo.force_frame[w, f, 1], eb, cb, qb)
            coef = fo.force_coef[w, f]
            if kind == FORCE_LINEAR_SPRING:
                xa = wp.transform_get_translation(Xa)
                xb = wp.transform_get_translation(Xb)
                n, tension = spring_tension(coef, xb - xa, (vb + wp.cross(ob, xb - cb)) - (va + wp.cross(oa, xa - ca)))
                gen = push(gen, ea, p, ca, a1, aw, tension * n, xa, zero)
                gen = push(gen, eb, p, cb, b1, bw, -tension * n, xb, zero)
            elif kind == FORCE_BODY_WRENCH:
                gen = push(gen, ea, p, ca, a1, aw, fo.force_vec[w, f, 0], ca, fo.force_vec[w, f, 1])
            else:  # a joint spring or torque: child (a) and parent (b) anchor frames
                a_w = wp.quat_rotate(wp.transform_get_rotation(Xb), fo.force_vec[w, f, 0])
                tau = coef[3]
                if kind == FORCE_JOINT_SPRING:
                    angle = hinge_angle(wp.transform_get_rotation(Xb), wp.transform_get_rotation(Xa),
                                        fo.force_vec[w, f, 0])
                    rate = wp.dot(a_w, oa - ob)
                    tau = -coef[0] * wrap_angle(angle - coef[2]) - coef[1] * rate
                gen = push(gen, ea, p, ca, a1, aw, zero, ca, tau * a_w)
                gen = push(gen, eb, p, cb, b1, bw, zero, cb, -tau * a_w)
    if controlled != 0:
        for b in range(fo.control_body.shape[1]):
            e = fo.control_body[w, b]
            if e >= 0:
                c, qe, ve, oe, e1, w1 = entity_at(worlds, state, w, e, p, q, R, axis, u, half)
                wrench = body_f[w, b]
                gen = push(gen, e, p, c, e1, w1, wp.spatial_top(wrench), c, wp.spatial_bottom(wrench))
        for j in range(fo.control_joint.shape[1]):
            ec = fo.control_joint[w, j, 0]
            ep = fo.control_joint[w, j, 1]
            if ec >= 0 and joint_effort[w, j] != 0.0:
                cp, qp, vp, op, p1, pw = entity_at(worlds, state, w, ep, p, q, R, axis, u, half)
                X = side_frame(fo.control_frame[w, j], ep, cp, qp)
                torque = joint_effort[w, j] * wp.quat_rotate(wp.transform_get_rotation(X), fo.control_axis[w, j])
                cc, qc, vc, oc, c1, cw = entity_at(worlds, state, w, ec, p, q, R, axis, u, half)
                gen = push(gen, ec, p, cc, c1, cw, zero, cc, torque)
                gen = push(gen, ep, p, cp, p1, pw, zero, cp, -torque)
    return gen


@wp.func
def spring_energy(worlds: TabulatedWorlds, state: TabulatedState, fo: TabulatedForces, w: int):
    """The potential energy [J] of world w's springs at its state: 1/2 k s^2 of a linear spring
    stretched by s (a tension-only one: only while stretched) or of a joint spring displaced by s
    from its rest angle."""
    p = state.position[w]
    q = state.orientation[w]
    R = wp.quat_to_matrix(q)
    axis = -(R * wp.vec3(0.0, 1.0, 0.0))
    u = vecnv()
    energy = float(0.0)
    for f in range(fo.force_count[w]):
        kind = fo.force_kind[w, f]
        if kind == FORCE_LINEAR_SPRING or kind == FORCE_JOINT_SPRING:
            ea = fo.force_entry[w, f, 0]
            eb = fo.force_entry[w, f, 1]
            ca, qa, va, oa, a1, aw = entity_at(worlds, state, w, ea, p, q, R, axis, u, 0.0)
            cb, qb, vb, ob, b1, bw = entity_at(worlds, state, w, eb, p, q, R, axis, u, 0.0)
            Xa = side_frame(fo.force_frame[w, f, 0], ea, ca, qa)
            Xb = side_frame(fo.force_frame[w, f, 1], eb, cb, qb)
            coef = fo.force_coef[w, f]
            stretch = float(0.0)
            if kind == FORCE_LINEAR_SPRING:
                stretch = wp.length(wp.transform_get_translation(Xb) - wp.transform_get_translation(Xa)) - coef[2]
                if coef[3] != 0.0 and stretch < 0.0:
                    stretch = 0.0
            else:
                angle = hinge_angle(wp.transform_get_rotation(Xb), wp.transform_get_rotation(Xa), fo.force_vec[w, f, 0])
                stretch = wrap_angle(angle - coef[2])
            energy += 0.5 * coef[0] * stretch * stretch
    return energy
