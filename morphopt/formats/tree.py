"""What the tree-structured formats (URDF, MJCF, USD articulations) need from a MechanismSpec: a
spanning tree of its joints with the loop-closing joints set apart, and host-side frame algebra.

A MechanismSpec has no tree: any joint may close a loop. The formats nest bodies in a tree and
describe the remaining joints separately (URDF: an extension element, MJCF: equality constraints,
USD: joints excluded from the articulation), so every exporter starts from spanning_tree().
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from engine import Joint, JointType, MechanismSpec

__all__ = ["SpanningTree", "TreeJoint", "anchor_frames", "body_frame", "body_twist", "frame", "initial_coordinate",
           "initial_rate", "matrix_to_quat", "metadata_json", "quat_to_matrix", "spanning_tree"]

# Joint types a tree edge may have in every tree format (URDF knows no others).
TREE_TYPES = (JointType.REVOLUTE, JointType.PRISMATIC, JointType.FIXED)


def metadata_json(metadata: dict | None) -> str:
    """A design's metadata as JSON text (keys sorted; NumPy scalars and arrays as plain values);
    TypeError naming any other value that JSON cannot hold."""
    def plain(value):
        if isinstance(value, np.generic | np.ndarray):
            return value.tolist()
        raise TypeError(f"metadata value {value!r} of type {type(value).__name__} is not JSON-able")

    return json.dumps({} if metadata is None else metadata, default=plain, sort_keys=True)


def quat_to_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix."""
    R = np.asarray(R, dtype=float)
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def frame(position, orientation) -> np.ndarray:
    """4x4 homogeneous transform of a position [m] and quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(orientation)
    T[:3, 3] = np.asarray(position, dtype=float)
    return T


def body_frame(spec: MechanismSpec, name: str | None) -> np.ndarray:
    """World transform of a body's frame at the initial state (identity for None, the world)."""
    if name is None:
        return np.eye(4)
    body = spec.bodies[spec.body_index[name]]
    return frame(body.position, body.orientation)


def anchor_frames(spec: MechanismSpec, joint: Joint) -> tuple[np.ndarray, np.ndarray]:
    """World transforms of a joint's parent and child anchor frames at the initial state."""
    parent = body_frame(spec, joint.parent) @ frame(joint.parent_position, joint.parent_orientation)
    child = body_frame(spec, joint.child) @ frame(joint.child_position, joint.child_orientation)
    return parent, child


def initial_coordinate(spec: MechanismSpec, joint: Joint) -> float:
    """The joint's coordinate at the initial state, as the engine measures it: the rotation [rad]
    of the child anchor frame about the axis relative to the parent's (revolute), or the child
    anchor's displacement [m] along the axis (prismatic); 0 for other types."""
    parent, child = anchor_frames(spec, joint)
    if joint.type == JointType.PRISMATIC:
        return float((parent[:3, :3] @ joint.axis) @ (child[:3, 3] - parent[:3, 3]))
    if joint.type != JointType.REVOLUTE:
        return 0.0
    q = matrix_to_quat(parent[:3, :3].T @ child[:3, :3])
    return 2.0 * math.atan2(float(q[:3] @ joint.axis), float(q[3]))


def body_twist(spec: MechanismSpec, name: str | None, point) -> tuple[np.ndarray, np.ndarray]:
    """Velocity [m/s] of the body's material point at world ``point`` and its angular velocity
    [rad/s], world frame, at the initial state (zeros for None, the world)."""
    if name is None:
        return np.zeros(3), np.zeros(3)
    body = spec.bodies[spec.body_index[name]]
    T = body_frame(spec, name)
    com = T[:3, :3] @ body.com + T[:3, 3]
    return body.velocity + np.cross(body.angular_velocity, np.asarray(point, float) - com), body.angular_velocity


