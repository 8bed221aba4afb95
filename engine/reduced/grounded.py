"""The GROUNDED plan: a fixed-base planar linkage of mobility one, stepped in its one coordinate.

A spec fits when every body hangs from the world through revolute and inline joints with parallel
axes, the linkage has mobility one and its coordinate (the driven joint's angle, else the first
revolute joint to the world) turns a full turn; no shapes over a ground, joint limits, armature,
joint damping, position drives or damped tension-only springs (those keep the tree plan). The world is read as
the fixed base of one engine.reduced.tabulated_tables sub-chain, so every link is a tabulated
function of q, and a world's motion is one scalar ODE

    M(q) q'' + M'(q) q'^2 / 2 = G(q) - D(q) q' + tau_drive + tau_control.

M, the generalized force G of gravity and of the force elements' springs and constant loads, and
their damping D are tabulated over the turn in float64 with their exact derivatives and read as
cubic Hermite splines (the step uses M's spline's own derivative), within O(h^4) of the
mechanism's (h: the sample spacing); in one coordinate every G(q) is conservative. The step is the
implicit midpoint rule in (q, p = M q') (symplectic: bounded energy error, second order), the
damping at the step's mean momentum, the velocity drive implicit at the end rate and clamped to
its effort limit (first order where they act, as in the other plans). A Control's joint_effort and body_f act at the midpoint through
the links' tabulated Jacobians. Loop closure is exact by construction; the body poses a Trace
measures are read from Hermite splines of the link tables (closure error about 1e-10 m).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import warp as wp

from engine.reduced.chains import ChainControl, check_control_arrays
from engine.reduced.tabulated_layout import _turn_angle, tabulated_layout
from engine.spatial import quat_matrix
from engine.spec import Body, JointDrive, JointType, MechanismSpec
from engine.reduced.tabulated_tables import TABLE_SAMPLES, wrap

wp.set_module_options({"enable_backward": False})

__all__ = ["GroundedModel", "GroundedState", "grounded_layout", "pack_grounded"]

GROUND = "(world)"  # the name of the fixed base the tables are built on (not a body of the result)
ITERATIONS = 12  # at most this many fixed-point iterations of an implicit midpoint step
CONVERGED = 1.0e-14  # [rad] the iterations stop once the midpoint angle moves less than this
RUNNING, DIVERGED, HALTED = 0, 1, 3  # stop codes (HALTED: frozen by set_halted, not a failure)
TWO_PI = wp.constant(wp.float64(2.0 * math.pi))
# the triple jump's sub-steps (Yoshida's fourth-order composition of a symmetric second-order step)
JUMP_OUTER = wp.constant(wp.float64(1.0 / (2.0 - 2.0 ** (1.0 / 3.0))))
JUMP_INNER = wp.constant(wp.float64(-(2.0 ** (1.0 / 3.0)) / (2.0 - 2.0 ** (1.0 / 3.0))))


@dataclasses.dataclass
class GroundedLayout:
    """A spec read as one grounded sub-chain: tab (the TabulatedLayout of the spec on a fixed base
    named GROUND), coordinate (the spec index of the joint whose angle is q), drive (target
    velocity [rad/s], damping [N m s/rad], effort limit [N m]; zeros and inf without a drive);
    samples (S, 6) over the turn of M [kg m^2], M', the generalized force G [N m] of gravity and
    the force elements' springs and loads, G', the force elements' damping D [N m s] and D';
    reach: the largest speed of a link's centre per unit coordinate rate [m/rad]."""

    spec: MechanismSpec
    tab: object
    coordinate: int
    drive: tuple
    samples: np.ndarray
    reach: float

    @property
    def closure_error(self) -> float:
        """The tables' closure error when read linearly [m] (the plan reads positions by Hermite splines)."""
        return self.tab.closure_error


