"""Closed chains in reduced coordinates: a spanning tree of revolute joints on fixed bodies, its
loops closed by constraint rows, one fused kernel launch per step.

In maximal coordinates DR Legs hanging has 186 constraint rows (36 revolute joints and a weld),
and a step factors their sparse Delassus matrix. Here the same mechanism has 30 coordinates (one
angle per joint of a spanning tree) and 30 loop rows (the 6 joints the tree leaves out), of which
the host keeps the 18 that are independent; a step factors the 30-square mass matrix along the
tree and the 18-square loop matrix densely, in shared memory, one thread block per world.

Model (``pack_chains``, host): the fixed set is the world and every body welded to it (a fixed
joint with no parent); a breadth-first search from it over the revolute joints gives the tree
(parents before children, one coordinate per tree joint: its angle, 0 where its two anchor frames
coincide, as engine.spec defines it); every other revolute joint closes a loop. Each loop has five
rows in the anchor frame of its first body: three position rows along the frame's axes and two
angular rows about two directions normal to the joint axis. The host evaluates the rows at the
initial pose in float64 and keeps a largest independent subset (Gram-Schmidt with pivoting): a
planar loop's out-of-plane rows are implied by its joints' parallel axes, and a redundant row
would make the loops' matrix singular. Only what this path models is accepted, with an error that
names the joint or body otherwise: revolute joints (and welds to the world), drives and armature
and damping on tree joints, no limits, no contact shapes, at most MAX_COORDS coordinates and
MAX_ROWS kept rows per world. Worlds of a batch may differ in everything (padded).

Step (``chain_step_kernel``, one block per world; the lanes share each stage, a barrier between
stages; on the CPU a block is one thread):
1. with the Moreau-Jean midpoint rule (SolverConfig.integrator, the default) the angles first move
   half a step, q += dt/2 u; the dynamics below are evaluated there (semi-implicit Euler: at q);
2. kinematics level by level of the tree (a lane per body): body poses, joint points and axes,
   body velocities, and the velocity-product accelerations (the accelerations at zero joint
   acceleration);
3. composite rigid-body sums, pulled up the tree level by level (a body's children are
   contiguous in the breadth-first order): the mass, first moment and inertia about the world
   origin of each subtree, and its gravity, inertial and gyroscopic wrench; the mass matrix
   M_ij = S_i . (I_j S_j) for each joint i moving body j (the only non-zeros), the generalized forces;
4. the joints' damping and PD drives implicit: (M + dt C) du = dt tau, C = damping + kd + h kp on
   the diagonal (h the rest of the step the angles still move); M~ = M + dt C factored by one lane
   as L^T D L along the tree (no fill: the sum of the bodies' depths squared instead of n^3 / 6),
   every solve along the ancestors only;
5. the kept loop rows G (a lane per row, along its two bodies' ancestors), X = M~^-1 G^T (a lane
   per row), A = G X + 1e-6 diag(G X) factored (dense Cholesky in shared memory, the lanes sharing
   each column), K = X A^-1 (a lane per coordinate), u = u_f + K (-(G u_f) - baumgarte phi / dt):
   the loops' velocity constraint holds exactly, not as a penalty;
6. q += h u, then SolverConfig.position_iterations Gauss-Newton projections of q back onto the
   loops' position constraint with the step's K (dq = -K phi(q), the tree's poses redone each time);
7. the poses and velocities of every body (COM frames, as engine.model's State) and a divergence
   guard (non-finite or faster than SolverConfig.max_speed: the world is frozen and flagged).

Order of accuracy: the midpoint step evaluates the velocity-product and gyroscopic terms with the
step's initial rates and the drives' terms backward (stable for stiff drives), so the motion is
first order in dt wherever those matter (DR Legs hanging at dt 10 ms: 3.1e-3 m from MuJoCo C's
float64 reference over 2 s, half that at 5 ms; the maximal-coordinate step: 5.6e-4 m). Evaluating
them at rates extrapolated to the midpoint, u + (u - u_previous) / 2, projected onto the loops'
tangent (G u = 0), made a three-link chain second order (3.8e-4 -> 2.4e-5 m at dt 4 ms, CPU, 0.4 s)
and a six-bar 1.4-2.8x closer in a CPU trial; not built (it needs the poses' factors before the
velocity pass, and a GPU timing).

Measured on an H100 at 4096 worlds (benchmarks/results/README.md, "DR Legs hanging and the
four-bar in reduced coordinates"): DR Legs hanging 0.374 ms per step with loops within 1.2e-7 m
and 1.2e-6 rad (MuJoCo Warp 0.801 ms, 5.9e-4 m; our maximal step 1.85 ms), 0.320 ms without the
projections; the four-bar at 16384 worlds 0.325 ms (MuJoCo Warp's Euler 0.401 ms). The first
kernel, with a dense Cholesky of M~ and full-detail kinematics every pass, took 0.685 ms on DR Legs.

The loops' error of the result is measured by the maximal-coordinate engine's own joint residuals
(engine.metrics on a maximal model of the same specs), from body_q.
"""

