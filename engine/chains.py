"""Closed chains in reduced coordinates: a spanning tree of revolute joints, on fixed bodies or
floating, its loops closed by constraint rows, contacts with the ground plane, one fused kernel
launch per step.

In maximal coordinates DR Legs hanging has 186 constraint rows (36 revolute joints and a weld),
and a step factors their sparse Delassus matrix. Here the same mechanism has 30 coordinates (one
angle per joint of a spanning tree) and 30 loop rows (the 6 joints the tree leaves out), of which
the host keeps the 18 that are independent; a step factors the 30-square mass matrix along the
tree and the 18-square loop matrix densely, in shared memory, one thread block per world.

Model (``pack_chains``, host): the fixed set is the world and every body welded to it (a fixed
joint with no parent). Bodies not connected to it through revolute joints form floating parts;
each has a root, its heaviest body, with six coordinates: the rates of its centre of mass's
velocity and of its angular velocity (world frame), its pose kept in ChainState.root (a
centre-of-mass frame, advanced by the exponential map). In the tree they are a chain of six
entries (five massless, then the root body's), ancestors of the whole part. The tree's joints are
chosen driven joints first, then nearest the roots (a shallow tree); a breadth-first search over
them orders the entries parents first (one coordinate per tree joint: its angle, 0 where its two
anchor frames coincide, as engine.spec defines it); every other revolute joint closes a loop. Each
loop has five rows in the anchor frame of its first body: three position rows along the frame's
axes and two angular rows about two directions normal to the joint axis. The host evaluates the
rows at the initial pose in float64 and keeps a largest independent subset (Gram-Schmidt with
pivoting): a planar loop's out-of-plane rows are implied by its joints' parallel axes, and a
redundant row would make the loops' matrix singular. A loop joint's armature a and damping c add a
soft row on its rate about its axis (compliance 1 / (a + dt c), the share a / (a + dt c) of its
last rate kept), the maximal engine's joint-space dynamics rows. Shapes collide with the ground
plane only (engine.collide.plane_point: a sphere's lowest point, a capsule's ends, a box's or a
cylinder's 4 deepest points within SolverConfig.contact_margin), up to contact_capacity contacts
per world (default: every candidate, at most MAX_CONTACTS); friction is the geometric mean of the
shape's and the ground's. The step kernel's contact tiles hold contact_working contacts (default:
the most any world has at its initial pose): a world that finds more in a step, within its
capacity, restores the step's start and a second kernel, with tiles for the full capacity, steps it
(bit for bit as that kernel alone would; work.contact_redone counts them). Shared memory sets how
many worlds an SM holds: DR Legs standing keeps 12 per SM with tiles for its feet's 8 contacts,
8 with tiles for all 12 candidates (1.20 against 1.59 ms per step at 4096 worlds on an H200).
Only what this path models is accepted, with an error that names the joint, shape or body otherwise:
revolute joints (and welds to the world), drives on tree joints, no limits, no restitution, at most
MAX_COORDS coordinates and MAX_ROWS rows per world. Drive effort limits are checked, not enforced: a
world whose drive torque exceeds its limit stops with the reason (ChainModel.failure_reasons).
Worlds of a batch may differ in everything (padded).

Step (``chain_step_kernel``, one block per world; the lanes share each stage, a barrier between
stages; on the CPU a block is one thread):
1. with the Moreau-Jean midpoint rule (SolverConfig.integrator, the default) the coordinates
   first move half a step, q += dt/2 u; the dynamics below are evaluated there (semi-implicit
   Euler: at q);
2. kinematics level by level of the tree (a lane per entry of the level, from a per-depth list):
   body poses, each coordinate's motion (axis a and its moment about the origin), body velocities,
   and the velocity-product accelerations (the accelerations at zero coordinate acceleration);
3. composite rigid-body sums, pulled up the tree level by level (a body's children are
   contiguous in the breadth-first order): the mass, first moment and inertia about the world
   origin of each subtree, and its gravity, inertial and gyroscopic wrench; the mass matrix
   M_ij = S_i . (I_j S_j) for each coordinate i moving body j (the only non-zeros), the
   generalized forces;
4. the joints' damping and PD drives implicit: (M + dt C) du = dt tau, C = damping + kd + h kp on
   the diagonal (h the rest of the step the angles still move); M~ = M + dt C factored as L^T D L
   along the tree by the lanes (each eliminated entry's ancestor pairs shared, a barrier per entry;
   no fill: the sum of the entries' depths squared instead of n^3 / 6),
   every solve along the ancestors only; M~ is packed in shared memory (row k: its ancestors and
   itself, roots first, a dense run in a 1-D tile; DR Legs standing 293 entries instead of 36 x 36),
   which lets 11 or more instead of 8 worlds share an SM; the solves' first pass (leaves first)
   skips the entries still 0 (a column of G^T or J^T is nonzero only along a few bodies' ancestors),
   and both passes take a leading chain that every entry descends from (a floating root's six
   entries: 180 of DR Legs standing's 293 walk steps) unrolled instead of walking its parents
   (CPU cycles of the X and Y solves -30 % and -25 %, bit for bit the same; not yet timed on a GPU);
5. the loops' rows G (a lane per row, along its two bodies' ancestors; kept rows, then soft rows),
   X = M~^-1 G^T (a lane per row), A = G X (wp.tile_matmul, as every dense product of the step)
   + compliance + 1e-6 diag(G X) factored (dense Cholesky
   in shared memory, the lanes sharing each column), u = u_f + X A^-1 (-(G u_f) - baumgarte phi / dt
   + share G u) (the solves with A's factor by the lanes, a barrier per column): the loops'
   velocity constraint holds exactly, not as a penalty;
6. contacts (compiled only for batches with shapes): candidates at the evaluation pose (a lane per
   shape, into shared memory), the rows J (normal and two tangents per contact, along the body's
   ancestors), P J^T = (M~^-1 - X A^-1 X^T) J^T (the response with the loops held), D = J P J^T,
   v_f = J u + the normal rows' bias (a gap closed in one step at most, a penetration pushed out by
   SolverConfig.contact_stabilization per step), a Jacobi preconditioner per contact (one scale for
   its three rows: the cone keeps its shape), then PADMM (ENGINE.md: De Saxce correction, Coulomb
   cone projection, an adaptive penalty with a new inverse of D + (eta + rho) I when it changes,
   SolverConfig's tolerances and iteration cap, every lane deciding alike) warm-started from each
   contact slot's last impulse and from the penalty the world's last step ended with (CONTACT_RHO
   on a new state); u += P J^T lambda;
7. q += h u, then SolverConfig.position_iterations Gauss-Newton projections of q back onto the
   loops' position constraint with the step's X and A (dq = -X A^-1 phi(q), the tree's poses redone
   each time; a floating root's six corrections turn and move its frame), stopped as soon as every
   kept row's error is within SolverConfig.projection_skip_floor [m] (angular rows:
   projection_skip_floor_angular [rad]; both 0: never): its correction would be float32 rounding.
   A still mechanism then skips them all (DR Legs standing: the projections' stage 33 k -> 18 k
   CPU cycles a step, loops 1.2e-7 m either way; on an H200, whose rounding sits at the floors, it
   still projects 0.6-0.7 times a step, none with 3x the floors). The check's kinematics carries the velocities, so
   that a stop also spares the final kinematics pass, and its errors go to shared memory in one
   pass (the correction's right-hand side and their sizes, which every lane then reads);
8. the poses and velocities of every body (COM frames, as engine.model's State) and a divergence
   guard (non-finite or faster than SolverConfig.max_speed: the world is frozen and flagged).

Order of accuracy: the midpoint step evaluates the velocity-product and gyroscopic terms with the
step's initial rates and the drives' terms backward (stable for stiff drives), so the motion is
first order in dt wherever those matter (DR Legs hanging at dt 10 ms: 3.1e-3 m from MuJoCo C's
float64 reference over 2 s, half that at 5 ms; the maximal-coordinate step: 5.6e-4 m; a free
floating chain's momenta drift at first order too). Evaluating them at rates extrapolated to the
midpoint, u + (u - u_previous) / 2, projected onto the loops' tangent (G u = 0), made a three-link
chain second order (3.8e-4 -> 2.4e-5 m at dt 4 ms, CPU, 0.4 s) and a six-bar 1.4-2.8x closer in a
CPU trial; not built (it needs the poses' factors before the velocity pass, and a GPU timing).

Measured at 4096 worlds (benchmarks/results/README.md, "DR Legs hanging and the four-bar in
reduced coordinates", "DR Legs standing in reduced coordinates", "DR Legs standing: where the
reduced step waited, and the packed mass matrix" and "DR Legs standing: the carried-over penalty
on the GPU, ..." and "DR Legs standing and hanging: the CPU-only changes timed, ..."), on an
H200: DR Legs standing with the feet's 8 contacts 1.20 ms per step against MuJoCo Warp's 1.34 ms
in one call (3.0 PADMM iterations a step, loops within 9.4e-8 m against its 4.2e-4 m; 1.59 ms with
all 12 candidates); DR Legs hanging 0.387 ms, loops within 1.6e-7 m (MuJoCo Warp 0.770 ms,
5.9e-4 m). The step is bound by latency, not bandwidth: the packed M~ made it 11 worlds per SM instead of 8
(2.15 -> 1.70 ms standing), and the warps wait on dependent arithmetic and shared-memory loads;
on DR Legs standing the column solves of X and Y (a lane per column along the ancestors), the
projections with their kinematics and the contact factor and PADMM take most of a world's step. The kernel is
capped at MAX_REGISTERS registers per thread (left to the compiler it took 168 on DR Legs hanging,
12 worlds per SM instead of 16: 0.53 instead of 0.41 ms).

The loops' error of the result is measured by the maximal-coordinate engine's own joint residuals
(engine.metrics on a maximal model of the same specs), from body_q.
"""

import functools
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import warp as wp

from engine.collide import PLANE_CONTACTS, plane_point, plane_point_count
from engine.contacts import contact_direction
from engine.padmm import project_cone
from engine.linalg.lanes import block_sync, tile_set
from engine.model import Integrator, SolverConfig
from engine.spec import JointType, MechanismSpec

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["ChainModel", "ChainState", "ChainStepper", "MAX_COORDS", "MAX_ROWS", "chain_layout", "pack_chains"]

MAX_COORDS = 48  # tree coordinates per world (a floating root counts six)
MAX_ROWS = 32  # kept loop rows per world
MAX_CONTACTS = 16  # contacts per world (three rows each)
MAX_SHAPES = 16  # shapes on moving bodies per world (4 candidate slots each: a shared tile of at most 64 rows)
# the contacts' initial ADMM penalty, in units of their preconditioned Delassus matrix's diagonal (1):
# SolverConfig.rho's 1e-3 let capped iterations return wild impulses on new contacts (CPU, a cap of 3:
# a six-bar on a box thrown 2.6 m up); at 1 the same stay put, for 7 instead of 4 iterations a step on
# DR Legs standing and 24 instead of 42 on a sliding box at the default tolerances. Each later step starts
# from the penalty its world's last step ended with (adaptive_rho): DR Legs standing settles at 1/64 and
# takes 3.0 iterations a step and no new factor instead of 6.8 and 1.3 (CPU, 1 s at dt 10 ms; its bodies
# 3.2e-5 m from the maximal engine converged to 1e-9 either way)
CONTACT_RHO = 1.0
KIND_REVOLUTE = wp.constant(0)  # a tree entry's coordinate: a revolute joint's angle,
KIND_LINEAR = wp.constant(1)  # a floating root's centre-of-mass velocity along a world axis (first three),
KIND_ANGULAR = wp.constant(2)  # its angular velocity about a world axis (next two)
KIND_ROOT = wp.constant(3)  # and about the z axis: the entry that is the root body
MAX_LOOPS = 32
ROW_TOLERANCE = 1.0e-4  # a loop row is redundant when the kept rows leave less than this of its norm
REGULARIZATION = wp.constant(1.0e-6)  # relative diagonal shift of the loops' matrix (rounding guard)
CHAIN_BLOCK = 32  # threads per world on a GPU (two warps for DR Legs standing's 36 coordinates: 2.04 -> 2.06 ms)
vec8f = wp.types.vector(length=8, dtype=float)  # a shape's candidate points' distances
TILE_STEP = 4  # the shared tiles are sized to the batch's padded coordinates and rows in steps of this (8: DR Legs
# standing 1.344 against 1.333 ms per step, H200, with the packed matrix a 1-D tile)
# registers per thread on CUDA: 128 lets 16 blocks (worlds) share an SM; left to the compiler the step
# takes 168 (DR Legs hanging, 12 blocks: 0.533 instead of 0.376 ms per step at 4096 worlds, H100)
MAX_REGISTERS = 128
MAX_PREFIX = 6  # the leading chain the solves take unrolled (a floating root's six entries)
MAX_PACKED = 4096  # entries of the packed mass matrix (a shared tile; MAX_COORDS' deepest chain needs 1176)