def grounded_layout(spec: MechanismSpec, samples: int = TABLE_SAMPLES) -> GroundedLayout:
    """The spec as a grounded one-DoF linkage; ValueError with one line naming what does not fit."""
    if spec.shapes and spec.ground is not None:
        raise ValueError(f"shape '{spec.shapes[0].name}' over a ground: the grounded plan has no contacts")
    world = [j for j in spec.joints if j.parent is None]
    if not world:
        raise ValueError("no joint to the world (a floating mechanism)")
    driven = [j for j in spec.joints if j.drive is not None]
    for joint in spec.joints:
        where = f"joint '{joint.name}'"
        if joint.type not in (JointType.REVOLUTE, JointType.INLINE):
            raise ValueError(f"{where} is {joint.type.name.lower()}: the grounded plan takes revolute and inline joints")
        if joint.has_limits or joint.armature > 0.0 or joint.damping > 0.0:
            raise ValueError(f"{where} has limits, armature or damping, which the grounded plan does not model")
        if joint.drive is not None and (joint.drive.stiffness > 0.0 or joint.parent is not None
                                        or joint.type != JointType.REVOLUTE):
            raise ValueError(f"{where}: the grounded plan takes one velocity drive on a revolute joint to the world")
    if len(driven) > 1:
        raise ValueError(f"joints '{driven[0].name}' and '{driven[1].name}' are both driven: one coordinate has one drive")
    revolute = [j for j in world if j.type == JointType.REVOLUTE]
    pick = driven[0] if driven else (revolute[0] if revolute else None)
    if pick is None:
        raise ValueError("no revolute joint to the world to take as the coordinate")
    base = Body(GROUND, 1.0, np.eye(3))
    joints = []
    for joint in spec.joints:
        change = {}
        if joint.parent is None:
            change["parent"] = GROUND
        if joint is pick and joint.drive is None:
            change["drive"] = JointDrive()  # marks the coordinate for the tables; acts as no drive
        joints.append(dataclasses.replace(joint, **change) if change else joint)
    on_base = dataclasses.replace(spec, bodies=[base] + list(spec.bodies), joints=joints, shapes=[], ground=None,
                                  forces=[])
    tab = tabulated_layout(on_base, samples=samples)
    if tab.base != 0 or len(tab.groups) != 1:
        raise ValueError("its bodies do not form one linkage of mobility one on the world")
    drive = pick.drive
    values = (0.0, 0.0, math.inf) if drive is None else (drive.target_velocity, drive.damping, drive.effort_limit)
    table, reach = _generalized(spec, tab)
    return GroundedLayout(spec, tab, spec.joints.index(pick), values, table, reach)


# -- tables ----------------------------------------------------------------------------------------------


class _Links:
    """The links of a grounded layout over the samples of a turn, in the state frame (float64): the
    position of a point fixed in a link and its first two derivatives in q."""

    def __init__(self, tab):
        g = tab.groups[0]
        t = g.table
        self.s, self.o = g.scale, np.asarray(g.origin, float)
        self.c0, self.c1, self.c2 = t.links, t.links_d1, t.links_d2
        self.samples = len(self.c0)
        self.R, self.P = quat_matrix(tab.orientation), np.asarray(tab.position, float)

    def point(self, k: int, u) -> tuple:
        """(S, 3) x3: a point at u (table frame, from the link's centre of mass) of link k, or with
        k < 0 the world point u (world frame): position, first and second derivatives in q."""
        S = self.samples
        if k < 0:
            p = np.broadcast_to(self.R.T @ (np.asarray(u, float) - self.P), (S, 3))
            return p, np.zeros((S, 3)), np.zeros((S, 3))
        x, d1, d2 = self.c0[:, k], self.c1[:, k], self.c2[:, k]
        c, n = np.cos(x[:, 2]), np.sin(x[:, 2])
        u = np.asarray(u, float)
        turned = np.stack([c * u[0] - n * u[2], np.full(S, u[1]), n * u[0] + c * u[2]], axis=1)  # rot_minus_y
        slope = np.stack([-n * u[0] - c * u[2], np.zeros(S), c * u[0] - n * u[2]], axis=1)  # its derivative in phi
        def plane(v):  # a table's (x, z) columns as state-frame vectors [m]
            return self.s * np.stack([v[:, 0], np.zeros(S), v[:, 1]], axis=1)

        p = self.o + plane(x) + turned
        dp = plane(d1) + d1[:, 2:3] * slope
        flat = turned.copy()
        flat[:, 1] = 0.0  # d2/dphi2 of rot_minus_y(phi) u: minus its in-plane part
        ddp = plane(d2) + d2[:, 2:3] * slope - (d1[:, 2:3] ** 2) * flat
        return p, dp, ddp

    def angle_at(self, k: int, q: float) -> float:
        """Link k's planar angle at coordinate q (its Hermite spline, as the kernels read it; 0 for the world)."""
        if k < 0:
            return 0.0
        step = 2.0 * math.pi / self.samples
        u = (q / step) % self.samples
        i0 = min(int(u), self.samples - 1)
        i1, f = (i0 + 1) % self.samples, u - i0
        y0, y1 = self.c0[i0, k, 2], self.c0[i0, k, 2] + wrap(self.c0[i1, k, 2] - self.c0[i0, k, 2])
        d0, d1 = self.c1[i0, k, 2], self.c1[i1, k, 2]
        return float((2 * f**3 - 3 * f**2 + 1) * y0 + (f**3 - 2 * f**2 + f) * step * d0 + (3 * f**2 - 2 * f**3) * y1
                     + (f**3 - f**2) * step * d1)

    def angle(self, k: int) -> tuple:
        """(S,) x3: link k's planar angle (0 for the world) and its first two derivatives in q."""
        if k < 0:
            return (np.zeros(self.samples),) * 3
        return self.c0[:, k, 2], self.c1[:, k, 2], self.c2[:, k, 2]


