"""The one conversion from a planar Linkage to engine.MechanismSpec.

Links become bodies built from rectangular bars between every pair of their nodes (width and
thickness [m], density [kg/m^3]); nodes shared by links become revolute joints about world -y,
except that the pivots closing kinematic loops become inline joints (close_loops_in_plane: no
redundant out-of-plane rows); ground nodes join links to the world; the crank gets a velocity
drive with an effort limit. Planar (x, y) maps to world (x, 0, y).

linkages_parts converts several linkages of one topology at once (a walker's legs): every number
is computed by the same operations as for one linkage, with one NumPy operation per step for all
their bars and links (stacked matmul makes the same BLAS call per item), and the bodies, joints and
points are made by the engine's batch constructors (engine.spec's Body.batch ...), so the specs are
the same to the last bit (tests/morphopt/test_build_reference.py holds the one-by-one reference).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from engine import Body, Joint, JointDrive, MechanismSpec, TrackedPoint
from morphopt.linkage.graph import Linkage
from morphopt.linkage.kinematics import solve_at

__all__ = ["ASSEMBLY_STEP", "BarStyle", "assemble", "link_body", "link_mesh", "linkage_parts", "linkages_parts",
           "to_spec"]

AXIS = (0.0, -1.0, 0.0)  # positive rotation is counter-clockwise in the planar (x, y) view


@dataclass(frozen=True)
class BarStyle:
    """Cross-section and material of the bars: width, thickness [m], density [kg/m^3]."""

    width: float = 0.01
    thickness: float = 0.005
    density: float = 2700.0


def world(xy) -> np.ndarray:
    """Planar point -> world point."""
    return np.array([xy[0], 0.0, xy[1]])


def planar_rotation(angle: float) -> tuple:
    """Quaternion (x, y, z, w) of a counter-clockwise planar rotation (about world -y)."""
    return (0.0, -math.sin(0.5 * angle), 0.0, math.cos(0.5 * angle))


_EYE = np.eye(3)
_ACROSS_THICKNESS = np.diag([1.0, 0.0, 1.0])  # identity minus the outer product of the thickness direction (y)


def _bar_inertia(start: np.ndarray, end: np.ndarray, style: BarStyle):
    """Mass [kg], centre (world) and inertia about the centre (world axes) of one bar."""
    axis = end - start
    length = math.sqrt(float(axis @ axis))
    mass = style.density * style.width * style.thickness * length
    u = axis / length
    v = np.array([u[2], 0.0, -u[0]])  # width direction in the plane: y x u (the thickness is along y)
    inertia = (mass / 12.0) * ((length**2) * (_EYE - np.outer(u, u))
                               + style.width**2 * (_EYE - np.outer(v, v))
                               + style.thickness**2 * _ACROSS_THICKNESS)
    return mass, 0.5 * (start + end), inertia


def link_mesh(points: list[np.ndarray], style: BarStyle):
    """The link's visual and fabrication geometry: one box per bar (as in link_body) as a trimesh
    mesh in world coordinates (the bars overlap at shared pivots, as their masses do)."""
    import trimesh

    boxes = []
    for i in range(len(points)):
        for j in range(i + 1, len(points)):
            start, end = points[i], points[j]
            axis = end - start
            length = float(np.linalg.norm(axis))
            u = axis / length
            w = np.array([0.0, 1.0, 0.0])
            v = np.cross(w, u)
            transform = np.eye(4)
            transform[:3, :3] = np.stack([u, v, w], axis=1)
            transform[:3, 3] = 0.5 * (start + end)
            boxes.append(trimesh.creation.box(extents=(length, style.width, style.thickness), transform=transform))
    return trimesh.util.concatenate(boxes)


def link_body(name: str, points: list[np.ndarray], style: BarStyle) -> Body:
    """A body made of bars between every pair of ``points`` (world), frame at points[0] with x
    towards points[1]."""
    bars = [_bar_inertia(points[i], points[j], style) for i in range(len(points)) for j in range(i + 1, len(points))]
    mass = sum(m for m, _, _ in bars)
    com = sum(m * c for m, c, _ in bars) / mass
    inertia = sum(I + m * ((c - com) @ (c - com) * np.eye(3) - np.outer(c - com, c - com)) for m, c, I in bars)
    direction = points[1] - points[0]
    angle = math.atan2(direction[2], direction[0])
    rotation = planar_rotation(angle)
    R = _matrix(rotation)
    return Body(name, mass, R.T @ inertia @ R, com=R.T @ (com - points[0]), position=points[0], orientation=rotation)


def _matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def to_spec(linkage: Linkage, *, style: BarStyle = BarStyle(), crank_damping: float = 50.0,
            effort_limit: float = 50.0, gravity=(0.0, 0.0, -9.81), start_at_speed: bool = True) -> MechanismSpec:
    """Build the MechanismSpec of ``linkage``, assembled at its crank phase, ground pivots on the world.

    crank_damping [N m s/rad] and effort_limit [N m] define the crank's velocity drive (target
    = crank.speed). With start_at_speed, bodies start with the loop-consistent velocities of the
    crank turning at speed (finite differences of the kinematics), else at rest.
    """
    bodies, joints, points = linkage_parts(linkage, style=style, crank_damping=crank_damping,
                                           effort_limit=effort_limit, start_at_speed=start_at_speed)
    return MechanismSpec(bodies, joints, points, gravity=gravity, name=linkage.name)


ASSEMBLY_STEP = 1e-6  # [rad]: the second crank angle of an assembly, for the finite-difference velocities


def assemble(linkages: list[Linkage]) -> list:
    """Every linkage solved at its crank phase and ASSEMBLY_STEP further, in one batched solve
    (morphopt.linkage.solve_at): what linkage_parts needs, for several linkages at once."""
    angles = np.array([[linkage.crank.phase, linkage.crank.phase + ASSEMBLY_STEP] for linkage in linkages])
    return solve_at(linkages, angles.reshape(len(linkages), 2))


def linkage_parts(linkage: Linkage, *, style: BarStyle = BarStyle(), crank_damping: float = 50.0,
                  effort_limit: float = 50.0, start_at_speed: bool = True, origin=(0.0, 0.0, 0.0), prefix: str = "",
                  base: Body | None = None, solution=None):
    """Bodies, joints and tracked points of ``linkage`` with its plane's origin at world ``origin``.

    Ground pivots join the ``base`` body (at rest) when given, else the world. Names get ``prefix``.
    solution: the linkage's entry of assemble() when it was solved in a batch with others (else
    it is solved here). Raises ValueError when the linkage cannot be assembled at its crank phase.
    """
    return next(linkages_parts([linkage], style=style, crank_damping=crank_damping, effort_limit=effort_limit,
                               start_at_speed=start_at_speed, origins=[origin], prefixes=[prefix], base=base,
                               solutions=None if solution is None else [solution]))


@dataclass(frozen=True)
class _Layout:
    """What linkage_parts does with every linkage of one topology, numbers aside (cached by
    Linkage.topology). nodes: names in solving order; links: (name, node indices); bars: (link,
    start node, end node) in link_body's order; slots[s]: (links with an s-th bar, those bars);
    joints: (name suffix, node, parent link or -1 for the base or world, child link, driven) in
    linkage_parts's order; points: (name, node, link)."""

    nodes: tuple
    links: tuple
    first: np.ndarray
    second: np.ndarray
    bar_link: np.ndarray
    bar_start: np.ndarray
    bar_end: np.ndarray
    link_bars: tuple
    slots: tuple
    joints: tuple
    joint_node: np.ndarray
    joint_link: np.ndarray
    joint_base: np.ndarray
    points: tuple