def _quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    return _quat_matrix(np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)])


def _perpendiculars(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e = np.eye(3)[int(np.argmin(np.abs(axis)))]
    t1 = np.cross(axis, e)
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(axis, t1)


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
                    lin[k] = np.cross(c, e)
                continue
            par = int(self.parent[k])
            Rp, pp = (np.eye(3), np.zeros(3)) if par < 0 else (R[par], p[par])
            Rj = Rp @ self.parent_R[k]
            point = pp + Rp @ self.parent_p[k]
            axis[k] = Rj @ self.axis[k]
            lin[k] = np.cross(point, axis[k])
            Rq = Rj @ _axis_angle(self.axis[k], q[k])
            R[k] = Rq @ self.child_R[k]
            p[k] = point + Rq @ self.child_p[k]
        return R, p, lin, axis

    def loop_rows(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All five rows of every loop at angles q: Jacobian (5 L, n) and error (5 L,)."""
        R, p, lin, axis = self.kinematics(q)
        n, L = self.n, len(self.loops)
        G = np.zeros((5 * L, n))
        phi = np.zeros(5 * L)
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
                d = dirs[:, part]
                r = 5 * li + part
                if part < 3:
                    phi[r] = d @ (xb - xa)
                else:
                    phi[r] = d @ np.cross(ax_a, ax_b)
                for sign, body, x in ((1.0, b, xb), (-1.0, a, xa)):
                    for j in (self.ancestors(body) if body >= 0 else []):
                        col = np.cross(axis[j], x) + lin[j] if part < 3 else axis[j]
                        G[r, j] += sign * (d @ col)
        return G, phi

    def axis_of_loop(self, li: int) -> np.ndarray:
        """Loop li's joint axis in its anchor frames."""
        return np.asarray(self.spec.joints[self.loops[li]].axis)


def _frame(q) -> np.ndarray:
    return _quat_matrix(np.asarray(q, dtype=np.float64))


def chain_layout(spec: MechanismSpec) -> ChainLayout:
    """The spanning tree and loops of one spec (module docstring), or ValueError naming what this
    path cannot model."""
    where = "engine.chains"
    bodies = spec.body_index
    fixed = {}
    for joint in spec.joints:
        if joint.type == JointType.FIXED:
            if joint.parent is not None:
                raise ValueError(f"{where}: joint '{joint.name}': only welds to the world are modelled, "
                                 f"this one welds '{joint.child}' to '{joint.parent}'")
            R = _frame(joint.parent_orientation) @ _frame(joint.child_orientation).T
            p = np.asarray(joint.parent_position) - R @ np.asarray(joint.child_position)
            fixed[bodies[joint.child]] = (R, p)
        elif joint.type != JointType.REVOLUTE:
            raise ValueError(f"{where}: joint '{joint.name}' is {joint.type.name.lower()}; only revolute joints "
                             f"and welds to the world are modelled")
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
        pose[i] = (_frame(body.orientation), np.asarray(body.position, dtype=np.float64))
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
    loops = [ji for ji in revolute if ji not in used]
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
        near_R, near_p = ((_frame(j.parent_orientation), np.asarray(j.parent_position)) if forward[k]
                          else (_frame(j.child_orientation), np.asarray(j.child_position)))
        far_R, far_p = ((_frame(j.child_orientation), np.asarray(j.child_position)) if forward[k]
                        else (_frame(j.parent_orientation), np.asarray(j.parent_position)))
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
                loop_R[li, side], loop_p[li, side] = Rf @ _frame(Rq), pf + Rf @ np.asarray(p)
            else:
                loop_body[li, side] = tree_index[b]
                loop_R[li, side], loop_p[li, side] = _frame(Rq), np.asarray(p)
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
                          or spec.joints[ji].damping > 0.0])
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


@wp.struct
class ChainArrays:
    tree_count: wp.array(dtype=wp.int32)
    depth_count: wp.array(dtype=wp.int32)
    loop_count: wp.array(dtype=wp.int32)
    row_count: wp.array(dtype=wp.int32)
    gravity: wp.array(dtype=wp.vec3)
    parent: wp.array2d(dtype=wp.int32)
    by_depth: wp.array2d(dtype=wp.int32)  # the entries ordered by depth (roots first)
    depth_start: wp.array2d(dtype=wp.int32)  # where depth d starts in by_depth (depth_count + 1 of them)
    level: wp.array2d(dtype=wp.int32)  # entry k's ancestors (its chain's length to the root)
    ancestor: wp.array2d(dtype=wp.int32)  # packed like M~: row k's ancestors, roots first, then k
    row_start: wp.array2d(dtype=wp.int32)  # where row k of the packed M~ starts (rows of level + 1 entries)
    first_child: wp.array2d(dtype=wp.int32)  # tree index of body k's first child, -1: none
    child_count: wp.array2d(dtype=wp.int32)
    joint_parent: wp.array2d(dtype=wp.transform)
    joint_child: wp.array2d(dtype=wp.transform)
    axis: wp.array2d(dtype=wp.vec3)
    com: wp.array2d(dtype=wp.vec3)
    mass: wp.array2d(dtype=float)
    inertia: wp.array2d(dtype=wp.mat33)
    armature: wp.array2d(dtype=float)
    damping: wp.array2d(dtype=float)
    kp: wp.array2d(dtype=float)
    kd: wp.array2d(dtype=float)
    q_target: wp.array2d(dtype=float)
    v_target: wp.array2d(dtype=float)
    body_out: wp.array2d(dtype=wp.int32)  # spec body index of tree body k
    loop_body: wp.array3d(dtype=wp.int32)  # (W, L, 2)
    loop_anchor: wp.array3d(dtype=wp.transform)  # (W, L, 2)
    loop_axis: wp.array2d(dtype=wp.vec3)
    loop_t1: wp.array2d(dtype=wp.vec3)
    loop_t2: wp.array2d(dtype=wp.vec3)
    row_loop: wp.array2d(dtype=wp.int32)
    row_part: wp.array2d(dtype=wp.int32)  # 0-2 position, 3-4 angular, 5 a loop joint's rate (soft)
    row_compliance: wp.array2d(dtype=float)  # soft rows: 1 / (armature + dt damping), else 0
    row_keep: wp.array2d(dtype=float)  # soft rows: armature / (armature + dt damping), else 0
    kind: wp.array2d(dtype=wp.int32)  # KIND_* of entry k
    sub_of: wp.array2d(dtype=wp.int32)  # the entry whose subtree coordinate k moves (a floating root's: the root)
    effort: wp.array2d(dtype=float)  # drive effort limit (checked, not enforced; inf: none)
    shape_count: wp.array(dtype=wp.int32)
    shape_entry: wp.array2d(dtype=wp.int32)  # tree entry of the shape's body
    shape_type: wp.array2d(dtype=wp.int32)
    shape_X: wp.array2d(dtype=wp.transform)  # in the body frame
    shape_size: wp.array2d(dtype=wp.vec3)
    shape_mu: wp.array2d(dtype=float)  # friction with the ground (geometric mean)
    ground_normal: wp.array(dtype=wp.vec3)
    ground_offset: wp.array(dtype=float)
    contact_capacity: wp.array(dtype=wp.int32)
    prefix: wp.array(dtype=wp.int32)  # leading entries that are a chain all others descend from (<= MAX_PREFIX)


@wp.struct
class ChainWork:
    pose: wp.array2d(dtype=wp.transform)  # body frames
    centre: wp.array2d(dtype=wp.vec3)  # centres of mass
    lin: wp.array2d(dtype=wp.vec3)  # coordinates' linear parts (the origin's velocity at a unit rate)
    axis: wp.array2d(dtype=wp.vec3)  # and angular parts (joint axes, world)
    omega: wp.array2d(dtype=wp.vec3)
    vel: wp.array2d(dtype=wp.vec3)
    alpha: wp.array2d(dtype=wp.vec3)  # velocity-product angular acceleration
    acc: wp.array2d(dtype=wp.vec3)  # velocity-product linear acceleration of the centre of mass
    inertia: wp.array2d(dtype=wp.mat33)  # world-frame inertia about the centre of mass
    wrench_t: wp.array2d(dtype=wp.vec3)  # per body, then per subtree: torque about the origin
    wrench_f: wp.array2d(dtype=wp.vec3)  # and force
    sub_mass: wp.array2d(dtype=float)  # per body, then per subtree: mass,
    sub_moment: wp.array2d(dtype=wp.vec3)  # first moment about the origin
    sub_inertia: wp.array2d(dtype=wp.mat33)  # and inertia about the origin
    force_n: wp.array2d(dtype=wp.vec3)  # subtree's inertia applied to the joint's motion: torque
    force_f: wp.array2d(dtype=wp.vec3)  # and force
    phi: wp.array2d(dtype=float)  # every loop's six errors (W, 6 L; the sixth, its rate row's, is 0)
    dirs: wp.array2d(dtype=wp.vec3)  # and directions
    ends: wp.array2d(dtype=wp.vec3)  # anchor points, 2 per loop
    q_start: wp.array2d(dtype=float)  # the step's initial angles and rates
    u_start: wp.array2d(dtype=float)
    root_start: wp.array2d(dtype=wp.transform)  # floating roots' centre-of-mass frames at the step's start
    diverged: wp.array(dtype=wp.int32)  # 0 running, DIVERGED or EFFORT_LIMIT (frozen)
    contact_count: wp.array(dtype=wp.int32)
    contact_slot: wp.array2d(dtype=wp.int32)  # candidate slot of each active contact
    contact_impulse: wp.array2d(dtype=wp.vec3)  # per candidate slot: the last impulse (normal, t1, t2), warm start
    contact_rho: wp.array(dtype=float)  # the contacts' penalty at the end of the last step (0: none yet)
    contact_dropped: wp.array(dtype=wp.int32)  # contacts within the margin beyond the capacity (last step)
    contact_overflow: wp.array(dtype=wp.int32)  # 1: this step found more contacts than the first kernel holds
    contact_redone: wp.array(dtype=wp.int32)  # steps the full-capacity kernel took over since the packing
    iterations: wp.array(dtype=wp.int32)  # PADMM iterations of the last step
    projections: wp.array(dtype=wp.int32)  # Gauss-Newton corrections of the last step (the floors stop them)
    stage_clock: wp.array2d(dtype=wp.int64)  # ChainModel.step(stages=True): clock readings (W, len(STAGES) + 1)
    matrix: wp.array3d(dtype=float)  # record: M~ (W, N, N)
    rows: wp.array3d(dtype=float)  # record: G (W, R, N)


POSES = wp.constant(0)  # kinematics' detail: body poses, joint points and axes
VELOCITIES = wp.constant(1)  # and the bodies' velocities
DYNAMICS = wp.constant(2)  # and the velocity-product accelerations and the world-frame inertias
DIVERGED = wp.constant(1)  # ChainWork.diverged: non-finite or faster than max_speed
EFFORT_LIMIT = wp.constant(2)  # a drive's torque past its effort limit


@wp.func
def free_body(m: ChainArrays, w: ChainWork, world: int, k: int, kind: int, u: wp.array2d(dtype=float),
              root: wp.array2d(dtype=wp.transform), detail: int):
    """Entry k of a floating root: the root body's pose from its centre-of-mass frame root[world, r]
    (r = sub_of[k], the root's entry), the coordinate's parts (a unit world axis e, linear: (0, e),
    angular about the centre of mass c: (e, c x e)), and with detail VELOCITIES the root's rates
    u[r - 5 .. r] (centre-of-mass velocity, angular velocity); its velocity-product accelerations are 0."""
    r = m.sub_of[world, k]
    Xc = root[world, r]
    c = wp.transform_get_translation(Xc)
    rot = wp.transform_get_rotation(Xc)
    w.pose[world, k] = wp.transform(c - wp.quat_rotate(rot, m.com[world, r]), rot)
    w.centre[world, k] = c
    e = m.axis[world, k]
    if kind == KIND_LINEAR:
        w.axis[world, k] = wp.vec3()
        w.lin[world, k] = e
    else:
        w.axis[world, k] = e
        w.lin[world, k] = wp.cross(c, e)
    if detail >= VELOCITIES:
        w.omega[world, k] = wp.vec3(u[world, r - 2], u[world, r - 1], u[world, r])
        w.vel[world, k] = wp.vec3(u[world, r - 5], u[world, r - 4], u[world, r - 3])
        if detail >= DYNAMICS:
            w.alpha[world, k] = wp.vec3()
            w.acc[world, k] = wp.vec3()
            Rb = wp.quat_to_matrix(rot)
            w.inertia[world, k] = Rb * m.inertia[world, k] * wp.transpose(Rb)


