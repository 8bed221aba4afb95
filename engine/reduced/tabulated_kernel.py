"""Device side of the tabulated path, less the step: constants, the batch's structs, the row and
factor helpers the step shares, and the kernels that read the reduced state (tracked points and
energy, body poses, freezing). The step kernel is engine.reduced.tabulated_step.

A world's generalized velocity is u = (v, w, qdot_1..L): the base's centre-of-mass velocity and
angular velocity (world frame) and the rates of its L sub-chains' driving coordinates. Link k of
sub-chain g moves with v_k = v + w x d_k + e_k qdot_g and w_k = w + a phi_k' qdot_g, where
d_k = R (o_g + s_g c_k(q)), e_k = s_g R c_k'(q), a = -R y (the plane normal) and phi_k the
link's planar angle; c_k, phi_k and their derivatives are read from the sub-chain's table
(engine.reduced.tabulated_tables) between samples, linearly.
"""

import math

import warp as wp

from engine.reduced.tabulated_layout import BASE_SLOTS as _BASE_SLOTS
from engine.reduced.tabulated_layout import MAX_GROUPS as _MAX_GROUPS
from engine.reduced.tabulated_layout import MAX_LINKS as _MAX_LINKS

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

MAX_GROUPS = wp.constant(_MAX_GROUPS)
NV = wp.constant(6 + _MAX_GROUPS)  # generalized velocities of the largest world
MAX_LINKS = wp.constant(_MAX_LINKS)  # links per sub-chain
BASE_SLOTS = wp.constant(_BASE_SLOTS)
MAX_CONTACTS = BASE_SLOTS + 2 * MAX_GROUPS  # slot k < 8: base point k; 8 + 2 g + e: end e of sub-chain g's shape
MAX_ROWS = wp.constant(MAX_GROUPS + 3 * MAX_CONTACTS)
TWO_PI = wp.constant(2.0 * math.pi)
# the tiled step's registers per thread on CUDA: at 64 an SM holds 32 worlds, at the compiler's 255
# only 8; a batch past TILED_ROUNDS rounds of 32 worlds per SM steps a thread per world
# (tiled_max_worlds). Measured: benchmarks/results/README.md, "Tabulated sub-chains: design notes".
TILED_REGISTERS = 64
TILED_WORLDS_PER_SM = 32
TILED_ROUNDS = 1.5


def tiled_max_worlds(device) -> int:
    """The most worlds ``device`` steps tiled (a block of lanes per world): TILED_ROUNDS rounds of
    TILED_WORLDS_PER_SM worlds on each of its SMs; 0 on the CPU."""
    device = wp.get_device(device)
    return int(TILED_ROUNDS * TILED_WORLDS_PER_SM * device.sm_count) if device.is_cuda else 0


ROW_VECS = wp.constant(3)  # vec4 per row in the rows' scratch (see row_at)
# a row's fields: the first two vec4 are what the PADMM iterations read (and the row velocity they write)
F_RHS = wp.constant(0)  # free velocity v_f (preconditioned)
F_MU = wp.constant(1)  # friction mu (contacts; -1 drive)
F_PEN = wp.constant(2)  # ADMM penalty
F_INV = wp.constant(3)  # 1 / (eta + penalty + P^2 R), set with the Woodbury factor
F_LO = wp.constant(4)  # lower and upper bounds (drives, preconditioned)
F_HI = wp.constant(5)
F_COL = wp.constant(6)  # the row's sub-chain column (6 + g; 5, below 6, for a base slot: none)
# 7: unused (the row velocity at the last iterate is PADMM state, in s1)
F_P = wp.constant(8)  # preconditioner P
F_R = wp.constant(9)  # compliance R (unscaled)
F_FREE = wp.constant(10)  # free drive flag
KINV_VECS = wp.constant(4)  # vec4 per row of the Woodbury inverse (NV <= 16 entries)
DIVERGED_NONFINITE = wp.constant(1)  # TabulatedModel.diverged: the state turned non-finite
DIVERGED_FAST = wp.constant(2)  # the base moved faster than SolverConfig.max_speed

vecnv = wp.types.vector(length=NV, dtype=wp.float32)
vecgroups = wp.types.vector(length=MAX_GROUPS, dtype=wp.float32)
# the sub-chains' sums of a step's set-up: mass, m d (3), the angular block (9), the base's bias force
# and torque (6), each sub-chain's bias force (MAX_GROUPS)
vecsetup = wp.types.vector(length=19 + MAX_GROUPS, dtype=wp.float32)
# an iteration's residuals (primal, dual, natural), largest impulse and merit: the first four
# reduced by their maximum, the merit by its sum (max4_sum1)
vecstats = wp.types.vector(length=5, dtype=wp.float32)