_LAYOUTS: dict = {}


def _layout_of(linkage: Linkage) -> _Layout:
    key = linkage.topology
    layout = _LAYOUTS.get(key)
    if layout is not None:
        return layout
    nodes = tuple(linkage.nodes)
    at = {name: i for i, name in enumerate(nodes)}
    links = tuple((link.name, tuple(at[n] for n in link.nodes)) for link in linkage.links)
    bars, link_bars = [], []
    for k, (_, ends) in enumerate(links):
        mine = []
        for i in range(len(ends)):
            for j in range(i + 1, len(ends)):
                mine.append(len(bars))
                bars.append((k, ends[i], ends[j]))
        link_bars.append(tuple(mine))
    slots = []
    for s in range(max(len(b) for b in link_bars)):
        which = [k for k, b in enumerate(link_bars) if len(b) > s]
        slots.append((np.array(which), np.array([link_bars[k][s] for k in which])))
    link_of = {}
    for k, link in enumerate(linkage.links):
        for node in link.nodes:
            link_of.setdefault(node, []).append(k)
    crank = linkage.crank
    joints = []
    for node, members in link_of.items():
        if node in linkage.ground:
            for k in members:
                driven = node == crank.center and crank.tip in linkage.links[k].nodes
                joints.append((f"{node}_{links[k][0]}", at[node], -1, k, driven))
            continue
        parent, *children = members
        for k in children:
            joints.append((f"{node}_{links[parent][0]}_{links[k][0]}", at[node], parent, k, False))
    points = tuple((point, at[node], link_of[node][0]) for point, node in linkage.points.items())
    # every end of a joint (parent then child) and of a tracked point, as (node, link or -1)
    ends = [(node, end) for _, node, parent, child, _ in joints for end in (parent, child)]
    ends += [(node, k) for _, node, k in points]
    layout = _Layout(nodes, links, np.array([ends[0] for _, ends in links]), np.array([ends[1] for _, ends in links]),
                     np.array([b[0] for b in bars]), np.array([b[1] for b in bars]), np.array([b[2] for b in bars]),
                     tuple(link_bars), tuple(slots), tuple(joints), np.array([n for n, _ in ends]),
                     np.array([max(k, 0) for _, k in ends]), np.array([k < 0 for _, k in ends]), points)
    if len(_LAYOUTS) >= 64:
        _LAYOUTS.pop(next(iter(_LAYOUTS)))
    _LAYOUTS[key] = layout
    return layout