@wp.func
def kinematics_body(m: ChainArrays, w: ChainWork, world: int, k: int, q: wp.array2d(dtype=float),
                    u: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.transform), detail: int):
    """Pose, coordinate parts (joint axis a and a's moment p x a about the origin, p the joint point)
    of tree entry k from its parent's (already done) and its joint's angle; with detail VELOCITIES
    its velocities, with DYNAMICS also its velocity-product accelerations and world-frame inertia.
    A floating root's entries: free_body."""
    kind = m.kind[world, k]
    if kind != KIND_REVOLUTE:
        free_body(m, w, world, k, kind, u, root, detail)
        return
    par = m.parent[world, k]
    Xp = wp.transform_identity()
    cpar = wp.vec3()
    if par >= 0:
        Xp = w.pose[world, par]
        cpar = w.centre[world, par]
    Xj = wp.transform_multiply(Xp, m.joint_parent[world, k])
    a_local = m.axis[world, k]
    aw = wp.quat_rotate(wp.transform_get_rotation(Xj), a_local)
    pj = wp.transform_get_translation(Xj)
    Xq = wp.transform_multiply(Xj, wp.transform(wp.vec3(), wp.quat_from_axis_angle(a_local, q[world, k])))
    Xb = wp.transform_multiply(Xq, m.joint_child[world, k])
    c = wp.transform_point(Xb, m.com[world, k])
    w.pose[world, k] = Xb
    w.centre[world, k] = c
    w.lin[world, k] = wp.cross(pj, aw)
    w.axis[world, k] = aw
    if detail >= VELOCITIES:
        uk = u[world, k]
        wpar = wp.vec3()
        vpar = wp.vec3()
        if par >= 0:
            wpar = w.omega[world, par]
            vpar = w.vel[world, par]
        omega = wpar + aw * uk
        r_pj = pj - cpar
        r_b = c - pj
        w.omega[world, k] = omega
        w.vel[world, k] = vpar + wp.cross(wpar, r_pj) + wp.cross(omega, r_b)
        if detail >= DYNAMICS:
            apar = wp.vec3()
            lpar = wp.vec3()
            if par >= 0:
                apar = w.alpha[world, par]
                lpar = w.acc[world, par]
            alpha = apar + wp.cross(wpar, aw * uk)
            acc_pj = lpar + wp.cross(apar, r_pj) + wp.cross(wpar, wp.cross(wpar, r_pj))
            w.alpha[world, k] = alpha
            w.acc[world, k] = acc_pj + wp.cross(alpha, r_b) + wp.cross(omega, wp.cross(omega, r_b))
            Rb = wp.quat_to_matrix(wp.transform_get_rotation(Xb))
            w.inertia[world, k] = Rb * m.inertia[world, k] * wp.transpose(Rb)


@wp.func
def kinematics(m: ChainArrays, w: ChainWork, world: int, lane: int, lanes: int, q: wp.array2d(dtype=float),
               u: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.transform), detail: int):
    """The tree's kinematics level by level (a lane per entry) to ``detail``. Entered after a barrier;
    leaves one."""
    for level in range(m.depth_count[world]):
        for t in range(m.depth_start[world, level] + lane, m.depth_start[world, level + 1], lanes):
            kinematics_body(m, w, world, m.by_depth[world, t], q, u, root, detail)
        block_sync()


@wp.func
def turned(X: wp.transform, dc: wp.vec3, r: wp.vec3):
    """The frame X moved by dc and turned by the rotation vector r (world frame)."""
    rot = wp.transform_get_rotation(X)
    angle = wp.length(r)
    if angle > 0.0:
        rot = wp.normalize(wp.quat_from_axis_angle(r / angle, angle) * rot)
    return wp.transform(wp.transform_get_translation(X) + dc, rot)


@wp.func
def advance(m: ChainArrays, world: int, k: int, q: wp.array2d(dtype=float), root: wp.array2d(dtype=wp.transform),
            u: wp.array2d(dtype=float), scale: float):
    """Entry k's coordinate moved by scale times its rate: an angle directly, a floating root's frame
    by its six rates at once (on its root entry; its other entries do nothing)."""
    kind = m.kind[world, k]
    if kind == KIND_REVOLUTE:
        q[world, k] = q[world, k] + scale * u[world, k]
    elif kind == KIND_ROOT:
        root[world, k] = turned(root[world, k], scale * wp.vec3(u[world, k - 5], u[world, k - 4], u[world, k - 3]),
                                scale * wp.vec3(u[world, k - 2], u[world, k - 1], u[world, k]))


@wp.func
def correction(X: Any, lam: Any, i: int, R: int):
    """Row i of X applied to lam = A^-1 phi (the kept rows' errors): coordinate i's Gauss-Newton
    correction (X A^-1 phi)_i."""
    acc = float(0.0)
    for r in range(R):
        acc += X[i, r] * lam[r]
    return acc


@wp.func
def project(m: ChainArrays, world: int, k: int, q: wp.array2d(dtype=float),
            root: wp.array2d(dtype=wp.transform), X: Any, lam: Any, R: int):
    """Entry k's coordinate moved by its Gauss-Newton correction -X A^-1 phi (lam = A^-1 phi; a
    floating root's six at once, on its root entry)."""
    kind = m.kind[world, k]
    if kind == KIND_REVOLUTE:
        q[world, k] = q[world, k] - correction(X, lam, k, R)
    elif kind == KIND_ROOT:
        dc = wp.vec3(correction(X, lam, k - 5, R), correction(X, lam, k - 4, R),
                     correction(X, lam, k - 3, R))
        dr = wp.vec3(correction(X, lam, k - 2, R), correction(X, lam, k - 1, R),
                     correction(X, lam, k, R))
        root[world, k] = turned(root[world, k], -dc, -dr)


@wp.func
def loop_errors(m: ChainArrays, w: ChainWork, world: int, lane: int, lanes: int):
    """Every loop's anchor points, row directions and five errors (a lane per loop)."""
    for li in range(lane, m.loop_count[world], lanes):
        xa = wp.vec3()
        xb = wp.vec3()
        qa = wp.quat_identity()
        qb = wp.quat_identity()
        for side in range(2):
            b = m.loop_body[world, li, side]
            X = m.loop_anchor[world, li, side]
            if b >= 0:
                X = wp.transform_multiply(w.pose[world, b], X)
            if side == 0:
                xa = wp.transform_get_translation(X)
                qa = wp.transform_get_rotation(X)
            else:
                xb = wp.transform_get_translation(X)
                qb = wp.transform_get_rotation(X)
        axis = m.loop_axis[world, li]
        cross = wp.cross(wp.quat_rotate(qa, axis), wp.quat_rotate(qb, axis))
        gap = xb - xa
        for part in range(6):
            d = wp.vec3()
            if part == 0:
                d = wp.quat_rotate(qa, wp.vec3(1.0, 0.0, 0.0))
            elif part == 1:
                d = wp.quat_rotate(qa, wp.vec3(0.0, 1.0, 0.0))
            elif part == 2:
                d = wp.quat_rotate(qa, wp.vec3(0.0, 0.0, 1.0))
            elif part == 3:
                d = wp.quat_rotate(qa, m.loop_t1[world, li])
            elif part == 4:
                d = wp.quat_rotate(qa, m.loop_t2[world, li])
            else:  # the joint's rate about its axis (armature and damping rows): no error
                d = wp.quat_rotate(qa, axis)
            e = wp.dot(d, gap)
            if part == 5:
                e = 0.0
            elif part >= 3:
                e = wp.dot(d, cross)
            w.phi[world, 6 * li + part] = e
            w.dirs[world, 6 * li + part] = d
        w.ends[world, 2 * li] = xa
        w.ends[world, 2 * li + 1] = xb


@wp.func
def loop_rows_of(m: ChainArrays, w: ChainWork, world: int, par: Any, r: int, G: Any, X: Any,
                 u: wp.array2d(dtype=float)):
    """Kept row r of G (and of G^T in X), by one lane: the row's rate from each tree joint that moves
    either of its loop's bodies (walking up from each; the second body's joints count +, the first's
    -; a common ancestor's cancel in the angular rows and nearly so in the position rows). The
    tiles' other entries stay 0. Returns (G u)_r, summed along the same walks."""
    rate = float(0.0)
    li = m.row_loop[world, r]
    part = m.row_part[world, r]
    d = w.dirs[world, 6 * li + part]
    for side in range(2):
        sign = float(1.0)
        if side == 0:
            sign = -1.0
        x = w.ends[world, 2 * li + side]
        j = m.loop_body[world, li, side]
        while j >= 0:
            aj = w.axis[world, j]
            value = sign * wp.dot(d, aj)
            if part < 3:
                value = sign * wp.dot(d, wp.cross(aj, x) + w.lin[world, j])
            total = G[r, j] + value
            tile_set(G, r, j, total)
            tile_set(X, j, r, total)
            rate += value * u[world, j]
            j = par[j]
    return rate


@wp.func
def factor_lanes(lane: int, lanes: int, n: int, A: Any, diag: Any, relative: float):
    """Lower Cholesky factor of the n x n shared tile A (its lower triangle, plus relative * A_jj on
    the diagonal): the factor's entries below the diagonal overwrite A's, its diagonal goes to the
    shared vector diag (A's own diagonal is kept). Left-looking, the lanes share each column's entries,
    every lane forms the pivot; one barrier per column. Entered after a barrier."""
    for j in range(n):
        s = A[j, j] * (1.0 + relative)
        for k in range(j):
            s -= A[j, k] * A[j, k]
        d = wp.sqrt(wp.max(s, 1.0e-30))
        inv = 1.0 / d
        for i in range(j + 1 + lane, n, lanes):
            t = A[i, j]
            for k in range(j):
                t -= A[i, k] * A[j, k]
            tile_set(A, i, j, t * inv)
        if lane == 0:
            tile_set(diag, j, d)
        block_sync()


# the step's stages as ChainModel.step(stages=True) times them (ChainModel.stage_cycles)
STAGES = ("kinematics and own terms", "subtree sums, forces, loop errors", "M~ and G", "tree factor",
          "X = M~^-1 G^T", "A = G X", "the loops' velocity solve", "contact candidates", "Y = M~^-1 J^T",
          "P J^T = Y - X A^-1 G Y", "J, v_f, D", "preconditioner, warm start", "contact factor and PADMM",
          "integration", "projections, velocities, guard", "output")


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return clock64();
#else
return (long long)__builtin_readcyclecounter();
#endif
""")
def clock_now() -> wp.int64:
    """The SM's cycle counter on CUDA, the processor's on the CPU."""
    ...


@wp.func
def stamp(w: ChainWork, world: int, lane: int, stage: int):
    """Lane 0 reads the clock into work.stage_clock[world, stage] (the end of stage - 1, the start
    of stage)."""
    if lane == 0:
        w.stage_clock[world, stage] = clock_now()


@wp.func
def solve_lanes(lane: int, lanes: int, n: int, L: Any, diag: Any, x: Any):
    """The shared vector x := (L L^T)^-1 x (factor_lanes' L and diag), the lanes sharing each
    column's updates: a barrier per column, 2 n in all. Entered after a barrier; leaves one."""
    for j in range(n):  # L y = x: x[i] -= L_ij y_j below column j, y_j = x[j] / d_j once x[j] is final
        yj = x[j] / diag[j]
        for i in range(j + 1 + lane, n, lanes):
            tile_set(x, i, x[i] - L[i, j] * yj)
        block_sync()
    for i in range(lane, n, lanes):
        tile_set(x, i, x[i] / diag[i])
    block_sync()
    for step in range(n):  # L^T z = y, the last column first
        j = n - 1 - step
        zj = x[j] / diag[j]
        for i in range(lane, j, lanes):
            tile_set(x, i, x[i] - L[j, i] * zj)
        block_sync()
    for i in range(lane, n, lanes):
        tile_set(x, i, x[i] / diag[i])
    block_sync()


@wp.func
def solve_column(n: int, L: Any, diag: Any, x: Any, col: int):
    """Column ``col`` of the shared tile x := (L L^T)^-1 x[:, col] (factor_lanes' L and diag), by one lane."""
    for i in range(n):
        s = x[i, col]
        for k in range(i):
            s -= L[i, k] * x[k, col]
        tile_set(x, i, col, s / diag[i])
    for step in range(n):
        i = n - 1 - step
        s = x[i, col]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k, col]
        tile_set(x, i, col, s / diag[i])


