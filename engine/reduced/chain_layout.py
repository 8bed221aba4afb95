"""The host side of closed chains in reduced coordinates (engine.reduced.chains): the spanning
tree and loop rows of one spec (chain_layout, a ChainLayout in float64 NumPy, whose kinematics the
tests use as a reference) and the helpers that size and fill the packed batch.

Why on the host: the tree and the independent loop rows are chosen once per spec, in float64, so
that the step kernel only walks a fixed tree and solves a non-singular loop matrix.
"""

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from engine.collide import PLANE_CONTACTS
from engine.spatial import cross3, quat_matrix
from engine.spec import JointType, MechanismSpec

__all__ = ["ChainLayout", "KIND_ANGULAR", "KIND_LINEAR", "KIND_REVOLUTE", "KIND_ROOT", "MAX_CONTACTS", "MAX_COORDS",
           "MAX_PREFIX", "MAX_ROWS", "MAX_SHAPES", "TILE_STEP", "chain_layout"]

MAX_COORDS = 48  # tree coordinates per world (a floating root counts six)
MAX_ROWS = 32  # kept loop rows per world
MAX_CONTACTS = 16  # contacts per world (three rows each)
MAX_SHAPES = 16  # shapes on moving bodies per world (4 candidate slots each: a shared tile of at most 64 rows)
KIND_REVOLUTE = wp.constant(0)  # a tree entry's coordinate: a revolute joint's angle,
KIND_LINEAR = wp.constant(1)  # a floating root's centre-of-mass velocity along a world axis (first three),
KIND_ANGULAR = wp.constant(2)  # its angular velocity about a world axis (next two)
KIND_ROOT = wp.constant(3)  # and about the z axis: the entry that is the root body
MAX_LOOPS = 32
ROW_TOLERANCE = 1.0e-4  # a loop row is redundant when the kept rows leave less than this of its norm
TILE_STEP = 4  # the shared tiles are sized to the batch's padded coordinates and rows in steps of this (against 8:
# benchmarks/results/README.md, "Reduced closed chains: design notes")
MAX_PREFIX = 6  # the leading chain the solves take unrolled (a floating root's six entries)
MAX_PACKED = 4096  # entries of the packed mass matrix (a shared tile; MAX_COORDS' deepest chain needs 1176)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    return quat_matrix((*(np.sin(angle / 2) * axis), np.cos(angle / 2)))