def _generalized(spec: MechanismSpec, tab) -> tuple:
    """(S, 6) samples of M, M', G, G', D, D' over the turn (see GroundedLayout) and the reach; raises
    ValueError naming a force element the grounded plan does not take."""
    from engine.forces import BodyWrench, JointSpring, JointTorque, LinearSpring

    g, links = tab.groups[0], _Links(tab)
    s, R = links.s, links.R
    m = np.asarray(g.link_mass, float)
    Iy = np.asarray(g.link_inertia, float)[:, 1, 1]  # about the plane normal (the table frame's y)
    c1, c2 = links.c1, links.c2
    M = (m * s * s * (c1[..., 0] ** 2 + c1[..., 1] ** 2) + Iy * c1[..., 2] ** 2).sum(axis=1)
    dM = 2.0 * (m * s * s * (c1[..., 0] * c2[..., 0] + c1[..., 1] * c2[..., 1]) + Iy * c1[..., 2] * c2[..., 2]).sum(axis=1)
    gs = R.T @ np.asarray(tab.gravity, float)  # gravity in the state frame
    G = (m * s * (gs[0] * c1[..., 0] + gs[2] * c1[..., 1])).sum(axis=1)
    dG = (m * s * (gs[0] * c2[..., 0] + gs[2] * c2[..., 1])).sum(axis=1)
    D, dD = np.zeros_like(M), np.zeros_like(M)
    index = spec.body_index
    where = {b - 1: (k, frame) for b, (_, k, frame) in enumerate(tab.bodies) if b > 0}  # spec body -> link, frame

    def link_of(name):
        return -1 if name is None else where[index[name]][0]

    def body_point(name, point):
        if name is None:
            return links.point(-1, point)
        k, frame = where[index[name]]
        return links.point(k, quat_matrix(frame) @ (np.asarray(point, float) - spec.bodies[index[name]].com))

    signs = _joint_signs_of(spec, R)
    for item in spec.forces:
        what = f"force element '{item.name}'"
        if isinstance(item, LinearSpring):
            if item.tension_only and item.damping > 0.0:
                raise ValueError(f"{what}: a tension-only spring with damping is not in the grounded plan")
            pa, da, dda = body_point(item.body_a, item.point_a)
            pb, db, ddb = body_point(item.body_b, item.point_b)
            d, dd, ddd = pa - pb, da - db, dda - ddb
            length = np.sqrt((d * d).sum(axis=1))
            if length.min() < 1e-9:
                raise ValueError(f"{what}: its two points meet during the turn")
            rate = (d * dd).sum(axis=1) / length
            curve = ((dd * dd).sum(axis=1) + (d * ddd).sum(axis=1) - rate**2) / length
            stretch = length - item.rest_length
            on = (stretch > 0.0) if item.tension_only else np.ones_like(length, bool)
            tension = np.where(on, item.stiffness * stretch, 0.0)
            G -= tension * rate
            dG -= np.where(on, item.stiffness * rate**2, 0.0) + tension * curve
            D += item.damping * rate**2
            dD += 2.0 * item.damping * rate * curve
        elif isinstance(item, (JointSpring, JointTorque)):
            j = next(i for i, joint in enumerate(spec.joints) if joint.name == item.joint)
            if signs[j] == 0.0:
                raise ValueError(f"{what}: its joint '{item.joint}' is not revolute")
            joint = spec.joints[j]
            ac, bc, cc = links.angle(link_of(joint.child))
            ap, bp, cp = links.angle(link_of(joint.parent))
            rate, curve = signs[j] * (bc - bp), signs[j] * (cc - cp)
            if isinstance(item, JointTorque):
                G += item.effort * rate
                dG += item.effort * curve
                continue
            kc, kp, q0 = link_of(joint.child), link_of(joint.parent), g.angle
            turned = (ac - links.angle_at(kc, q0)) - (ap - links.angle_at(kp, q0))
            # (where the joint passes the far side of the rest position the force flips, as in the other plans;
            # the spline spreads the flip over one sample interval)
            off = wrap(_joint_angle(spec, joint) + signs[j] * wrap(turned) - item.rest_position)
            G -= item.stiffness * off * rate
            dG -= item.stiffness * (rate**2 + off * curve)
            D += item.damping * rate**2
            dD += 2.0 * item.damping * rate * curve
        elif isinstance(item, BodyWrench):
            k = link_of(item.body)
            p, dp, ddp = links.point(k, (0.0, 0.0, 0.0))
            a, b, c = links.angle(k)
            f, torque = R.T @ item.force, R.T @ item.torque
            G += dp @ f - torque[1] * b  # the link turns about -y of the state frame
            dG += ddp @ f - torque[1] * c
        else:
            raise ValueError(f"{what}: a {type(item).__name__} is not in the grounded plan")
    reach = float(s * np.sqrt(c1[..., 0] ** 2 + c1[..., 1] ** 2).max())
    return np.stack([M, dM, G, dG, D, dD], axis=1), reach