@wp.func
def tree_factor(m: ChainArrays, world: int, lane: int, lanes: int, lvl: Any, start: Any, n: int, H: Any):
    """In place: the mass matrix (packed in H: row k's entries against its ancestors and itself at
    start[k] + the column's level, a dense run ordered roots first; breadth-first order, parents
    first) as L^T D L, L unit lower triangular with entries only where the column is an ancestor of
    the row (no fill: the subtrees stay apart), D on the diagonal. Work: the sum over entries of their
    level squared, instead of n^3 / 6. Eliminating entry k (leaves first) subtracts
    H_ki H_kj / H_kk from every entry (i, j) of its ancestors' rows, j up to i: the lanes share those
    pairs (distinct entries, reading row k, which no other pair writes), a barrier per entry; row k is
    never touched again, so its division by H_kk waits for one pass at the end. Entered after a
    barrier; leaves one."""
    for step in range(n):
        k = n - 1 - step
        lk = lvl[k]
        if lk > 0:  # (every lane alike)
            ok = start[k]
            hkk = H[ok + lk]
            for e in range(lane, lk * (lk + 1) / 2, lanes):  # pair e: ancestor at level li, its entry p <= li
                li = int((wp.sqrt(8.0 * float(e) + 1.0) - 1.0) * 0.5)
                if (li + 1) * (li + 2) / 2 <= e:
                    li += 1
                elif li * (li + 1) / 2 > e:
                    li -= 1
                p = e - li * (li + 1) / 2
                ei = start[m.ancestor[world, ok + li]] + p
                hki = H[ok + li]
                tile_set(H, ei, H[ei] - hki * H[ok + p] / hkk)
            block_sync()
    for k in range(lane, n, lanes):
        ok = start[k]
        lk = lvl[k]
        hkk = H[ok + lk]
        for p in range(lk):
            tile_set(H, ok + p, H[ok + p] / hkk)
    block_sync()


@functools.cache
def tree_solves(unroll: int):
    """tree_solve_column and tree_solve_vector for batches whose prefixes (ChainArrays.prefix) are at
    most ``unroll`` long (MAX_PREFIX, or 0 where no world has one: no unrolled code, whose registers
    cost DR Legs hanging 7 % of its step on an H200)."""

    @wp.func
    def tree_solve_column(par: Any, lvl: Any, start: Any, n: int, pre: int, H: Any, x: Any, col: int):
        """Column col of the shared tile x := M^-1 x[:, col] with tree_factor's L^T D L, by one lane:
        L^T leaves first, D, then L roots first, each along the ancestors only. The first pass skips the
        entries still 0 (a column of G^T or J^T is nonzero only along a few bodies' ancestors, and the
        pass keeps it so). The first pre entries (pre <= unroll) are a chain that is every entry's
        ancestry's start (a floating root's six): an entry's ancestors among them are entries 0 .. j at
        its row's first j + 1 places, taken unrolled instead of walking the parents."""
        for step in range(n):
            i = n - 1 - step
            xi = x[i, col]
            if xi != 0.0:
                e = start[i] + lvl[i]
                j = par[i]
                while j >= pre:
                    e -= 1
                    tile_set(x, j, col, x[j, col] - H[e] * xi)
                    j = par[j]
                b = start[i]
                for t in range(wp.static(unroll)):
                    if t <= j:
                        tile_set(x, t, col, x[t, col] - H[b + t] * xi)
        for i in range(n):
            e = start[i] + lvl[i]
            s = x[i, col] / H[e]
            j = par[i]
            while j >= pre:
                e -= 1
                s -= H[e] * x[j, col]
                j = par[j]
            b = start[i]
            for t in range(wp.static(unroll)):  # (from the deepest: the walk's order)
                p = wp.static(unroll - 1) - t
                if p <= j:
                    s -= H[b + p] * x[p, col]
            tile_set(x, i, col, s)

    @wp.func
    def tree_solve_vector(par: Any, lvl: Any, start: Any, n: int, pre: int, H: Any, x: Any):
        """The shared vector x := M^-1 x with tree_factor's L^T D L, by one lane (as tree_solve_column)."""
        for step in range(n):
            i = n - 1 - step
            xi = x[i]
            e = start[i] + lvl[i]
            j = par[i]
            while j >= pre:
                e -= 1
                tile_set(x, j, x[j] - H[e] * xi)
                j = par[j]
            b = start[i]
            for t in range(wp.static(unroll)):
                if t <= j:
                    tile_set(x, t, x[t] - H[b + t] * xi)
        for i in range(n):
            e = start[i] + lvl[i]
            s = x[i] / H[e]
            j = par[i]
            while j >= pre:
                e -= 1
                s -= H[e] * x[j]
                j = par[j]
            b = start[i]
            for t in range(wp.static(unroll)):
                p = wp.static(unroll - 1) - t
                if p <= j:
                    s -= H[b + p] * x[p]
            tile_set(x, i, s)

    return tree_solve_column, tree_solve_vector


@wp.func
def own_terms(m: ChainArrays, w: ChainWork, world: int, k: int, g: wp.vec3):
    """Body k's own mass, first moment and inertia about the origin, and its gravity, inertial and
    gyroscopic wrench (torque about the origin, force), into the subtree accumulators."""
    mk = m.mass[world, k]
    c = w.centre[world, k]
    inertia = w.inertia[world, k]
    om = w.omega[world, k]
    f = mk * (g - w.acc[world, k])
    w.wrench_t[world, k] = -(inertia * w.alpha[world, k]) - wp.cross(om, inertia * om) + wp.cross(c, f)
    w.wrench_f[world, k] = f
    w.sub_mass[world, k] = mk
    w.sub_moment[world, k] = mk * c
    w.sub_inertia[world, k] = inertia + mk * (wp.dot(c, c) * wp.identity(n=3, dtype=float) - wp.outer(c, c))


@wp.func
def add_children(m: ChainArrays, w: ChainWork, world: int, k: int):
    """Body k's subtree sums: its own terms plus its children's subtree sums (the children are
    contiguous in the breadth-first order)."""
    first = m.first_child[world, k]
    if first >= 0:
        sm = w.sub_mass[world, k]
        sh = w.sub_moment[world, k]
        sI = w.sub_inertia[world, k]
        st = w.wrench_t[world, k]
        sf = w.wrench_f[world, k]
        for c in range(first, first + m.child_count[world, k]):
            sm += w.sub_mass[world, c]
            sh += w.sub_moment[world, c]
            sI += w.sub_inertia[world, c]
            st += w.wrench_t[world, c]
            sf += w.wrench_f[world, c]
        w.sub_mass[world, k] = sm
        w.sub_moment[world, k] = sh
        w.sub_inertia[world, k] = sI
        w.wrench_t[world, k] = st
        w.wrench_f[world, k] = sf


@wp.func
def candidates_within(cand: Any, shapes: int, margin: float):
    """How many of plane_candidates' rows of ``shapes`` shapes lie within the margin."""
    count = int(0)
    for slot in range(4 * shapes):
        if cand[slot, 3] < margin:
            count += 1
    return count


@wp.func
def plane_candidates(m: ChainArrays, w: ChainWork, world: int, s: int, n: wp.vec3, off: float, margin: float,
                     cand: Any):
    """Shape s's candidate contacts against the ground plane into rows 4 s .. 4 s + 3 of the shared
    tile cand (point, distance; 1e30: none): a sphere's lowest point, a capsule's ends', and of a box's
    corners or a cylinder's rim points (engine.collide.plane_point) the 4 deepest within the margin,
    in their own order (a slot keeps its point from step to step while the same points are the
    deepest: the warm start's key; when they change, a slot's last impulse starts another point,
    which costs iterations, not accuracy)."""
    entry = m.shape_entry[world, s]
    X = wp.transform_multiply(w.pose[world, entry], m.shape_X[world, s])
    kind = m.shape_type[world, s]
    size = m.shape_size[world, s]
    count = plane_point_count(kind)
    depth = vec8f()  # each point's distance above the plane, evaluated once
    for k in range(count):
        depth[k] = wp.dot(n, plane_point(kind, X, size, n, k)) - off
    chosen = int(0)  # bit k: point k is kept
    if count <= 4:
        chosen = (1 << count) - 1
    else:
        for pick in range(4):  # the deepest unchosen point within the margin, four times
            best = int(-1)
            deepest = margin
            for k in range(count):
                if (chosen & (1 << k)) == 0 and depth[k] < deepest:
                    deepest = depth[k]
                    best = k
            if best >= 0:
                chosen = chosen | (1 << best)
    slot = 4 * s
    for k in range(count):
        if (chosen & (1 << k)) != 0:
            p = plane_point(kind, X, size, n, k)
            tile_set(cand, slot, 0, p[0])
            tile_set(cand, slot, 1, p[1])
            tile_set(cand, slot, 2, p[2])
            tile_set(cand, slot, 3, depth[k])
            slot += 1
    while slot < 4 * s + 4:
        tile_set(cand, slot, 3, 1.0e30)
        slot += 1


@wp.func
def contact_factor(lane: int, lanes: int, m3: int, D: Any, ddiag: Any, fdiag: Any, Finv: Any, shift: float):
    """Finv = (D + shift I)^-1 for the m3 x m3 contact matrix whose upper triangle (and ddiag, its
    diagonal) hold D: the lower triangle is refilled from the upper and factored in place
    (factor_lanes), then Finv a column per lane. Entered after a barrier; leaves one."""
    for e in range(lane, m3 * m3, lanes):
        a = e // m3
        b = e % m3
        if b < a:
            tile_set(D, a, b, D[b, a])
        elif a == b:
            tile_set(D, a, a, ddiag[a] + shift)
    block_sync()
    factor_lanes(lane, lanes, m3, D, fdiag, 0.0)
    for r in range(lane, m3, lanes):  # column r (symmetric: also row r), a lane per column
        for j in range(m3):
            value = float(0.0)
            if j == r:
                value = 1.0
            tile_set(Finv, j, r, value)
        solve_column(m3, D, fdiag, Finv, r)
    block_sync()


@wp.func
def contact_residuals(nc: int, res_p: Any, res_d: Any, res_y: Any):
    """The largest primal and dual residuals and impulse over the nc contacts (every lane alike)."""
    out = wp.vec3()
    for c in range(nc):
        out = wp.vec3(wp.max(out[0], res_p[c]), wp.max(out[1], res_d[c]), wp.max(out[2], res_y[c]))
    return out