def _perpendiculars(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e = np.eye(3)[int(np.argmin(np.abs(axis)))]
    t1 = cross3(axis, e)
    t1 /= np.linalg.norm(t1)
    return t1, cross3(axis, t1)


@dataclass
class ChainLayout:
    """One world's tree and loops (host, float64): what pack_chains uploads, and a NumPy model of
    the kinematics used for the row selection (and by tests as a reference)."""

    spec: MechanismSpec
    tree_body: list  # spec body index of tree body k (breadth-first order)
    parent: np.ndarray  # (n,) tree index of the parent, -1: fixed
    depth: np.ndarray  # (n,)
    joint: list  # spec joint index of tree joint k
    parent_R: np.ndarray  # (n, 3, 3) joint frame in the parent's frame (world frame for a fixed parent)
    parent_p: np.ndarray  # (n, 3)
    child_R: np.ndarray  # (n, 3, 3) child frame in the joint frame
    child_p: np.ndarray  # (n, 3)
    axis: np.ndarray  # (n, 3) in the joint frame
    q0: np.ndarray  # (n,) initial angles
    u0: np.ndarray  # (n,) initial rates
    loops: list  # spec joint index of each loop joint
    loop_body: np.ndarray  # (L, 2) tree index of its first and second body, -1: fixed
    loop_R: np.ndarray  # (L, 2, 3, 3) anchor frames in those bodies' frames (world frame when fixed)
    loop_p: np.ndarray  # (L, 2, 3)
    loop_dirs: np.ndarray  # (L, 5, 3) the rows' directions in the first anchor frame
    rows: np.ndarray  # (R, 2) kept rows: loop, part (0-2 position, 3-4 angular)
    kind: np.ndarray  # (n,) KIND_REVOLUTE, or a floating root's KIND_LINEAR x3, KIND_ANGULAR x2, KIND_ROOT
    sub_of: np.ndarray  # (n,) the entry whose subtree coordinate k moves: itself, or its floating root's entry
    shapes: list  # spec shape index of each shape on a moving body (they collide with the ground plane)
    soft: list  # loops whose joint has armature or damping: a soft row on its rate each (after the kept rows)
    inline: list = ()  # loops whose joint is inline: their first anchor frame turned so that its z axis is the
    # joint's axis, their only rows the position rows along its x and y axes (parts 0 and 1)
    fixed: dict = None  # spec body index -> (R, p), its frame in the world, of each body welded to the world

    @property
    def n(self) -> int:
        """Tree coordinates (one per tree joint, one per body off the fixed set)."""
        return len(self.tree_body)

    def ancestors(self, k: int) -> list[int]:
        """Tree body k and its ancestors (the tree joints that move it), k first."""
        out = []
        while k >= 0:
            out.append(k)
            k = int(self.parent[k])
        return out

    def kinematics(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Body frames (R (n,3,3), p (n,3)), each coordinate's linear part (n,3: the velocity its
        unit rate gives the point at the world origin) and angular part (n,3: the world axis) at
        coordinates q. A floating root's six coordinates are a chart about its initial pose: its
        centre of mass moved by q[0:3] and its frame turned by the rotation vector q[3:6]."""
        n = self.n
        R = np.zeros((n, 3, 3))
        p = np.zeros((n, 3))
        lin = np.zeros((n, 3))
        axis = np.zeros((n, 3))
        for k in range(n):
            if self.kind[k] != KIND_REVOLUTE:
                root = int(self.sub_of[k])
                com = np.asarray(self.spec.bodies[self.tree_body[root]].com)
                r0 = root - 5
                rvec = q[r0 + 3:r0 + 6]
                angle = float(np.linalg.norm(rvec))
                turn = np.eye(3) if angle == 0.0 else _axis_angle(rvec / angle, angle)
                R[k] = turn @ self.parent_R[root]
                c = self.parent_p[root] + self.parent_R[root] @ com + q[r0:r0 + 3]
                p[k] = c - R[k] @ com
                e = self.axis[k]
                if self.kind[k] == KIND_LINEAR:
                    lin[k] = e
                else:
                    axis[k] = e
                    lin[k] = cross3(c, e)
                continue
            par = int(self.parent[k])
            Rp, pp = (np.eye(3), np.zeros(3)) if par < 0 else (R[par], p[par])
            Rj = Rp @ self.parent_R[k]
            point = pp + Rp @ self.parent_p[k]
            axis[k] = Rj @ self.axis[k]
            lin[k] = cross3(point, axis[k])
            Rq = Rj @ _axis_angle(self.axis[k], q[k])
            R[k] = Rq @ self.child_R[k]
            p[k] = point + Rq @ self.child_p[k]
        return R, p, lin, axis

    def loop_rows(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All five rows of every loop at angles q: Jacobian (5 L, n) and error (5 L,); an inline
        loop's rows 2-4 (along its axis, angular) are no constraint and stay 0."""
        R, p, lin, axis = self.kinematics(q)
        n, L = self.n, len(self.loops)
        G = np.zeros((5 * L, n))
        phi = np.zeros(5 * L)
        inline = set(self.inline)
        for li in range(L):
            frames = []
            for side in range(2):
                b = int(self.loop_body[li, side])
                Rb, pb = (np.eye(3), np.zeros(3)) if b < 0 else (R[b], p[b])
                frames.append((Rb @ self.loop_R[li, side], pb + Rb @ self.loop_p[li, side], b))
            (Ra, xa, a), (Rb_, xb, b) = frames
            ax_a = Ra @ self.axis_of_loop(li)
            ax_b = Rb_ @ self.axis_of_loop(li)
            dirs = Ra @ self.loop_dirs[li].T  # (3, 5)
            for part in range(5):
                if li in inline and part >= 2:
                    continue
                d = dirs[:, part]
                r = 5 * li + part
                if part < 3:
                    phi[r] = d @ (xb - xa)
                else:
                    phi[r] = d @ cross3(ax_a, ax_b)
                # an inline loop's rates at its second anchor on both bodies: its rows' directions turn with
                # the first body while the anchors part along the axis (a revolute loop's anchors coincide)
                for sign, body, x in ((1.0, b, xb), (-1.0, a, xb if li in inline else xa)):
                    for j in (self.ancestors(body) if body >= 0 else []):
                        col = cross3(axis[j], x) + lin[j] if part < 3 else axis[j]
                        G[r, j] += sign * (d @ col)
        return G, phi

    def axis_of_loop(self, li: int) -> np.ndarray:
        """Loop li's joint axis in its anchor frames (an inline loop's first anchor frame is turned:
        its z axis)."""
        if li in self.inline:
            return np.array([0.0, 0.0, 1.0])
        return np.asarray(self.spec.joints[self.loops[li]].axis)


def chain_layout(spec: MechanismSpec) -> ChainLayout:
    """The spanning tree and loops of one spec, or ValueError naming what this path cannot model.

    The fixed set is the world and every body welded to it (a fixed joint with no parent). Bodies
    not connected to it through revolute joints form floating parts; each has a root, its heaviest
    body, with six coordinates: the rates of its centre of mass's velocity and of its angular
    velocity (world frame), its pose kept in ChainState.root (a centre-of-mass frame, advanced by the
    exponential map). In the tree they are a chain of six entries (five massless, then the root
    body's), ancestors of the whole part. The tree's joints are revolute joints, chosen driven joints
    first, then nearest the roots (a shallow tree); a breadth-first search over them orders the
    entries parents first (one coordinate per tree joint: its angle, 0 where its two anchor frames
    coincide, as engine.spec defines it). Every other revolute joint closes a loop of five rows in
    the anchor frame of its first body: three position rows along the frame's axes and two angular
    rows about two directions normal to the joint axis. Every inline joint closes a loop too (never
    a tree joint: it leaves the anchor's slide along its axis and every rotation free) with two
    rows, the anchor's position normal to the axis (its first anchor frame turned so that the axis
    is the frame's z axis: position rows 0 and 1). The host evaluates the rows at the initial pose
    in float64 and keeps a largest independent subset (_independent_rows): a planar loop's
    out-of-plane rows are implied by its joints' parallel axes, and a redundant row would make the
    loops' matrix singular. A loop joint's armature a and damping c add a soft row on its rate about
    its axis (compliance 1 / (a + dt c), the share a / (a + dt c) of its last rate kept), the maximal
    engine's joint-space dynamics rows.

    Modelled: revolute joints, inline loop closures and welds to the world, drives on tree joints
    (effort limits checked, not enforced), no limits, no restitution, shapes on moving bodies
    colliding with the ground plane only (at most MAX_SHAPES), at most MAX_COORDS coordinates and
    MAX_ROWS rows per world."""
    where = "engine.reduced.chains"
    bodies = spec.body_index
    fixed = {}
    for joint in spec.joints:
        if joint.type == JointType.FIXED:
            if joint.parent is not None:
                raise ValueError(f"{where}: joint '{joint.name}': only welds to the world are modelled, "
                                 f"this one welds '{joint.child}' to '{joint.parent}'")
            R = quat_matrix(joint.parent_orientation) @ quat_matrix(joint.child_orientation).T
            p = np.asarray(joint.parent_position) - R @ np.asarray(joint.child_position)
            fixed[bodies[joint.child]] = (R, p)
        elif joint.type not in (JointType.REVOLUTE, JointType.INLINE):
            raise ValueError(f"{where}: joint '{joint.name}' is {joint.type.name.lower()}; only revolute joints, "
                             f"inline loop closures and welds to the world are modelled")
        elif joint.has_limits:
            raise ValueError(f"{where}: joint '{joint.name}' has limits; limits are not modelled")
    for shape in spec.shapes:
        if spec.ground is None:
            raise ValueError(f"{where}: shape '{shape.name}': shapes collide with the ground plane only, and the "
                             f"mechanism has none")
        if shape.restitution > 0.0 or spec.ground.restitution > 0.0:
            raise ValueError(f"{where}: shape '{shape.name}': restitution is not modelled")
    pose = {}
    for i, body in enumerate(spec.bodies):
        pose[i] = (quat_matrix(body.orientation), np.asarray(body.position, dtype=np.float64))
    # the spanning tree: every body's distance (in joints) from the fixed set, or from its floating
    # component's root (the component's heaviest body); driven joints first (drives act on tree
    # joints only), then the others nearest the roots first (a shallow tree)
    revolute = [ji for ji, j in enumerate(spec.joints) if j.type == JointType.REVOLUTE]

    def end_of(name):
        return None if name is None else bodies[name]

    neighbours = {i: [] for i in range(len(spec.bodies))}
    neighbours[None] = []
    for ji in revolute:
        a, b = end_of(spec.joints[ji].parent), end_of(spec.joints[ji].child)
        a, b = (None if a in fixed else a), (None if b in fixed else b)
        neighbours[a].append(b)
        neighbours[b].append(a)

    def distances(start):
        dist, queue = {start: 0}, [start]
        while queue:
            here = queue.pop(0)
            for other in neighbours[here]:
                if other not in dist:
                    dist[other] = dist[here] + 1
                    queue.append(other)
        return dist

    dist = distances(None)
    roots = []
    for i, body in enumerate(spec.bodies):
        if i in dist or i in fixed:
            continue
        component = distances(i)
        root = max(sorted(b for b in component if b is not None), key=lambda b: spec.bodies[b].mass)
        roots.append(root)
        dist.update(distances(root))
    group = {}

    def find(x):
        while group.get(x, x) != x:
            x = group[x]
        return x

    def key(b):
        return None if b is None or b in fixed else b

    def reach(ji):
        ends = sorted((dist[key(end_of(spec.joints[ji].parent))], dist[key(end_of(spec.joints[ji].child))]))
        return (spec.joints[ji].drive is None, *ends, ji)

    order = sorted(revolute, key=reach)
    used = set()
    for ji in order:
        a, b = find(key(end_of(spec.joints[ji].parent))), find(key(end_of(spec.joints[ji].child)))
        if a != b:
            group[a] = b
            used.add(ji)
    tree_index = {}  # spec body -> tree index
    tree_body, parent, depth, joint_of, forward, kind, sub_of = [], [], [], [], [], [], []
    level = {}

    def grow(queue):  # breadth-first over the tree joints from the bodies in queue (None: the fixed set)
        while queue:
            here = queue.pop(0)
            for ji in sorted(used):
                joint = spec.joints[ji]
                a, b = key(end_of(joint.parent)), key(end_of(joint.child))
                if a == here:
                    other, fwd = b, True
                elif b == here:
                    other, fwd = a, False
                else:
                    continue
                if other is None or other in tree_index:
                    continue
                tree_index[other] = len(tree_body)
                tree_body.append(other)
                parent.append(-1 if here is None else tree_index[here])
                depth.append(0 if here is None else level[here] + 1)
                level[other] = depth[-1]
                joint_of.append(ji)
                forward.append(fwd)
                kind.append(KIND_REVOLUTE)
                sub_of.append(len(tree_body) - 1)
                queue.append(other)

    grow([None])
    for root in roots:  # a floating root: five massless entries and the root body's, a chain of six
        first = len(tree_body)
        for f in range(6):
            tree_body.append(root)
            parent.append(-1 if f == 0 else first + f - 1)  # the chain starts at no parent
            depth.append(0)
            joint_of.append(-1)
            forward.append(True)
            kind.append(KIND_LINEAR if f < 3 else (KIND_ANGULAR if f < 5 else KIND_ROOT))
            sub_of.append(first + 5)
        tree_index[root] = first + 5
        level[root] = 0
        grow([root])
    for i, body in enumerate(spec.bodies):
        if i not in tree_index and i not in fixed:
            raise AssertionError(f"body '{body.name}' left out of the tree")
    n = len(tree_body)
    if n > MAX_COORDS:
        raise ValueError(f"{where}: {n} tree coordinates, at most {MAX_COORDS} are modelled")
    # every revolute joint off the tree closes a loop, and every inline joint (never a tree joint)
    loops = [ji for ji, j in enumerate(spec.joints)
             if (j.type == JointType.REVOLUTE and ji not in used) or j.type == JointType.INLINE]
    for ji in loops:
        j = spec.joints[ji]
        if j.drive is not None:
            raise ValueError(f"{where}: joint '{j.name}' closes a loop of driven joints; drives are modelled on "
                             f"tree joints only")
        ends = [None if j.parent is None else bodies[j.parent], bodies[j.child]]
        if all(e is None or e in fixed for e in ends):
            raise ValueError(f"{where}: joint '{j.name}' joins two fixed bodies")
    if len(loops) > MAX_LOOPS:
        raise ValueError(f"{where}: {len(loops)} loop joints, at most {MAX_LOOPS} are modelled")

    def fixed_frame(b):  # (R, p) of a fixed spec body frame, or the world
        return (np.eye(3), np.zeros(3)) if b is None else fixed[b]

    parent_R = np.zeros((n, 3, 3))
    parent_p = np.zeros((n, 3))
    child_R = np.tile(np.eye(3), (n, 1, 1))
    child_p = np.zeros((n, 3))
    axis = np.zeros((n, 3))
    q0 = np.zeros(n)
    u0 = np.zeros(n)
    for k in range(n):
        if kind[k] != KIND_REVOLUTE:  # a floating root: its initial frame; rates: centre of mass and angular
            body = spec.bodies[tree_body[k]]
            f = k - (sub_of[k] - 5)
            parent_R[k], parent_p[k] = pose[tree_body[k]]
            axis[k] = np.eye(3)[f % 3]
            u0[k] = (np.asarray(body.velocity) if f < 3 else np.asarray(body.angular_velocity))[f % 3]
            continue
        j = spec.joints[joint_of[k]]
        near_name, far_name = (j.parent, j.child) if forward[k] else (j.child, j.parent)
        near_R, near_p = ((quat_matrix(j.parent_orientation), np.asarray(j.parent_position)) if forward[k]
                          else (quat_matrix(j.child_orientation), np.asarray(j.child_position)))
        far_R, far_p = ((quat_matrix(j.child_orientation), np.asarray(j.child_position)) if forward[k]
                        else (quat_matrix(j.parent_orientation), np.asarray(j.parent_position)))
        a = np.asarray(j.axis) * (1.0 if forward[k] else -1.0)
        near = None if near_name is None else bodies[near_name]
        if parent[k] < 0:  # the joint frame in the world frame
            Rf, pf = fixed_frame(near) if near is None or near in fixed else pose[near]
            parent_R[k], parent_p[k] = Rf @ near_R, pf + Rf @ near_p
        else:
            parent_R[k], parent_p[k] = near_R, near_p
        child_R[k] = far_R.T
        child_p[k] = -far_R.T @ far_p
        axis[k] = a
        # initial angle: the far anchor frame relative to the near one, about the axis
        Rn = (pose[near][0] if near is not None and parent[k] >= 0 else np.eye(3)) @ parent_R[k]
        Rfar = pose[bodies[far_name]][0] @ far_R
        rel = Rn.T @ Rfar
        s = 0.5 * np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
        c = 0.5 * (np.trace(rel) - 1.0)
        q0[k] = math.atan2(float(s @ a), c)
        w_far = np.asarray(spec.bodies[bodies[far_name]].angular_velocity)
        w_near = np.zeros(3) if near is None or near in fixed else np.asarray(spec.bodies[near].angular_velocity)
        u0[k] = float((Rn @ a) @ (w_far - w_near))
    loop_body = np.zeros((len(loops), 2), dtype=np.int64)
    loop_R = np.zeros((len(loops), 2, 3, 3))
    loop_p = np.zeros((len(loops), 2, 3))
    loop_dirs = np.zeros((len(loops), 5, 3))
    for li, ji in enumerate(loops):
        j = spec.joints[ji]
        for side, (name, Rq, p) in enumerate(((j.parent, j.parent_orientation, j.parent_position),
                                              (j.child, j.child_orientation, j.child_position))):
            b = None if name is None else bodies[name]
            if b is None or b in fixed:
                Rf, pf = fixed_frame(b)
                loop_body[li, side] = -1
                loop_R[li, side], loop_p[li, side] = Rf @ quat_matrix(Rq), pf + Rf @ np.asarray(p)
            else:
                loop_body[li, side] = tree_index[b]
                loop_R[li, side], loop_p[li, side] = quat_matrix(Rq), np.asarray(p)
        if j.type == JointType.INLINE:  # the first anchor frame turned to (t1, t2, axis): its x and y rows are
            t1, t2 = _perpendiculars(np.asarray(j.axis))  # the anchor's position normal to the axis
            loop_R[li, 0] = loop_R[li, 0] @ np.column_stack([t1, t2, np.asarray(j.axis)])
            t1, t2 = _perpendiculars(np.array([0.0, 0.0, 1.0]))
        else:
            t1, t2 = _perpendiculars(np.asarray(j.axis))
        loop_dirs[li] = np.stack([np.eye(3)[0], np.eye(3)[1], np.eye(3)[2], t1, t2])
    shapes = [si for si, shape in enumerate(spec.shapes) if bodies[shape.body] not in fixed]
    if len(shapes) > MAX_SHAPES:
        raise ValueError(f"{where}: {len(shapes)} shapes on moving bodies (shape '{spec.shapes[shapes[-1]].name}'), "
                         f"at most {MAX_SHAPES} are modelled")
    layout = ChainLayout(spec, tree_body, np.array(parent, dtype=np.int64), np.array(depth, dtype=np.int64),
                         joint_of, parent_R, parent_p, child_R, child_p, axis, q0, u0, loops, loop_body, loop_R,
                         loop_p, loop_dirs, np.zeros((0, 2), dtype=np.int64), np.array(kind, dtype=np.int64),
                         np.array(sub_of, dtype=np.int64), shapes,
                         [li for li, ji in enumerate(loops) if spec.joints[ji].armature > 0.0
                          or spec.joints[ji].damping > 0.0],
                         [li for li, ji in enumerate(loops) if spec.joints[ji].type == JointType.INLINE])
    layout.fixed = fixed
    layout.rows = _independent_rows(layout)
    if len(layout.rows) + len(layout.soft) > MAX_ROWS:
        raise ValueError(f"{where}: {len(layout.rows)} independent loop rows and {len(layout.soft)} loop joints with "
                         f"armature or damping, at most {MAX_ROWS} rows are modelled")
    return layout


def _independent_rows(layout: ChainLayout) -> np.ndarray:
    """The loop rows kept (at the initial angles), by Gram-Schmidt with pivoting: each time the row
    whose part outside the span of the rows kept so far is largest, measured against the largest
    norm among the rows of its kind (position rows in metres per radian, angular rows in radians per
    radian), until none is above ROW_TOLERANCE. A planar loop's out-of-plane rows are zero there up
    to the model's rounding; the pivoting keeps, of rows that say the same, the best conditioned (a
    row that only grazes the constraint would lose it as the mechanism moves). Returned in row
    order."""
    if not layout.loops:
        return np.zeros((0, 2), dtype=np.int64)
    G, _ = layout.loop_rows(layout.q0)
    norms = np.linalg.norm(G, axis=1)
    angular = np.arange(len(G)) % 5 >= 3
    scale = np.where(angular, max(norms[angular].max(), 1e-300), max(norms[~angular].max(), 1e-300))
    rest = G.copy()
    kept = []
    while len(kept) < len(G):
        size = np.linalg.norm(rest, axis=1) / scale
        size[kept] = 0.0
        r = int(np.argmax(size))
        if size[r] <= ROW_TOLERANCE:
            break
        kept.append(r)
        unit = rest[r] / np.linalg.norm(rest[r])
        rest -= np.outer(rest @ unit, unit)
    return np.array([(r // 5, r % 5) for r in sorted(kept)], dtype=np.int64).reshape(-1, 2)


def _capacity(layout: ChainLayout, cap: int | None) -> int:
    """A world's contact capacity: its shapes' candidate contacts against the ground plane (a
    sphere 1, a capsule 2, a box or a cylinder 4), at most MAX_CONTACTS and cap."""
    count = sum(PLANE_CONTACTS[layout.spec.shapes[s].type] for s in layout.shapes)
    return min(count, MAX_CONTACTS, MAX_CONTACTS if cap is None else cap)


def _tile_size(count: int) -> int:
    return max(TILE_STEP, -(-count // TILE_STEP) * TILE_STEP)


def _packed_rows(parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per tree entry (parents first) its level (ancestors) and the packed mass matrix's row starts
    (row k: level[k] + 1 entries, its ancestors roots first, then itself), with the total appended."""
    level = np.zeros(len(parent), dtype=np.int32)
    for k, p in enumerate(parent):
        level[k] = 0 if p < 0 else level[p] + 1
    return level, np.r_[0, np.cumsum(level + 1)].astype(np.int32)


def _prefix(level: np.ndarray) -> int:
    """How many leading entries (at most MAX_PREFIX) form a chain every other entry descends from:
    entry l is the only one at level l (a floating root's six entries, where the world has nothing
    else; a fixed base's single first joint)."""
    count = 0
    while count < min(MAX_PREFIX, len(level)) and level[count] == count and np.count_nonzero(level == count) == 1:
        count += 1
    return count


def _packed_tile(size: int) -> int:
    """The packed mass matrix's shared tile for a batch whose largest world's has ``size`` entries:
    size rounded up to TILE_STEP, at most MAX_PACKED."""
    if size > MAX_PACKED:  # (MAX_COORDS keeps a chain's sum of levels within it)
        raise ValueError(f"pack_chains: a packed mass matrix of {size} entries exceeds the largest shared tile "
                         f"({MAX_PACKED})")
    return _tile_size(size)


def _transform(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(R, p) as a wp.transform's 7 floats (p, quaternion x y z w)."""
    w = math.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    if w > 1e-6:
        q = np.array([(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(max(0.0, 1.0 + R[i, i] - R[j, j] - R[k, k])) * 2.0
        q = np.zeros(4)
        q[i] = s / 4.0
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    return np.concatenate((p, q / np.linalg.norm(q)))