def _joint_signs(lay: GroundedLayout) -> np.ndarray:
    """_joint_signs_of a layout's spec."""
    return _joint_signs_of(lay.spec, quat_matrix(lay.tab.orientation))


def _joint_signs_of(spec: MechanismSpec, R: np.ndarray) -> np.ndarray:
    """Per spec joint +1 or -1: its axis along the state frame's -y (R's second column negated: the
    planar angle's sense) or against it; 0 for an inline joint (no joint effort acts on it)."""
    normal = -R[:, 1]
    index = spec.body_index
    out = np.zeros(len(spec.joints))
    for j, joint in enumerate(spec.joints):
        if joint.type != JointType.REVOLUTE:
            continue
        frame = np.eye(3) if joint.parent is None else quat_matrix(spec.bodies[index[joint.parent]].orientation)
        axis = frame @ quat_matrix(joint.parent_orientation) @ np.asarray(joint.axis, float)
        out[j] = 1.0 if axis @ normal > 0.0 else -1.0
    return out


def _joint_angle(spec: MechanismSpec, joint) -> float:
    """A revolute joint's coordinate [rad] at the spec's pose (as engine.joints measures it)."""
    index = spec.body_index
    parent = np.eye(3) if joint.parent is None else quat_matrix(spec.bodies[index[joint.parent]].orientation)
    child = quat_matrix(spec.bodies[index[joint.child]].orientation)
    rel = (parent @ quat_matrix(joint.parent_orientation)).T @ (child @ quat_matrix(joint.child_orientation))
    return _turn_angle(rel, np.asarray(joint.axis, float))


# -- device side -----------------------------------------------------------------------------------------


@wp.struct
class GroundedArrays:
    """A batch's tables and per-world constants (see pack_grounded)."""

    samples: int
    energy: wp.array2d(dtype=wp.vec4d)  # (U, S): M, M', G, G' per distinct world
    damping: wp.array2d(dtype=wp.vec2d)  # (U, S): D, D'
    energy_of: wp.array(dtype=wp.int32)  # (W,)
    smooth: wp.array(dtype=wp.int32)  # (W,) 1: no drive damping, no force element damping (the triple jump)
    links0: wp.array3d(dtype=wp.vec3d)  # (T, S, K): unit-scale link centre (x, z) and angle
    links1: wp.array3d(dtype=wp.vec3d)  # their first derivatives in q
    links2: wp.array3d(dtype=wp.vec3d)  # second derivatives
    table_of: wp.array(dtype=wp.int32)  # (W,)
    scale: wp.array(dtype=wp.float64)
    origin: wp.array(dtype=wp.vec3d)  # the coordinate joint's pivot, state frame, from the state frame's origin
    frame: wp.array(dtype=wp.mat33d)  # the state frame's axes in the world
    position: wp.array(dtype=wp.vec3d)  # the state frame's origin in the world
    orientation: wp.array(dtype=wp.quat)  # the state frame as a quaternion
    drive: wp.array(dtype=wp.vec3d)  # target velocity, damping, effort limit
    reach: wp.array(dtype=wp.float64)
    body_count: wp.array(dtype=wp.int32)
    body_link: wp.array2d(dtype=wp.int32)  # (W, B) link of each spec body
    body_frame: wp.array2d(dtype=wp.quat)  # the body's orientation in its link's table frame
    joint_count: wp.array(dtype=wp.int32)
    joint_child: wp.array2d(dtype=wp.int32)  # (W, J) link of the joint's child, -1 the world
    joint_parent: wp.array2d(dtype=wp.int32)
    joint_sign: wp.array2d(dtype=wp.float64)


@wp.func
def sample_of(q: wp.float64, samples: int):
    """The samples around q and the weight of the second (a non-finite q reads sample 0)."""
    n = wp.float64(samples)
    u = q * n / TWO_PI
    u = u - n * wp.floor(u / n)
    if not (u >= wp.float64(0.0) and u < n):
        u = wp.float64(0.0)
    i0 = wp.min(int(u), samples - 1)
    i1 = i0 + 1
    if i1 >= samples:
        i1 = 0
    return i0, i1, u - wp.float64(i0)


