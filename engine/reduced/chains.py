"""Closed chains in reduced coordinates: a spanning tree of revolute joints, on fixed bodies or
floating, its loops closed by constraint rows (revolute and inline joints), contacts with the
ground plane, one fused kernel launch per step.

Why: in maximal coordinates every joint is a block of rows and a step factors their Delassus
matrix; here a step factors the tree's mass matrix (one angle per tree joint) and the small matrix
of the loops' independent rows in shared memory, one thread block per world. chain_layout
(engine.reduced.chain_layout) chooses the tree and rows, pack_chains pads a batch of worlds that
may differ in everything, ChainModel.step advances it (engine.reduced.chain_kernel), and a
ChainState holds the coordinates and every body's COM pose and velocity as engine.model's State
does: the loops' error is measured by the maximal engine's own joint residuals (engine.metrics on a
maximal model of the same specs) from body_q. Measurements: benchmarks/results/README.md, "Reduced
closed chains: design notes".
"""

import functools
import math
from typing import Sequence

import numpy as np
import warp as wp

from engine.config import Integrator, SolverConfig
from engine.reduced.chain_kernel import CHAIN_BLOCK, MAX_REGISTERS, chain_step_kernel
from engine.reduced.chain_layout import (KIND_ANGULAR, KIND_LINEAR, KIND_REVOLUTE, KIND_ROOT, MAX_CONTACTS, MAX_PREFIX,
                                         MAX_ROWS, ChainLayout, _capacity, _packed_rows, _packed_tile, _prefix, _tile_size,
                                         _transform, chain_layout)
from engine.reduced.chain_stages import (STAGES, VELOCITIES, ChainArrays, ChainWork, candidates_within, kinematics,
                                         plane_candidates)
from engine.spatial import quat_matrix
from engine.spec import MechanismSpec

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["CONTACT_RHO", "ChainModel", "ChainState", "pack_chains"]