@functools.cache
def chain_step_kernel(coords: int, rows: int, contacts: int = 0, slots: int = TILE_STEP,
                      registers: int | None = MAX_REGISTERS, packed_size: int = TILE_STEP,
                      stages: bool = False, unroll: int = MAX_PREFIX, handover: int = 0):
    """The step kernel with shared tiles sized by coords (tree coordinates, at least MAX_PREFIX),
    rows (kept loop rows), contacts (contact rows; 0: no contact code), slots (candidate contacts)
    and packed_size (the packed mass matrix), each a multiple of TILE_STEP (coords may be MAX_PREFIX
    instead), and at most ``registers`` registers per thread on CUDA (module docstring: the step).
    stages: lane 0 writes a clock reading at the end of each of STAGES into work.stage_clock (the
    same step otherwise; without it the readings are compiled out). unroll: the longest prefix
    (ChainArrays.prefix) the tree solves take unrolled (tree_solves; 0: none, every prefix read as 0).
    handover (ChainModel.contact_working): 0 the only kernel of a step; 1 the first of two, handing a
    world that finds more contacts than its tiles hold to 2, the second, which steps only those
    (the code of each role compiled only into its kernel)."""

    per_contact = _tile_size(contacts // 3)  # the tiles of one entry per contact
    tree_solve_column, tree_solve_vector = tree_solves(unroll)
    # tile_matmul: Warp's register-blocked scalar product (cuBLASDx for these small tiles: DR Legs standing
    # 1.294 against 1.290 ms per step, 1.682 against 1.630 with 12 contacts, H200, and a long LTO build)
    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=registers,
               module_options={"enable_mathdx_gemm": False})
    def chain_step_body(m: ChainArrays, w: ChainWork, dt: float, baumgarte: float, iterations: int, max_speed: float,
                        midpoint: int, record: int, margin: float, stabilization: float, eta: float, rho0: float,
                        adaptive: int, rho_interval: int, tolerance: float, relative_tolerance: float,
                        max_iterations: int, skip_floor: float, skip_floor_angular: float, working: int,
                        q: wp.array2d(dtype=float), u: wp.array2d(dtype=float),
                        root: wp.array2d(dtype=wp.transform), body_q: wp.array2d(dtype=wp.transform),
                        body_qd: wp.array2d(dtype=wp.spatial_vector)):
        world, lane = wp.tid()
        lanes = wp.block_dim()
        if wp.static(handover == 2):  # the full-capacity kernel steps only the worlds the first one handed over
            if w.contact_overflow[world] == 0:
                return
        Mt = wp.tile_zeros(shape=packed_size, dtype=float, storage="shared")  # M~, then its factor (packed)
        # G, then J, then (D + (eta + rho) I)^-1
        Gt = wp.tile_zeros(shape=(wp.static(max(rows, contacts)), wp.static(max(coords, contacts))), dtype=float,
                           storage="shared")
        Xt = wp.tile_zeros(shape=(coords, rows), dtype=float, storage="shared")  # X = M~^-1 G^T
        At = wp.tile_zeros(shape=(rows, rows), dtype=float, storage="shared")  # A = G X, then its factor
        diag_a = wp.tile_zeros(shape=rows, dtype=float, storage="shared")
        vec = wp.tile_zeros(shape=coords, dtype=float, storage="shared")  # dt tau, then du = M~^-1 dt tau
        rhs = wp.tile_zeros(shape=rows, dtype=float, storage="shared")
        sizes = wp.tile_zeros(shape=rows, dtype=float, storage="shared")  # the projections' check
        # the tree's parents: the solves and the factor walk them in dependent steps (shared: no
        # global load on that path)
        par = wp.tile_zeros(shape=coords, dtype=wp.int32, storage="shared")
        lvl = wp.tile_zeros(shape=coords, dtype=wp.int32, storage="shared")  # ancestors (of the entry)
        rstart = wp.tile_zeros(shape=coords, dtype=wp.int32, storage="shared")  # packed M~'s row starts
        n = m.tree_count[world]
        for i in range(lane, n, lanes):
            tile_set(par, i, m.parent[world, i])
            tile_set(lvl, i, m.level[world, i])
            tile_set(rstart, i, m.row_start[world, i])
        R = m.row_count[world]
        chain_prefix = int(0)
        if wp.static(unroll > 0):
            chain_prefix = m.prefix[world]
        depths = m.depth_count[world]
        frozen = w.diverged[world]
        block_sync()
        if wp.static(handover == 2):
            if lane == 0:  # (every lane has read the flag)
                w.contact_overflow[world] = 0
        if wp.static(stages):
            stamp(w, world, lane, 0)
        lead = dt  # q+ = q_eval + lead u+
        if midpoint != 0:
            lead = 0.5 * dt
        if frozen == 0:
            for i in range(lane, n, lanes):  # kept for a step that diverges; Moreau-Jean: to the midpoint
                w.q_start[world, i] = q[world, i]
                w.u_start[world, i] = u[world, i]
                w.root_start[world, i] = root[world, i]
                if midpoint != 0:
                    advance(m, world, i, q, root, u, lead)
            block_sync()
            kinematics(m, w, world, lane, lanes, q, u, root, DYNAMICS)
            g = m.gravity[world]
            for k in range(lane, n, lanes):
                own_terms(m, w, world, k, g)
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 1)
            for step in range(depths - 1):  # subtree sums, deepest parents first
                level = depths - 2 - step
                for t in range(m.depth_start[world, level] + lane, m.depth_start[world, level + 1], lanes):
                    add_children(m, w, world, m.by_depth[world, t])
                block_sync()
            for i in range(lane, n, lanes):  # per coordinate: its subtree's inertia applied to its motion, its force
                a = w.axis[world, i]
                s_lin = w.lin[world, i]
                b = m.sub_of[world, i]
                cm = w.sub_mass[world, b]
                ch = w.sub_moment[world, b]
                w.force_n[world, i] = w.sub_inertia[world, b] * a + wp.cross(ch, s_lin)
                w.force_f[world, i] = cm * s_lin - wp.cross(ch, a)
                ui = u[world, i]
                tau = wp.dot(a, w.wrench_t[world, b]) + wp.dot(s_lin, w.wrench_f[world, b]) - m.damping[world, i] * ui
                tau += m.kp[world, i] * (m.q_target[world, i] - q[world, i] - lead * ui)
                tau += m.kd[world, i] * (m.v_target[world, i] - ui)
                tile_set(vec, i, dt * tau)
            loop_errors(m, w, world, lane, lanes)
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 2)
            for i in range(lane, n, lanes):  # M~: row i against its ancestors j (packed: at rstart[i] + lvl[j])
                j = i
                e = rstart[i] + lvl[i]
                while j >= 0:
                    value = wp.dot(w.axis[world, j], w.force_n[world, i]) + wp.dot(w.lin[world, j], w.force_f[world, i])
                    if j == i:
                        value += m.armature[world, i] + dt * (m.damping[world, i] + m.kd[world, i]
                                                              + lead * m.kp[world, i])
                    tile_set(Mt, e, value)
                    if record != 0:
                        w.matrix[world, i, j] = value
                        w.matrix[world, j, i] = value
                    j = par[j]
                    e -= 1
            for r in range(lane, R, lanes):  # G along the two bodies' ancestors, and G^T into X
                tile_set(rhs, r, loop_rows_of(m, w, world, par, r, Gt, Xt, u))  # (G u, for the right-hand side)
            block_sync()
            if record != 0:
                for e in range(lane, R * n, lanes):
                    w.rows[world, e // n, e % n] = Gt[e // n, e % n]
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 3)
            tree_factor(m, world, lane, lanes, lvl, rstart, n, Mt)
            if wp.static(stages):
                stamp(w, world, lane, 4)
            for col in range(lane, R + 1, lanes):  # X = M~^-1 G^T a column per lane, and du = M~^-1 (dt tau)
                if col < R:
                    tree_solve_column(par, lvl, rstart, n, chain_prefix, Mt, Xt, col)
                else:
                    tree_solve_vector(par, lvl, rstart, n, chain_prefix, Mt, vec)
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 5)
            wp.tile_matmul(wp.tile_view(Gt, offset=(0, 0), shape=(rows, coords)), Xt, At, 1.0, 0.0)  # A = G X
            block_sync()
            for r in range(lane, R, lanes):  # (a soft row's compliance on its diagonal)
                tile_set(At, r, r, At[r, r] + m.row_compliance[world, r])
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 6)
            for r in range(lane, R, lanes):  # the right-hand side: -(G u_f) - baumgarte phi / dt (+ keep G u)
                start = rhs[r]  # G u (u_f = u + du, du in vec; a soft row's armature keeps a share of G u)
                acc = start
                for j in range(n):
                    acc += Gt[r, j] * vec[j]
                tile_set(rhs, r, -acc + m.row_keep[world, r] * start
                         - baumgarte / dt * w.phi[world, 6 * m.row_loop[world, r] + m.row_part[world, r]])
            factor_lanes(lane, lanes, R, At, diag_a, REGULARIZATION)  # (At keeps A's factor to the step's end)
            solve_lanes(lane, lanes, R, At, diag_a, rhs)
            for i in range(lane, n, lanes):  # u = u_f + X A^-1 rhs
                acc = u[world, i] + vec[i]
                for r in range(R):
                    acc += Xt[i, r] * rhs[r]
                u[world, i] = acc
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 7)
            if wp.static(contacts > 0):
                Yt = wp.tile_zeros(shape=(coords, contacts), dtype=float, storage="shared")  # M~^-1 J^T, then P J^T
                # G M~^-1 J^T, then D (upper triangle) and its factor
                Dt = wp.tile_zeros(shape=(wp.static(max(rows, contacts)), contacts), dtype=float, storage="shared")
                # per candidate slot: point (3), distance; then per contact: point, distance, friction, slot, entry
                cand = wp.tile_zeros(shape=(slots, 8), dtype=float, storage="shared")
                vf = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                pre = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                ddiag = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                fdiag = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                xs = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                xn = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                ys = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                zs = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                bs = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                res_p = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")
                res_d = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")
                res_y = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")
                mus = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")  # friction per contact
                shapes = m.shape_count[world]
                nrm = m.ground_normal[world]
                off = m.ground_offset[world]
                for s in range(lane, shapes, lanes):  # candidates: a lane per shape, at the evaluation poses
                    plane_candidates(m, w, world, s, nrm, off, margin, cand)
                block_sync()
                if lane == 0:  # the contacts within the margin, in slot order, up to the capacity (rows of cand)
                    found = int(0)
                    if wp.static(handover == 1):
                        found = candidates_within(cand, shapes, margin)
                    if found > working and working < m.contact_capacity[world]:  # more than these tiles hold:
                        w.contact_overflow[world] = 1  # the full-capacity kernel takes the step over
                        w.contact_redone[world] = w.contact_redone[world] + 1
                    else:
                        count = int(0)
                        dropped = int(0)
                        for slot in range(4 * shapes):  # (row count <= slot: its columns 4-7 are free)
                            if cand[slot, 3] < margin:
                                if count < m.contact_capacity[world]:
                                    for f in range(4):
                                        tile_set(cand, count, 4 + f, cand[slot, f])
                                    w.contact_slot[world, count] = slot
                                    count += 1
                                else:
                                    dropped += 1
                                    w.contact_impulse[world, slot] = wp.vec3()
                            else:
                                w.contact_impulse[world, slot] = wp.vec3()
                        w.contact_count[world] = count
                        if count == 0:  # off the ground: the next contacts start from CONTACT_RHO
                            w.contact_rho[world] = 0.0
                        w.contact_dropped[world] = dropped
                        w.iterations[world] = 0
                block_sync()
                if wp.static(handover == 1):
                    if w.contact_overflow[world] != 0:  # handed over: the step's start restored, nothing else written
                        for i in range(lane, n, lanes):
                            q[world, i] = w.q_start[world, i]
                            u[world, i] = w.u_start[world, i]
                            root[world, i] = w.root_start[world, i]
                        return
                if wp.static(stages):
                    stamp(w, world, lane, 8)
                nc = w.contact_count[world]
                m3 = 3 * nc
                if nc > 0:
                    for ct in range(lane, nc, lanes):  # J^T into Y: a lane per contact, along its body's ancestors
                        slot = w.contact_slot[world, ct]
                        x = wp.vec3(cand[ct, 4], cand[ct, 5], cand[ct, 6])
                        tile_set(mus, ct, m.shape_mu[world, slot // 4])
                        for part in range(3):
                            d = contact_direction(nrm, part)
                            j = m.shape_entry[world, slot // 4]
                            while j >= 0:
                                value = wp.dot(d, wp.cross(w.axis[world, j], x) + w.lin[world, j])
                                tile_set(Yt, j, 3 * ct + part, value)
                                j = par[j]
                    block_sync()
                    for col in range(lane, m3, lanes):  # Y = M~^-1 J^T
                        tree_solve_column(par, lvl, rstart, n, chain_prefix, Mt, Yt, col)
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 9)
                    wp.tile_matmul(wp.tile_view(Gt, offset=(0, 0), shape=(rows, coords)), Yt,  # G Y
                                   wp.tile_view(Dt, offset=(0, 0), shape=(rows, contacts)), 1.0, 0.0)
                    block_sync()
                    for col in range(lane, m3, lanes):  # A^-1 G Y, a column per lane
                        solve_column(R, At, diag_a, Dt, col)
                    block_sync()
                    # Y := Y - X A^-1 G Y = P J^T, P = M~^-1 - X A^-1 X^T
                    wp.tile_matmul(Xt, wp.tile_view(Dt, offset=(0, 0), shape=(rows, contacts)), Yt, -1.0, 1.0)
                    for e in range(lane, R * n, lanes):  # G is done with: its tile takes J (rows 0 .. m3)
                        tile_set(Gt, e // n, e % n, float(0.0))
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 10)
                    for ct in range(lane, nc, lanes):  # J, and v_f = J u + bias: a lane per contact
                        slot = w.contact_slot[world, ct]
                        x = wp.vec3(cand[ct, 4], cand[ct, 5], cand[ct, 6])
                        for part in range(3):
                            d = contact_direction(nrm, part)
                            acc = float(0.0)
                            j = m.shape_entry[world, slot // 4]
                            while j >= 0:
                                value = wp.dot(d, wp.cross(w.axis[world, j], x) + w.lin[world, j])
                                tile_set(Gt, 3 * ct + part, j, value)
                                acc += value * u[world, j]
                                j = par[j]
                            if part == 0:  # closing a gap d > 0 at most, a penetration pushed out by a share per step
                                dist = cand[ct, 7]  # (at the evaluation pose: the next one is a step of u+ away)
                                if dist > 0.0:
                                    acc += dist / dt
                                else:
                                    acc += stabilization * dist / dt
                            tile_set(vf, 3 * ct + part, acc)
                    block_sync()
                    wp.tile_matmul(wp.tile_view(Gt, offset=(0, 0), shape=(contacts, coords)), Yt,  # D = J P J^T
                                   wp.tile_view(Dt, offset=(0, 0), shape=(contacts, contacts)), 1.0, 0.0)
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 11)
                    for ct in range(lane, nc, lanes):  # Jacobi preconditioner, one scale per contact (cones keep)
                        mean = (Dt[3 * ct, 3 * ct] + Dt[3 * ct + 1, 3 * ct + 1] + Dt[3 * ct + 2, 3 * ct + 2]) / 3.0
                        scale = 1.0 / wp.sqrt(wp.max(mean, 1.0e-20))
                        for part in range(3):
                            tile_set(pre, 3 * ct + part, scale)
                    block_sync()
                    for e in range(lane, m3 * m3, lanes):
                        ra = e // m3
                        rb = e % m3
                        if rb >= ra:
                            tile_set(Dt, ra, rb, Dt[ra, rb] * pre[ra] * pre[rb])
                    for ct in range(lane, nc, lanes):  # warm start: the slot's last impulse
                        impulse = w.contact_impulse[world, w.contact_slot[world, ct]]
                        for part in range(3):
                            r = 3 * ct + part
                            tile_set(vf, r, vf[r] * pre[r])
                            tile_set(xs, r, impulse[part] / pre[r])
                            tile_set(ys, r, impulse[part] / pre[r])
                    block_sync()
                    for r in range(lane, m3, lanes):  # z = D x + v_f: the rows' velocity at the warm start
                        tile_set(ddiag, r, Dt[r, r])  # (a new contact's 0: its approach speed / rho would
                        acc = float(0.0)  # make the first projections' impulses huge, wrong if the cap stops them)
                        c0 = 3 * (r / 3)
                        if xs[c0] != 0.0 or xs[c0 + 1] != 0.0 or xs[c0 + 2] != 0.0:
                            acc = vf[r]
                            for j in range(m3):
                                acc += Dt[wp.min(r, j), wp.max(r, j)] * xs[j]
                        tile_set(zs, r, acc)
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 12)
                    rho = rho0  # J is done with: Gt takes (D + (eta + rho) I)^-1 (At keeps A's factor)
                    if adaptive != 0 and w.contact_rho[world] > 0.0:  # where the last step's adaptation left it,
                        warm = int(0)  # while a contact carries its impulse over (new ones alone: CONTACT_RHO)
                        for r in range(m3):
                            if xs[r] != 0.0:
                                warm = 1
                        if warm != 0:
                            rho = w.contact_rho[world]
                    contact_factor(lane, lanes, m3, Dt, ddiag, fdiag, Gt, eta + rho)
                    its = int(0)
                    done = int(0)
                    while its < max_iterations and done == 0:  # PADMM (ENGINE.md), every lane alike
                        for r in range(lane, m3, lanes):
                            shift = float(0.0)  # De Saxce
                            if r % 3 == 0:
                                shift = mus[r / 3] * wp.sqrt(
                                    zs[r + 1] * zs[r + 1] + zs[r + 2] * zs[r + 2])
                            tile_set(bs, r, -(vf[r] + shift) + eta * xs[r] + rho * ys[r] + zs[r])
                        block_sync()
                        for r in range(lane, m3, lanes):
                            acc = float(0.0)
                            for j in range(m3):
                                acc += Gt[r, j] * bs[j]
                            tile_set(xn, r, acc)
                        block_sync()
                        for ct in range(lane, nc, lanes):
                            r = 3 * ct
                            mu = mus[ct]
                            y = project_cone(xn[r] - zs[r] / rho, xn[r + 1] - zs[r + 1] / rho,
                                             xn[r + 2] - zs[r + 2] / rho, mu)
                            rp = float(0.0)
                            rd = float(0.0)
                            ym = float(0.0)
                            for part in range(3):
                                rp = wp.max(rp, wp.abs(xn[r + part] - y[part]))
                                dual = eta * (xn[r + part] - xs[r + part]) + rho * (y[part] - ys[r + part])
                                rd = wp.max(rd, wp.abs(dual))
                                ym = wp.max(ym, wp.abs(y[part]))
                                tile_set(zs, r + part, zs[r + part] - rho * (xn[r + part] - y[part]))
                                tile_set(xs, r + part, xn[r + part])
                                tile_set(ys, r + part, y[part])
                            tile_set(res_p, ct, rp)
                            tile_set(res_d, ct, rd)
                            tile_set(res_y, ct, ym)
                        block_sync()
                        largest = contact_residuals(nc, res_p, res_d, res_y)
                        its += 1
                        tol = tolerance + relative_tolerance * largest[2]
                        if largest[0] <= tol and largest[1] <= tol:
                            done = 1
                        elif adaptive != 0 and its % rho_interval == 0:
                            new_rho = rho
                            if largest[0] > 10.0 * largest[1]:
                                new_rho = wp.min(rho * 4.0, 1.0e3)
                            elif largest[1] > 10.0 * largest[0]:
                                new_rho = wp.max(rho / 4.0, 1.0e-5)
                            if new_rho != rho:
                                rho = new_rho
                                contact_factor(lane, lanes, m3, Dt, ddiag, fdiag, Gt, eta + rho)
                    for ct in range(lane, nc, lanes):  # the impulses (unscaled), kept per slot for the next step
                        r = 3 * ct
                        w.contact_impulse[world, w.contact_slot[world, ct]] = wp.vec3(
                            pre[r] * ys[r], pre[r + 1] * ys[r + 1], pre[r + 2] * ys[r + 2])
                    if lane == 0:
                        w.iterations[world] = its
                        w.contact_rho[world] = rho
                    for i in range(lane, n, lanes):  # u += P J^T lambda
                        acc = float(0.0)
                        for r in range(m3):
                            acc += Yt[i, r] * pre[r] * ys[r]
                        u[world, i] = u[world, i] + acc
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 13)
            for i in range(lane, n, lanes):  # q += lead u; a drive past its effort limit stops the world
                ui = u[world, i]
                effort = m.kp[world, i] * (m.q_target[world, i] - q[world, i] - lead * ui)
                effort += m.kd[world, i] * (m.v_target[world, i] - ui)
                if wp.abs(effort) > m.effort[world, i]:
                    w.diverged[world] = EFFORT_LIMIT
                advance(m, world, i, q, root, u, lead)
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 14)
            fresh = int(0)  # the last kinematics pass was at the final angles, with velocities
            applied = int(0)
            for it in range(iterations):  # Gauss-Newton projections onto the loops with the step's factors
                kinematics(m, w, world, lane, lanes, q, u, root, VELOCITIES)
                loop_errors(m, w, world, lane, lanes)
                block_sync()
                for r in range(lane, R, lanes):  # the kept rows' errors (a soft row's: 0), their sizes
                    part = m.row_part[world, r]  # signed by kind for the check (angular: negative)
                    err = w.phi[world, 6 * m.row_loop[world, r] + part]
                    tile_set(rhs, r, err)
                    size = wp.abs(err)
                    if part >= 3:
                        size = -size
                    tile_set(sizes, r, size)
                block_sync()
                worst = float(0.0)  # every lane alike: the largest errors, linear and angular
                worst_angular = float(0.0)
                for r in range(R):
                    size = sizes[r]
                    if size >= 0.0:
                        worst = wp.max(worst, size)
                    else:
                        worst_angular = wp.max(worst_angular, -size)
                if (skip_floor > 0.0 or skip_floor_angular > 0.0) and worst <= skip_floor and (
                        worst_angular <= skip_floor_angular):  # closed to rounding: no correction, final poses
                    fresh = 1
                    break
                solve_lanes(lane, lanes, R, At, diag_a, rhs)
                for i in range(lane, n, lanes):
                    project(m, world, i, q, root, Xt, rhs, R)
                applied += 1
                block_sync()
            if lane == 0:
                w.projections[world] = applied
            if fresh == 0:
                kinematics(m, w, world, lane, lanes, q, u, root, VELOCITIES)
            for k in range(lane, n, lanes):  # the divergence guard
                c = w.centre[world, k]
                v = w.vel[world, k]
                om = w.omega[world, k]
                if not (wp.isfinite(c) and wp.isfinite(v) and wp.isfinite(om)) or wp.length(v) > max_speed:
                    w.diverged[world] = DIVERGED
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 15)
            if w.diverged[world] == 0:
                for k in range(lane, n, lanes):
                    b = m.body_out[world, k]
                    if b >= 0:
                        body_q[world, b] = wp.transform(w.centre[world, k], wp.transform_get_rotation(w.pose[world, k]))
                        body_qd[world, b] = wp.spatial_vector(w.vel[world, k], w.omega[world, k])
            else:  # frozen at the last good step: its coordinates, rates and bodies
                for i in range(lane, n, lanes):
                    q[world, i] = w.q_start[world, i]
                    u[world, i] = w.u_start[world, i]
                    root[world, i] = w.root_start[world, i]
            if wp.static(stages):
                stamp(w, world, lane, 16)

    return chain_step_body


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
    return np.r_[p, q / np.linalg.norm(q)]