def initial_rate(spec: MechanismSpec, joint: Joint) -> float:
    """The rate of initial_coordinate at the initial state: the child's angular velocity relative to
    the parent about the axis [rad/s] (revolute), or the relative velocity of the child anchor along
    the axis [m/s] (prismatic); 0 for other types."""
    if joint.type not in (JointType.REVOLUTE, JointType.PRISMATIC):
        return 0.0
    parent, child = anchor_frames(spec, joint)
    v_child, w_child = body_twist(spec, joint.child, child[:3, 3])
    v_parent, w_parent = body_twist(spec, joint.parent, child[:3, 3])
    relative = w_child - w_parent if joint.type == JointType.REVOLUTE else v_child - v_parent
    return float((parent[:3, :3] @ joint.axis) @ relative)


@dataclass(frozen=True)
class TreeJoint:
    """A joint of the spanning tree, oriented from the tree parent (None: the world) to the child.

    reversed: the tree runs from the spec's child to its parent (the exporter swaps the anchor
    frames; the coordinate changes sign)."""

    joint: Joint
    parent: str | None
    child: str
    reversed: bool


@dataclass(frozen=True)
class SpanningTree:
    """order: bodies, each after its tree parent. tree: body -> the TreeJoint to its parent (bodies
    without one float freely: ``roots``). loops: the joints outside the tree, in spec order."""

    order: list[str]
    tree: dict[str, TreeJoint]
    roots: list[str]
    loops: list[Joint]

    def children(self, parent: str | None) -> list[TreeJoint]:
        """Tree joints whose tree parent is ``parent`` (None: the world), in tree order."""
        return [self.tree[b] for b in self.order if b in self.tree and self.tree[b].parent == parent]


def spanning_tree(spec: MechanismSpec, *, any_type: bool = False) -> SpanningTree:
    """A spanning forest of the spec's joints, rooted at the world where a component has a world
    joint, else at its heaviest body (a floating base).

    Joints enter the tree in this order of preference: types every tree format has (revolute,
    prismatic, fixed) before others, driven joints before undriven ones (a drive must sit on a tree
    joint in URDF and MJCF), world joints first, then spec order. The joints left out close loops.
    Raises ValueError naming the joint when a tree joint would need a type the formats lack,
    unless ``any_type`` (USD articulations take every joint type).
    """
    WORLD = None
    root: dict = {}

    def find(node):
        root.setdefault(node, node)
        while root[node] != node:
            root[node] = root[root[node]]
            node = root[node]
        return node

    def preference(k):
        joint = spec.joints[k]
        return (joint.type not in TREE_TYPES, joint.drive is None, joint.parent is not None, k)

    in_tree = set()
    for k in sorted(range(len(spec.joints)), key=preference):
        joint = spec.joints[k]
        a, b = find(("w",) if joint.parent is None else joint.parent), find(joint.child)
        if a != b:
            root[a] = b
            in_tree.add(k)
    adjacency: dict = {}
    for k in sorted(in_tree):
        joint = spec.joints[k]
        adjacency.setdefault(joint.parent, []).append((k, joint.child, False))
        adjacency.setdefault(joint.child, []).append((k, joint.parent, True))
    order, tree, roots, seen = [], {}, [], {WORLD}

    def grow(start):
        frontier = [start]
        while frontier:
            node = frontier.pop(0)
            for k, other, reverse in adjacency.get(node, []):
                if other in seen:
                    continue
                joint = spec.joints[k]
                if joint.type not in TREE_TYPES and not any_type:
                    raise ValueError(f"joint '{joint.name}': a {joint.type.name.lower()} joint cannot be a tree joint "
                                     f"in URDF/MJCF/USD articulations; close the loop with it or use revolute, "
                                     f"prismatic or fixed joints on the tree")
                seen.add(other)
                order.append(other)
                tree[other] = TreeJoint(joint, node, other, reverse)
                frontier.append(other)

    grow(WORLD)
    remaining = [b for b in spec.bodies if b.name not in seen]
    while remaining:
        base = max(remaining, key=lambda b: b.mass)  # first of equal masses
        seen.add(base.name)
        order.append(base.name)
        roots.append(base.name)
        grow(base.name)
        remaining = [b for b in remaining if b.name not in seen]
    loops = [j for k, j in enumerate(spec.joints) if k not in in_tree]
    return SpanningTree(order, tree, roots, loops)
