"""Closed chains in reduced coordinates (the TREE plan): a spanning tree of revolute joints, on
fixed bodies or floating, its loops closed by constraint rows (revolute and inline joints),
contacts with the ground plane, one fused kernel launch per step.

Why: a step factors the tree's mass matrix (one angle per tree joint) and the small matrix of the
loops' independent rows in shared memory, one thread block per world, instead of the Delassus
matrix of every joint's rows. chain_layout (engine.reduced.chain_layout) chooses the tree and
rows, pack_chains pads a batch of worlds that may differ in everything, ChainModel.step advances
it (engine.reduced.chain_kernel), and a ChainState holds the coordinates and every body's COM pose
and velocity as engine.model's State does, so the loops' error is measured by the maximal
engine's own joint residuals. Measurements: benchmarks/results/README.md, "Reduced closed chains:
design notes".
"""

import functools
import math
from typing import Sequence

import numpy as np
import warp as wp

from engine.config import Integrator, SolverConfig
from engine.forces import BodyWrench, JointSpring, LinearSpring
from engine.model import FORCE_BODY_WRENCH, FORCE_JOINT_SPRING, FORCE_JOINT_TORQUE, FORCE_LINEAR_SPRING
from engine.reduced.chain_kernel import CHAIN_BLOCK, MAX_REGISTERS, chain_step_kernel
from engine.reduced.chain_layout import (KIND_ANGULAR, KIND_LINEAR, KIND_REVOLUTE, KIND_ROOT, MAX_CONTACTS, MAX_PREFIX,
                                         MAX_ROWS, ChainLayout, _capacity, _packed_rows, _packed_tile, _prefix, _tile_size,
                                         _transform, chain_layout)
from engine.reduced.chain_stages import (STAGES, VELOCITIES, ChainArrays, ChainLoads, ChainWork, NoLoads, body_out,
                                         candidates_within, kinematics, plane_candidates)
from engine.spatial import quat_matrix
from engine.spec import JointType, MechanismSpec

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["CONTACT_RHO", "ChainControl", "ChainModel", "ChainState", "pack_chains"]