class ChainState:
    """Coordinates q and rates u (W, N: angles; a floating root's six rates are its centre of mass's
    velocity and its angular velocity, world frame), floating roots' centre-of-mass frames root
    (W, N transform, on their root entries), and every body's COM pose and velocity as engine.model's
    State holds them (body_q (W, B) transform, body_qd (W, B) spatial_vector: v, w)."""

    def __init__(self, q, u, root, body_q, body_qd):
        self.q, self.u, self.root, self.body_q, self.body_qd = q, u, root, body_q, body_qd


class ChainModel:
    """A padded batch of closed chains in reduced coordinates (pack_chains)."""

    def __init__(self, layouts: list, arrays: ChainArrays, work: ChainWork, init: dict, config: SolverConfig,
                 dt: float, device, capacity: int = 0):
        self.layouts, self.arrays, self.work, self._init = layouts, arrays, work, init
        self.config, self.dt, self.device = config, dt, device
        self.num_worlds = len(layouts)
        self.max_rows = max(len(lay.rows) + len(lay.soft) for lay in layouts)
        self.coords = max(_tile_size(max(lay.n for lay in layouts)), MAX_PREFIX)  # (the solves index 0 .. 5)
        self.tile_rows = _tile_size(self.max_rows)
        self.contact_capacity = capacity  # the largest world's
        self.max_registers = MAX_REGISTERS
        self.tile_slots = _tile_size(4 * max(len(lay.shapes) for lay in layouts))  # candidate slots (4 per shape)
        self.tile_contacts = _tile_size(3 * capacity) if capacity else 0
        self.contact_working = capacity  # contacts the first kernel's tiles hold (pack_chains sets it)
        self.tile_working = self.tile_contacts
        self.packed_size = _packed_tile(arrays.ancestor.shape[1])  # the packed M~'s tile
        # the tree solves' unrolled prefix: compiled only where a world has one (a floating root)
        self.unroll = MAX_PREFIX if int(arrays.prefix.numpy().max(initial=0)) > 0 else 0

    def state(self) -> ChainState:
        """A new state at the initial pose (the contacts' warm start, kept in the model's work, is
        cleared: a new trajectory starts without the last one's impulses and from CONTACT_RHO)."""
        self.work.contact_impulse.zero_()
        self.work.contact_rho.zero_()
        return ChainState(*(wp.array(self._init[k], device=self.device, dtype=t) for k, t in
                            (("q", float), ("u", float), ("root", wp.transform), ("body_q", wp.transform),
                             ("body_qd", wp.spatial_vector))))

    def step(self, state: ChainState, record: bool = False, stages: bool = False) -> None:
        """Advance state by one step of self.dt (in place). record: also write the step's mass matrix
        M~ into work.matrix (W, coords, coords) and its kept loop rows G into work.rows (W, rows, coords).
        stages: also time the step's STAGES (a kernel with clock readings; stage_cycles reads them)."""
        c = self.config
        if record and self.work.matrix.shape != (self.num_worlds, self.coords, self.coords):  # on first use
            self.work.matrix = wp.zeros((self.num_worlds, self.coords, self.coords), dtype=float, device=self.device)
            self.work.rows = wp.zeros((self.num_worlds, self.tile_rows, self.coords), dtype=float, device=self.device)
        if stages:
            if self.work.stage_clock.shape != (self.num_worlds, len(STAGES) + 1):
                self.work.stage_clock = wp.zeros((self.num_worlds, len(STAGES) + 1), dtype=wp.int64,
                                                 device=self.device)
            self.work.stage_clock.zero_()
        block = CHAIN_BLOCK if wp.get_device(self.device).is_cuda else 1
        # the first kernel's contact tiles hold contact_working contacts; a world that finds more (within its
        # capacity) is handed to a second kernel with tiles for the full capacity (launched only if smaller)
        passes = [(self.tile_working, 0)]
        if self.tile_working < self.tile_contacts:
            passes = [(self.tile_working, 1), (self.tile_contacts, 2)]
        for tile, handover in passes:
            kernel = chain_step_kernel(self.coords, self.tile_rows, tile, self.tile_slots, self.max_registers,
                                       self.packed_size, bool(stages), self.unroll, handover)
            wp.launch_tiled(kernel, dim=[self.num_worlds], block_dim=block, device=self.device,
                            inputs=[self.arrays, self.work, float(self.dt), float(c.baumgarte),
                                    int(c.position_iterations), float(c.max_speed),
                                    int(c.integrator == Integrator.MOREAU_JEAN), int(record), float(c.contact_margin),
                                    float(c.contact_stabilization), float(c.eta), CONTACT_RHO, int(c.adaptive_rho),
                                    max(1, int(c.rho_update_interval)), float(c.tolerance),
                                    float(c.relative_tolerance), int(c.max_iterations), float(c.projection_skip_floor),
                                    float(c.projection_skip_floor_angular), tile // 3, state.q, state.u,
                                    state.root, state.body_q, state.body_qd])

    def stage_cycles(self) -> dict:
        """The last step(stages=True)'s clock cycles per stage (STAGES), the mean over the worlds that
        ran it (a stage with no such world, e.g. the contacts' in a batch without any: absent): cycles
        of the world's block from the stage's start to its end, which on a GPU include the waits for
        the other blocks sharing its SM."""
        clock = self.work.stage_clock.numpy().astype(np.int64)
        if clock.shape != (self.num_worlds, len(STAGES) + 1):
            raise RuntimeError("ChainModel.stage_cycles: no step(stages=True) has run")
        out = {}
        previous = clock[:, 0]
        for k, name in enumerate(STAGES, start=1):
            ran = (clock[:, k] != 0) & (previous != 0)
            if ran.any():
                out[name] = float((clock[ran, k] - previous[ran]).mean())
            previous = np.where(clock[:, k] != 0, clock[:, k], previous)
        return out

    @property
    def diverged(self) -> np.ndarray:
        """Worlds stopped (frozen at their last good step), as a NumPy bool array (W,): diverged, or a
        drive past its effort limit (failure_reasons says which)."""
        return self.work.diverged.numpy().astype(bool)

    def failure_reasons(self) -> list:
        """Per world: None while it runs, else why it stopped ("diverged": non-finite or faster than
        SolverConfig.max_speed; "effort limit": a drive's torque past its effort limit, which this
        path checks but does not enforce)."""
        names = {0: None, 1: "diverged", 2: "effort limit"}
        return [names[int(v)] for v in self.work.diverged.numpy()]


