"""Which MechanismSpecs the tabulated path takes, and their layout (host side, NumPy).

A spec fits when one floating body (the base: no joint to the world) carries sub-chains: the
connected components of the other bodies, each a planar linkage of revolute and inline joints
whose axes are all parallel (one plane normal per world, any direction in the base frame), of
mobility one (3 n - 2 j = 1 with the joints to the base; an inline joint is two rows in the
plane, as a revolute one) and turned by exactly one driven revolute joint to the base. Every link
of a sub-chain is then a function of that joint's coordinate q, tabulated over a turn
(engine.reduced.tabulated_tables), so that a world has 6 + L coordinates.

Frames: the reduced state's frame (the "state frame") is the base's body frame turned by a
constant rotation (TabulatedLayout.frame) that takes its y axis to the plane normal; a link's
"table frame" is that frame turned about -y by the link's planar angle phi (x along the link,
y the normal), its body frame a constant rotation (SubChain.link_frame) away. A sub-chain's scale
is the longest distance from a link's centre of mass to one of its joints, or from its origin to
a pivot on the base. A table's cache key: (samples, link count, every joint's pair of links (the
base as K), their anchors at unit scale, the driving link, the sign and offset of its angle
against q, the contact shape's link and centre at unit scale), every number rounded to
KEY_DIGITS decimals.

Nothing here knows a mechanism's anatomy: contact slots come from shapes
(TabulatedLayout.base_slots, SubChain.shape) and tracked points are the spec's own.
"""

from __future__ import annotations

import contextlib
import gc
import hashlib
import math
import operator
from dataclasses import dataclass, field

import numpy as np

from engine.pack import collision_pairs
from engine.reduced.tabulated_tables import (NEWTON_TOLERANCE, START_TOLERANCE, TABLE_SAMPLES, SubChainTable, _Planar,
                                            cached, cached_branches, cached_table, wrap)
from engine.spatial import cross, quat_matrix
from engine.spec import JointType, MechanismSpec, ShapeType

__all__ = ["BASE_SLOTS", "MAX_GROUPS", "MAX_LINKS", "SubChain", "TabulatedLayout", "tabulated_analyses",
           "tabulated_layout", "tabulated_layouts"]

MAX_GROUPS = 8  # sub-chains per world (the kernel's generalized velocities: 6 + MAX_GROUPS)
MAX_LINKS = 8  # bodies per sub-chain
BASE_SLOTS = 8  # contact slots of the base's shapes (a box's corners, sphere centres, capsule ends)
KEY_DIGITS = 12  # normalized geometry is rounded to this many decimals in a table's cache key (and a new table made from it)
PLANE_TOLERANCE = 1e-6  # relative to a sub-chain's scale: off-plane offsets and axis mismatches it accepts

_Y = np.array([0.0, 1.0, 0.0])