@wp.func
def hermite(y0: wp.float64, d0: wp.float64, y1: wp.float64, d1: wp.float64, f: wp.float64, step: wp.float64):
    """The cubic Hermite spline through (y0, d0) and (y1, d1) a ``step`` apart, at weight f: value, derivative."""
    one, two, three = wp.float64(1.0), wp.float64(2.0), wp.float64(3.0)
    f2 = f * f
    f3 = f2 * f
    value = (two * f3 - three * f2 + one) * y0 + (f3 - two * f2 + f) * step * d0 + (three * f2 - two * f3) * y1 \
        + (f3 - f2) * step * d1
    six = wp.float64(6.0)
    slope = (six * f2 - six * f) / step * (y0 - y1) + (three * f2 - wp.float64(4.0) * f + one) * d0 \
        + (three * f2 - two * f) * d1
    return value, slope


@wp.func
def dynamics(a: GroundedArrays, w: int, q: wp.float64):
    """M(q), M'(q), G(q) and D(q) of world w from its splines."""
    i0, i1, f = sample_of(q, a.samples)
    t = a.energy_of[w]
    e0 = a.energy[t, i0]
    e1 = a.energy[t, i1]
    step = TWO_PI / wp.float64(a.samples)
    M, dM = hermite(e0[0], e0[1], e1[0], e1[1], f, step)
    G, dG = hermite(e0[2], e0[3], e1[2], e1[3], f, step)
    d0 = a.damping[t, i0]
    d1 = a.damping[t, i1]
    D, dD = hermite(d0[0], d0[1], d1[0], d1[1], f, step)
    return M, dM, G, D


@wp.func
def link_at(a: GroundedArrays, w: int, k: int, q: wp.float64):
    """Link k at q: centre in the world (Hermite on the table), its velocity per unit rate (world),
    angle and angle rate per unit rate."""
    i0, i1, f = sample_of(q, a.samples)
    t = a.table_of[w]
    step = TWO_PI / wp.float64(a.samples)
    p0 = a.links0[t, i0, k]
    p1 = a.links0[t, i1, k]
    d0 = a.links1[t, i0, k]
    d1 = a.links1[t, i1, k]
    s0 = a.links2[t, i0, k]
    s1 = a.links2[t, i1, k]
    turn = p1[2] - p0[2]
    turn = turn - TWO_PI * wp.round(turn / TWO_PI)  # the driving link's angle wraps once per turn
    x, dx = hermite(p0[0], d0[0], p1[0], d1[0], f, step)
    z, dz = hermite(p0[1], d0[1], p1[1], d1[1], f, step)
    ang, dang = hermite(p0[2], d0[2], p0[2] + turn, d1[2], f, step)
    vx, ddx = hermite(d0[0], s0[0], d1[0], s1[0], f, step)
    vz, ddz = hermite(d0[1], s0[1], d1[1], s1[1], f, step)
    va, dda = hermite(d0[2], s0[2], d1[2], s1[2], f, step)
    R = a.frame[w]
    s = a.scale[w]
    centre = a.position[w] + R * (a.origin[w] + wp.vec3d(s * x, wp.float64(0.0), s * z))
    return centre, R * wp.vec3d(s * vx, wp.float64(0.0), s * vz), ang, va


@wp.func
def link_rate(a: GroundedArrays, w: int, k: int, q: wp.float64):
    """Link k's angle rate per unit coordinate rate at q (its Hermite spline, as link_at reads it)."""
    i0, i1, f = sample_of(q, a.samples)
    t = a.table_of[w]
    d0 = a.links1[t, i0, k]
    d1 = a.links1[t, i1, k]
    rate, slope = hermite(d0[2], a.links2[t, i0, k][2], d1[2], a.links2[t, i1, k][2], f, TWO_PI / wp.float64(a.samples))
    return rate


@wp.func
def control_force(a: GroundedArrays, w: int, q: wp.float64, body_f: wp.array2d(dtype=wp.spatial_vector),
                  joint_effort: wp.array2d(dtype=float)):
    """The generalized force [N m] of a Control's body wrenches and joint efforts at q."""
    R = a.frame[w]
    normal = -(R * wp.vec3d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0)))
    out = wp.float64(0.0)
    for b in range(a.body_count[w]):
        k = a.body_link[w, b]
        c, e, ang, rate = link_at(a, w, k, q)
        f = body_f[w, b]
        lin = wp.spatial_top(f)
        tor = wp.spatial_bottom(f)
        out += wp.dot(wp.vec3d(lin), e) + wp.dot(wp.vec3d(tor), normal) * rate
    for j in range(a.joint_count[w]):
        sign = a.joint_sign[w, j]
        if sign != wp.float64(0.0):
            rate = wp.float64(0.0)
            kc = a.joint_child[w, j]
            kp = a.joint_parent[w, j]
            if kc >= 0:
                rate += link_rate(a, w, kc, q)
            if kp >= 0:
                rate -= link_rate(a, w, kp, q)
            out += wp.float64(joint_effort[w, j]) * sign * rate
    return out