def _dots(a: np.ndarray) -> np.ndarray:
    """a[i] @ a[i] of every vector along the last axis of a: matmul's dot of each (the same BLAS
    call as the 1-D ``a[i] @ a[i]``)."""
    return (a[..., None, :] @ a[..., :, None])[..., 0, 0]


def _matrices(q: np.ndarray) -> np.ndarray:
    """_matrix of every quaternion of q (..., 4), the same operations element by element."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1)], axis=-2)


def _sums(terms: np.ndarray, slots) -> np.ndarray:
    """Python's sum (0 + first + second ...) of every link's bar terms (L, bars, ...) -> (L, links, ...)."""
    _, bars = slots[0]  # every link has a first bar: the links in order
    out = 0 + terms[:, bars]
    for links, bars in slots[1:]:
        out[:, links] = out[:, links] + terms[:, bars]
    return out


def _numbers(layout: _Layout, linkages: list, solutions: list, origins: list, styles: list,
             start_at_speed: bool, bases: list) -> dict:
    """Every number linkage_parts computes for linkages of one layout, as arrays over (linkage, ...)
    (each entry computed by the same operations as linkage_parts's own, one item at a time).
    styles, bases: one per linkage (a style's numbers enter as per-linkage columns, the same
    products element by element as its scalars)."""
    h = ASSEMBLY_STEP
    paths = np.array([[solution.nodes[name][:2] for name in layout.nodes] for solution in solutions])  # (L, N, 2, 2)
    speed = np.array([linkage.crank.speed if start_at_speed else 0.0 for linkage in linkages])
    rate = (paths[:, :, 1] - paths[:, :, 0]) / h * speed[:, None, None]
    flat = np.zeros(paths.shape[:2] + (3,))
    flat[..., 0], flat[..., 2] = paths[:, :, 0, 0], paths[:, :, 0, 1]
    place = flat + np.array([np.asarray(origin, dtype=float) for origin in origins])[:, None, :]  # world(xy) + origin
    velocity = np.zeros_like(flat)
    velocity[..., 0], velocity[..., 2] = rate[..., 0], rate[..., 1]
    # link_body: bars (_bar_inertia), then each link's sums
    start, end = place[:, layout.bar_start], place[:, layout.bar_end]
    axis = end - start
    length = np.sqrt(_dots(axis))
    mass = np.array([style.density * style.width * style.thickness for style in styles])[:, None] * length
    u = axis / length[..., None]
    v = np.stack([u[..., 2], np.zeros_like(length), -u[..., 0]], axis=-1)
    squared = np.array([x**2 for x in length.ravel().tolist()]).reshape(length.shape)  # Python's float power
    inertia = (mass / 12.0)[..., None, None] * ((squared[..., None, None] * (_EYE - u[..., :, None] * u[..., None, :])
                                                 + np.array([style.width**2 for style in styles])[:, None, None, None]
                                                 * (_EYE - v[..., :, None] * v[..., None, :]))
                                                + np.array([style.thickness**2 for style in styles])[:, None, None, None]
                                                * _ACROSS_THICKNESS)
    centre = 0.5 * (start + end)
    bar_mass = mass.tolist()
    link_mass = [[sum(row[b] for b in bars) for bars in layout.link_bars] for row in bar_mass]
    com = _sums(mass[..., None] * centre, layout.slots) / np.array(link_mass)[..., None]
    d = centre - com[:, layout.bar_link]
    parallel = _dots(d)[..., None, None] * np.eye(3) - d[..., :, None] * d[..., None, :]
    inertia = _sums(inertia + mass[..., None, None] * parallel, layout.slots)
    p0, p1 = place[:, layout.first], place[:, layout.second]
    direction = p1 - p0
    rotation = [[planar_rotation(math.atan2(dz, dx)) for (dx, _, dz) in row] for row in direction.tolist()]
    q = np.array(rotation)
    R = _matrices(q)
    RT = R.swapaxes(-1, -2)
    body_inertia = RT @ inertia @ R
    body_com = (RT @ (com - p0)[..., None])[..., 0]
    # the bodies' frames as Body stores them (_quaternion: q / |q|), then linkage_parts's velocities
    unit = q / np.sqrt(_dots(q))[..., None]
    M = _matrices(unit)
    arm = (M @ body_com[..., None])[..., 0]
    v0, v1 = velocity[:, layout.first], velocity[:, layout.second]
    dv = v1 - v0
    omega = (direction[..., 2] * dv[..., 0] - direction[..., 0] * dv[..., 2]) / np.maximum(_dots(direction), 1e-300)
    zero = np.zeros_like(omega)
    body_velocity = v0 + np.stack([omega * arm[..., 2], zero, -omega * arm[..., 0]], axis=-1)
    angular_velocity = np.stack([zero, omega, zero], axis=-1)
    # joint anchors and tracked points in their bodies' frames: _matrix(orientation).T @ (point - position)
    anchor = place[:, layout.joint_node]
    link = layout.joint_link
    local = (M[:, link].swapaxes(-1, -2) @ (anchor - p0[:, link])[..., None])[..., 0]
    on_base = [n for n, base in enumerate(bases) if base is not None]
    if on_base:  # _matrix(base.orientation).T @ (anchor - base.position) of every linkage on a base
        rows, ends = np.array(on_base)[:, None], layout.joint_base
        turn = _matrices(np.array([bases[n].orientation for n in on_base], dtype=float)).swapaxes(-1, -2)
        offset = anchor[rows, ends] - np.array([bases[n].position for n in on_base], dtype=float)[:, None, :]
        local[rows, ends] = (turn[:, None] @ offset[..., None])[..., 0]
    return dict(place=place, link_mass=link_mass, mass=np.array(link_mass), body_inertia=body_inertia,
                body_com=body_com, p0=p0, rotation=rotation, rotation_array=q, velocity=body_velocity,
                angular_velocity=angular_velocity, anchor=anchor, local=local)


def _closing(ends: list) -> set:
    """The joints close_loops_in_plane makes inline, from their (parent name or None, child name,
    driven) in order."""
    root = {}

    def find(name):
        while root.setdefault(name, name) != name:
            root[name] = root[root[name]]
            name = root[name]
        return name

    closing = set()
    for k in sorted(range(len(ends)), key=lambda k: not ends[k][2]):  # driven joints join first
        parent, child, _ = ends[k]
        a, b = find(parent if parent is not None else "\0world"), find(child)
        if a != b:
            root[a] = b
        else:
            closing.add(k)
    return closing


def _parts(layout: _Layout, numbers: dict, linkages: list, prefixes: list, bases: list, style_args: tuple):
    """linkage_parts's objects for every entry of ``numbers`` (the group's linkages, prefixes), made
    by the engine's batch constructors (their checks on the arrays of the whole group at once):
    a list of (bodies, joints, points) per linkage, or None when a constructor's check fails or a
    driven joint closes a loop (then _parts_one_by_one, per linkage, raises the constructors'
    errors in linkage_parts's order)."""
    crank_damping, effort_limit = style_args
    count, K, P = len(layout.joints), len(layout.links), len(layout.points)
    names, joint_names, parents, children, kinds, drives = [], [], [], [], [], []
    closings = {}  # _closing sees only which names are equal: per (world, links named like the base) once
    for linkage, prefix, base in zip(linkages, prefixes, bases):
        base_name = None if base is None else base.name
        mine = [prefix + name for name, _ in layout.links]
        ends = [(base_name if parent < 0 else mine[parent], mine[child], driven)
                for _, _, parent, child, driven in layout.joints]
        key = (base_name is None, tuple(k for k, name in enumerate(mine) if name == base_name))
        if key not in closings:
            closing = _closing(ends)
            closings[key] = (closing, ["inline" if j in closing else "revolute" for j in range(count)])
        closing, kind = closings[key]
        if any(ends[j][2] for j in closing):  # as close_loops_in_plane makes it (and Joint refuses it)
            return None
        names += mine
        joint_names += [prefix + suffix for suffix, *_ in layout.joints]
        parents += [e[0] for e in ends]
        children += [e[1] for e in ends]
        kinds += kind
        drives += [JointDrive(damping=crank_damping, target_velocity=linkage.crank.speed, effort_limit=effort_limit)
                   if driven else None for _, _, driven in ends]
    L = len(linkages)
    bodies = Body.batch(names, numbers["mass"].reshape(-1), numbers["body_inertia"].reshape(-1, 3, 3),
                        numbers["body_com"].reshape(-1, 3), numbers["p0"].reshape(-1, 3),
                        numbers["rotation_array"].reshape(-1, 4), numbers["velocity"].reshape(-1, 3),
                        numbers["angular_velocity"].reshape(-1, 3))
    anchor, local = numbers["anchor"], numbers["local"]
    world = np.array([[parent < 0 and base is None for _, _, parent, _, _ in layout.joints] for base in bases])
    parent_position = np.where(world.reshape(L, count, 1), anchor[:, 0:2 * count:2],
                               local[:, 0:2 * count:2]).reshape(-1, 3)
    joints = Joint.batch(joint_names, kinds, parents, children, parent_position,
                         local[:, 1:2 * count:2].reshape(-1, 3), AXIS, drives)
    points = TrackedPoint.batch([prefix + name for prefix in prefixes for name, _, _ in layout.points],
                                [names[n * K + k] for n in range(L) for _, _, k in layout.points],
                                local[:, 2 * count:].reshape(-1, 3))
    if bodies is None or joints is None or points is None:
        return None
    return [(bodies[n * K:(n + 1) * K], joints[n * count:(n + 1) * count], points[n * P:(n + 1) * P]) for n in range(L)]


def _parts_one_by_one(layout: _Layout, numbers: dict, index: int, linkage: Linkage, prefix: str, base: Body | None,
                      style_args: tuple):
    """linkage_parts's objects for entry ``index`` of ``numbers``, each through its constructor in
    linkage_parts's order."""
    crank_damping, effort_limit = style_args
    bodies = []
    for k, (name, _) in enumerate(layout.links):
        body = Body(prefix + name, numbers["link_mass"][index][k], numbers["body_inertia"][index, k],
                    com=numbers["body_com"][index, k], position=numbers["p0"][index, k],
                    orientation=numbers["rotation"][index][k])
        body.velocity = numbers["velocity"][index, k]
        body.angular_velocity = numbers["angular_velocity"][index, k]
        bodies.append(body)
    anchor, local = numbers["anchor"][index], numbers["local"][index]
    base_name = None if base is None else base.name
    ends = [(base_name if parent < 0 else bodies[parent].name, bodies[child].name, driven)
            for _, _, parent, child, driven in layout.joints]
    closing = _closing(ends)
    joints, late = [], []
    for j, (suffix, _, parent, child, driven) in enumerate(layout.joints):
        parent_position = anchor[2 * j] if parent < 0 and base is None else local[2 * j]
        drive = None
        if driven:
            drive = JointDrive(damping=crank_damping, target_velocity=linkage.crank.speed, effort_limit=effort_limit)
        kind = "inline" if j in closing and drive is None else "revolute"
        joints.append(Joint(prefix + suffix, kind, ends[j][0], ends[j][1], parent_position=parent_position,
                            child_position=local[2 * j + 1], axis=AXIS, drive=drive))
        if j in closing and drive is not None:
            late.append(j)
    points = []
    for p, (name, _, k) in enumerate(layout.points):
        points.append(TrackedPoint(prefix + name, bodies[k].name, local[2 * len(layout.joints) + p]))
    for j in late:  # a driven joint that closes a loop: as close_loops_in_plane makes it (and refuses it)
        joints[j] = dataclasses.replace(joints[j], type="inline")
    return bodies, joints, points


def linkages_parts(linkages: list, *, style: BarStyle = BarStyle(), crank_damping: float = 50.0,
                   effort_limit: float = 50.0, start_at_speed: bool = True, origins=None, prefixes=None,
                   base: Body | None = None, solutions=None, styles=None, bases=None):
    """linkage_parts of every linkage in turn, their numbers computed together (one NumPy operation
    per step for all links of the linkages of one topology, such as a walker's legs): yields each
    linkage's (bodies, joints, points), equal to linkage_parts's to the last bit, and builds them
    (or raises linkage_parts's ValueError) when that linkage's turn comes. origins, prefixes: one
    per linkage (default: the world origin, no prefix); solutions: their entries of assemble()
    (else they are solved here, together); styles, bases: one per linkage in place of style and
    base (a generation's legs, each walker's on its own torso and at its own scale, in one call)."""
    linkages = list(linkages)
    origins = [(0.0, 0.0, 0.0)] * len(linkages) if origins is None else list(origins)
    prefixes = [""] * len(linkages) if prefixes is None else list(prefixes)
    styles = [style] * len(linkages) if styles is None else list(styles)
    bases = [base] * len(linkages) if bases is None else list(bases)
    solutions = (assemble(linkages) if linkages else []) if solutions is None else list(solutions)
    ready = next((i for i, s in enumerate(solutions) if not s.feasible), len(linkages))
    groups = {}
    for i in range(ready):
        groups.setdefault(linkages[i].topology, []).append(i)
    where = {}
    for indices in groups.values():
        layout = _layout_of(linkages[indices[0]])
        numbers = _numbers(layout, [linkages[i] for i in indices], [solutions[i] for i in indices],
                           [origins[i] for i in indices], [styles[i] for i in indices], start_at_speed,
                           [bases[i] for i in indices])
        made = _parts(layout, numbers, [linkages[i] for i in indices], [prefixes[i] for i in indices],
                      [bases[i] for i in indices], (crank_damping, effort_limit))
        for n, i in enumerate(indices):
            where[i] = (layout, numbers, n, None if made is None else made[n])
    for i, linkage in enumerate(linkages):
        if i == ready:
            raise ValueError(f"linkage '{linkage.name}' cannot be assembled: {solutions[i].reason}")
        layout, numbers, n, made = where[i]
        yield made if made is not None else _parts_one_by_one(layout, numbers, n, linkage, prefixes[i], bases[i],
                                                               (crank_damping, effort_limit))


def close_loops_in_plane(joints: list) -> list:
    """Keep the revolute joints of a spanning tree of the bodies (driven joints first) and make
    every loop-closing pivot an inline joint (two rows: the pivot stays on the partner's axis).

    The tree's revolute joints already hold every body in the plane, so of a closing revolute's
    five rows three (the out-of-plane translation and both tilts) would repeat what the tree
    imposes. Repeated rows make every walker's constraint system singular in as many directions
    (54 for a walker of six legs with three loops each), and the solvers then spend their
    iterations on residuals in those directions; the inline closure removes them and leaves the
    motion the same.
    """
    closing = _closing([(joint.parent, joint.child, joint.drive is not None) for joint in joints])
    return [dataclasses.replace(joint, type="inline") if k in closing else joint for k, joint in enumerate(joints)]