@wp.func
def max4_sum1(a: vecstats, b: vecstats):
    """The reduction of an iteration's statistics: largest of the first four, sum of the last."""
    return vecstats(wp.max(a[0], b[0]), wp.max(a[1], b[1]), wp.max(a[2], b[2]), wp.max(a[3], b[3]), a[4] + b[4])


@wp.struct
class TabulatedWorlds:
    """The batch's tables (value, first and second derivative in the driving coordinate) and every
    world's parameters, as the step reads them (see TabulatedModel): per table its link count and
    contact link; per sub-chain its table, scale, origin, drive (target, damping, effort limit) and
    contact shape (radius, half length, planar angle on its link, friction; radius < 0: none); per
    link its mass and inertia (table frame); per world the base (mass, ground on, ground offset,
    unused), its inertia (state frame), its contact slots (point in the state frame, radius;
    radius < 0: empty) with their friction, gravity and the ground's relief."""

    samples: int
    table_links: wp.array(dtype=wp.int32)
    table_contact_link: wp.array(dtype=wp.int32)
    links0: wp.array3d(dtype=wp.vec3)
    links1: wp.array3d(dtype=wp.vec3)
    links2: wp.array3d(dtype=wp.vec3)
    contact0: wp.array2d(dtype=wp.vec3)
    contact1: wp.array2d(dtype=wp.vec3)
    group_count: wp.array(dtype=wp.int32)
    group_table: wp.array2d(dtype=wp.int32)
    group_scale: wp.array2d(dtype=float)
    group_origin: wp.array2d(dtype=wp.vec3)
    link_mass: wp.array2d(dtype=float)
    link_inertia: wp.array2d(dtype=wp.mat33)
    drive: wp.array2d(dtype=wp.vec3)
    group_shape: wp.array2d(dtype=wp.vec4)
    base: wp.array(dtype=wp.vec4)
    base_inertia: wp.array(dtype=wp.mat33)
    base_slot: wp.array2d(dtype=wp.vec4)
    base_slot_mu: wp.array2d(dtype=float)
    gravity: wp.array(dtype=wp.vec3)
    relief: wp.array(dtype=wp.vec4)  # the ground's relief: amplitude, 2 pi / wavelength, phases (0: flat)


@wp.struct
class TabulatedState:
    """Every world's state: the base's centre-of-mass position, the state frame's orientation,
    the base's velocity and angular velocity (world frame), the driving coordinates and rates."""

    position: wp.array(dtype=wp.vec3)
    orientation: wp.array(dtype=wp.quat)
    velocity: wp.array(dtype=wp.vec3)
    angular_velocity: wp.array(dtype=wp.vec3)
    coord: wp.array2d(dtype=float)
    coord_rate: wp.array2d(dtype=float)


# -- helpers ---------------------------------------------------------------------------------------


@wp.func
def table_read(table: wp.array3d(dtype=wp.vec3), t: int, i0: int, i1: int, f: float, k: int):
    """Entry k of table t between samples i0 and i1 (weight f on i1), linearly."""
    return table[t, i0, k] * (1.0 - f) + table[t, i1, k] * f


@wp.func
def link_read(table: wp.array3d(dtype=wp.vec3), t: int, i0: int, i1: int, f: float, k: int):
    """A link's (x, z, angle) between two samples; the angle steps by its difference wrapped to
    (-pi, pi] (a driving link's angle wraps once per turn between the last sample and the first)."""
    a = table[t, i0, k]
    b = table[t, i1, k]
    d = b[2] - a[2]
    d = d - TWO_PI * wp.round(d / TWO_PI)
    return wp.vec3(a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * d)


@wp.func
def contact_read(table: wp.array2d(dtype=wp.vec3), t: int, i0: int, i1: int, f: float):
    """The contact-centre entry of table t between samples i0 and i1, linearly."""
    return table[t, i0] * (1.0 - f) + table[t, i1] * f


@wp.func
def plane(R: wp.mat33, p: wp.vec3):
    """In-plane vector (x, z, .) in the world frame: the state frame's R times (x, 0, z)."""
    return R * wp.vec3(p[0], 0.0, p[1])


@wp.func
def plane3(R: wp.mat33, p: wp.vec3):
    """Table point (x, z, offset along the normal) in the world frame: R times (x, offset, z)."""
    return R * wp.vec3(p[0], p[2], p[1])


@wp.func
def rot_minus_y(angle: float):
    """Rotation by ``angle`` about -y (counter-clockwise in the sub-chain's plane)."""
    c = wp.cos(angle)
    s = wp.sin(angle)
    return wp.mat33(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c)