@functools.cache
def step_kernel(controlled: bool):
    """The grounded step: ``steps`` steps of every running world in one launch (the state stays in
    registers); controlled: compiled with a Control's forces. A world without drive damping (its
    forces all conservative) steps by the symmetric triple jump of three midpoint steps (fourth
    order; the middle one backwards in time), a driven one by one midpoint step (a backward step
    would undo its damping)."""

    @wp.func
    def midpoint(a: GroundedArrays, w: int, q: wp.float64, p: wp.float64, M0: wp.float64, dt: wp.float64,
                 dr: wp.vec3d, body_f: wp.array2d(dtype=wp.spatial_vector), joint_effort: wp.array2d(dtype=float)):
        """One implicit-midpoint step of dt in (q, p = M q') from q, p and M0 = M(q): (q, p, M(q), drive
        torque) at its end."""
        half = wp.float64(0.5) * dt
        qm = q + half * p / M0
        pm = p
        pe = p
        td = wp.float64(0.0)
        for _it in range(ITERATIONS):
            last = qm
            M, dM, G, D = dynamics(a, w, qm)
            vm = pm / M
            force = wp.float64(0.5) * dM * vm * vm + G
            if wp.static(controlled):
                force += control_force(a, w, qm, body_f, joint_effort)
            pf = p + dt * force
            # the force elements' damping at the step's mean momentum (trapezoidal), the velocity drive
            # implicit at the end rate pe / M(q_end) and clamped to its effort limit
            drag = dt * D / (wp.float64(2.0) * M)
            Me = M
            if dr[1] > wp.float64(0.0):
                Me, dMe, Ge, De = dynamics(a, w, wp.float64(2.0) * qm - q)
            pe = (pf - drag * p + dt * dr[1] * dr[0]) / (wp.float64(1.0) + drag + dt * dr[1] / Me)
            td = wp.clamp(dr[1] * (dr[0] - pe / Me), -dr[2], dr[2])
            pe = (pf - drag * p + dt * td) / (wp.float64(1.0) + drag)
            pm = wp.float64(0.5) * (p + pe)
            qm = q + half * pm / M
            if wp.abs(qm - last) <= wp.float64(CONVERGED):
                break
        q1 = wp.float64(2.0) * qm - q
        q1 = q1 - TWO_PI * wp.floor(q1 / TWO_PI)
        M1, dM1, G1, D1 = dynamics(a, w, q1)
        return q1, pe, M1, td

    @wp.kernel(enable_backward=False, module="unique")
    def grounded_step(a: GroundedArrays, q_: wp.array(dtype=wp.float64), v_: wp.array(dtype=wp.float64),
                      torque: wp.array(dtype=wp.float64), stop: wp.array(dtype=wp.int32), steps: int,
                      dt: wp.float64, max_speed: wp.float64, body_f: wp.array2d(dtype=wp.spatial_vector),
                      joint_effort: wp.array2d(dtype=float)):
        w = wp.tid()
        if stop[w] != RUNNING:
            return
        dr = a.drive[w]
        q = q_[w]
        M, dM, G, D = dynamics(a, w, q)
        p = M * v_[w]  # the momentum and M(q) carry over from one midpoint step to the next
        tau = torque[w]
        jump = a.smooth[w] != 0
        for _ in range(steps):
            q1 = q
            p1 = p
            M1 = M
            td = wp.float64(0.0)
            if jump:
                q1, p1, M1, td = midpoint(a, w, q1, p1, M1, JUMP_OUTER * dt, dr, body_f, joint_effort)
                q1, p1, M1, td = midpoint(a, w, q1, p1, M1, JUMP_INNER * dt, dr, body_f, joint_effort)
                q1, p1, M1, td = midpoint(a, w, q1, p1, M1, JUMP_OUTER * dt, dr, body_f, joint_effort)
            else:
                q1, p1, M1, td = midpoint(a, w, q1, p1, M1, dt, dr, body_f, joint_effort)
            if not (wp.isfinite(q1) and wp.isfinite(p1) and wp.isfinite(M1)):
                stop[w] = DIVERGED
                break
            q = q1
            p = p1
            M = M1
            tau = td
            if wp.abs(p / M) * a.reach[w] >= max_speed:
                stop[w] = DIVERGED
                break
        q_[w] = q
        v_[w] = p / M
        torque[w] = tau

    return grounded_step