def matrix_quat(m: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (w >= 0)."""
    t = np.trace(m)
    if t > 0.0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q) / np.linalg.norm(q)
    return q if q[3] >= 0.0 else -q


def rot_minus_y(angle: float) -> np.ndarray:
    """Rotation by ``angle`` about -y: counter-clockwise in the (x, z) plane."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def _turn_angle(m: np.ndarray, axis: np.ndarray) -> float:
    """The angle [rad] of rotation m about the unit ``axis``, as engine.joints measures a revolute
    joint's coordinate (2 atan2 of the quaternion's part along the axis and its w >= 0)."""
    q = matrix_quat(m)
    return 2.0 * math.atan2(float(q[:3] @ axis), float(q[3]))


@dataclass
class SubChain:
    """One sub-chain of a world. joint: the spec index of its driving joint; bodies: spec body
    indices in table link order; table (unit scale) and scale [m]; origin: its driving pivot in
    the state frame relative to the base's centre of mass [m] (y: the plane of its links'
    centres); angle, rate: the driving coordinate q [rad] and its rate [rad/s] at the start;
    link_mass (K,) [kg], link_inertia (K, 3, 3) about the centre in the table frame [kg m^2];
    link_frame (K, 4): each body's orientation in its table frame (quaternion x, y, z, w);
    drive: target velocity [rad/s], damping [N m s/rad], effort limit [N m]; shape: the contact
    shape's spec index, radius [m], half length [m] (0: a sphere), its axis's planar angle in the
    link's table frame [rad] and its friction with the ground (the geometric mean), or None."""

    joint: int
    bodies: list
    table: SubChainTable
    scale: float
    origin: np.ndarray
    angle: float
    rate: float
    link_mass: np.ndarray
    link_inertia: np.ndarray
    link_frame: np.ndarray
    drive: tuple
    shape: tuple | None = None

    @property
    def closure_error(self) -> float:
        """The table's closure error at this sub-chain's scale [m]."""
        return self.table.closure_error * self.scale


@dataclass
class TabulatedLayout:
    """A MechanismSpec read as a floating base carrying tabulated sub-chains (see the module
    docstring). base: the base's spec index; frame: the state frame in the base's body frame
    (quaternion; identity when the joints turn about the base's y axis); position, orientation,
    velocity, angular_velocity: the state frame's start (centre of mass [m], quaternion, world
    frame [m/s], [rad/s]); base_mass [kg], base_inertia (3, 3) in the state frame [kg m^2];
    groups: the SubChains; base_slots: the base's contact points, each (point (3,) in the state
    frame relative to the centre of mass [m], radius [m] below it, friction, shape index);
    ground: None or (offset [m], friction) of the plane z = offset; points: per tracked point
    (sub-chain or -1 for the base, link, offset (3,) [m] from that body's centre of mass in its
    state or table frame); bodies: per spec body (sub-chain or -1, link, its orientation in the
    state or table frame as a quaternion)."""

    spec: MechanismSpec
    base: int
    frame: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    base_mass: float
    base_inertia: np.ndarray
    groups: list
    base_slots: list
    ground: tuple | None
    gravity: np.ndarray
    points: list = field(default_factory=list)
    bodies: list = field(default_factory=list)

    @property
    def point_names(self) -> list:
        """The spec's tracked point names, in its order."""
        return [p.name for p in self.spec.points]

    @property
    def closure_error(self) -> float:
        """The largest closure error of this world's tables at their scales [m] (0 without any)."""
        return max((g.closure_error for g in self.groups), default=0.0)


def _choose_base(spec: MechanismSpec) -> int:
    """The base: the body that is the parent of the most driven joints, then the body of the most
    driven joints, then of the most joints, then the first."""
    score = [[0, 0, 0, -i] for i in range(len(spec.bodies))]
    index = spec.body_index
    for joint in spec.joints:
        if joint.parent is not None and joint.drive is not None:
            score[index[joint.parent]][0] += 1
        for name in (joint.parent, joint.child):
            if name is not None:
                score[index[name]][1] += joint.drive is not None
                score[index[name]][2] += 1
    return max(range(len(spec.bodies)), key=lambda i: score[i])


def _components(spec: MechanismSpec, base: int) -> list:
    """The connected components of the bodies other than the base (lists of body indices in spec
    order), ordered by their first body."""
    index = spec.body_index
    root = list(range(len(spec.bodies)))

    def find(i):
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    for joint in spec.joints:
        a, b = index[joint.parent], index[joint.child]
        if base not in (a, b):
            root[find(a)] = find(b)
    groups = {}
    for i in range(len(spec.bodies)):
        if i != base:
            groups.setdefault(find(i), []).append(i)
    return sorted(groups.values(), key=lambda g: g[0])


def _frame_to(normal: np.ndarray) -> np.ndarray:
    """A rotation matrix Q with Q y = +-normal: the identity when the normal is along y, else the
    shortest turn of y onto the normal (its sign nearest y)."""
    n = normal if normal @ _Y >= 0.0 else -normal
    axis = cross(_Y, n)
    s, c = np.linalg.norm(axis), float(_Y @ n)
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def _planar_angle(m: np.ndarray) -> float:
    """The planar angle (about -y) of a body orientation m in the state frame: its x axis's
    direction in (x, z), or its z axis's when x lies along y."""
    x = m[:, 0]
    if math.hypot(x[0], x[2]) > 1e-3:
        return math.atan2(x[2], x[0])
    z = m[:, 2]
    return math.atan2(-z[0], z[2])


def _rounded(values) -> tuple:
    """Numbers of a table's cache key (+ 0.0: no negative zero)."""
    return tuple(round(float(v), KEY_DIGITS) + 0.0 for v in np.ravel(values))


# -- the array path ------------------------------------------------------------------------------------
#
# tabulated_layout reads a spec with arrays: every body's and joint's matrices at once, and the
# sub-chains that share their local structure (a walker's identical linkages) together;
# tabulated_layouts reads the specs of one structure (a study's walkers of one topology) together as
# well, every array with a leading axis of specs. Each number is computed
# by the operations tabulated_plain._plain_layout applies to it one item at a time (stacked matmul runs the same
# BLAS call per item; element-wise NumPy and Python floats round alike; reductions, transcendental
# functions and Python's round keep their own form), so both give the same layout to the last bit.
# What depends only on a spec's structure (names, joint graph, shapes' bodies, types and groups) is
# cached by that structure. A spec the array path does not take as it is (a check fails, or an
# array is not a C-ordered float64 of its shape) goes through _plain_layout, which names the first
# thing wrong.

_F64 = np.dtype(np.float64)
_STRUCTURES: dict = {}  # structure key -> _Structure, or None where _plain_layout refuses the structure
STRUCTURE_CACHE = 256  # structures kept (by key, oldest dropped first)


@dataclass
class _Chain:
    """One sub-chain's structure: comp (spec body indices, table order), joints (spec joint indices),
    driver (spec index), ends per joint (parent, child) as (is base, body index, link index or K),
    k_d (the driving link), base_side, contact (shape index, link) or None, signature (what
    sub-chains computed together share)."""

    comp: list
    joints: list
    driver: int
    ends: list
    k_d: int
    base_side: str
    contact: tuple | None
    signature: tuple


@dataclass
class _Structure:
    """What tabulated_layout reads from a spec's structure alone (see _analyse)."""

    base: int
    ends: list
    chains: list
    batches: list
    base_shapes: list
    where_is: dict
    point_bodies: list
    point_at: list = field(default_factory=list)  # per tracked point (sub-chain or -1, link)
    body_at: list = field(default_factory=list)  # per spec body (sub-chain or -1, link)


def _structure_key(spec: MechanismSpec) -> tuple:
    return (tuple(b.name for b in spec.bodies),
            tuple((j.parent, j.child, j.type, j.drive is not None) for j in spec.joints),
            tuple((s.body, s.type, s.collision_group) for s in spec.shapes), spec.ground is None,
            tuple(p.body for p in spec.points))


def _analyse(spec: MechanismSpec) -> _Structure | None:
    """The structure's facts, in _plain_layout's terms; None when one of its structural checks fails."""
    joints = spec.joints
    index = spec.body_index
    if any(joint.parent is None for joint in joints):
        return None
    base = _choose_base(spec)
    components = _components(spec, base)
    if len(components) > MAX_GROUPS:
        return None
    member = {b: g for g, comp in enumerate(components) for b in comp}
    of_group = [[] for _ in components]
    ends = []
    for j, joint in enumerate(joints):
        a, b = index[joint.parent], index[joint.child]
        ends.append((a, b))
        of_group[member[b] if a == base else member[a]].append(j)
        if joint.type not in (JointType.REVOLUTE, JointType.INLINE) or (joint.drive is not None and base not in (a, b)):
            return None
    shapes_of = {}
    if spec.ground is not None:
        for s, shape in enumerate(spec.shapes):
            shapes_of.setdefault(index[shape.body], []).append(s)
    if any(b >= 0 for _, b in collision_pairs(spec)):
        return None
    chains = []
    for comp, joint_list in zip(components, of_group):
        K = len(comp)
        driven = [j for j in joint_list if joints[j].drive is not None]
        if K > MAX_LINKS or 3 * K - 2 * len(joint_list) != 1 or len(driven) != 1:
            return None
        link_of = {i: k for k, i in enumerate(comp)}
        driver = joints[driven[0]]
        base_side = "parent" if index[driver.parent] == base else "child"
        chain_ends = []
        for j in joint_list:
            pair = []
            for i in ends[j]:
                pair.append((i == base, i, K if i == base else link_of[i]))
            chain_ends.append(tuple(pair))
        k_d = link_of[index[driver.child if base_side == "parent" else driver.parent]]
        on = [s for i in comp for s in shapes_of.get(i, [])]
        contact = None
        if len(on) > 1:
            return None
        if on:
            item = spec.shapes[on[0]]
            if item.type not in (ShapeType.CAPSULE, ShapeType.SPHERE):
                return None
            contact = (on[0], link_of[index[item.body]])
        signature = (K, tuple((joints[j].type, tuple((e[0], e[2]) for e in pair)) for j, pair in zip(joint_list, chain_ends)),
                     joint_list.index(driven[0]), k_d, base_side,
                     None if contact is None else (contact[1], spec.shapes[contact[0]].type))
        chains.append(_Chain(list(comp), list(joint_list), driven[0], chain_ends, k_d, base_side, contact, signature))
    batches = {}
    for g, chain in enumerate(chains):
        batches.setdefault(chain.signature, []).append(g)
    slots = {ShapeType.BOX: 8, ShapeType.CAPSULE: 2, ShapeType.SPHERE: 1}
    base_shapes = shapes_of.get(base, [])
    if any(spec.shapes[s].type not in slots for s in base_shapes) or \
            sum(slots[spec.shapes[s].type] for s in base_shapes) > BASE_SLOTS:
        return None
    where_is = {base: (-1, 0)}
    for g, chain in enumerate(chains):
        for k, i in enumerate(chain.comp):
            where_is[i] = (g, k)
    point_bodies = [index[p.body] for p in spec.points]
    return _Structure(base, ends, chains, list(batches.values()), base_shapes, where_is, point_bodies,
                      [where_is[i] for i in point_bodies], [where_is[i] for i in range(len(spec.bodies))])


def _regular(arrays: list, shape: tuple) -> bool:
    """Whether every item is a float64 ndarray of ``shape`` (its dimensions, first length and size;
    C order is checked where _joined copies the items). Dtypes compare by value: an unpickled
    array's (a spec built in a worker process) is an equal float64 dtype but another object."""
    return (set(map(type, arrays)) <= {np.ndarray} and set(map(_DTYPE, arrays)) <= {_F64}
            and set(map(_NDIM, arrays)) <= {len(shape)} and set(map(len, arrays)) <= {shape[0]}
            and set(map(_SIZE, arrays)) <= {math.prod(shape)})


def _quat_matrices(q: np.ndarray) -> np.ndarray:
    """quat_matrix of every row of q (..., 4): the same operations, element by element."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1)], axis=-2)


def _dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a[i] @ b[i] of the last axes (matmul's dot, as each 1-D ``a @ b`` and ``a.dot(b)`` computes it)."""
    return (a[..., None, :] @ b[..., :, None])[..., 0, 0]


def _matrix_quats(m: np.ndarray) -> np.ndarray:
    """matrix_quat of every matrix of m (N, 3, 3): the same operations and branches, item by item."""
    n = m.shape[0]
    q = np.empty((n, 4))
    t = (m[:, 0, 0] + m[:, 1, 1]) + m[:, 2, 2]  # np.trace's sum
    up = t > 0.0
    if up.any():
        a, s = m[up], 2.0 * np.sqrt(t[up] + 1.0)
        q[up] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 1, 0] - a[:, 0, 1]) / s,
                          0.25 * s], axis=-1)
    down = ~up
    if down.any():
        a = m[down]
        rows = np.arange(len(a))
        i = np.argmax(np.diagonal(a, axis1=1, axis2=2), axis=1)
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(np.maximum(1.0 + a[rows, i, i] - a[rows, j, j] - a[rows, k, k], 1e-300))
        part = np.empty((len(a), 4))
        part[rows, 3] = (a[rows, k, j] - a[rows, j, k]) / s
        part[rows, i] = 0.25 * s
        part[rows, j] = (a[rows, j, i] + a[rows, i, j]) / s
        part[rows, k] = (a[rows, k, i] + a[rows, i, k]) / s
        q[down] = part
    q = q / np.sqrt(_dots(q, q))[:, None]  # np.linalg.norm: sqrt(q.dot(q))
    flip = ~(q[:, 3] >= 0.0)
    q[flip] = -q[flip]
    return q