import functools
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import warp as wp

from engine.linear import block_sync, tile_set
from engine.model import Integrator, SolverConfig
from engine.spec import JointType, MechanismSpec

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["ChainModel", "ChainState", "ChainStepper", "MAX_COORDS", "MAX_ROWS", "chain_layout", "pack_chains"]

MAX_COORDS = 32  # tree coordinates per world (a shared 32 x 32 tile)
MAX_ROWS = 32  # kept loop rows per world
MAX_LOOPS = 32
ROW_TOLERANCE = 1.0e-4  # a loop row is redundant when the kept rows leave less than this of its norm
REGULARIZATION = wp.constant(1.0e-6)  # relative diagonal shift of the loops' matrix (rounding guard)
CHAIN_BLOCK = 32  # threads per world on a GPU
TILE_STEP = 8  # the shared tiles are sized to the batch's padded coordinates and rows in steps of this




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
        """Body frames (R (n,3,3), p (n,3)), joint points (n,3) and world axes (n,3) at angles q."""
        n = self.n
        R = np.zeros((n, 3, 3))
        p = np.zeros((n, 3))
        point = np.zeros((n, 3))
        axis = np.zeros((n, 3))
        for k in range(n):
            par = int(self.parent[k])
            Rp, pp = (np.eye(3), np.zeros(3)) if par < 0 else (R[par], p[par])
            Rj = Rp @ self.parent_R[k]
            point[k] = pp + Rp @ self.parent_p[k]
            axis[k] = Rj @ self.axis[k]
            Rq = Rj @ _axis_angle(self.axis[k], q[k])
            R[k] = Rq @ self.child_R[k]
            p[k] = point[k] + Rq @ self.child_p[k]
        return R, p, point, axis

    def loop_rows(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All five rows of every loop at angles q: Jacobian (5 L, n) and error (5 L,)."""
        R, p, point, axis = self.kinematics(q)
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
                        col = np.cross(axis[j], x - point[j]) if part < 3 else axis[j]
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
    if spec.shapes:
        raise ValueError(f"{where}: contact shapes are not modelled (shape '{spec.shapes[0].name}')")
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
        elif joint.drive is not None and math.isfinite(joint.drive.effort_limit):
            raise ValueError(f"{where}: joint '{joint.name}': drive effort limits are not modelled")
    pose = {}
    for i, body in enumerate(spec.bodies):
        pose[i] = (_frame(body.orientation), np.asarray(body.position, dtype=np.float64))
    tree_index = {}  # spec body -> tree index
    tree_body, parent, depth, joint_of, forward = [], [], [], [], []
    frontier = [None] + sorted(fixed)  # None: the world
    seen = set(fixed)
    used = set()
    level = {b: 0 for b in fixed}
    level[None] = 0
    queue = list(frontier)
    while queue:
        here = queue.pop(0)
        here_name = None if here is None else spec.bodies[here].name
        for ji, joint in enumerate(spec.joints):
            if ji in used or joint.type != JointType.REVOLUTE:
                continue
            if joint.parent == here_name:
                other, fwd = bodies[joint.child], True
            elif joint.child == here_name and here is not None:
                if joint.parent is None:
                    continue
                other, fwd = bodies[joint.parent], False
            else:
                continue
            if other in seen:
                continue
            used.add(ji)
            seen.add(other)
            tree_index[other] = len(tree_body)
            tree_body.append(other)
            parent.append(-1 if here is None or here in fixed else tree_index[here])
            depth.append(0 if here is None or here in fixed else level[here] + 1)
            level[other] = depth[-1]
            joint_of.append(ji)
            forward.append(fwd)
            queue.append(other)
    for i, body in enumerate(spec.bodies):
        if i not in seen:
            raise ValueError(f"{where}: body '{body.name}' is not connected to the world through revolute joints "
                             f"(floating bodies are not modelled)")
    n = len(tree_body)
    if n > MAX_COORDS:
        raise ValueError(f"{where}: {n} tree coordinates, at most {MAX_COORDS} are modelled")
    loops = [ji for ji, j in enumerate(spec.joints) if j.type == JointType.REVOLUTE and ji not in used]
    for ji in loops:
        j = spec.joints[ji]
        if j.drive is not None or j.armature > 0.0 or j.damping > 0.0:
            raise ValueError(f"{where}: joint '{j.name}' closes a loop; drives, armature and damping are modelled on "
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
    child_R = np.zeros((n, 3, 3))
    child_p = np.zeros((n, 3))
    axis = np.zeros((n, 3))
    q0 = np.zeros(n)
    u0 = np.zeros(n)
    for k in range(n):
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
    layout = ChainLayout(spec, tree_body, np.array(parent, dtype=np.int64), np.array(depth, dtype=np.int64),
                         joint_of, parent_R, parent_p, child_R, child_p, axis, q0, u0, loops, loop_body, loop_R,
                         loop_p, loop_dirs, np.zeros((0, 2), dtype=np.int64))
    layout.rows = _independent_rows(layout)
    if len(layout.rows) > MAX_ROWS:
        raise ValueError(f"{where}: {len(layout.rows)} independent loop rows, at most {MAX_ROWS} are modelled")
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
    depth: wp.array2d(dtype=wp.int32)
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
    row_part: wp.array2d(dtype=wp.int32)


@wp.struct
class ChainWork:
    pose: wp.array2d(dtype=wp.transform)  # body frames
    centre: wp.array2d(dtype=wp.vec3)  # centres of mass
    point: wp.array2d(dtype=wp.vec3)  # joint points
    axis: wp.array2d(dtype=wp.vec3)  # joint axes, world
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
    phi: wp.array2d(dtype=float)  # every loop's five errors (W, 5 L)
    dirs: wp.array2d(dtype=wp.vec3)  # and directions
    ends: wp.array2d(dtype=wp.vec3)  # anchor points, 2 per loop
    u_free: wp.array2d(dtype=float)
    q_start: wp.array2d(dtype=float)  # the step's initial angles and rates
    u_start: wp.array2d(dtype=float)
    diverged: wp.array(dtype=wp.int32)
    matrix: wp.array3d(dtype=float)  # record: M~ (W, N, N)
    rows: wp.array3d(dtype=float)  # record: G (W, R, N)


POSES = wp.constant(0)  # kinematics' detail: body poses, joint points and axes
VELOCITIES = wp.constant(1)  # and the bodies' velocities
DYNAMICS = wp.constant(2)  # and the velocity-product accelerations and the world-frame inertias


@wp.func
def kinematics_body(m: ChainArrays, w: ChainWork, world: int, k: int, q: float, u: float, detail: int):
    """Pose, joint point and axis of tree body k from its parent's (already done) and its joint's
    angle q; with detail VELOCITIES its velocities (rate u), with DYNAMICS also its velocity-product
    accelerations and world-frame inertia."""
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
    Xq = wp.transform_multiply(Xj, wp.transform(wp.vec3(), wp.quat_from_axis_angle(a_local, q)))
    Xb = wp.transform_multiply(Xq, m.joint_child[world, k])
    c = wp.transform_point(Xb, m.com[world, k])
    w.pose[world, k] = Xb
    w.centre[world, k] = c
    w.point[world, k] = pj
    w.axis[world, k] = aw
    if detail >= VELOCITIES:
        wpar = wp.vec3()
        vpar = wp.vec3()
        if par >= 0:
            wpar = w.omega[world, par]
            vpar = w.vel[world, par]
        omega = wpar + aw * u
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
            alpha = apar + wp.cross(wpar, aw * u)
            acc_pj = lpar + wp.cross(apar, r_pj) + wp.cross(wpar, wp.cross(wpar, r_pj))
            w.alpha[world, k] = alpha
            w.acc[world, k] = acc_pj + wp.cross(alpha, r_b) + wp.cross(omega, wp.cross(omega, r_b))
            Rb = wp.quat_to_matrix(wp.transform_get_rotation(Xb))
            w.inertia[world, k] = Rb * m.inertia[world, k] * wp.transpose(Rb)


@wp.func
def kinematics(m: ChainArrays, w: ChainWork, world: int, lane: int, lanes: int, q: wp.array2d(dtype=float),
               u: wp.array2d(dtype=float), detail: int):
    """The tree's kinematics level by level (a lane per body) to ``detail``. Entered after a barrier;
    leaves one."""
    n = m.tree_count[world]
    for level in range(m.depth_count[world]):
        for k in range(lane, n, lanes):
            if m.depth[world, k] == level:
                kinematics_body(m, w, world, k, q[world, k], u[world, k], detail)
        block_sync()


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
        for part in range(5):
            d = wp.vec3()
            if part == 0:
                d = wp.quat_rotate(qa, wp.vec3(1.0, 0.0, 0.0))
            elif part == 1:
                d = wp.quat_rotate(qa, wp.vec3(0.0, 1.0, 0.0))
            elif part == 2:
                d = wp.quat_rotate(qa, wp.vec3(0.0, 0.0, 1.0))
            elif part == 3:
                d = wp.quat_rotate(qa, m.loop_t1[world, li])
            else:
                d = wp.quat_rotate(qa, m.loop_t2[world, li])
            e = wp.dot(d, gap)
            if part >= 3:
                e = wp.dot(d, cross)
            w.phi[world, 5 * li + part] = e
            w.dirs[world, 5 * li + part] = d
        w.ends[world, 2 * li] = xa
        w.ends[world, 2 * li + 1] = xb


@wp.func
def loop_rows_of(m: ChainArrays, w: ChainWork, world: int, r: int, G: Any, X: Any):
    """Kept row r of G (and of G^T in X), by one lane: the row's rate from each tree joint that moves
    either of its loop's bodies (walking up from each; the second body's joints count +, the first's
    -; a common ancestor's cancel in the angular rows and nearly so in the position rows). The
    tiles' other entries stay 0."""
    li = m.row_loop[world, r]
    part = m.row_part[world, r]
    d = w.dirs[world, 5 * li + part]
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
                value = sign * wp.dot(d, wp.cross(aj, x - w.point[world, j]))
            total = G[r, j] + value
            tile_set(G, r, j, total)
            tile_set(X, j, r, total)
            j = m.parent[world, j]


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


@wp.func
def solve_row(n: int, L: Any, diag: Any, x: Any, row: int):
    """Row ``row`` of the shared tile x := (L L^T)^-1 x[row, :] (factor_lanes' L and diag), by one lane."""
    for i in range(n):
        s = x[row, i]
        for k in range(i):
            s -= L[i, k] * x[row, k]
        tile_set(x, row, i, s / diag[i])
    for step in range(n):
        i = n - 1 - step
        s = x[row, i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[row, k]
        tile_set(x, row, i, s / diag[i])


@wp.func
def tree_factor(m: ChainArrays, world: int, n: int, H: Any):
    """In place, by one lane: the mass matrix H (its lower triangle; breadth-first order, parents
    first) as L^T D L, L unit lower triangular with entries only where the column is an ancestor of
    the row (no fill: the subtrees stay apart), D on the diagonal. Work: the sum over bodies of their
    depth squared, instead of n^3 / 6."""
    for step in range(n):
        k = n - 1 - step
        hkk = H[k, k]
        i = m.parent[world, k]
        while i >= 0:
            a = H[k, i] / hkk
            j = i
            while j >= 0:
                tile_set(H, i, j, H[i, j] - a * H[k, j])
                j = m.parent[world, j]
            tile_set(H, k, i, a)
            i = m.parent[world, i]


@wp.func
def tree_solve_column(m: ChainArrays, world: int, n: int, H: Any, x: Any, col: int):
    """Column col of the shared tile x := M^-1 x[:, col] with tree_factor's L^T D L, by one lane:
    L^T leaves first, D, then L roots first, each along the ancestors only."""
    for step in range(n):
        i = n - 1 - step
        xi = x[i, col]
        j = m.parent[world, i]
        while j >= 0:
            tile_set(x, j, col, x[j, col] - H[i, j] * xi)
            j = m.parent[world, j]
    for i in range(n):
        s = x[i, col] / H[i, i]
        j = m.parent[world, i]
        while j >= 0:
            s -= H[i, j] * x[j, col]
            j = m.parent[world, j]
        tile_set(x, i, col, s)


@wp.func
def tree_solve_vector(m: ChainArrays, world: int, n: int, H: Any, x: Any):
    """The shared vector x := M^-1 x with tree_factor's L^T D L, by one lane."""
    for step in range(n):
        i = n - 1 - step
        xi = x[i]
        j = m.parent[world, i]
        while j >= 0:
            tile_set(x, j, x[j] - H[i, j] * xi)
            j = m.parent[world, j]
    for i in range(n):
        s = x[i] / H[i, i]
        j = m.parent[world, i]
        while j >= 0:
            s -= H[i, j] * x[j]
            j = m.parent[world, j]
        tile_set(x, i, s)


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


@functools.cache
def chain_step_kernel(coords: int, rows: int):
    """The step kernel with shared tiles of coords x coords (tree coordinates) and rows x rows (kept
    loop rows), each a multiple of TILE_STEP (module docstring: the step)."""

    @wp.kernel(enable_backward=False, module="unique")
    def chain_step_body(m: ChainArrays, w: ChainWork, dt: float, baumgarte: float, iterations: int, max_speed: float,
                        midpoint: int, record: int, q: wp.array2d(dtype=float), u: wp.array2d(dtype=float),
                          body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector)):
        world, lane = wp.tid()
        lanes = wp.block_dim()
        Mt = wp.tile_zeros(shape=(coords, coords), dtype=float, storage="shared")  # M~, then its factor
        Gt = wp.tile_zeros(shape=(rows, coords), dtype=float, storage="shared")  # G
        Xt = wp.tile_zeros(shape=(coords, rows), dtype=float, storage="shared")  # M~^-1 G^T, then K = X A^-1
        At = wp.tile_zeros(shape=(rows, rows), dtype=float, storage="shared")  # A = G X, then its factor
        diag_a = wp.tile_zeros(shape=rows, dtype=float, storage="shared")
        vec = wp.tile_zeros(shape=coords, dtype=float, storage="shared")  # dt tau, then du
        rhs = wp.tile_zeros(shape=rows, dtype=float, storage="shared")
        n = m.tree_count[world]
        R = m.row_count[world]
        depths = m.depth_count[world]
        frozen = w.diverged[world]
        block_sync()
        lead = dt  # q+ = q_eval + lead u+
        if midpoint != 0:
            lead = 0.5 * dt
        if frozen == 0:
            for i in range(lane, n, lanes):  # kept for a step that diverges; Moreau-Jean: to the midpoint
                w.q_start[world, i] = q[world, i]
                w.u_start[world, i] = u[world, i]
                if midpoint != 0:
                    q[world, i] = q[world, i] + lead * u[world, i]
            block_sync()
            kinematics(m, w, world, lane, lanes, q, u, DYNAMICS)
            g = m.gravity[world]
            for k in range(lane, n, lanes):
                own_terms(m, w, world, k, g)
            block_sync()
            for step in range(depths - 1):  # subtree sums, deepest parents first
                level = depths - 2 - step
                for k in range(lane, n, lanes):
                    if m.depth[world, k] == level:
                        add_children(m, w, world, k)
                block_sync()
            for i in range(lane, n, lanes):  # per joint: its subtree's inertia applied to its motion, its force
                a = w.axis[world, i]
                s_lin = wp.cross(w.point[world, i], a)
                cm = w.sub_mass[world, i]
                ch = w.sub_moment[world, i]
                w.force_n[world, i] = w.sub_inertia[world, i] * a + wp.cross(ch, s_lin)
                w.force_f[world, i] = cm * s_lin - wp.cross(ch, a)
                ui = u[world, i]
                tau = wp.dot(a, w.wrench_t[world, i]) + wp.dot(s_lin, w.wrench_f[world, i]) - m.damping[world, i] * ui
                tau += m.kp[world, i] * (m.q_target[world, i] - q[world, i] - lead * ui)
                tau += m.kd[world, i] * (m.v_target[world, i] - ui)
                tile_set(vec, i, dt * tau)
            loop_errors(m, w, world, lane, lanes)
            block_sync()
            for i in range(lane, n, lanes):  # M~: row i against its ancestors j (the tile's other entries stay 0)
                j = i
                while j >= 0:
                    a = w.axis[world, j]
                    value = wp.dot(a, w.force_n[world, i]) + wp.dot(wp.cross(w.point[world, j], a), w.force_f[world, i])
                    if j == i:
                        value += m.armature[world, i] + dt * (m.damping[world, i] + m.kd[world, i]
                                                              + lead * m.kp[world, i])
                    tile_set(Mt, i, j, value)
                    if record != 0:
                        w.matrix[world, i, j] = value
                        w.matrix[world, j, i] = value
                    j = m.parent[world, j]
            for r in range(lane, R, lanes):  # G along the two bodies' ancestors, and G^T into X
                loop_rows_of(m, w, world, r, Gt, Xt)
            block_sync()
            if record != 0:
                for e in range(lane, R * n, lanes):
                    w.rows[world, e // n, e % n] = Gt[e // n, e % n]
            block_sync()
            if lane == 0:
                tree_factor(m, world, n, Mt)
            block_sync()
            for col in range(lane, R + 1, lanes):  # X = M~^-1 G^T a column per lane, and du = M~^-1 (dt tau)
                if col < R:
                    tree_solve_column(m, world, n, Mt, Xt, col)
                else:
                    tree_solve_vector(m, world, n, Mt, vec)
            block_sync()
            for i in range(lane, n, lanes):
                w.u_free[world, i] = u[world, i] + vec[i]
            for e in range(lane, R * R, lanes):  # A = G X (lower triangle)
                r = e // R
                s = e % R
                if s <= r:
                    acc = float(0.0)
                    for j in range(n):
                        acc += Gt[r, j] * Xt[j, s]
                    tile_set(At, r, s, acc)
            block_sync()
            for r in range(lane, R, lanes):  # the right-hand side: -(G u_f) - baumgarte phi / dt
                acc = float(0.0)
                for j in range(n):
                    acc += Gt[r, j] * w.u_free[world, j]
                tile_set(rhs, r, -acc - baumgarte / dt * w.phi[world, 5 * m.row_loop[world, r] + m.row_part[world, r]])
            factor_lanes(lane, lanes, R, At, diag_a, REGULARIZATION)
            for i in range(lane, n, lanes):  # K = X A^-1, a row per lane
                solve_row(R, At, diag_a, Xt, i)
            block_sync()
            for i in range(lane, n, lanes):  # u = u_f + K rhs, q += lead u
                acc = w.u_free[world, i]
                for r in range(R):
                    acc += Xt[i, r] * rhs[r]
                u[world, i] = acc
                q[world, i] = q[world, i] + lead * acc
            block_sync()
            for it in range(iterations):  # Gauss-Newton projections onto the loops with the step's factors
                kinematics(m, w, world, lane, lanes, q, u, POSES)
                loop_errors(m, w, world, lane, lanes)
                block_sync()
                for i in range(lane, n, lanes):
                    acc = float(0.0)
                    for r in range(R):
                        acc += Xt[i, r] * w.phi[world, 5 * m.row_loop[world, r] + m.row_part[world, r]]
                    q[world, i] = q[world, i] - acc
                block_sync()
            kinematics(m, w, world, lane, lanes, q, u, VELOCITIES)
            for k in range(lane, n, lanes):  # the divergence guard
                c = w.centre[world, k]
                v = w.vel[world, k]
                om = w.omega[world, k]
                if not (wp.isfinite(c) and wp.isfinite(v) and wp.isfinite(om)) or wp.length(v) > max_speed:
                    w.diverged[world] = 1
            block_sync()
            if w.diverged[world] == 0:
                for k in range(lane, n, lanes):
                    b = m.body_out[world, k]
                    body_q[world, b] = wp.transform(w.centre[world, k], wp.transform_get_rotation(w.pose[world, k]))
                    body_qd[world, b] = wp.spatial_vector(w.vel[world, k], w.omega[world, k])
            else:  # frozen at the last good step: its angles, rates and bodies
                for i in range(lane, n, lanes):
                    q[world, i] = w.q_start[world, i]
                    u[world, i] = w.u_start[world, i]

    return chain_step_body


def _tile_size(count: int) -> int:
    return max(TILE_STEP, -(-count // TILE_STEP) * TILE_STEP)


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
    """Angles q and rates u (W, MAX_COORDS), and every body's COM pose and velocity as engine.model's
    State holds them (body_q (W, B) transform, body_qd (W, B) spatial_vector: v, w)."""

    def __init__(self, q, u, body_q, body_qd):
        self.q, self.u, self.body_q, self.body_qd = q, u, body_q, body_qd


class ChainModel:
    """A padded batch of closed chains in reduced coordinates (pack_chains)."""

    def __init__(self, layouts: list, arrays: ChainArrays, work: ChainWork, init: dict, config: SolverConfig,
                 dt: float, device):
        self.layouts, self.arrays, self.work, self._init = layouts, arrays, work, init
        self.config, self.dt, self.device = config, dt, device
        self.num_worlds = len(layouts)
        self.max_rows = max(len(lay.rows) for lay in layouts)
        self.coords = _tile_size(max(lay.n for lay in layouts))
        self.tile_rows = _tile_size(self.max_rows)

    def state(self) -> ChainState:
        """A new state at the initial pose."""
        return ChainState(*(wp.array(self._init[k], device=self.device, dtype=t) for k, t in
                            (("q", float), ("u", float), ("body_q", wp.transform), ("body_qd", wp.spatial_vector))))

    def step(self, state: ChainState, record: bool = False) -> None:
        """Advance state by one step of self.dt (in place). record: also write the step's mass matrix
        M~ into work.matrix (W, coords, coords) and its kept loop rows G into work.rows (W, rows, coords)."""
        c = self.config
        if record and self.work.matrix.shape != (self.num_worlds, self.coords, self.coords):  # on first use
            self.work.matrix = wp.zeros((self.num_worlds, self.coords, self.coords), dtype=float, device=self.device)
            self.work.rows = wp.zeros((self.num_worlds, self.tile_rows, self.coords), dtype=float, device=self.device)
        block = CHAIN_BLOCK if wp.get_device(self.device).is_cuda else 1
        kernel = chain_step_kernel(self.coords, self.tile_rows)
        wp.launch_tiled(kernel, dim=[self.num_worlds], block_dim=block, device=self.device,
                        inputs=[self.arrays, self.work, float(self.dt), float(c.baumgarte), int(c.position_iterations),
                                float(c.max_speed), int(c.integrator == Integrator.MOREAU_JEAN), int(record), state.q,
                                state.u, state.body_q, state.body_qd])

    @property
    def diverged(self) -> np.ndarray:
        """Worlds flagged diverged (frozen), as a NumPy bool array (W,)."""
        return self.work.diverged.numpy().astype(bool)


def pack_chains(specs: Sequence[MechanismSpec], device=None, *, config: SolverConfig | None = None,
                dt: float = 1.0e-3) -> ChainModel:
    """Pack one world per spec (they may differ) into a ChainModel on ``device``. SolverConfig's
    baumgarte, position_iterations and max_speed apply; ValueError naming the world and the joint
    or body this path cannot model."""
    config = config or SolverConfig()
    if not (isinstance(dt, (int, float)) and not isinstance(dt, bool) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"pack_chains: dt must be a positive number of seconds, got {dt!r}")
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
    f = {k: np.zeros((W, N)) for k in ("mass", "armature", "damping", "kp", "kd", "q_target", "v_target", "q", "u")}
    i32 = {k: np.zeros((W, N), dtype=np.int32) for k in ("parent", "depth", "body_out", "first_child", "child_count")}
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
    body_q = np.zeros((W, B, 7))
    body_q[..., 6] = 1.0
    body_qd = np.zeros((W, B, 6))
    counts = np.zeros((4, W), dtype=np.int32)
    gravity = np.zeros((W, 3))
    for w_, lay in enumerate(layouts):
        spec = lay.spec
        n = lay.n
        counts[:, w_] = (n, (lay.depth.max() + 1) if n else 0, len(lay.loops), len(lay.rows))
        gravity[w_] = spec.gravity
        for k in range(n):
            body = spec.bodies[lay.tree_body[k]]
            joint = spec.joints[lay.joint[k]]
            i32["parent"][w_, k] = lay.parent[k]
            i32["depth"][w_, k] = lay.depth[k]
            i32["body_out"][w_, k] = lay.tree_body[k]
            children = np.flatnonzero(lay.parent == k)
            i32["first_child"][w_, k] = children[0] if len(children) else -1
            i32["child_count"][w_, k] = len(children)
            if len(children) and not np.array_equal(children, np.arange(children[0], children[0] + len(children))):
                raise AssertionError("breadth-first order keeps siblings contiguous")
            jp[w_, k] = _transform(lay.parent_R[k], lay.parent_p[k])
            jc[w_, k] = _transform(lay.child_R[k], lay.child_p[k])
            v3["axis"][w_, k] = lay.axis[k]
            v3["com"][w_, k] = body.com
            f["mass"][w_, k] = body.mass
            inertia[w_, k] = body.inertia
            f["armature"][w_, k] = joint.armature
            f["damping"][w_, k] = joint.damping
            if joint.drive is not None:
                f["kp"][w_, k] = joint.drive.stiffness
                f["kd"][w_, k] = joint.drive.damping
                f["q_target"][w_, k] = joint.drive.target_position
                f["v_target"][w_, k] = joint.drive.target_velocity
            f["q"][w_, k] = lay.q0[k]
            f["u"][w_, k] = lay.u0[k]
        for li in range(len(lay.loops)):
            joint = spec.joints[lay.loops[li]]
            for side in range(2):
                loop_body[w_, li, side] = lay.loop_body[li, side]
                loop_anchor[w_, li, side] = _transform(lay.loop_R[li, side], lay.loop_p[li, side])
            loop_axis[w_, li] = joint.axis
            loop_t[0, w_, li], loop_t[1, w_, li] = lay.loop_dirs[li, 3], lay.loop_dirs[li, 4]
        row_loop[w_, :len(lay.rows)] = lay.rows[:, 0]
        row_part[w_, :len(lay.rows)] = lay.rows[:, 1]
        for i, body in enumerate(spec.bodies):
            R = _frame(body.orientation)
            body_q[w_, i] = np.r_[np.asarray(body.position) + R @ np.asarray(body.com), body.orientation]
    # every world from its distinct spec's rows
    f = {k: v[kind_of] for k, v in f.items()}
    i32 = {k: v[kind_of] for k, v in i32.items()}
    v3 = {k: v[kind_of] for k, v in v3.items()}
    inertia, jp, jc, loop_body, loop_anchor, loop_axis = (x[kind_of] for x in (inertia, jp, jc, loop_body, loop_anchor,
                                                                               loop_axis))
    loop_t, counts = loop_t[:, kind_of], counts[:, kind_of]
    row_loop, row_part, body_q, body_qd, gravity = (x[kind_of] for x in (row_loop, row_part, body_q, body_qd, gravity))
    layouts = [layouts[k] for k in kind_of]
    W = len(specs)
    # the initial body poses and velocities from the tree (fixed bodies keep the spec's)
    dev = device
    a = ChainArrays()
    a.tree_count, a.depth_count, a.loop_count, a.row_count = (
        wp.array(c, dtype=wp.int32, device=dev) for c in counts)
    a.gravity = wp.array(gravity, dtype=wp.vec3, device=dev)
    for k in ("parent", "depth", "body_out", "first_child", "child_count"):
        setattr(a, k, wp.array(i32[k], dtype=wp.int32, device=dev))
    a.joint_parent = wp.array(jp, dtype=wp.transform, device=dev)
    a.joint_child = wp.array(jc, dtype=wp.transform, device=dev)
    a.axis = wp.array(v3["axis"], dtype=wp.vec3, device=dev)
    a.com = wp.array(v3["com"], dtype=wp.vec3, device=dev)
    a.inertia = wp.array(inertia, dtype=wp.mat33, device=dev)
    for k in ("mass", "armature", "damping", "kp", "kd", "q_target", "v_target"):
        setattr(a, k, wp.array(f[k], dtype=float, device=dev))
    a.loop_body = wp.array(loop_body, dtype=wp.int32, device=dev)
    a.loop_anchor = wp.array(loop_anchor, dtype=wp.transform, device=dev)
    a.loop_axis = wp.array(loop_axis, dtype=wp.vec3, device=dev)
    a.loop_t1 = wp.array(loop_t[0], dtype=wp.vec3, device=dev)
    a.loop_t2 = wp.array(loop_t[1], dtype=wp.vec3, device=dev)
    a.row_loop = wp.array(row_loop, dtype=wp.int32, device=dev)
    a.row_part = wp.array(row_part, dtype=wp.int32, device=dev)
    k = ChainWork()
    for name, dtype in (("pose", wp.transform), ("centre", wp.vec3), ("point", wp.vec3), ("axis", wp.vec3),
                        ("omega", wp.vec3), ("vel", wp.vec3), ("alpha", wp.vec3), ("acc", wp.vec3),
                        ("inertia", wp.mat33), ("wrench_t", wp.vec3), ("wrench_f", wp.vec3), ("force_n", wp.vec3),
                        ("force_f", wp.vec3), ("sub_mass", float), ("sub_moment", wp.vec3), ("sub_inertia", wp.mat33)):
        setattr(k, name, wp.zeros((W, N), dtype=dtype, device=dev))
    k.phi = wp.zeros((W, 5 * L), dtype=float, device=dev)
    k.dirs = wp.zeros((W, 5 * L), dtype=wp.vec3, device=dev)
    k.ends = wp.zeros((W, 2 * L), dtype=wp.vec3, device=dev)
    k.u_free = wp.zeros((W, N), dtype=float, device=dev)
    k.q_start = wp.zeros((W, N), dtype=float, device=dev)
    k.u_start = wp.zeros((W, N), dtype=float, device=dev)
    k.diverged = wp.zeros(W, dtype=wp.int32, device=dev)
    k.matrix = wp.zeros((1, 1, 1), dtype=float, device=dev)  # ChainModel.step(record=True) sizes them
    k.rows = wp.zeros((1, 1, 1), dtype=float, device=dev)
    init = {"q": f["q"], "u": f["u"], "body_q": body_q, "body_qd": body_qd}
    model = ChainModel(layouts, a, k, init, config, float(dt), device)
    # body poses and velocities at the initial angles: one step's kinematics, no integration
    state = model.state()
    # blocks of one thread: kinematics' barriers must be reached by every thread of a block, and worlds differ in depth
    wp.launch_tiled(initial_bodies_kernel, dim=[W], block_dim=1, device=dev,
                    inputs=[a, k, state.q, state.u, state.body_q, state.body_qd])
    model._init["body_q"] = state.body_q.numpy()
    model._init["body_qd"] = state.body_qd.numpy()
    return model


@wp.kernel(enable_backward=False)
def initial_bodies_kernel(m: ChainArrays, w: ChainWork, q: wp.array2d(dtype=float), u: wp.array2d(dtype=float),
                          body_q: wp.array2d(dtype=wp.transform), body_qd: wp.array2d(dtype=wp.spatial_vector)):
    """Tree bodies' COM poses and velocities from q and u (a block of one thread per world)."""
    world, lane = wp.tid()
    kinematics(m, w, world, 0, 1, q, u, VELOCITIES)
    for k in range(m.tree_count[world]):
        b = m.body_out[world, k]
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