# the contacts' initial ADMM penalty (Tuning.rho None), in units of their preconditioned Delassus
# diagonal; later steps start from their world's last penalty. Why not the maximal plan's 1e-3:
# benchmarks/results/README.md, "Reduced closed chains: design notes"
CONTACT_RHO = 1.0
# ChainLoads' fields (the rest of pack_chains's arrays are ChainArrays')
LOAD_FIELDS = frozenset(name for name in ChainLoads.vars)
# ChainArrays' and ChainLoads' fields of a Warp vector, matrix or transform type (the others: int32 or float)
ARRAY_TYPES = {"gravity": wp.vec3, "shape_X": wp.transform, "shape_size": wp.vec3, "ground_normal": wp.vec3,
               "axis": wp.vec3, "com": wp.vec3, "inertia": wp.mat33, "joint_parent": wp.transform,
               "joint_child": wp.transform, "loop_anchor": wp.transform, "loop_axis": wp.vec3, "loop_t1": wp.vec3,
               "loop_t2": wp.vec3, "force_frame": wp.transform, "force_vec": wp.vec3, "force_coef": wp.vec4,
               "control_frame": wp.transform, "control_axis": wp.vec3}


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
                 dt: float, device, capacity: int = 0, loads=None):
        self.layouts, self.arrays, self.work, self._init = layouts, arrays, work, init
        self.loads = loads  # force elements and Control targets (a kernel with neither takes NoLoads)
        self._no_loads = NoLoads()
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
        self.forces = any(lay.spec.forces for lay in layouts)  # the force elements' code compiled in only where needed
        self.max_bodies = max(len(lay.spec.bodies) for lay in layouts)
        self.max_joints = max(1, max(len(lay.spec.joints) for lay in layouts))
        # the loads' Control arrays of a step without one (never read: its code is compiled out)
        if self.loads is not None:
            self.loads.body_f = wp.zeros((1, 1), dtype=wp.spatial_vector, device=device)
            self.loads.joint_effort = wp.zeros((1, 1), dtype=float, device=device)
        self._loads_by_control: dict = {}  # id(control) -> (control, its ChainLoads)

    def loads_for(self, control):
        """The step kernel's loads argument: NoLoads without force elements and Control, else the
        batch's ChainLoads with the Control's body_f and joint_effort (one struct per Control, made
        on its first step)."""
        if control is None:
            return self.loads if self.forces else self._no_loads
        kept = self._loads_by_control.get(id(control))
        if kept is None or kept[0] is not control:
            loads = ChainLoads()
            for name in ChainLoads.vars:
                setattr(loads, name, getattr(self.loads, name))
            loads.body_f, loads.joint_effort = control.body_f, control.joint_effort
            if len(self._loads_by_control) >= 8:  # (a batch meets few Controls; keep no old ones alive)
                self._loads_by_control.clear()
            kept = self._loads_by_control[id(control)] = (control, loads)
        return kept[1]

    def control(self) -> "ChainControl":
        """A new ChainControl (zeros): body_f (W, B) and joint_effort (W, J) in spec order."""
        return ChainControl(wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.spatial_vector, device=self.device),
                            wp.zeros((self.num_worlds, self.max_joints), dtype=float, device=self.device))

    def check_control(self, control) -> None:
        """check_control_arrays for this batch (host work: call it once, not per step)."""
        check_control_arrays(control, "tree", self.num_worlds, self.max_bodies, self.max_joints, self.device)

    def state(self) -> ChainState:
        """A new state at the initial pose (the contacts' warm start, kept in the model's work, is
        cleared: a new trajectory starts without the last one's impulses and from rho_init)."""
        self.work.contact_impulse.zero_()
        self.work.contact_rho.zero_()
        return ChainState(*(wp.array(self._init[k], device=self.device, dtype=t) for k, t in
                            (("q", float), ("u", float), ("root", wp.transform), ("body_q", wp.transform),
                             ("body_qd", wp.spatial_vector))))

    def step(self, state: ChainState, record: bool = False, stages: bool = False, control=None) -> None:
        """Advance state by one step of self.dt (in place). record: also write the step's mass matrix
        M~ into work.matrix (W, coords, coords) and its kept loop rows G into work.rows (W, rows, coords).
        stages: also time the step's STAGES (a kernel with clock readings; stage_cycles reads them).
        control: a ChainControl (check_control) whose arrays the kernel reads at this step (None:
        the kernel without the Control's code)."""
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
        # a world that finds more contacts than the first kernel's tiles hold is handed to a second
        # kernel with tiles for its full capacity (launched only where the first's are smaller)
        passes = [(self.tile_working, 0)]
        if self.tile_working < self.tile_contacts:
            passes = [(self.tile_working, 1), (self.tile_contacts, 2)]
        loads = self.loads_for(control)
        for tile, handover in passes:
            kernel = chain_step_kernel(self.coords, self.tile_rows, tile, self.tile_slots, self.max_registers,
                                       self.packed_size, bool(stages), self.unroll, handover, self.inline,
                                       self.forces, control is not None)
            wp.launch_tiled(kernel, dim=[self.num_worlds], block_dim=block, device=self.device,
                            inputs=[self.arrays, self.work, loads, float(self.dt), float(c.baumgarte),
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
    """Pack one world per spec (they may differ) into a ChainModel on ``device``.

    SolverConfig's integrator, baumgarte, position_iterations and max_speed apply, and for contacts
    contact_margin, contact_stabilization, tolerance, relative_tolerance and max_iterations; of its
    Tuning eta, adaptive_rho, rho_update_interval, the projection skip floors, rho (None:
    CONTACT_RHO), tree_registers and tree_contact_working. contact_capacity: contacts kept per world
    and step (None: every candidate of its shapes, at most MAX_CONTACTS; the rest are counted in
    work.contact_dropped). A world that finds more contacts than the first kernel's tiles hold is
    stepped again by a second kernel with tiles for its full capacity (work.contact_redone), so that
    rare contacts cost no occupancy. layouts: chain_layout(spec) of each spec, already made
    (engine.plan). ValueError naming the world and the joint, shape or body this path cannot model."""
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
    S = max(1, max(len(lay.shapes) for lay in layouts))
    packs = [_packed_rows(lay.parent) for lay in layouts]  # per distinct layout: levels, packed row starts
    identity = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    # ChainArrays' fields on the host, one row per distinct layout
    h = {k: np.zeros((W, N)) for k in ("mass", "armature", "damping", "kp", "kd", "q_target", "v_target", "effort")}
    h.update({k: np.zeros((W, N), dtype=np.int32) for k in ("parent", "by_depth", "body_out", "first_child",
                                                            "child_count", "kind", "sub_of", "level", "row_start")})
    h.update({k: np.zeros(W, dtype=np.int32) for k in ("tree_count", "depth_count", "loop_count", "row_count",
                                                       "shape_count", "contact_capacity", "prefix")})
    h["ancestor"] = np.zeros((W, max(int(starts[-1]) for _, starts in packs)), dtype=np.int32)
    h["depth_start"] = np.zeros((W, N + 1), dtype=np.int32)
    h["gravity"] = np.zeros((W, 3))
    h["shape_entry"] = np.zeros((W, S), dtype=np.int32)
    h["shape_type"] = np.zeros((W, S), dtype=np.int32)
    h["shape_X"] = np.tile(identity, (W, S, 1))
    h["shape_size"] = np.zeros((W, S, 3))
    h["shape_mu"] = np.zeros((W, S))
    h["ground_normal"] = np.tile([0.0, 0.0, 1.0], (W, 1))
    h["ground_offset"] = np.zeros(W)
    h["axis"] = np.zeros((W, N, 3))
    h["com"] = np.zeros((W, N, 3))
    h["inertia"] = np.tile(np.eye(3), (W, N, 1, 1))
    h["joint_parent"] = np.tile(identity, (W, N, 1))
    h["joint_child"] = np.tile(identity, (W, N, 1))
    h["loop_body"] = np.full((W, L, 2), -1, dtype=np.int32)
    h["loop_anchor"] = np.tile(identity, (W, L, 2, 1))
    h["loop_axis"] = np.zeros((W, L, 3))
    h["loop_t1"] = np.zeros((W, L, 3))
    h["loop_t2"] = np.zeros((W, L, 3))
    h["loop_inline"] = np.zeros((W, L), dtype=np.int32)
    h["row_loop"] = np.zeros((W, MAX_ROWS), dtype=np.int32)
    h["row_part"] = np.zeros((W, MAX_ROWS), dtype=np.int32)
    h["row_compliance"] = np.zeros((W, MAX_ROWS))  # soft rows: 1 / (armature + dt damping)
    h["row_keep"] = np.zeros((W, MAX_ROWS))  # soft rows: armature / (armature + dt damping)
    F = max(1, max(len(lay.spec.forces) for lay in layouts))  # force slots per world (apply_forces)
    h["force_count"] = np.zeros(W, dtype=np.int32)
    h["force_kind"] = np.zeros((W, F), dtype=np.int32)
    h["force_entry"] = np.full((W, F, 2), -1, dtype=np.int32)
    h["force_frame"] = np.tile(identity, (W, F, 2, 1))
    h["force_vec"] = np.zeros((W, F, 2, 3))
    h["force_coef"] = np.zeros((W, F, 4))
    J = max(1, max(len(lay.spec.joints) for lay in layouts))  # a Control's joints (apply_control)
    h["control_body"] = np.full((W, B), -1, dtype=np.int32)
    h["control_joint"] = np.full((W, J, 2), -1, dtype=np.int32)
    h["control_frame"] = np.tile(identity, (W, J, 1))
    h["control_axis"] = np.zeros((W, J, 3))
    init = {"q": np.zeros((W, N)), "u": np.zeros((W, N)), "root": np.tile(identity, (W, N, 1)),
            "body_q": np.tile(identity, (W, B, 1)), "body_qd": np.zeros((W, B, 6))}
    for w_, lay in enumerate(layouts):
        spec = lay.spec
        n = lay.n
        depths = (lay.depth.max() + 1) if n else 0
        h["tree_count"][w_], h["depth_count"][w_] = n, depths
        h["loop_count"][w_], h["row_count"][w_] = len(lay.loops), len(lay.rows) + len(lay.soft)
        h["gravity"][w_] = spec.gravity
        level, packed = packs[w_]
        h["level"][w_, :n], h["row_start"][w_, :n] = level, packed[:-1]
        h["by_depth"][w_, :n] = np.argsort(lay.depth, kind="stable")
        h["depth_start"][w_, :depths + 1] = np.searchsorted(lay.depth, np.arange(depths + 1),
                                                            sorter=np.argsort(lay.depth, kind="stable"))
        for k in range(n):
            j = k
            while j >= 0:
                h["ancestor"][w_, packed[k] + level[j]] = j
                j = lay.parent[j]
        for k in range(n):
            body = spec.bodies[lay.tree_body[k]]
            kind = int(lay.kind[k])
            h["parent"][w_, k] = lay.parent[k]
            h["kind"][w_, k] = kind
            h["sub_of"][w_, k] = lay.sub_of[k]
            children = np.flatnonzero(lay.parent == k)
            if kind in (KIND_LINEAR, KIND_ANGULAR):  # a floating root's massless entries: no subtree sums
                children = children[:0]
            h["first_child"][w_, k] = children[0] if len(children) else -1
            h["child_count"][w_, k] = len(children)
            if len(children) and not np.array_equal(children, np.arange(children[0], children[0] + len(children))):
                raise AssertionError("breadth-first order keeps siblings contiguous")
            h["joint_parent"][w_, k] = _transform(lay.parent_R[k], lay.parent_p[k])
            h["joint_child"][w_, k] = _transform(lay.child_R[k], lay.child_p[k])
            h["axis"][w_, k] = lay.axis[k]
            h["com"][w_, k] = body.com
            h["effort"][w_, k] = np.inf
            init["q"][w_, k] = lay.q0[k]
            init["u"][w_, k] = lay.u0[k]
            if kind in (KIND_LINEAR, KIND_ANGULAR):
                h["body_out"][w_, k] = -1
                h["inertia"][w_, k] = 0.0
                continue
            h["body_out"][w_, k] = lay.tree_body[k]
            h["mass"][w_, k] = body.mass
            h["inertia"][w_, k] = body.inertia
            if kind == KIND_ROOT:
                init["root"][w_, k] = np.concatenate((lay.parent_p[k] + lay.parent_R[k] @ np.asarray(body.com),
                                                       body.orientation))
                continue
            joint = spec.joints[lay.joint[k]]
            h["armature"][w_, k] = joint.armature
            h["damping"][w_, k] = joint.damping
            if joint.drive is not None:
                h["kp"][w_, k] = joint.drive.stiffness
                h["kd"][w_, k] = joint.drive.damping
                h["q_target"][w_, k] = joint.drive.target_position
                h["v_target"][w_, k] = joint.drive.target_velocity
                h["effort"][w_, k] = joint.drive.effort_limit
        tree_index = {b: k for k, b in enumerate(lay.tree_body) if lay.kind[k] in (KIND_REVOLUTE, KIND_ROOT)}
        _pack_forces(h, w_, lay, tree_index)
        _pack_control(h, w_, lay, tree_index)
        h["shape_count"][w_] = len(lay.shapes)
        h["contact_capacity"][w_] = _capacity(lay, contact_capacity)
        h["prefix"][w_] = _prefix(level)
        if spec.ground is not None:
            if spec.ground.relief is not None:  # (engine.pack's plan refuses it first)
                raise ValueError(f"mechanism '{spec.name}': its ground has relief, which only the tabulated plan "
                                 f"simulates")
            h["ground_normal"][w_], h["ground_offset"][w_] = spec.ground.normal, spec.ground.offset
        for s, si in enumerate(lay.shapes):
            shape = spec.shapes[si]
            h["shape_entry"][w_, s] = tree_index[spec.body_index[shape.body]]
            h["shape_type"][w_, s] = int(shape.type)
            h["shape_X"][w_, s] = np.concatenate((shape.position, shape.orientation))
            h["shape_size"][w_, s] = shape.size
            h["shape_mu"][w_, s] = math.sqrt(shape.friction * spec.ground.friction)
        for li in range(len(lay.loops)):
            for side in range(2):
                h["loop_body"][w_, li, side] = lay.loop_body[li, side]
                h["loop_anchor"][w_, li, side] = _transform(lay.loop_R[li, side], lay.loop_p[li, side])
            h["loop_axis"][w_, li] = lay.axis_of_loop(li)
            h["loop_inline"][w_, li] = li in lay.inline
            h["loop_t1"][w_, li], h["loop_t2"][w_, li] = lay.loop_dirs[li, 3], lay.loop_dirs[li, 4]
        h["row_loop"][w_, :len(lay.rows)] = lay.rows[:, 0]
        h["row_part"][w_, :len(lay.rows)] = lay.rows[:, 1]
        for s, li in enumerate(lay.soft):  # armature and damping of a loop joint: a soft row on its rate
            joint = spec.joints[lay.loops[li]]
            r = len(lay.rows) + s
            h["row_loop"][w_, r], h["row_part"][w_, r] = li, 5
            gain = joint.armature + dt * joint.damping
            h["row_compliance"][w_, r], h["row_keep"][w_, r] = 1.0 / gain, joint.armature / gain
        for i, body in enumerate(spec.bodies):
            R = quat_matrix(body.orientation)
            init["body_q"][w_, i] = np.concatenate((np.asarray(body.position) + R @ np.asarray(body.com),
                                                     body.orientation))
    # every world from its distinct spec's rows
    h = {k: v[kind_of] for k, v in h.items()}
    init = {k: v[kind_of] for k, v in init.items()}
    layouts = [layouts[k] for k in kind_of]
    W = len(specs)
    dev = device
    a, loads = ChainArrays(), ChainLoads()
    for name, value in h.items():
        dtype = ARRAY_TYPES.get(name, wp.int32 if value.dtype == np.int32 else float)
        setattr(loads if name in LOAD_FIELDS else a, name, wp.array(value, dtype=dtype, device=dev))
    k = ChainWork()
    for name, dtype in (("pose", wp.transform), ("centre", wp.vec3), ("lin", wp.vec3), ("axis", wp.vec3),
                        ("omega", wp.vec3), ("vel", wp.vec3), ("alpha", wp.vec3), ("acc", wp.vec3),
                        ("inertia", wp.mat33), ("wrench_t", wp.vec3), ("wrench_f", wp.vec3), ("force_n", wp.vec3),
                        ("force_f", wp.vec3), ("sub_mass", float), ("sub_moment", wp.vec3), ("sub_inertia", wp.mat33),
                        ("q_start", float), ("u_start", float), ("root_start", wp.transform)):
        setattr(k, name, wp.zeros((W, N), dtype=dtype, device=dev))
    for name in ("diverged", "contact_count", "contact_dropped", "contact_overflow", "contact_redone", "iterations",
                 "projections"):
        setattr(k, name, wp.zeros(W, dtype=wp.int32, device=dev))
    k.phi = wp.zeros((W, 6 * L), dtype=float, device=dev)
    k.dirs = wp.zeros((W, 6 * L), dtype=wp.vec3, device=dev)
    k.ends = wp.zeros((W, 2 * L), dtype=wp.vec3, device=dev)
    k.contact_slot = wp.zeros((W, MAX_CONTACTS), dtype=wp.int32, device=dev)
    k.contact_impulse = wp.zeros((W, 4 * S), dtype=wp.vec3, device=dev)  # a slot per candidate (4 per shape)
    k.contact_rho = wp.zeros(W, dtype=float, device=dev)
    k.stage_clock = wp.zeros((1, 1), dtype=wp.int64, device=dev)  # ChainModel.step(stages=True) sizes it
    k.matrix = wp.zeros((1, 1, 1), dtype=float, device=dev)  # ChainModel.step(record=True) sizes them
    k.rows = wp.zeros((1, 1, 1), dtype=float, device=dev)
    model = ChainModel(layouts, a, k, init, config, float(dt), device, int(h["contact_capacity"].max()), loads)
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


def _pack_forces(h: dict, w_: int, lay: ChainLayout, tree_index: dict) -> None:
    """World w_'s force slots (ChainArrays.force_*, chain_stages.apply_forces): each side's tree entry
    and frame in that body's frame, or -1 and the frame in the world for the world and bodies
    welded to it (whose wrenches go nowhere)."""

    def side(name, R, p):  # (entry, frame as a transform) of a frame (R, p) in body ``name``'s frame
        b = None if name is None else lay.spec.body_index[name]
        if b in tree_index:
            return tree_index[b], _transform(R, p)
        if b is not None:  # welded to the world
            Rf, pf = lay.fixed[b]
            R, p = Rf @ R, pf + Rf @ p
        return -1, _transform(R, p)

    pack_force_slots(h, w_, lay.spec, side)


def pack_force_slots(h: dict, w_: int, spec: MechanismSpec, side) -> None:
    """World w_'s force slots in h's force_count, force_kind, force_entry (W, F, 2), force_frame
    (W, F, 2, 7), force_vec (W, F, 2, 3) and force_coef (W, F, 4) from ``spec``'s force elements, for
    a reduced plan whose ``side(body name or None, R, p)`` gives the entry a frame (R, p) in that
    body's frame moves with and the frame as a transform relative to it: a spring-damper's points
    (coef: stiffness, damping, rest length, tension only), a body wrench's body (vec: force,
    torque), a joint element's child then parent anchor frames (vec: the axis; coef: stiffness,
    damping, rest position, or the effort last)."""
    eye = np.eye(3)
    h["force_count"][w_] = len(spec.forces)
    for f, item in enumerate(spec.forces):
        if isinstance(item, LinearSpring):
            kind = FORCE_LINEAR_SPRING
            sides = [side(item.body_a, eye, item.point_a), side(item.body_b, eye, item.point_b)]
            coef = (item.stiffness, item.damping, item.rest_length, float(item.tension_only))
        elif isinstance(item, BodyWrench):
            kind = FORCE_BODY_WRENCH
            sides = [side(item.body, eye, np.zeros(3))]
            h["force_vec"][w_, f] = item.force, item.torque
            coef = (0.0, 0.0, 0.0, 0.0)
        else:  # a JointSpring or JointTorque on a revolute joint (the reduced plans take no other with either)
            joint = spec.joints[[j.name for j in spec.joints].index(item.joint)]
            sides = [side(joint.child, quat_matrix(joint.child_orientation), np.asarray(joint.child_position)),
                     side(joint.parent, quat_matrix(joint.parent_orientation), np.asarray(joint.parent_position))]
            h["force_vec"][w_, f, 0] = joint.axis
            if isinstance(item, JointSpring):
                kind = FORCE_JOINT_SPRING
                coef = (item.stiffness, item.damping, item.rest_position, 0.0)
            else:
                kind = FORCE_JOINT_TORQUE
                coef = (0.0, 0.0, 0.0, item.effort)
        h["force_kind"][w_, f] = kind
        h["force_coef"][w_, f] = coef
        for s, (entry, frame) in enumerate(sides):
            h["force_entry"][w_, f, s] = entry
            h["force_frame"][w_, f, s] = frame


def check_control_arrays(control, plan: str, num_worlds: int, max_bodies: int, max_joints: int, device) -> None:
    """Raise ValueError unless ``control`` has body_f (W, >= B) spatial_vector and joint_effort
    (W, >= J) float arrays on ``device``, and refuse a Control with drive targets (the maximal
    plan's): a reduced plan takes its targets from the specs and would not read them."""
    if any(hasattr(control, name) for name in ("joint_target_position", "joint_target_velocity")):
        raise ValueError(f"control: the {plan} plan takes its drive targets from the specs and would not read this "
                         f"Control's joint_target_* arrays; step it with model.control() (body_f, joint_effort), "
                         f"or pack with coordinates='maximal' to drive the targets from a Control")
    for name, dtype, count in (("body_f", wp.spatial_vector, max_bodies), ("joint_effort", wp.float32, max_joints)):
        a = getattr(control, name, None)
        if not isinstance(a, wp.array) or a.ndim != 2 or a.dtype != dtype or a.shape[0] != num_worlds \
                or a.shape[1] < count or a.device != wp.get_device(device):
            raise ValueError(f"control: the {plan} plan reads {name} as a ({num_worlds}, {count}) "
                             f"{dtype.__name__} array on {device} (model.control() makes one), got "
                             f"{getattr(a, 'shape', None) if a is not None else 'none'}")


def _pack_control(h: dict, w_: int, lay: ChainLayout, tree_index: dict) -> None:
    """World w_'s Control targets (ChainArrays.control_*, chain_stages.apply_control): each spec
    body's tree entry, and each revolute joint's sides (child, parent) with its parent anchor frame
    and axis, a side welded to the world as -1 with the frame in the world."""
    spec = lay.spec
    for b in range(len(spec.bodies)):
        h["control_body"][w_, b] = tree_index.get(b, -1)
    for j, joint in enumerate(spec.joints):
        if joint.type != JointType.REVOLUTE:  # (the tree takes revolute, inline and fixed joints)
            continue
        R, p = quat_matrix(joint.parent_orientation), np.asarray(joint.parent_position, float)
        sides = []
        for name in (joint.child, joint.parent):
            b = None if name is None else spec.body_index[name]
            sides.append(tree_index.get(b, -1) if b is not None else -1)
        if sides[1] < 0 and joint.parent is not None:  # the parent welded to the world: its anchor in the world
            Rf, pf = lay.fixed[spec.body_index[joint.parent]]
            R, p = Rf @ R, pf + Rf @ p
        h["control_joint"][w_, j] = sides
        h["control_frame"][w_, j] = _transform(R, p)
        h["control_axis"][w_, j] = joint.axis


class ChainControl:
    """A Control of the reduced plans (ChainModel.control, TabulatedModel.control): body_f (W, B)
    spatial_vector, each spec body's external wrench (force [N], torque [N m]) at its centre of
    mass, world frame; joint_effort (W, J) float, each revolute spec joint's torque [N m] (on its
    child, its opposite on its parent). Drive targets come from the specs."""

    def __init__(self, body_f, joint_effort):
        self.body_f, self.joint_effort = body_f, joint_effort


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
        body_out(m, w, world, k, body_q, body_qd)