@wp.kernel
def grounded_bodies(a: GroundedArrays, q_: wp.array(dtype=wp.float64), v_: wp.array(dtype=wp.float64),
                    body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector)):
    """Every spec body's centre-of-mass pose and twist (world frame) at the state."""
    w, b = wp.tid()
    if b >= a.body_count[w]:
        return
    centre, e, ang, rate = link_at(a, w, a.body_link[w, b], q_[w])
    v = v_[w]
    R = a.frame[w]
    normal = -(R * wp.vec3d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0)))
    turn = wp.quat_from_axis_angle(wp.vec3(0.0, -1.0, 0.0), float(ang))
    body_q[w, b] = wp.transform(wp.vec3(centre), a.orientation[w] * turn * a.body_frame[w, b])
    body_qd[w, b] = wp.spatial_vector(wp.vec3(e * v), wp.vec3(normal * (rate * v)))


# -- host side -------------------------------------------------------------------------------------------


class GroundedState:
    """The batch's coordinates: q [rad] (the coordinate joint's angle, wrapped to [0, 2 pi)) and its
    rate v [rad/s], float64 (W,); torque: the drive's torque of the last step [N m]."""

    def __init__(self, q, v, torque):
        self.q, self.v, self.torque = q, v, torque


class GroundedModel:
    """A packed batch of grounded worlds (pack_grounded): step(state, steps, control) advances in
    place; bodies(state) reads every spec body's pose and twist; stop (W,) RUNNING, DIVERGED or
    HALTED per world (state() sets every world running again)."""

    def __init__(self, layouts: list, device, dt: float, max_speed: float):
        self.layouts, self.device, self.dt, self.max_speed = layouts, wp.get_device(device), float(dt), float(max_speed)
        W = len(layouts)
        self.num_worlds = W
        self.max_bodies = max(1, max(len(l.spec.bodies) for l in layouts))
        self.max_joints = max(1, max(len(l.spec.joints) for l in layouts))
        K = max(len(l.tab.groups[0].bodies) for l in layouts)
        S = layouts[0].tab.groups[0].table.samples
        # a batch often repeats one layout (one spec object): each distinct one is read once
        distinct, of_world = {}, np.zeros(W, np.int64)
        for w, lay in enumerate(layouts):
            of_world[w] = distinct.setdefault(id(lay), (len(distinct), lay))[0]
        U = len(distinct)
        h = dict(scale=np.zeros(U), origin=np.zeros((U, 3)), frame=np.zeros((U, 3, 3)), position=np.zeros((U, 3)),
                 orientation=np.zeros((U, 4), np.float32), drive=np.zeros((U, 3)), reach=np.zeros(U),
                 body_count=np.zeros(U, np.int32), body_link=np.zeros((U, self.max_bodies), np.int32),
                 body_frame=np.tile(np.array([0, 0, 0, 1], np.float32), (U, self.max_bodies, 1)),
                 joint_count=np.zeros(U, np.int32), joint_child=np.full((U, self.max_joints), -1, np.int32),
                 joint_parent=np.full((U, self.max_joints), -1, np.int32), joint_sign=np.zeros((U, self.max_joints)),
                 q0=np.zeros(U), v0=np.zeros(U), table_of=np.zeros(U, np.int32), energy_of=np.zeros(U, np.int32),
                 smooth=np.zeros(U, np.int32))
        tables, energies = {}, {}
        for u, lay in distinct.values():
            tab, g = lay.tab, lay.tab.groups[0]
            h["table_of"][u] = tables.setdefault(id(g.table), (len(tables), g.table))[0]
            h["reach"][u] = lay.reach
            h["energy_of"][u] = energies.setdefault(lay.samples.tobytes(), (len(energies), lay.samples))[0]
            h["smooth"][u] = lay.drive[1] == 0.0 and not lay.samples[:, 4].any()
            h["scale"][u], h["origin"][u] = g.scale, g.origin
            h["frame"][u], h["position"][u] = quat_matrix(tab.orientation), tab.position
            h["orientation"][u] = tab.orientation
            h["drive"][u] = lay.drive
            spec = lay.spec
            h["body_count"][u] = len(spec.bodies)
            for b, (group, k, frame) in enumerate(tab.bodies[1:]):  # body 0 of the table's spec is the world
                h["body_link"][u, b], h["body_frame"][u, b] = k, frame
            link = {i - 1: k for k, i in enumerate(g.bodies)}
            index = spec.body_index
            h["joint_count"][u] = len(spec.joints)
            h["joint_sign"][u, :len(spec.joints)] = _joint_signs(lay)
            for j, joint in enumerate(spec.joints):
                h["joint_child"][u, j] = link[index[joint.child]]
                h["joint_parent"][u, j] = -1 if joint.parent is None else link[index[joint.parent]]
            h["q0"][u], h["v0"][u] = g.angle, g.rate
        h = {name: value[of_world] for name, value in h.items()}  # per world
        if len({t.samples for _, t in tables.values()}) != 1:
            raise ValueError("pack_grounded: the worlds' tables differ in samples per turn")
        links = [np.zeros((len(tables), S, K, 3)) for _ in range(3)]
        for i, t in tables.values():
            n = t.links.shape[1]
            links[0][i, :, :n], links[1][i, :, :n], links[2][i, :, :n] = t.links, t.links_d1, t.links_d2
        a = GroundedArrays()
        a.samples = S
        samples = np.stack([e for _, e in energies.values()])
        a.energy = wp.array(np.ascontiguousarray(samples[..., :4]), dtype=wp.vec4d, device=self.device)
        a.damping = wp.array(np.ascontiguousarray(samples[..., 4:]), dtype=wp.vec2d, device=self.device)
        a.smooth = wp.array(h["smooth"], dtype=wp.int32, device=self.device)
        a.energy_of = wp.array(h["energy_of"], dtype=wp.int32, device=self.device)
        a.links0, a.links1, a.links2 = (wp.array(x, dtype=wp.vec3d, device=self.device) for x in links)
        a.table_of = wp.array(h["table_of"], dtype=wp.int32, device=self.device)
        types = dict(scale=wp.float64, origin=wp.vec3d, frame=wp.mat33d, position=wp.vec3d, orientation=wp.quat,
                     drive=wp.vec3d, reach=wp.float64, body_count=wp.int32, body_link=wp.int32, body_frame=wp.quat,
                     joint_count=wp.int32, joint_child=wp.int32, joint_parent=wp.int32, joint_sign=wp.float64)
        for name, dtype in types.items():
            setattr(a, name, wp.array(h[name], dtype=dtype, device=self.device))
        self.arrays = a
        self._start = (h["q0"], h["v0"])
        self.distinct = (len(tables), len(energies))
        self.closure_error = max(l.closure_error for l in layouts)
        self.stop = wp.zeros(W, dtype=wp.int32, device=self.device)
        self._no_f = wp.zeros((1, 1), dtype=wp.spatial_vector, device=self.device)
        self._no_e = wp.zeros((1, 1), dtype=float, device=self.device)

    def state(self) -> GroundedState:
        """A new state at the specs' initial poses and rates; every world running again."""
        d = self.device
        self.stop.zero_()
        return GroundedState(wp.array(self._start[0], dtype=wp.float64, device=d),
                             wp.array(self._start[1], dtype=wp.float64, device=d),
                             wp.zeros(self.num_worlds, dtype=wp.float64, device=d))

    def control(self) -> ChainControl:
        """A new Control (zeros): body_f (W, B) wrenches at the bodies' centres (world frame), joint_effort
        (W, J) torques on revolute joints (on the child, the opposite on the parent), driven or not."""
        return ChainControl(wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.spatial_vector, device=self.device),
                            wp.zeros((self.num_worlds, self.max_joints), dtype=float, device=self.device))

    def check_control(self, control) -> None:
        """chains.check_control_arrays for this batch."""
        check_control_arrays(control, "grounded", self.num_worlds, self.max_bodies, self.max_joints, self.device)

    def step(self, state: GroundedState, steps: int = 1, control=None) -> None:
        """``steps`` steps of every running world, in place (one launch; capturable)."""
        body_f, effort = (self._no_f, self._no_e) if control is None else (control.body_f, control.joint_effort)
        wp.launch(step_kernel(control is not None), dim=self.num_worlds, device=self.device,
                  inputs=[self.arrays, state.q, state.v, state.torque, self.stop, int(steps), wp.float64(self.dt),
                          wp.float64(self.max_speed), body_f, effort])

    def bodies(self, state: GroundedState) -> tuple:
        """(body_q, body_qd) (W, B) of the state: every spec body's centre-of-mass pose and twist."""
        body_q = wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.transform, device=self.device)
        body_qd = wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.spatial_vector, device=self.device)
        wp.launch(grounded_bodies, dim=(self.num_worlds, self.max_bodies), device=self.device,
                  inputs=[self.arrays, state.q, state.v], outputs=[body_q, body_qd])
        return body_q, body_qd


def pack_grounded(specs: list, device=None, *, dt: float, max_speed: float, layouts: list | None = None) -> GroundedModel:
    """A GroundedModel of the specs (their grounded_layout, made here when not given)."""
    layouts = layouts if layouts is not None else [grounded_layout(s) for s in specs]
    return GroundedModel(layouts, device, dt, max_speed)