def pack_chains(specs: Sequence[MechanismSpec], device=None, *, config: SolverConfig | None = None,
                dt: float = 1.0e-3, contact_capacity: int | None = None,
                contact_working: int | None = None) -> ChainModel:
    """Pack one world per spec (they may differ) into a ChainModel on ``device``. SolverConfig's
    integrator, baumgarte, position_iterations and max_speed apply, and for contacts contact_margin,
    contact_stabilization, eta, adaptive_rho, rho_update_interval, tolerance, relative_tolerance and
    max_iterations (the penalty starts at CONTACT_RHO, not SolverConfig.rho, then at each world's last
    one). contact_capacity:
    contacts kept per world and step
    (None: every candidate of its shapes, at most MAX_CONTACTS; those beyond are counted in
    work.contact_dropped). contact_working: the contacts the step kernel's tiles hold (None: the most
    any world has within the margin at its initial pose, at least 1; at most the capacity); a world
    that finds more in a step, within its capacity, is stepped again from the step's start by a
    second kernel with tiles for the full capacity (work.contact_redone counts those steps), so the
    shared memory of contacts that seldom occur costs no occupancy. ValueError naming the world and
    the joint, shape or body this path cannot model."""
    config = config or SolverConfig()
    if not (isinstance(dt, (int, float)) and not isinstance(dt, bool) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"pack_chains: dt must be a positive number of seconds, got {dt!r}")
    if contact_capacity is not None and not (isinstance(contact_capacity, (int, np.integer))
                                             and not isinstance(contact_capacity, bool) and contact_capacity >= 0):
        raise ValueError(f"pack_chains: contact_capacity must be a non-negative integer, got {contact_capacity!r}")
    if contact_working is not None and not (isinstance(contact_working, (int, np.integer))
                                            and not isinstance(contact_working, bool) and contact_working >= 1):
        raise ValueError(f"pack_chains: contact_working must be a positive integer, got {contact_working!r}")
    specs = list(specs)
    if not specs:
        raise ValueError("pack_chains: needs at least one MechanismSpec")
    distinct, kind_of, layouts = {}, [], []  # one layout per distinct spec object
    for index, spec in enumerate(specs):
        if id(spec) not in distinct:
            try:
                layouts.append(chain_layout(spec))
            except ValueError as exc:
                raise ValueError(f"world {index} ({spec.name}): {exc}") from exc
            distinct[id(spec)] = len(layouts) - 1
        kind_of.append(distinct[id(spec)])
    kind_of = np.array(kind_of)
    W, N = len(layouts), _tile_size(max(lay.n for lay in layouts))  # per-coordinate arrays: the padded size
    L = max(1, max(len(lay.loops) for lay in layouts))
    B = max(len(lay.spec.bodies) for lay in layouts)
    f = {k: np.zeros((W, N)) for k in ("mass", "armature", "damping", "kp", "kd", "q_target", "v_target", "q", "u",
                                       "effort")}
    packs = [_packed_rows(lay.parent) for lay in layouts]  # per distinct layout: levels, packed row starts
    ancestor = np.zeros((W, max(int(starts[-1]) for _, starts in packs)), dtype=np.int32)
    i32 = {k: np.zeros((W, N), dtype=np.int32) for k in ("parent", "by_depth", "body_out", "first_child",
                                                         "child_count", "kind", "sub_of", "level", "row_start")}
    depth_start = np.zeros((W, N + 1), dtype=np.int32)
    S = max(1, max(len(lay.shapes) for lay in layouts))
    shape_i32 = {k: np.zeros((W, S), dtype=np.int32) for k in ("entry", "type")}
    shape_X = np.zeros((W, S, 7))
    shape_X[..., 6] = 1.0
    shape_size = np.zeros((W, S, 3))
    shape_mu = np.zeros((W, S))
    ground = np.zeros((W, 4))  # normal, offset
    ground[:, 2] = 1.0
    per_world = np.zeros((3, W), dtype=np.int32)  # shapes, contact capacity, the solves' prefix
    root = np.zeros((W, N, 7))
    root[..., 6] = 1.0
    v3 = {k: np.zeros((W, N, 3)) for k in ("axis", "com")}
    inertia = np.tile(np.eye(3), (W, N, 1, 1))
    jp = np.zeros((W, N, 7))
    jc = np.zeros((W, N, 7))
    jp[..., 6] = jc[..., 6] = 1.0
    loop_body = np.full((W, L, 2), -1, dtype=np.int32)
    loop_anchor = np.zeros((W, L, 2, 7))
    loop_anchor[..., 6] = 1.0
    loop_axis = np.zeros((W, L, 3))
    loop_t = np.zeros((2, W, L, 3))
    row_loop = np.zeros((W, MAX_ROWS), dtype=np.int32)
    row_part = np.zeros((W, MAX_ROWS), dtype=np.int32)
    row_soft = np.zeros((2, W, MAX_ROWS))  # compliance, keep
    body_q = np.zeros((W, B, 7))
    body_q[..., 6] = 1.0
    body_qd = np.zeros((W, B, 6))
    counts = np.zeros((4, W), dtype=np.int32)
    gravity = np.zeros((W, 3))
    for w_, lay in enumerate(layouts):
        spec = lay.spec
        n = lay.n
        counts[:, w_] = (n, (lay.depth.max() + 1) if n else 0, len(lay.loops), len(lay.rows) + len(lay.soft))
        gravity[w_] = spec.gravity
        level, packed = packs[w_]
        i32["level"][w_, :n], i32["row_start"][w_, :n] = level, packed[:-1]
        i32["by_depth"][w_, :n] = np.argsort(lay.depth, kind="stable")
        depth_start[w_, :counts[1, w_] + 1] = np.searchsorted(lay.depth, np.arange(counts[1, w_] + 1),
                                                              sorter=np.argsort(lay.depth, kind="stable"))
        for k in range(n):
            j = k
            while j >= 0:
                ancestor[w_, packed[k] + level[j]] = j
                j = lay.parent[j]
        for k in range(n):
            body = spec.bodies[lay.tree_body[k]]
            kind = int(lay.kind[k])
            i32["parent"][w_, k] = lay.parent[k]
            i32["kind"][w_, k] = kind
            i32["sub_of"][w_, k] = lay.sub_of[k]
            children = np.flatnonzero(lay.parent == k)
            if kind in (KIND_LINEAR, KIND_ANGULAR):  # a floating root's massless entries: no subtree sums
                children = children[:0]
            i32["first_child"][w_, k] = children[0] if len(children) else -1
            i32["child_count"][w_, k] = len(children)
            if len(children) and not np.array_equal(children, np.arange(children[0], children[0] + len(children))):
                raise AssertionError("breadth-first order keeps siblings contiguous")
            jp[w_, k] = _transform(lay.parent_R[k], lay.parent_p[k])
            jc[w_, k] = _transform(lay.child_R[k], lay.child_p[k])
            v3["axis"][w_, k] = lay.axis[k]
            v3["com"][w_, k] = body.com
            f["effort"][w_, k] = np.inf
            f["q"][w_, k] = lay.q0[k]
            f["u"][w_, k] = lay.u0[k]
            if kind in (KIND_LINEAR, KIND_ANGULAR):
                i32["body_out"][w_, k] = -1
                inertia[w_, k] = 0.0
                continue
            i32["body_out"][w_, k] = lay.tree_body[k]
            f["mass"][w_, k] = body.mass
            inertia[w_, k] = body.inertia
            if kind == KIND_ROOT:
                root[w_, k] = np.r_[lay.parent_p[k] + lay.parent_R[k] @ np.asarray(body.com), body.orientation]
                continue
            joint = spec.joints[lay.joint[k]]
            f["armature"][w_, k] = joint.armature
            f["damping"][w_, k] = joint.damping
            if joint.drive is not None:
                f["kp"][w_, k] = joint.drive.stiffness
                f["kd"][w_, k] = joint.drive.damping
                f["q_target"][w_, k] = joint.drive.target_position
                f["v_target"][w_, k] = joint.drive.target_velocity
                f["effort"][w_, k] = joint.drive.effort_limit
        tree_index = {b: k for k, b in enumerate(lay.tree_body) if lay.kind[k] in (KIND_REVOLUTE, KIND_ROOT)}
        per_world[:, w_] = (len(lay.shapes), _capacity(lay, contact_capacity), _prefix(packs[w_][0]))
        if spec.ground is not None:
            ground[w_] = np.r_[spec.ground.normal, spec.ground.offset]
        for s, si in enumerate(lay.shapes):
            shape = spec.shapes[si]
            shape_i32["entry"][w_, s] = tree_index[spec.body_index[shape.body]]
            shape_i32["type"][w_, s] = int(shape.type)
            shape_X[w_, s] = np.r_[shape.position, shape.orientation]
            shape_size[w_, s] = shape.size
            shape_mu[w_, s] = math.sqrt(shape.friction * spec.ground.friction)
        for li in range(len(lay.loops)):
            joint = spec.joints[lay.loops[li]]
            for side in range(2):
                loop_body[w_, li, side] = lay.loop_body[li, side]
                loop_anchor[w_, li, side] = _transform(lay.loop_R[li, side], lay.loop_p[li, side])
            loop_axis[w_, li] = joint.axis
            loop_t[0, w_, li], loop_t[1, w_, li] = lay.loop_dirs[li, 3], lay.loop_dirs[li, 4]
        row_loop[w_, :len(lay.rows)] = lay.rows[:, 0]
        row_part[w_, :len(lay.rows)] = lay.rows[:, 1]
        for s, li in enumerate(lay.soft):  # armature and damping of a loop joint: a soft row on its rate
            joint = spec.joints[lay.loops[li]]
            r = len(lay.rows) + s
            row_loop[w_, r], row_part[w_, r] = li, 5
            gain = joint.armature + dt * joint.damping
            row_soft[:, w_, r] = (1.0 / gain, joint.armature / gain)
        for i, body in enumerate(spec.bodies):
            R = _frame(body.orientation)
            body_q[w_, i] = np.r_[np.asarray(body.position) + R @ np.asarray(body.com), body.orientation]
    # every world from its distinct spec's rows
    f = {k: v[kind_of] for k, v in f.items()}
    i32 = {k: v[kind_of] for k, v in i32.items()}
    ancestor, depth_start = ancestor[kind_of], depth_start[kind_of]
    v3 = {k: v[kind_of] for k, v in v3.items()}
    inertia, jp, jc, loop_body, loop_anchor, loop_axis = (x[kind_of] for x in (inertia, jp, jc, loop_body, loop_anchor,
                                                                               loop_axis))
    loop_t, counts, row_soft = loop_t[:, kind_of], counts[:, kind_of], row_soft[:, kind_of]
    row_loop, row_part, body_q, body_qd, gravity = (x[kind_of] for x in (row_loop, row_part, body_q, body_qd, gravity))
    shape_i32 = {k: v[kind_of] for k, v in shape_i32.items()}
    shape_X, shape_size, shape_mu, ground, root = (x[kind_of] for x in (shape_X, shape_size, shape_mu, ground, root))
    per_world = per_world[:, kind_of]
    layouts = [layouts[k] for k in kind_of]
    W = len(specs)
    # the initial body poses and velocities from the tree (fixed bodies keep the spec's)
    dev = device
    a = ChainArrays()
    a.tree_count, a.depth_count, a.loop_count, a.row_count = (
        wp.array(c, dtype=wp.int32, device=dev) for c in counts)
    a.gravity = wp.array(gravity, dtype=wp.vec3, device=dev)
    for k in ("parent", "by_depth", "body_out", "first_child", "child_count", "kind", "sub_of", "level", "row_start"):
        setattr(a, k, wp.array(i32[k], dtype=wp.int32, device=dev))
    a.depth_start = wp.array(depth_start, dtype=wp.int32, device=dev)
    a.ancestor = wp.array(ancestor, dtype=wp.int32, device=dev)
    a.shape_count = wp.array(per_world[0], dtype=wp.int32, device=dev)
    a.contact_capacity = wp.array(per_world[1], dtype=wp.int32, device=dev)
    a.prefix = wp.array(per_world[2], dtype=wp.int32, device=dev)
    a.shape_entry = wp.array(shape_i32["entry"], dtype=wp.int32, device=dev)
    a.shape_type = wp.array(shape_i32["type"], dtype=wp.int32, device=dev)
    a.shape_X = wp.array(shape_X, dtype=wp.transform, device=dev)
    a.shape_size = wp.array(shape_size, dtype=wp.vec3, device=dev)
    a.shape_mu = wp.array(shape_mu, dtype=float, device=dev)
    a.ground_normal = wp.array(ground[:, :3], dtype=wp.vec3, device=dev)
    a.ground_offset = wp.array(ground[:, 3], dtype=float, device=dev)
    a.joint_parent = wp.array(jp, dtype=wp.transform, device=dev)
    a.joint_child = wp.array(jc, dtype=wp.transform, device=dev)
    a.axis = wp.array(v3["axis"], dtype=wp.vec3, device=dev)
    a.com = wp.array(v3["com"], dtype=wp.vec3, device=dev)
    a.inertia = wp.array(inertia, dtype=wp.mat33, device=dev)
    for k in ("mass", "armature", "damping", "kp", "kd", "q_target", "v_target", "effort"):
        setattr(a, k, wp.array(f[k], dtype=float, device=dev))
    a.loop_body = wp.array(loop_body, dtype=wp.int32, device=dev)
    a.loop_anchor = wp.array(loop_anchor, dtype=wp.transform, device=dev)
    a.loop_axis = wp.array(loop_axis, dtype=wp.vec3, device=dev)
    a.loop_t1 = wp.array(loop_t[0], dtype=wp.vec3, device=dev)
    a.loop_t2 = wp.array(loop_t[1], dtype=wp.vec3, device=dev)
    a.row_loop = wp.array(row_loop, dtype=wp.int32, device=dev)
    a.row_part = wp.array(row_part, dtype=wp.int32, device=dev)
    a.row_compliance = wp.array(row_soft[0], dtype=float, device=dev)
    a.row_keep = wp.array(row_soft[1], dtype=float, device=dev)
    k = ChainWork()
    for name, dtype in (("pose", wp.transform), ("centre", wp.vec3), ("lin", wp.vec3), ("axis", wp.vec3),
                        ("omega", wp.vec3), ("vel", wp.vec3), ("alpha", wp.vec3), ("acc", wp.vec3),
                        ("inertia", wp.mat33), ("wrench_t", wp.vec3), ("wrench_f", wp.vec3), ("force_n", wp.vec3),
                        ("force_f", wp.vec3), ("sub_mass", float), ("sub_moment", wp.vec3), ("sub_inertia", wp.mat33)):
        setattr(k, name, wp.zeros((W, N), dtype=dtype, device=dev))
    k.phi = wp.zeros((W, 6 * L), dtype=float, device=dev)
    k.dirs = wp.zeros((W, 6 * L), dtype=wp.vec3, device=dev)
    k.ends = wp.zeros((W, 2 * L), dtype=wp.vec3, device=dev)
    k.q_start = wp.zeros((W, N), dtype=float, device=dev)
    k.u_start = wp.zeros((W, N), dtype=float, device=dev)
    k.root_start = wp.zeros((W, N), dtype=wp.transform, device=dev)
    k.diverged = wp.zeros(W, dtype=wp.int32, device=dev)
    slots = 4 * S
    k.contact_count = wp.zeros(W, dtype=wp.int32, device=dev)
    k.contact_slot = wp.zeros((W, MAX_CONTACTS), dtype=wp.int32, device=dev)
    k.contact_impulse = wp.zeros((W, slots), dtype=wp.vec3, device=dev)
    k.contact_rho = wp.zeros(W, dtype=float, device=dev)
    k.contact_dropped = wp.zeros(W, dtype=wp.int32, device=dev)
    k.contact_overflow = wp.zeros(W, dtype=wp.int32, device=dev)
    k.contact_redone = wp.zeros(W, dtype=wp.int32, device=dev)
    k.iterations = wp.zeros(W, dtype=wp.int32, device=dev)
    k.projections = wp.zeros(W, dtype=wp.int32, device=dev)
    k.stage_clock = wp.zeros((1, 1), dtype=wp.int64, device=dev)  # ChainModel.step(stages=True) sizes it
    k.matrix = wp.zeros((1, 1, 1), dtype=float, device=dev)  # ChainModel.step(record=True) sizes them
    k.rows = wp.zeros((1, 1, 1), dtype=float, device=dev)
    init = {"q": f["q"], "u": f["u"], "root": root, "body_q": body_q, "body_qd": body_qd}
    model = ChainModel(layouts, a, k, init, config, float(dt), device, int(per_world[1].max()))
    # body poses and velocities at the initial angles: one step's kinematics, no integration
    state = model.state()
    # blocks of one thread: kinematics' barriers must be reached by every thread of a block, and worlds differ in depth
    wp.launch_tiled(initial_bodies_kernel, dim=[W], block_dim=1, device=dev,
                    inputs=[a, k, state.q, state.u, state.root, state.body_q, state.body_qd])
    model._init["body_q"] = state.body_q.numpy()
    model._init["body_qd"] = state.body_qd.numpy()
    if model.tile_contacts:
        if contact_working is None:  # the most contacts any world has at its initial pose
            found = wp.zeros(W, dtype=wp.int32, device=dev)
            wp.launch_tiled(initial_contacts_kernel(model.tile_slots), dim=[W], block_dim=1, device=dev,
                            inputs=[a, k, float(config.contact_margin), found])
            contact_working = int(found.numpy().max())
        model.tile_working = _tile_size(3 * min(max(1, contact_working), model.contact_capacity))
        model.contact_working = min(model.tile_working // 3, model.contact_capacity)  # (the tiles' room)
    return model


@functools.cache
def initial_contacts_kernel(slots: int):
    """A kernel counting each world's candidate contacts within the margin at the poses in its work
    (after initial_bodies_kernel), at most its capacity (a block of one thread per world)."""

    @wp.kernel(enable_backward=False, module="unique")
    def initial_contacts(m: ChainArrays, w: ChainWork, margin: float, found: wp.array(dtype=wp.int32)):
        world, lane = wp.tid()
        cand = wp.tile_zeros(shape=(slots, 8), dtype=float, storage="shared")
        shapes = m.shape_count[world]
        for s in range(shapes):
            plane_candidates(m, w, world, s, m.ground_normal[world], m.ground_offset[world], margin, cand)
        found[world] = wp.min(candidates_within(cand, shapes, margin), m.contact_capacity[world])

    return initial_contacts


@wp.kernel(enable_backward=False)
def initial_bodies_kernel(m: ChainArrays, w: ChainWork, q: wp.array2d(dtype=float), u: wp.array2d(dtype=float),
                          root: wp.array2d(dtype=wp.transform), body_q: wp.array2d(dtype=wp.transform),
                          body_qd: wp.array2d(dtype=wp.spatial_vector)):
    """Tree bodies' COM poses and velocities from q, u and root (a block of one thread per world)."""
    world, lane = wp.tid()
    kinematics(m, w, world, 0, 1, q, u, root, VELOCITIES)
    for k in range(m.tree_count[world]):
        b = m.body_out[world, k]
        if b >= 0:
            body_q[world, b] = wp.transform(w.centre[world, k], wp.transform_get_rotation(w.pose[world, k]))
            body_qd[world, b] = wp.spatial_vector(w.vel[world, k], w.omega[world, k])


class ChainStepper:
    """Advance a ChainModel chunk by chunk, replaying a captured CUDA graph of ``chunk`` steps on
    CUDA (eager elsewhere)."""

    def __init__(self, model: ChainModel, state: ChainState, chunk: int = 10, capture: bool | None = None):
        self.model, self.state, self.chunk = model, state, int(chunk)
        device = wp.get_device(model.device)
        self.capture = device.is_cuda if capture is None else (capture and device.is_cuda)
        self._graph = None

    def _run(self):
        for _ in range(self.chunk):
            self.model.step(self.state)

    def advance(self) -> None:
        """Advance self.state by one chunk (the first call on CUDA runs it and captures the graph)."""
        if not self.capture:
            self._run()
            return
        if self._graph is None:
            self._run()  # compile and load outside the capture
            with wp.ScopedCapture(device=self.model.device) as capture:
                self._run()
            self._graph = capture.graph
            return
        wp.capture_launch(self._graph)