@wp.func
def table_index(ang: float, samples: int):
    """Sample pair and weight of a driving coordinate: i0, i1, f (a non-finite one reads sample 0,
    never outside the table)."""
    u = ang * float(samples) / TWO_PI
    u = u - float(samples) * wp.floor(u / float(samples))
    if not (u >= 0.0 and u < float(samples)):
        u = 0.0
    i0 = int(u)
    if i0 >= samples:
        i0 = samples - 1
    i1 = i0 + 1
    if i1 >= samples:
        i1 = 0
    return i0, i1, u - float(i0)


@wp.func
def cholesky(a: wp.array2d(dtype=float), w: int, n: int, out: wp.array2d(dtype=float)):
    """Lower Cholesky factor of a's leading n x n block into out (row-major, NV columns)."""
    for j in range(n):
        s = a[w, j * NV + j]
        for k in range(j):
            s -= out[w, j * NV + k] * out[w, j * NV + k]
        d = wp.sqrt(wp.max(s, 1.0e-20))
        out[w, j * NV + j] = d
        for i in range(j + 1, n):
            t = a[w, i * NV + j]
            for k in range(j):
                t -= out[w, i * NV + k] * out[w, j * NV + k]
            out[w, i * NV + j] = t / d


@wp.func
def chol_solve(L: wp.array2d(dtype=float), w: int, n: int, b: vecnv):
    """(L L^T)^-1 b for the lower factor L of world w (its leading n x n block)."""
    y = b
    for i in range(n):
        s = y[i]
        for k in range(i):
            s -= L[w, i * NV + k] * y[k]
        y[i] = s / L[w, i * NV + i]
    for ii in range(n):
        i = n - 1 - ii
        s = y[i]
        for k in range(i + 1, n):
            s -= L[w, k * NV + i] * y[k]
        y[i] = s / L[w, i * NV + i]
    return y


@wp.func
def forward_norm2(L: wp.array2d(dtype=float), w: int, n: int, b: vecnv, first: int):
    """|L^-1 b|^2 = b^T (L L^T)^-1 b for the lower factor L of world w, b zero before index first
    (so is L^-1 b: the forward substitution starts there)."""
    y = b
    total = float(0.0)
    for i in range(first, n):
        s = y[i]
        for k in range(first, i):
            s -= L[w, i * NV + k] * y[k]
        y[i] = s / L[w, i * NV + i]
        total += y[i] * y[i]
    return total


# row scratch layout: three vec4 per row, fields F_RHS ... F_FREE (an iteration reads the first
# two: (v_f, mu, penalty, 1 / S) and (lower, upper, sub-chain column, velocity)). A drive row's
# Jacobian is zero but in its sub-chain column, a contact row's but in the base's six columns and
# its sub-chain column: the PADMM iterations read a compact copy of the preconditioned rows, two vec4
# per row (the base's six entries, the sub-chain column's, 0; row_dot, row_add).
@wp.func
def row_at(rows: wp.array2d(dtype=wp.vec4), w: int, r: int, c: int):
    """Field c of row r of world w in the rows' scratch."""
    return rows[w, r * ROW_VECS + c / 4][c % 4]


@wp.func
def set_row(rows: wp.array2d(dtype=wp.vec4), w: int, r: int, c: int, value: float):
    """Set field c of row r of world w in the rows' scratch."""
    v = rows[w, r * ROW_VECS + c / 4]
    v[c % 4] = value
    rows[w, r * ROW_VECS + c / 4] = v


@wp.func
def penalty(rows: wp.array2d(dtype=wp.vec4), w: int, r: int):
    """A row's ADMM penalty."""
    return rows[w, r * ROW_VECS][F_PEN]


@wp.func
def set_penalties(rows: wp.array2d(dtype=wp.vec4), w: int, m: int, rho: float, rho0: float):
    """Every row's penalty: rho, or min(rho, rho0) for a free drive row."""
    for r in range(m):
        value = rho
        if row_at(rows, w, r, F_FREE) == 1.0:
            value = wp.min(rho, rho0)
        set_row(rows, w, r, F_PEN, value)


@wp.func
def row_dot(Jc: wp.array2d(dtype=wp.vec4), w: int, r: int, contact: bool, col: int, u: vecnv):
    """Row r of world w's (preconditioned) Jacobian times u, from its compact copy: a contact
    row's base columns, and the sub-chain column ``col`` (below 6: none)."""
    b = Jc[w, 2 * r + 1]
    s = float(0.0)
    if contact:
        a = Jc[w, 2 * r]
        s = a[0] * u[0] + a[1] * u[1] + a[2] * u[2] + a[3] * u[3] + b[0] * u[4] + b[1] * u[5]
    if col >= 6:
        uc = float(0.0)
        for c in range(6, NV):  # a select over constant indices keeps u in registers
            if c == col:
                uc = u[c]
        s += b[2] * uc
    return s