# the contacts' initial ADMM penalty (Tuning.rho None), in units of their preconditioned Delassus matrix's
# diagonal (1): the maximal plan's 1e-3 let capped iterations return wild impulses on new contacts, at 1 they
# stay put. Each later step starts from the penalty its world's last step ended with (adaptive_rho). The
# trials: benchmarks/results/README.md, "Reduced closed chains: design notes"
CONTACT_RHO = 1.0


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
        # register cap per thread of the step kernel on CUDA (Tuning.tree_registers; None: the compiler's choice)
        registers = config.tuning.tree_registers
        self.max_registers = MAX_REGISTERS if registers is None else (registers or None)
        self.rho_init = config.tuning.rho_or(CONTACT_RHO)  # the contacts' starting penalty (Tuning.rho)
        self.tile_slots = _tile_size(4 * max(len(lay.shapes) for lay in layouts))  # candidate slots (4 per shape)
        self.tile_contacts = _tile_size(3 * capacity) if capacity else 0
        self.contact_working = capacity  # contacts the first kernel's tiles hold (pack_chains sets it)
        self.tile_working = self.tile_contacts
        self.packed_size = _packed_tile(arrays.ancestor.shape[1])  # the packed M~'s tile
        # the tree solves' unrolled prefix: compiled only where a world has one (a floating root)
        self.unroll = MAX_PREFIX if int(arrays.prefix.numpy().max(initial=0)) > 0 else 0
        self.inline = any(lay.inline for lay in layouts)  # the inline loops' rows compiled in only where needed

    def state(self) -> ChainState:
        """A new state at the initial pose (the contacts' warm start, kept in the model's work, is
        cleared: a new trajectory starts without the last one's impulses and from rho_init)."""
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
                                       self.packed_size, bool(stages), self.unroll, handover, self.inline)
            wp.launch_tiled(kernel, dim=[self.num_worlds], block_dim=block, device=self.device,
                            inputs=[self.arrays, self.work, float(self.dt), float(c.baumgarte),
                                    int(c.position_iterations), float(c.max_speed),
                                    int(c.integrator == Integrator.MOREAU_JEAN), int(record), float(c.contact_margin),
                                    float(c.contact_stabilization), float(c.tuning.eta), self.rho_init,
                                    int(c.tuning.adaptive_rho), max(1, int(c.tuning.rho_update_interval)),
                                    float(c.tolerance), float(c.relative_tolerance), int(c.max_iterations),
                                    float(c.tuning.projection_skip_floor), float(c.tuning.projection_skip_floor_angular),
                                    tile // 3, state.q, state.u,
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
                layouts: Sequence[ChainLayout] | None = None) -> ChainModel:
    """Pack one world per spec (they may differ) into a ChainModel on ``device``. SolverConfig's
    integrator, baumgarte, position_iterations and max_speed apply, and for contacts contact_margin,
    contact_stabilization, tolerance, relative_tolerance and max_iterations; of its Tuning eta,
    adaptive_rho, rho_update_interval, the projection skip floors, rho (the contacts' starting
    penalty, None: CONTACT_RHO; each later step starts at its world's last one), tree_registers and
    tree_contact_working. contact_capacity: contacts kept per world and step (None: every candidate
    of its shapes, at most MAX_CONTACTS; those beyond are counted in work.contact_dropped). A world
    that finds more contacts than the kernel's tiles hold (Tuning.tree_contact_working), within its
    capacity, is stepped again from the step's start by a second kernel with tiles for the full
    capacity (work.contact_redone counts those steps), so that contacts that seldom occur cost no
    occupancy. layouts: chain_layout(spec) of each spec, already made (engine.plan). ValueError
    naming the world and the joint, shape or body this path cannot model."""
    config = config or SolverConfig()
    if not (isinstance(dt, (int, float)) and not isinstance(dt, bool) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"pack_chains: dt must be a positive number of seconds, got {dt!r}")
    if contact_capacity is not None and not (isinstance(contact_capacity, (int, np.integer))
                                             and not isinstance(contact_capacity, bool) and contact_capacity >= 0):
        raise ValueError(f"pack_chains: contact_capacity must be a non-negative integer, got {contact_capacity!r}")
    contact_working = config.tuning.tree_contact_working  # (Tuning checked it: None or >= 1)
    specs = list(specs)
    if not specs:
        raise ValueError("pack_chains: needs at least one MechanismSpec")
    given = None if layouts is None else list(layouts)
    if given is not None and (len(given) != len(specs) or any(lay.spec is not spec for lay, spec in zip(given, specs))):
        raise ValueError("pack_chains: layouts must be chain_layout(spec) of each spec, in order")
    distinct, kind_of, layouts = {}, [], []  # one layout per distinct spec object
    for index, spec in enumerate(specs):
        if id(spec) not in distinct:
            try:
                layouts.append(chain_layout(spec) if given is None else given[index])
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
    loop_inline = np.zeros((W, L), dtype=np.int32)
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
            for side in range(2):
                loop_body[w_, li, side] = lay.loop_body[li, side]
                loop_anchor[w_, li, side] = _transform(lay.loop_R[li, side], lay.loop_p[li, side])
            loop_axis[w_, li] = lay.axis_of_loop(li)
            loop_inline[w_, li] = li in lay.inline
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
            R = quat_matrix(body.orientation)
            body_q[w_, i] = np.r_[np.asarray(body.position) + R @ np.asarray(body.com), body.orientation]
    # every world from its distinct spec's rows
    f = {k: v[kind_of] for k, v in f.items()}
    i32 = {k: v[kind_of] for k, v in i32.items()}
    ancestor, depth_start = ancestor[kind_of], depth_start[kind_of]
    v3 = {k: v[kind_of] for k, v in v3.items()}
    inertia, jp, jc, loop_body, loop_anchor, loop_axis, loop_inline = (
        x[kind_of] for x in (inertia, jp, jc, loop_body, loop_anchor, loop_axis, loop_inline))
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
    a.loop_inline = wp.array(loop_inline, dtype=wp.int32, device=dev)
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

