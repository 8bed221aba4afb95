"""The one conversion from a planar Linkage to engine.MechanismSpec.

Links become bodies built from rectangular bars between every pair of their nodes (width and
thickness [m], density [kg/m^3]); nodes shared by links become revolute joints about world -y,
except that the pivots closing kinematic loops become inline joints (close_loops_in_plane: no
redundant out-of-plane rows); ground nodes join links to the world; the crank gets a velocity
drive with an effort limit. Planar (x, y) maps to world (x, 0, y).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from engine import Body, Joint, JointDrive, MechanismSpec, TrackedPoint
from morphopt.linkage.graph import Linkage
from morphopt.linkage.kinematics import solve_at

__all__ = ["ASSEMBLY_STEP", "BarStyle", "assemble", "link_body", "link_mesh", "linkage_parts", "to_spec"]

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
    crank = linkage.crank
    h = ASSEMBLY_STEP
    if solution is None:
        solution = assemble([linkage])[0]

    if not solution.feasible:
        raise ValueError(f"linkage '{linkage.name}' cannot be assembled: {solution.reason}")
    origin = np.asarray(origin, dtype=float)

    def place(xy):
        return world(xy) + origin

    node_xy = {name: path[0] for name, path in solution.nodes.items()}
    node_rate = {name: (path[1] - path[0]) / h * (crank.speed if start_at_speed else 0.0)
                 for name, path in solution.nodes.items()}
    bodies, joints, link_of = [], [], {}
    for link in linkage.links:
        points = [place(node_xy[n]) for n in link.nodes]
        body = link_body(prefix + link.name, points, style)
        # rigid-body velocity from the first two nodes' planar velocities
        v0, v1 = world(node_rate[link.nodes[0]]), world(node_rate[link.nodes[1]])
        r = points[1] - points[0]
        dv = v1 - v0
        omega_y = (r[2] * dv[0] - r[0] * dv[2]) / max(float(r @ r), 1e-300)  # (r x dv)_y / |r|^2
        arm = _matrix(body.orientation) @ body.com  # from points[0] to the centre of mass
        body.velocity = v0 + np.array([omega_y * arm[2], 0.0, -omega_y * arm[0]])  # + (0, omega_y, 0) x arm

        body.angular_velocity = np.array([0.0, omega_y, 0.0])
        bodies.append(body)
        for node in link.nodes:
            link_of.setdefault(node, []).append((link, body))
    for node, members in link_of.items():
        anchor = place(node_xy[node])
        if node in linkage.ground:
            for link, body in members:
                drive = None
                if node == crank.center and crank.tip in link.nodes:
                    drive = JointDrive(damping=crank_damping, target_velocity=crank.speed, effort_limit=effort_limit)
                parent_position = anchor if base is None else _local(base, anchor)
                joints.append(Joint(f"{prefix}{node}_{link.name}", "revolute", None if base is None else base.name,
                                    body.name, parent_position=parent_position, child_position=_local(body, anchor),
                                    axis=AXIS, drive=drive))
            continue
        (parent_link, parent_body), *children = members
        for link, body in children:
            joints.append(Joint(f"{prefix}{node}_{parent_link.name}_{link.name}", "revolute", parent_body.name,
                                body.name, parent_position=_local(parent_body, anchor),
                                child_position=_local(body, anchor), axis=AXIS))
    points = []
    for point, node in linkage.points.items():
        _, body = link_of[node][0]
        points.append(TrackedPoint(prefix + point, body.name, _local(body, place(node_xy[node]))))
    return bodies, close_loops_in_plane(joints), points


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
    root = {}

    def find(name):
        while root.setdefault(name, name) != name:
            root[name] = root[root[name]]
            name = root[name]
        return name

    out = list(joints)
    for k in sorted(range(len(joints)), key=lambda k: joints[k].drive is None):  # driven joints join first
        joint = joints[k]
        a, b = find(joint.parent if joint.parent is not None else "\0world"), find(joint.child)
        if a != b:
            root[a] = b
        else:
            out[k] = dataclasses.replace(joint, type="inline")
    return out


def _local(body: Body, point: np.ndarray) -> np.ndarray:
    """World point in the body frame."""
    return _matrix(body.orientation).T @ (point - body.position)