_BOX_SIGNS = np.array([[-1.0 if k % 2 else 1.0, -1.0 if (k // 2) % 2 else 1.0, -1.0 if k >= 4 else 1.0]
                       for k in range(8)])  # a box's corners in _plain_layout's order


def _rot_minus_ys(angles) -> np.ndarray:
    """rot_minus_y of every angle (Python floats or NumPy scalars; math's cosine and sine), stacked."""
    angles = [float(a) for a in angles]
    c = np.array([math.cos(a) for a in angles])
    s = np.array([math.sin(a) for a in angles])
    out = np.zeros((len(angles), 3, 3))
    out[:, 0, 0], out[:, 0, 2], out[:, 1, 1], out[:, 2, 0], out[:, 2, 2] = c, -s, 1.0, s, c
    return out


def _rounded_rows(values: np.ndarray) -> list:
    """_rounded of every row of values (N, ...): Python's round(v, KEY_DIGITS) + 0.0, found as
    rint(v 10^6) / 10^6 (the same nearest double) where v 10^6 is clearly off a half, else by round."""
    flat = values.reshape(len(values), -1)
    y = flat * 10.0**KEY_DIGITS
    fraction = y - np.floor(y)
    out = np.rint(y) / 10.0**KEY_DIGITS + 0.0
    clear = (np.abs(fraction - 0.5) > 1e-9 + 4e-16 * np.abs(y)) & (np.abs(y) < 2.0**50)
    if not clear.all():
        for r, c in zip(*np.nonzero(~clear)):
            out[r, c] = round(float(flat[r, c]), KEY_DIGITS) + 0.0
    return [tuple(row) for row in out.tolist()]


def tabulated_layout(spec: MechanismSpec, *, samples: int = TABLE_SAMPLES) -> TabulatedLayout:
    """Read ``spec`` as a floating base carrying one-DoF planar sub-chains and tabulate each over
    ``samples`` per turn (cached by geometry: see the module docstring). Raises ValueError with one
    line naming the body, joint or shape that prevents it. The base is the parent of the most
    driven joints (then the body of the most driven joints, of the most joints, the first).

    The analysis runs on arrays (see the array path's notes above); a spec that it does not take
    as it is goes through _plain_layout, item by item, with the same result (tabulated_layouts
    analyses a batch together)."""
    structure = _structure(spec)
    layout = None if structure is None else _array_layout(spec, structure, samples)
    return layout if layout is not None else _plain(spec, samples)


def _structure(spec: MechanismSpec, key: tuple | None = None) -> _Structure | None:
    """The cached _Structure of the spec's structure key (analysed on first sight)."""
    key = _structure_key(spec) if key is None else key
    structure = _STRUCTURES.get(key, False)
    if structure is False:
        structure = _analyse(spec)
        if len(_STRUCTURES) >= STRUCTURE_CACHE:
            _STRUCTURES.pop(next(iter(_STRUCTURES)))
        _STRUCTURES[key] = structure
    return structure


def tabulated_layouts(specs, *, samples: int = TABLE_SAMPLES, analyses=None) -> list:
    """tabulated_layout of every spec, analysed together: per spec its TabulatedLayout, or the
    ValueError tabulated_layout raises for it (returned, not raised). Specs of one structure key
    (a study's walkers of one topology: the same bodies, joint graph and shapes in other
    dimensions) share one structural analysis and go through the array path as one batch, every
    number by the operations of a spec alone; then, in the order of ``specs``, each spec's tables
    are looked up (or made) and a spec the array path left goes item by item, as one call per spec
    would. Equal to tabulated_layout of each spec in turn, to the last bit.

    analyses: per spec what tabulated_analyses gave for it, perhaps in another process (None
    entries, and entries whose spec_tie or sample count differ, are analysed here); the caller
    vouches that the specs have not changed since."""
    with _collector_off():
        return _layouts_together(list(specs), samples, analyses)


def tabulated_analyses(specs, *, samples: int = TABLE_SAMPLES) -> list:
    """The array path's part of tabulated_layouts, per spec (everything but the tables, which are
    looked up in the packing process's cache): what a process that built the specs can work out
    beside them and send with them (morphopt.build's workers), so that the packing process only
    reads tables and fills arrays. Each entry, (spec_tie, samples, numbers), is small and
    picklable."""
    specs = list(specs)
    out = [None] * len(specs)
    with _collector_off():
        for key, indices in _by_structure(specs).items():
            structure, digest = _structure(specs[indices[0]], key), _digest(key)
            made = _pending_layouts([specs[i] for i in indices], structure, samples) if structure else \
                [None] * len(indices)
            for i, numbers in zip(indices, made):
                out[i] = ((digest, _body_numbers(specs[i])), samples, numbers)
    return out


@contextlib.contextmanager
def _collector_off():
    """A block without the cyclic garbage collector: thousands of new objects, none of them
    garbage, would only set it off again and again."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if collecting:
            gc.enable()


def _by_structure(specs: list) -> dict:
    """Structure key -> the indices of the specs of that structure, in order."""
    groups = {}
    for i, spec in enumerate(specs):
        groups.setdefault(_structure_key(spec), []).append(i)
    return groups


def spec_tie(spec: MechanismSpec) -> tuple:
    """What ties an analysis made elsewhere to its spec: its structure's digest, body masses and
    positions (engine.prepare's entries; they do not prove a spec unchanged)."""
    return _digest(_structure_key(spec)), _body_numbers(spec)


def _body_numbers(spec: MechanismSpec) -> tuple:
    """The bodies' masses and positions (spec_tie's numbers)."""
    bodies = spec.bodies
    return tuple(map(_MASS, bodies)), b"".join(np.asarray(b.position, float).tobytes() for b in bodies)


_MASS = operator.attrgetter("mass")


def _digest(key: tuple) -> bytes:
    """A structure key's digest, the same in every process (str hashes are salted per process)."""
    return hashlib.blake2b(repr(key).encode(), digest_size=16).digest()


def _layouts_together(specs: list, samples: int, analyses=None) -> list:
    """tabulated_layouts' work (the collector off)."""
    pending, structures = [None] * len(specs), [None] * len(specs)
    for key, indices in _by_structure(specs).items():
        structure = _structure(specs[indices[0]], key)
        if structure is None:
            continue
        left = indices
        if analyses is not None:
            digest, left = _digest(key), []
            for i in indices:
                given = analyses[i]
                if given is not None and given[1] == samples and given[0] == (digest, _body_numbers(specs[i])):
                    pending[i], structures[i] = given[2], structure
                else:
                    left.append(i)
        for i, numbers in zip(left, _pending_layouts([specs[i] for i in left], structure, samples) if left else ()):
            pending[i], structures[i] = numbers, structure
    # the tables cached now, for every sub-chain of one key at once (cached_table's first match)
    by_key = {}
    for i, numbers in enumerate(pending):
        for g, (fields, key, _, closed, _, _) in enumerate(numbers["chains"] if numbers else ()):
            by_key.setdefault(key, []).append((i, g, closed, fields["angle"]))
    found = {}
    for key, items in by_key.items():
        tables = cached_branches(key, np.array([c for _, _, c, _ in items]), np.array([q for _, _, _, q in items]))
        for (i, g, _, _), table in zip(items, tables):
            found[i, g] = table
    out = []
    for i, spec in enumerate(specs):
        try:
            if pending[i] is None:
                out.append(_plain(spec, samples))
            else:
                known = [found.get((i, g)) for g in range(len(pending[i]["chains"]))]
                out.append(_finish(spec, structures[i], pending[i], samples, known))
        except ValueError as exc:
            out.append(exc)
    return out


def _array_layout(spec: MechanismSpec, st: _Structure, samples: int) -> TabulatedLayout | None:
    """tabulated_layout on arrays for a spec of structure ``st``; None where _plain_layout must decide."""
    numbers = _pending_layouts([spec], st, samples)[0]
    return None if numbers is None else _finish(spec, st, numbers, samples)


class _Refused(Exception):
    """A check of the array path failed for the specs that ``mask`` marks (None: unknown which)."""

    def __init__(self, mask=None):
        super().__init__()
        self.mask = None if mask is None else np.asarray(mask, bool)


def _takes(spec: MechanismSpec) -> tuple | None:
    """The spec's vectors the array path reads (every body's com and inertia, every joint's axis,
    parent and child position) when it takes the spec's values as they are: no joint limit,
    armature, damping or drive stiffness, and every vector a float64 array of its shape (_regular;
    _joined refuses one that is not C-ordered); else None."""
    bodies, joints = spec.bodies, spec.joints
    values = set(map(_JOINT_VALUES, joints))  # (limit_lower, limit_upper, armature, damping) of each
    if any(math.isfinite(low) or math.isfinite(high) or armature > 0.0 or damping > 0.0
           for low, high, armature, damping in values):
        return None
    if any(drive is not None and drive.stiffness > 0.0 for drive in map(_DRIVE, joints)):
        return None
    vectors = (list(map(_COM, bodies)), list(map(_INERTIA, bodies)), list(map(_AXIS, joints)),
               list(map(_PARENT_POSITION, joints)), list(map(_CHILD_POSITION, joints)))
    if all(_regular(v, shape) for v, shape in zip(vectors, ((3,), (3, 3), (3,), (3,), (3,)))):
        return vectors
    return None


_JOINT_VALUES = operator.attrgetter("limit_lower", "limit_upper", "armature", "damping")
_DRIVE, _AXIS = operator.attrgetter("drive"), operator.attrgetter("axis")
_PARENT_POSITION, _CHILD_POSITION = operator.attrgetter("parent_position"), operator.attrgetter("child_position")
_COM, _INERTIA = operator.attrgetter("com"), operator.attrgetter("inertia")
_ORIENTATION, _POSITION = operator.attrgetter("orientation"), operator.attrgetter("position")
_ANGULAR_VELOCITY = operator.attrgetter("angular_velocity")
_PARENT_ORIENTATION = operator.attrgetter("parent_orientation")
_CHILD_ORIENTATION = operator.attrgetter("child_orientation")
_DTYPE, _NDIM, _SIZE = operator.attrgetter("dtype"), operator.attrgetter("ndim"), operator.attrgetter("size")


def _joined(arrays: list, shape: tuple) -> np.ndarray:
    """Float64 arrays (checked by _regular) stacked into one array of ``shape`` by copying their
    bytes (the same numbers as np.array of the list, at a third of its cost); raises _Refused when
    one is not C-ordered or the bytes do not fill ``shape`` (an item of other lengths)."""
    try:
        data = bytearray(b"".join(arrays))  # a strided array has no bytes-like form: TypeError
    except TypeError:
        raise _Refused() from None
    if len(data) != 8 * math.prod(shape):
        raise _Refused()
    return np.frombuffer(data, dtype=np.float64).reshape(shape) if data else np.zeros(shape)


def _pending_layouts(specs: list, st: _Structure, samples: int) -> list:
    """The array path's numbers (everything but the tables: see _finish) for specs of structure
    ``st``, computed together (a leading axis of specs on every array; each number by the
    operations of one spec alone); None for a spec whose checks fail (_plain_layout decides)."""
    out = [None] * len(specs)
    vectors = [_takes(spec) for spec in specs]
    taken = [i for i, v in enumerate(vectors) if v is not None]
    while taken:
        try:
            made = _numbers_of([specs[i] for i in taken], [vectors[i] for i in taken], st, samples)
        except _Refused as refused:
            if len(taken) == 1:
                break
            mask = refused.mask
            if mask is None:  # the batch's arrays do not stack: ask each spec alone
                mask = [_pending_layouts([specs[i]], st, samples)[0] is None for i in taken]
            taken = [i for i, bad in zip(taken, mask) if not bad]
            continue
        for i, numbers in zip(taken, made):
            out[i] = numbers
        break
    return out


def _finish(spec: MechanismSpec, st: _Structure, numbers: dict, samples: int, known=None) -> TabulatedLayout:
    """The layout of a spec from its array-path numbers: its sub-chains' tables in order (known:
    per sub-chain the table cached_branches found, or None; a table no longer cached, or none:
    cached_table looks it up or computes a new one, which may raise ValueError: the linkage jams), base slots and the rest (what
    _assemble makes, its numbers computed with the batch)."""
    groups = []
    for g, (fields, key, planar, closed, contact, what) in enumerate(numbers["chains"]):
        table = known[g] if known is not None and cached(key, known[g]) else \
            cached_table(key, planar, closed, fields["angle"], samples, contact, what)
        groups.append(SubChain(table=table, **fields))
    base, Q, ground = st.base, numbers["Q"], numbers["ground"]
    base_body = spec.bodies[base]
    base_slots = _base_slots(spec, st.base_shapes, base_body.com, Q, ground)
    points = [(g, k, local) for (g, k), local in zip(st.point_at, numbers["points"])]
    frame = numbers["base_frame"]
    body_frames = [(-1, 0, frame) if g < 0 else (g, k, groups[g].link_frame[k]) for g, k in st.body_at]
    return TabulatedLayout(spec, base, numbers["frame"], numbers["base_com"], numbers["orientation"],
                           base_body.velocity.copy(), base_body.angular_velocity.copy(), float(base_body.mass),
                           numbers["base_inertia"], groups, base_slots, ground, np.asarray(spec.gravity, float),
                           points, body_frames)


def _numbers_of(specs: list, vectors: list, st: _Structure, samples: int) -> list:
    """_pending_layouts for specs that passed _takes (vectors: what it gave for each): per spec
    the numbers _finish reads; raises _Refused for specs a check fails."""
    S = len(specs)
    bodies0, joints0 = specs[0].bodies, specs[0].joints
    B, J = len(bodies0), len(joints0)
    gathered = []
    for getter, items, shape in ((_ORIENTATION, "bodies", (4,)), (_POSITION, "bodies", (3,)),
                                 (_ANGULAR_VELOCITY, "bodies", (3,)), (_PARENT_ORIENTATION, "joints", (4,)),
                                 (_CHILD_ORIENTATION, "joints", (4,))):
        flat = [a for spec in specs for a in map(getter, getattr(spec, items))]
        count = B if items == "bodies" else J
        try:  # whatever numbers they are, as _plain_layout reads them
            array = np.array(flat, dtype=float)
        except (TypeError, ValueError):
            raise _Refused() from None
        if array.shape != (S * count,) + shape:
            raise _Refused()
        gathered.append(array.reshape((S, count) + shape))
    orientation, position, angular_velocity, parent_frames, child_frames = gathered
    joint_frames = np.stack([parent_frames, child_frames], axis=2)
    com_local, inertia, axes, parent_positions, child_positions = (
        _joined([a for v in vectors for a in v[k]], (S, n) + shape)
        for k, (n, shape) in enumerate(((B, (3,)), (B, (3, 3)), (J, (3,)), (J, (3,)), (J, (3,)))))
    base = st.base
    R_base = _quat_matrices(orientation[:, base])  # quat_matrix of each base's orientation
    base_com = position[:, base] + (R_base @ com_local[:, base, :, None])[..., 0]
    world_R = _quat_matrices(orientation)  # (S, B, 3, 3)
    frames = _quat_matrices(joint_frames)  # (S, J, 2, 3, 3): every joint's parent and child anchor frame
    # one plane normal: every joint's axis in the base frame
    Q = np.empty((S, 3, 3))
    Q[:] = np.eye(3)
    if J:
        a_index = np.array([a for a, _ in st.ends])
        b_index = np.array([b for _, b in st.ends])
        R_base_T = R_base.swapaxes(-1, -2)[:, None]
        axis_p = ((R_base_T @ world_R[:, a_index] @ frames[:, :, 0]) @ axes[..., None])[..., 0]
        axis_c = ((R_base_T @ world_R[:, b_index] @ frames[:, :, 1]) @ axes[..., None])[..., 0]
        normal = axis_p[:, 0]
        off, tilt = cross(normal[:, None], axis_p), cross(axis_c, axis_p)
        revolute = np.array([j.type == JointType.REVOLUTE for j in joints0])
        refused = (np.sqrt(_dots(off, off))[:, 1:] > PLANE_TOLERANCE).any(axis=1) | \
            (revolute & (np.sqrt(_dots(tilt, tilt)) > PLANE_TOLERANCE)).any(axis=1)
        if refused.any():
            raise _Refused(refused)
        frames_to = {}  # _frame_to of each distinct normal (a batch's normals are mostly one)
        for s, key in enumerate(map(bytes, normal)):
            if key not in frames_to:
                frames_to[key] = _frame_to(normal[s])
            Q[s] = frames_to[key]
    R_state = R_base @ Q
    R_state_T = R_state.swapaxes(-1, -2)
    state_R = R_state_T[:, None] @ world_R
    com_world = position + (world_R @ com_local[..., None])[..., 0]
    grounds = []
    refused = np.zeros(S, bool)
    for s, spec in enumerate(specs):
        ground = None
        if spec.ground is not None:
            g = spec.ground
            if np.abs(g.normal - np.array([0.0, 0.0, 1.0])).max() > 1e-9 or g.restitution > 0.0 or \
                    any(shape.restitution > 0.0 for shape in spec.shapes):
                refused[s] = True
            ground = (float(g.offset), float(g.friction))
        grounds.append(ground)
    if refused.any():
        raise _Refused(refused)
    chains = [[None] * len(st.chains) for _ in range(S)]
    numbers = (R_state_T, state_R, world_R, R_base, frames, com_world, com_local, inertia, axes, parent_positions,
               child_positions, position, angular_velocity, base_com, grounds, samples)
    for batch in st.batches:
        made = _sub_chain_batch(specs, st, batch, *numbers)
        for s in range(S):
            for g, chain in zip(batch, made[s]):
                chains[s][g] = chain
    # _assemble's numbers: tracked points in their link's table frame (or the base's state frame),
    # the frames as quaternions, the base's inertia in the state frame
    points = np.zeros((S, len(st.point_at), 3))
    on_link = [p for p, (g, _) in enumerate(st.point_at) if g >= 0]
    on_base = [p for p, (g, _) in enumerate(st.point_at) if g < 0]
    position = np.array([[p.position for p in spec.points] for spec in specs], dtype=float).reshape(S, -1, 3)
    if on_link:
        frames_at = np.array([[chains[s][g][0]["link_frame"][k] for g, k in (st.point_at[p] for p in on_link)]
                              for s in range(S)])
        body = [st.point_bodies[p] for p in on_link]
        points[:, on_link] = (_quat_matrices(frames_at) @ (position[:, on_link] - com_local[:, body])[..., None])[..., 0]
    if on_base:
        points[:, on_base] = (Q.swapaxes(-1, -2)[:, None] @ (position[:, on_base]
                                                             - com_local[:, base][:, None])[..., None])[..., 0]
    frame, orientation, base_frame = (_matrix_quats(m) for m in (Q, R_state, Q.swapaxes(-1, -2)))
    base_inertia = Q.swapaxes(-1, -2) @ inertia[:, base] @ Q
    return [dict(chains=chains[s], Q=Q[s], base_com=base_com[s], ground=grounds[s], points=points[s], frame=frame[s],
                 orientation=orientation[s], base_frame=base_frame[s], base_inertia=base_inertia[s]) for s in range(S)]


def _base_slots(spec: MechanismSpec, shape_indices, com: np.ndarray, Q: np.ndarray, ground: tuple) -> list:
    """The base's contact slots (TabulatedLayout.base_slots) of its shapes ``shape_indices`` (com: the
    base's centre of mass in its body frame): a box's corners, a capsule's ends, a sphere's centre;
    ValueError for another shape."""
    slots = []
    for s in shape_indices:
        shape = spec.shapes[s]
        centre = Q.T @ (shape.position - com)
        turn = Q.T @ quat_matrix(shape.orientation)
        mu = math.sqrt(shape.friction * ground[1])
        if shape.type == ShapeType.BOX:
            slots += [(centre + turn @ (signs * shape.size), 0.0, mu, s) for signs in _BOX_SIGNS]
        elif shape.type == ShapeType.CAPSULE:
            for e in (1.0, -1.0):
                slots.append((centre + e * shape.size[1] * turn[:, 2], float(shape.size[0]), mu, s))
        elif shape.type == ShapeType.SPHERE:
            slots.append((centre, float(shape.size[0]), mu, s))
        else:
            raise ValueError(f"shape '{shape.name}' is a {shape.type.name.lower()}: the base's contact slots take "
                             f"boxes, capsules and spheres")
    return slots


def _assemble(spec, base, Q, R_state, base_com, groups, base_slots, ground, where_is, point_bodies) -> TabulatedLayout:
    """The TabulatedLayout of both paths, with its tracked points and body frames. where_is: spec body
    -> (sub-chain or -1 for the base, link); point_bodies: each tracked point's spec body index."""
    bodies, base_body = spec.bodies, spec.bodies[base]
    points = []
    for point, i in zip(spec.points, point_bodies):
        g, k = where_is[i]
        if g < 0:
            points.append((-1, 0, Q.T @ (point.position - base_body.com)))
        else:
            C = quat_matrix(groups[g].link_frame[k])
            points.append((g, k, C @ (point.position - bodies[i].com)))
    base_frame = matrix_quat(Q.T)
    body_frames = []
    for i in range(len(bodies)):
        g, k = where_is[i]
        body_frames.append((-1, 0, base_frame) if g < 0 else (g, k, groups[g].link_frame[k]))
    return TabulatedLayout(spec, base, matrix_quat(Q), base_com, matrix_quat(R_state), base_body.velocity.copy(),
                           base_body.angular_velocity.copy(), float(base_body.mass), Q.T @ base_body.inertia @ Q,
                           groups, base_slots, ground, np.asarray(spec.gravity, float), points, body_frames)


def _sub_chain_batch(specs, st, batch, R_state_T, state_R, world_R, R_base, frames, com_world, com_local,
                     inertia, axes, parent_positions, child_positions, position, angular_velocity, base_com, grounds,
                     samples):
    """_plain_layout's _sub_chain for the sub-chains ``batch`` (one signature) of every spec at once
    (arrays (S, G, ...)): per spec and sub-chain (SubChain fields but the table, table key,
    _Planar, closed start pose, contact, name for errors); raises _Refused for the specs whose
    checks fail."""
    chains = [st.chains[g] for g in batch]
    first = chains[0]
    S, G, K, base = len(specs), len(chains), len(first.comp), st.base
    joints0 = specs[0].joints
    comp = np.array([chain.comp for chain in chains])  # (G, K)
    joint_list = np.array([chain.joints for chain in chains])  # (G, n)
    n = joint_list.shape[1]
    SR = state_R[:, comp]  # (S, G, K, 3, 3)
    # _planar_angle of every link (math's atan2 and hypot, item by item): its x axis's direction in
    # (x, z), or its z axis's when x lies along y
    x0_, x2_ = SR[..., 0, 0].reshape(-1).tolist(), SR[..., 2, 0].reshape(-1).tolist()
    z0_, z2_ = SR[..., 0, 2].reshape(-1).tolist(), SR[..., 2, 2].reshape(-1).tolist()
    along_x = [h > 1e-3 for h in map(math.hypot, x0_, x2_)]
    phi0 = list(map(math.atan2, [a if x else -b for a, b, x in zip(x2_, z0_, along_x)],
                    [a if x else b for a, b, x in zip(x0_, z2_, along_x)]))
    phi = np.array(phi0).reshape(S, G, K)
    C = _rot_minus_ys([-p for p in phi0]).reshape(S, G, K, 3, 3) @ SR
    com = (R_state_T[:, None, None] @ (com_world[:, comp] - base_com[:, None, None])[..., None])[..., 0]  # (S, G, K, 3)
    drivers = [chain.driver for chain in chains]
    base_side = first.base_side
    driver_local = (parent_positions if base_side == "parent" else child_positions)[:, drivers]  # (S, G, 3)
    base_R = world_R[:, base][:, None]
    pivot = (R_state_T[:, None] @ (position[:, base][:, None] + (base_R @ driver_local[..., None])[..., 0]
                                   - base_com[:, None])[..., None])[..., 0]  # (S, G, 3)
    # every joint's two ends: base ends in the state frame from the pivot, link ends in the table frame
    side_base = np.array([e[0] for pair in first.ends for e in pair])  # (2 n,)
    side_link = np.array([e[2] for pair in first.ends for e in pair])
    side_body = np.array([[e[1] for pair in chain.ends for e in pair] for chain in chains])  # (G, 2 n)
    end_position = np.stack([parent_positions[:, joint_list], child_positions[:, joint_list]], axis=3).reshape(
        S, G, 2 * n, 3)
    at_base = (R_state_T[:, None, None] @ (position[:, base][:, None, None]
                                           + (base_R[:, None] @ end_position[..., None])[..., 0]
                                           - base_com[:, None, None])[..., None])[..., 0]
    link = np.minimum(side_link, K - 1)
    on_link = (C[:, :, link] @ (end_position - com_local[:, side_body])[..., None])[..., 0]
    planar = np.where(side_base[:, None], np.stack([at_base[..., 0] - pivot[:, :, None, 0],
                                                    at_base[..., 2] - pivot[:, :, None, 2]], axis=-1),
                      on_link[..., [0, 2]])
    height = np.where(side_base, at_base[..., 1], com[:, :, link, 1] + on_link[..., 1])
    reach = np.hypot(planar[..., 0], planar[..., 1])
    refused = ~(np.isfinite(reach).all(axis=(1, 2)) & np.isfinite(height).all(axis=(1, 2))
                & np.isfinite(com).all(axis=(1, 2, 3)))
    scale = reach.max(axis=2)  # (S, G)
    revolute = np.array([joints0[j].type == JointType.REVOLUTE for j in first.joints])
    apart = np.abs(height[..., 0::2] - height[..., 1::2]) > 1e-6 * np.maximum(1.0, np.abs(com).max(axis=(2, 3)))[..., None]
    refused |= (apart & revolute).any(axis=(1, 2)) | ~(scale > 0.0).all(axis=1)
    plane_y = np.ascontiguousarray(com[..., 1]).reshape(S * G, K).mean(axis=1).reshape(S, G)
    refused |= (np.abs(com[..., 1] - plane_y[..., None]) > PLANE_TOLERANCE * scale[..., None]).any(axis=(1, 2))
    if refused.any():
        raise _Refused(refused)
    ja = np.array([pair[0][2] for pair in first.ends])
    jb = np.array([pair[1][2] for pair in first.ends])
    ra = planar[:, :, 0::2] / scale[..., None, None]
    rb = planar[:, :, 1::2] / scale[..., None, None]
    k_d = first.k_d
    # the driving coordinate q against the driving link's angle (_sub_chain's q_of, twice per sub-chain)
    base_orientation = R_state_T @ R_base  # R_state^T quat_matrix(base orientation), per spec
    angles = np.concatenate([phi[:, :, k_d], phi[:, :, k_d] + 0.25], axis=1)  # (S, 2 G)
    turned = _rot_minus_ys(angles.reshape(-1)).reshape(S, 2 * G, 3, 3) @ np.concatenate([C[:, :, k_d], C[:, :, k_d]],
                                                                                         axis=1)
    Qp, Qc = frames[:, drivers + drivers, 0], frames[:, drivers + drivers, 1]
    if base_side == "parent":
        rel = (base_orientation[:, None] @ Qp).swapaxes(-1, -2) @ (turned @ Qc)
    else:
        rel = (turned @ Qp).swapaxes(-1, -2) @ (base_orientation[:, None] @ Qc)
    q = _matrix_quats(rel.reshape(-1, 3, 3))
    along = _dots(q[:, :3], axes[:, drivers + drivers].reshape(-1, 3))
    q_of = np.array([2.0 * math.atan2(a, w) for a, w in zip(along.tolist(), q[:, 3].tolist())]).reshape(S, 2 * G)
    q0 = q_of[:, :G]
    sign = np.round(wrap(q_of[:, G:] - q0) / 0.25)
    refused = ~(np.abs(sign) == 1.0).all(axis=1)
    if refused.any():
        raise _Refused(refused)
    offset = phi[:, :, k_d] - sign * q0
    parent_i = [st.ends[j][0] for j in drivers]
    child_i = [st.ends[j][1] for j in drivers]
    axis_w = ((world_R[:, parent_i] @ frames[:, drivers, 0]) @ axes[:, drivers][..., None])[..., 0]
    rate = _dots(angular_velocity[:, child_i] - angular_velocity[:, parent_i], axis_w)
    x0 = np.stack([(com[..., 0] - pivot[:, :, None, 0]) / scale[..., None],
                   (com[..., 2] - pivot[:, :, None, 2]) / scale[..., None], phi], axis=-1).reshape(S, G, 3 * K)
    batched = _Planar(K, ja, jb, ra, rb, k_d, sign, offset)
    closed = x0.copy()
    ok = np.abs(batched.residual(x0, q0)).max(axis=-1) < NEWTON_TOLERANCE
    sign_l, offset_l, q0_l = sign.tolist(), offset.tolist(), q0.tolist()
    planars = [[_Planar(K, ja, jb, ra[s, g], rb[s, g], k_d, sign_l[s][g], offset_l[s][g]) for g in range(G)]
               for s in range(S)]
    for s, g in zip(*np.nonzero(~ok)):
        closed[s, g], ok[s, g] = planars[s][g].newton(x0[s, g], q0_l[s][g])
    moved = closed - x0
    moved[..., 2::3] = wrap(moved[..., 2::3])
    refused = ~ok.all(axis=1) | (np.abs(moved).max(axis=(1, 2)) > START_TOLERANCE)
    if refused.any():
        raise _Refused(refused)
    # the contact shape
    shape = [[None] * G for _ in range(S)]
    contact = [[None] * G for _ in range(S)]
    contact_keys = None
    if first.contact is not None:
        k = first.contact[1]
        items = [[spec.shapes[chain.contact[0]] for chain in chains] for spec in specs]
        at = comp[:, k]
        item_position = np.array([[item.position for item in row] for row in items], dtype=float)
        local = (C[:, :, k] @ (item_position - com_local[:, at])[..., None])[..., 0]  # (S, G, 3)
        angle, half = [[0.0] * G for _ in range(S)], [[0.0] * G for _ in range(S)]
        if items[0][0].type == ShapeType.CAPSULE:
            turn = _quat_matrices(np.array([[item.orientation for item in row] for row in items], dtype=float))
            axis = (C[:, :, k] @ turn[..., :, 2, None])[..., 0]
            refused = (np.abs(axis[..., 1]) > PLANE_TOLERANCE).any(axis=1)
            if refused.any():
                raise _Refused(refused)
            angle = [[math.atan2(a[2], a[0]) for a in row] for row in axis.tolist()]
            half = [[float(item.size[1]) for item in row] for row in items]
        contact_local = local / scale[..., None]
        for s in range(S):
            mu = grounds[s][1]
            for g, item in enumerate(items[s]):
                shape[s][g] = (chains[g].contact[0], float(item.size[0]), half[s][g], angle[s][g],
                               math.sqrt(item.friction * mu))
                contact[s][g] = (k, contact_local[s, g])
        contact_keys = _rounded_rows(contact_local.reshape(S * G, 3))
    pairs = tuple(zip(ja.tolist(), jb.tolist()))
    ra_keys, rb_keys = _rounded_rows(ra.reshape(S * G, -1)), _rounded_rows(rb.reshape(S * G, -1))
    turn_keys = _rounded_rows(np.array([[math.cos(o), math.sin(o)] for o in offset.reshape(-1).tolist()]))
    link_inertia = C @ inertia[:, comp] @ C.swapaxes(-1, -2)
    link_frame = _matrix_quats(C.reshape(-1, 3, 3)).reshape(S, G, K, 4)
    masses = [[spec.bodies[i].mass for i in comp.reshape(-1).tolist()] for spec in specs]
    if all(type(m) is float for row in masses for m in row):  # Python floats: one array keeps their values
        link_mass = np.array(masses).reshape(S, G, K)
    else:  # as _sub_chain makes each, from whatever the spec holds
        link_mass = [[np.array(row[g * K:(g + 1) * K]) for g in range(G)] for row in masses]
    origin = np.stack([pivot[..., 0], plane_y, pivot[..., 2]], axis=-1)  # (S, G, 3)
    scale_l, q0_f, rate_l = scale.tolist(), q0.tolist(), rate.tolist()
    out = []
    for s, spec in enumerate(specs):
        mine = []
        for g, chain in enumerate(chains):
            item = s * G + g
            driver = spec.joints[chain.driver]
            key = (samples, K, pairs, ra_keys[item], rb_keys[item], k_d, sign_l[s][g], turn_keys[item],
                   None if contact[s][g] is None else (contact[s][g][0], contact_keys[item]))
            drive = driver.drive
            fields = dict(joint=chain.driver, bodies=list(chain.comp), scale=scale_l[s][g],
                          origin=origin[s, g], angle=q0_f[s][g], rate=rate_l[s][g], link_mass=link_mass[s][g],
                          link_inertia=link_inertia[s, g], link_frame=link_frame[s, g],
                          drive=(float(drive.target_velocity), float(drive.damping), float(drive.effort_limit)),
                          shape=shape[s][g])
            mine.append((fields, key, planars[s][g], closed[s, g], contact[s][g],
                         f"sub-chain turned by joint '{driver.name}'"))
        out.append(mine)
    return out


def _plain(spec: MechanismSpec, samples: int) -> TabulatedLayout:
    """engine.reduced.tabulated_plain's layout of one spec (imported here: it builds on this module)."""
    from engine.reduced.tabulated_plain import _plain_layout

    return _plain_layout(spec, samples=samples)