@wp.func
def row_add(Jc: wp.array2d(dtype=wp.vec4), w: int, r: int, contact: bool, col: int, t: float, g: vecnv):
    """g + t times row r of world w's (preconditioned) Jacobian (see row_dot)."""
    out = g
    b = Jc[w, 2 * r + 1]
    if contact:
        a = Jc[w, 2 * r]
        out[0] += a[0] * t
        out[1] += a[1] * t
        out[2] += a[2] * t
        out[3] += a[3] * t
        out[4] += b[0] * t
        out[5] += b[1] * t
    if col >= 6:
        v = b[2] * t
        for c in range(6, NV):
            if c == col:
                out[c] += v
    return out


@wp.func
def jrow_dot(J: wp.array2d(dtype=float), w: int, r: int, n: int, u: vecnv):
    """Row r of world w's Jacobian times u."""
    s = float(0.0)
    for c in range(NV):
        s += J[w, r * NV + c] * u[c]
    return s


@wp.func
def project_row(rows: wp.array2d(dtype=wp.vec4), w: int, r: int, a: float, b: float, c: float):
    """Projection of a row's value (a drive: clamp) or a contact triplet's (a, b, c) onto its cone;
    returns the projected triplet (drives use the first component only)."""
    mu = row_at(rows, w, r, F_MU)
    if mu < 0.0:
        return wp.vec3(wp.clamp(a, row_at(rows, w, r, F_LO), row_at(rows, w, r, F_HI)), 0.0, 0.0)
    return project_cone(mu, a, b, c)


@wp.func
def project_cone(mu: float, a: float, b: float, c: float):
    """Projection of a contact triplet (normal a, tangents b, c) onto the cone of friction mu."""
    t = wp.sqrt(b * b + c * c)
    if t <= mu * a:
        return wp.vec3(a, b, c)
    if mu * t <= -a:
        return wp.vec3(0.0, 0.0, 0.0)
    n = (a + mu * t) / (1.0 + mu * mu)
    return wp.vec3(n, mu * n * b / t, mu * n * c / t)


# -- reading the state -----------------------------------------------------------------------------


@wp.func
def link_pose(worlds: TabulatedWorlds, state: TabulatedState, w: int, gi: int, k: int, R: wp.mat33):
    """Link k of sub-chain gi of world w: its centre of mass relative to the base's (world axes),
    the velocity it adds per unit driving rate (world axes, scaled) and (angle, angle rate per unit
    driving rate, unused) as a vec3 each."""
    t = worlds.group_table[w, gi]
    s = worlds.group_scale[w, gi]
    i0, i1, f = table_index(state.coord[w, gi], worlds.samples)
    c0 = link_read(worlds.links0, t, i0, i1, f, k)
    c1 = table_read(worlds.links1, t, i0, i1, f, k)
    d = R * (worlds.group_origin[w, gi] + wp.vec3(s * c0[0], 0.0, s * c0[1]))
    return d, plane(R, c1) * s, wp.vec3(c0[2], c1[2], 0.0)


@wp.kernel
def body_poses(
    worlds: TabulatedWorlds,
    state: TabulatedState,
    body_count: wp.array(dtype=wp.int32),
    body_group: wp.array2d(dtype=wp.int32),
    body_link: wp.array2d(dtype=wp.int32),
    body_frame: wp.array2d(dtype=wp.quat),
    # out
    body_q: wp.array2d(dtype=wp.transform),
    body_qd: wp.array2d(dtype=wp.spatial_vector),
):
    """Every spec body's centre-of-mass pose (body frame orientation) and twist (centre-of-mass
    velocity, angular velocity; world frame), as engine.model's body_q and body_qd, from the
    reduced state: the base's, or a link's through its table."""
    w, b = wp.tid()
    if b >= body_count[w]:
        return
    p = state.position[w]
    q = state.orientation[w]
    R = wp.quat_to_matrix(q)
    v = state.velocity[w]
    om = state.angular_velocity[w]
    gi = body_group[w, b]
    if gi < 0:
        body_q[w, b] = wp.transform(p, q * body_frame[w, b])
        body_qd[w, b] = wp.spatial_vector(v, om)
        return
    d, e1, ang = link_pose(worlds, state, w, gi, body_link[w, b], R)
    rate = state.coord_rate[w, gi]
    turn = wp.quat_from_axis_angle(wp.vec3(0.0, -1.0, 0.0), ang[0])
    body_q[w, b] = wp.transform(p + d, q * turn * body_frame[w, b])
    axis = -(R * wp.vec3(0.0, 1.0, 0.0))
    body_qd[w, b] = wp.spatial_vector(v + wp.cross(om, d) + e1 * rate, om + axis * (ang[1] * rate))


@wp.kernel
def freeze_worlds(halted: wp.array(dtype=wp.int32), frozen: wp.array(dtype=wp.int32)):
    """Freeze the worlds marked in ``halted``."""
    w = wp.tid()
    if halted[w] != 0:
        frozen[w] = 1
