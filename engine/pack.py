"""pack_worlds: turn a list of MechanismSpec (all different, if you like) into one padded Model."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import warp as wp

from engine.collide import PAIR_CONTACTS, PAIR_SLOTS, PLANE_CONTACTS
from engine.fused import FUSED_MAX_ROWS, FUSED_REGISTERS, fused_fits
from engine.health import far_flags
from engine.config import MAXIMAL_RHO, SolverConfig
from engine.model import Model, Workspace
from engine.plan import ORDER, Coordinates, Plan, choose, fastest
from engine.linalg.sparse_analysis import batch_schedule_cost, bilateral_factor_rows, build_patterns, make_system
from engine.spatial import rotate
from engine.forces import BodyWrench, JointSpring, JointTorque, LinearSpring
from engine.spec import JOINT_ROW_COUNT, JointType, MechanismSpec, joint_dynamics_rows

__all__ = ["MAX_DENSE_ROWS", "dense_rows_needed", "pack", "pack_worlds"]

ROW_KINDS = {  # bilateral row kinds per joint type: 0 linear [m], 1 angular [rad]
    JointType.REVOLUTE: (0, 0, 0, 1, 1),
    JointType.PRISMATIC: (0, 0, 1, 1, 1),
    JointType.SPHERICAL: (0, 0, 0),
    JointType.UNIVERSAL: (0, 0, 0, 1),
    JointType.CYLINDRICAL: (0, 0, 1, 1),
    JointType.FIXED: (0, 0, 0, 1, 1, 1),
    JointType.INLINE: (0, 0),
}
ROW_TILE = 8  # the padded row count is a multiple of this (tile size of the Delassus matrix)
MAX_DENSE_ROWS = 144  # largest per-world Delassus tile the dense solver factors in on-chip memory


def collision_pairs(spec: MechanismSpec) -> list[tuple[int, int]]:
    """Shape pairs (a, b) that may touch, b = -1 for the ground plane, a of lower or equal type.

    Filtered out: shapes of one body, bodies joined by a joint, shapes sharing a non-zero
    collision group, and cylinders against anything but the plane.
    """
    index = spec.body_index
    jointed = {frozenset((index[j.parent], index[j.child])) for j in spec.joints if j.parent is not None}
    pairs = [(s, -1) for s in range(len(spec.shapes))] if spec.ground is not None else []
    for i, a in enumerate(spec.shapes):
        for j in range(i + 1, len(spec.shapes)):
            b = spec.shapes[j]
            ba, bb = index[a.body], index[b.body]
            if ba == bb or frozenset((ba, bb)) in jointed:
                continue
            if a.collision_group and a.collision_group == b.collision_group:
                continue
            first, second = (i, j) if a.type <= b.type else (j, i)
            types = (spec.shapes[first].type, spec.shapes[second].type)
            if types in PAIR_CONTACTS:
                pairs.append((first, second))
    return pairs


def pair_contacts(spec: MechanismSpec, a: int, b: int) -> int:
    """Most contacts shapes a and b (b = -1: the ground plane) can produce at once."""
    return PLANE_CONTACTS[spec.shapes[a].type] if b < 0 else PAIR_CONTACTS[(spec.shapes[a].type, spec.shapes[b].type)]


def contact_worst_case(spec: MechanismSpec, pairs) -> int:
    """Most contacts the pairs of a world can produce at once."""
    return sum(pair_contacts(spec, a, b) for a, b in pairs)


def default_contact_capacity(spec: MechanismSpec) -> int:
    """Contacts per step a world keeps by default: what its pairs can produce, at most 4 per shape + 8."""
    return min(contact_worst_case(spec, collision_pairs(spec)), 4 * len(spec.shapes) + 8)


def dense_rows_needed(spec: MechanismSpec, contact_capacity: int | None = None) -> int:
    """Constraint rows of a world in the dense solver: joint, drive and limit rows + 3 per contact."""
    capacity = default_contact_capacity(spec) if contact_capacity is None else contact_capacity
    return spec.row_count + 3 * capacity


def body_row_lists(row_body_c: np.ndarray, row_body_p: np.ndarray, contact_row_start: np.ndarray, bodies: int):
    """Per world, each body's joint, drive and limit rows (those below contact_row_start, whose
    bodies never change) in row order, coded 2 i + side (side 0: the body is the row's child, 1:
    its parent): (W, B) begin and end into the (W, K) codes. engine.integrate.row_sum_listed sums a
    body's rows through them, in the order a scan of all rows would."""
    W = len(row_body_c)
    begin = np.zeros((W, bodies), np.int32)
    end = np.zeros((W, bodies), np.int32)
    lists = []
    for w in range(W):
        rows = np.arange(int(contact_row_start[w]))
        codes = np.concatenate([2 * rows, 2 * rows + 1])
        owner = np.concatenate([row_body_c[w, rows], row_body_p[w, rows]])
        keep = owner >= 0
        codes, owner = codes[keep], owner[keep]
        order = np.lexsort((codes, owner))  # by body, then by row (a row never has one body on both sides)
        codes, owner = codes[order], owner[order]
        counts = np.bincount(owner, minlength=bodies)[:bodies]
        end[w] = np.cumsum(counts)
        begin[w] = end[w] - counts
        lists.append(codes)
    out = np.zeros((W, max(1, max(len(c) for c in lists))), np.int32)
    for w, codes in enumerate(lists):
        out[w, :len(codes)] = codes
    return begin, end, out


def factor_rows(specs, pairs, h) -> tuple[np.ndarray, np.ndarray]:
    """The rows of the sparse solver's factor (engine.linalg.sparse) and their bodies, per world: the
    joint rows, then three rows for each candidate contact slot of every collision pair (pair p,
    slot m: rows start + 3 (4 p + m) ..; slots a pair never fills are padding), so that a contact
    row always sits where its bodies are known in advance; then padding to the batch's largest.
    Returns (body_c, body_p), each (W, factor rows)."""
    sizes = [int(h["contact_row_start"][w]) + 3 * PAIR_SLOTS * len(pairs[w]) for w in range(len(specs))]
    V = max(max(sizes), 1)
    body_c = np.full((len(specs), V), -1, np.int32)
    body_p = np.full((len(specs), V), -1, np.int32)
    for w, spec in enumerate(specs):
        start = int(h["contact_row_start"][w])
        body_c[w, :start] = h["row_body_c"][w, :start]
        body_p[w, :start] = h["row_body_p"][w, :start]
        for p, (a, b) in enumerate(pairs[w]):
            rows = slice(start + 3 * PAIR_SLOTS * p, start + 3 * (PAIR_SLOTS * p + pair_contacts(spec, a, b)))
            body_c[w, rows] = h["shape_body"][w, a]
            body_p[w, rows] = -1 if b < 0 else h["shape_body"][w, b]
    return body_c, body_p


def _pack_joints(h: dict, w: int, joints: list, index: dict, coms: list) -> int:
    """World w's joint entries and joint, drive and limit rows in the host arrays ``h``, each joint's
    numbers written in one array assignment per field; returns the world's row count."""
    if not joints:
        return 0
    n = len(joints)
    parent = [-1 if joint.parent is None else index[joint.parent] for joint in joints]
    child = [index[joint.child] for joint in joints]
    zero = np.zeros(3)
    h["joint_type"][w, :n] = [int(joint.type) for joint in joints]
    h["joint_parent"][w, :n] = parent
    h["joint_child"][w, :n] = child
    h["joint_X_p"][w, :n] = np.concatenate([
        np.array([joint.parent_position for joint in joints], float) - np.array([zero if p < 0 else coms[p] for p in parent]),
        np.array([joint.parent_orientation for joint in joints], float)], axis=1)
    h["joint_X_c"][w, :n] = np.concatenate([
        np.array([joint.child_position for joint in joints], float) - np.array([coms[c] for c in child]),
        np.array([joint.child_orientation for joint in joints], float)], axis=1)
    h["joint_axis"][w, :n] = [joint.axis for joint in joints]
    h["joint_axis2"][w, :n] = [joint.axis2 for joint in joints]
    h["joint_armature"][w, :n] = [joint.armature for joint in joints]
    h["joint_damping"][w, :n] = [joint.damping for joint in joints]
    row, starts, kinds, bodies_p, bodies_c = 0, [], [], [], []
    for j, joint in enumerate(joints):
        starts.append(row)
        joint_kinds = ROW_KINDS[joint.type]
        assert len(joint_kinds) == JOINT_ROW_COUNT[joint.type]
        extra = [kind for kind, present in zip((2, 2), joint_dynamics_rows(joint)) if present]
        sides = joint.limit_sides
        count = len(joint_kinds) + len(extra) + len(sides)
        kinds += [*joint_kinds, *extra, *([3] * len(sides))]
        bodies_p += [parent[j]] * count
        bodies_c += [child[j]] * count
        row += len(joint_kinds)
        if joint.drive is not None:
            drive = joint.drive
            h["joint_stiffness"][w, j] = drive.stiffness
            h["joint_drive_damping"][w, j] = drive.damping
            h["joint_effort_limit"][w, j] = min(drive.effort_limit, 1.0e30)
            h["joint_target_position_init"][w, j] = drive.target_position
            h["joint_target_velocity_init"][w, j] = drive.target_velocity
        for name, present in zip(("joint_inertia_row", "joint_drive_row"), joint_dynamics_rows(joint)):
            if present:
                h[name][w, j] = row
                row += 1
        for side in sides:
            name = "lower" if side > 0 else "upper"
            h[f"joint_limit_{name}"][w, j] = getattr(joint, f"limit_{name}")
            h[f"joint_limit_{name}_row"][w, j] = row
            row += 1
    h["joint_row_start"][w, :n] = starts
    h["row_kind"][w, :row] = kinds
    h["row_body_p"][w, :row] = bodies_p
    h["row_body_c"][w, :row] = bodies_c
    return row


FORCE_KINDS = {LinearSpring: 0, JointSpring: 1, BodyWrench: 2, JointTorque: 3}  # engine.model FORCE_*
FORCE_JOINT_EFFORT_SLOT = 4


def pack_forces(specs: Sequence[MechanismSpec]) -> dict:
    """Host arrays of the force slots (engine.model.ForceArrays) of every world: its spec's force
    elements in order, then a FORCE_JOINT_EFFORT slot per undriven revolute or prismatic joint
    (Control.joint_effort there; a drive's row takes it on a driven joint). Points in COM frames."""
    slots = []
    for spec in specs:
        undriven = [j for j, joint in enumerate(spec.joints) if joint.drive is None and
                    joint.type in (JointType.REVOLUTE, JointType.PRISMATIC)]
        slots.append(len(spec.forces) + len(undriven))
    W, F = len(specs), max(1, max(slots))
    f32 = np.float32
    h = {"force_count": np.array(slots, np.int32), "force_kind": np.zeros((W, F), np.int32),
         "force_body_a": np.full((W, F), -1, np.int32), "force_body_b": np.full((W, F), -1, np.int32),
         "force_joint": np.zeros((W, F), np.int32), "force_point_a": np.zeros((W, F, 3), f32),
         "force_point_b": np.zeros((W, F, 3), f32), "force_stiffness": np.zeros((W, F), f32),
         "force_damping": np.zeros((W, F), f32), "force_rest": np.zeros((W, F), f32),
         "force_tension_only": np.zeros((W, F), np.int32), "force_force": np.zeros((W, F, 3), f32),
         "force_torque": np.zeros((W, F, 3), f32), "force_effort": np.zeros((W, F), f32)}
    for w, spec in enumerate(specs):
        if not slots[w]:
            continue
        index = spec.body_index
        joint_index = {joint.name: j for j, joint in enumerate(spec.joints)}

        def joint_slot(k, j, kind):
            joint = spec.joints[j]
            h["force_kind"][w, k] = kind
            h["force_joint"][w, k] = j
            h["force_body_a"][w, k] = index[joint.child]
            h["force_body_b"][w, k] = -1 if joint.parent is None else index[joint.parent]

        for k, item in enumerate(spec.forces):
            kind = FORCE_KINDS[type(item)]
            if isinstance(item, LinearSpring):
                a = index[item.body_a]
                b = -1 if item.body_b is None else index[item.body_b]
                h["force_kind"][w, k] = kind
                h["force_body_a"][w, k], h["force_body_b"][w, k] = a, b
                h["force_point_a"][w, k] = item.point_a - spec.bodies[a].com
                h["force_point_b"][w, k] = item.point_b - (0.0 if b < 0 else spec.bodies[b].com)
                h["force_stiffness"][w, k], h["force_damping"][w, k] = item.stiffness, item.damping
                h["force_rest"][w, k] = item.rest_length
                h["force_tension_only"][w, k] = int(item.tension_only)
            elif isinstance(item, BodyWrench):
                h["force_kind"][w, k] = kind
                h["force_body_a"][w, k] = index[item.body]
                h["force_force"][w, k], h["force_torque"][w, k] = item.force, item.torque
            else:
                joint_slot(k, joint_index[item.joint], kind)
                if isinstance(item, JointSpring):
                    h["force_stiffness"][w, k], h["force_damping"][w, k] = item.stiffness, item.damping
                    h["force_rest"][w, k] = item.rest_position
                else:
                    h["force_effort"][w, k] = item.effort
        k = len(spec.forces)
        for j, joint in enumerate(spec.joints):
            if joint.drive is None and joint.type in (JointType.REVOLUTE, JointType.PRISMATIC):
                joint_slot(k, j, FORCE_JOINT_EFFORT_SLOT)
                k += 1
    # each body's slots, as lists: force_body_slot[w, force_body_start[w, b]:force_body_start[w, b + 1]]
    B = max(len(spec.bodies) for spec in specs)
    h["force_body_start"] = np.zeros((W, B + 1), np.int32)
    h["force_body_slot"] = np.zeros((W, 2 * F), np.int32)
    for w in range(W):
        n = slots[w]
        sides = np.concatenate([h["force_body_a"][w, :n], h["force_body_b"][w, :n]])
        slot = np.arange(2 * n) % max(n, 1)
        order = np.lexsort((slot, sides))  # by body, then in slot order
        on_body = order[sides[order] >= 0]
        h["force_body_slot"][w, :len(on_body)] = slot[on_body]
        h["force_body_start"][w] = np.searchsorted(sides[on_body], np.arange(B + 1))
    return h


def force_summary(specs: Sequence[MechanismSpec]) -> str:
    """The batch's force elements counted by kind ("2 spring-dampers, 1 body wrench"), or "none"."""
    names = {LinearSpring: ("spring-damper", "spring-dampers"), JointSpring: ("joint spring", "joint springs"),
             BodyWrench: ("body wrench", "body wrenches"), JointTorque: ("joint torque", "joint torques")}
    counts = dict.fromkeys(names, 0)
    for spec in specs:
        for item in spec.forces:
            counts[type(item)] += 1
    parts = [f"{n} {names[t][n != 1]}" for t, n in counts.items() if n]
    return ", ".join(parts) if parts else "none"


def pack(specs: Sequence[MechanismSpec], device=None, *, config: SolverConfig | None = None, dt: float = 1.0e-3,
         contact_capacity: int | None = None, coordinates=None, prepared=None):
    """Pack one world per spec into a batch on ``device``, in the coordinates and kernels the plan
    chooses (engine.plan; ``print(model.plan)`` says which and why).

    Args:
        specs: the worlds (MechanismSpec); they may differ in everything.
        device: Warp device ("cpu", "cuda", ...); None = Warp's default.
        config: SolverConfig (default settings when None).
        dt: time step of every world [s].
        contact_capacity: contacts kept per world and step (None: what the shapes can produce).
        coordinates: None (automatic) or an engine.plan.Coordinates (or its value: "grounded",
            "tabulated", "tree", "maximal") to force, for benchmarks and tests; a world it does not fit raises
            ValueError naming the world and the reason.
        prepared: engine.prepare(specs) made ahead (in the processes that built the specs), for
            these specs unchanged since; None: the analysis runs here.

    Returns:
        the packed model for engine.step / engine.Stepper / engine.rollout: an engine.Model for
        maximal coordinates, an engine.reduced.model.ReducedModel for reduced ones, an
        engine.grouped.GroupedModel (one of those per group) where the worlds admit different
        coordinates; each carries ``plan``.
    """
    specs, config = _checked_arguments("pack", specs, config, dt, contact_capacity, "a positive number of seconds")
    device = wp.get_device(device)
    if prepared is not None and len(prepared) != len(specs):
        raise ValueError(f"engine.pack: prepared has {len(prepared)} entries for {len(specs)} specs")
    if coordinates is not None:
        plan, layouts = choose(specs, device, coordinates, contact_capacity, prepared)
        return _pack_planned(specs, plan, layouts, device, config, dt, contact_capacity)
    kinds, layouts, refused = fastest(specs, contact_capacity, prepared)
    order = [kind for kind in ORDER if kind in kinds]
    if len(order) == 1:
        plan = Plan(order[0], len(specs), str(device), refused=refused)
        return _pack_planned(specs, plan, None if order[0] is Coordinates.MAXIMAL else layouts, device, config, dt,
                             contact_capacity)
    from engine.grouped import GroupedModel, grouped_plan
    groups = []
    for kind in order:  # each group in the fastest coordinates its worlds admit
        indices = [w for w, k in enumerate(kinds) if k is kind]
        plan = Plan(kind, len(indices), str(device), refused=[(k, r) for k, r in refused if ORDER.index(k) <
                                                                ORDER.index(kind)])
        part = _pack_planned([specs[w] for w in indices], plan, None if kind is Coordinates.MAXIMAL else
                             [layouts[w] for w in indices], device, config, dt, contact_capacity)
        groups.append((indices, part))
    plan = grouped_plan([part.plan for _, part in groups], [len(i) for i, _ in groups], device)
    return GroupedModel(groups, specs, plan, config, dt, device)


def _pack_planned(specs, plan, layouts, device, config, dt, contact_capacity):
    """The packed model of ``plan`` (one kind of coordinates for every world of ``specs``)."""
    from engine.plan import describe_maximal, describe_reduced

    if plan.coordinates is Coordinates.MAXIMAL:
        model = pack_worlds(specs, device, config=config, dt=dt, contact_capacity=contact_capacity)
        model.plan = describe_maximal(plan, model)
        return model
    if plan.coordinates is Coordinates.GROUNDED:
        from engine.reduced.grounded import pack_grounded
        from engine.reduced.model import GroundedPlanModel
        inner = pack_grounded(specs, device, dt=dt, max_speed=config.max_speed, layouts=layouts)
        model = GroundedPlanModel(inner, specs, plan, config, dt, device)
    elif plan.coordinates is Coordinates.TREE:
        from engine.reduced.chains import pack_chains
        from engine.reduced.model import TreeModel
        inner = pack_chains(specs, device, config=config, dt=dt, contact_capacity=contact_capacity, layouts=layouts)
        model = TreeModel(inner, specs, plan, config, dt, device)
    else:
        from engine.reduced.model import TabulatedPlanModel
        from engine.reduced.tabulated import pack_tabulated
        inner = pack_tabulated(specs, device=device, dt=dt, config=config, layouts=layouts)
        model = TabulatedPlanModel(inner, specs, plan, config, dt, device)
    describe_reduced(plan, model)
    return model


def _checked_arguments(who: str, specs, config, dt, contact_capacity, dt_rule: str) -> tuple[list, SolverConfig]:
    """``specs`` as a list and ``config`` (default settings when None), after checking them, ``dt``
    (``dt_rule`` says what it must be) and ``contact_capacity``: ValueError naming ``who``."""
    if isinstance(specs, (MechanismSpec, str, bytes)) or not hasattr(specs, "__iter__"):
        raise ValueError(f"{who}: specs must be a list of MechanismSpec, got {type(specs).__name__}")
    specs = list(specs)
    if not specs:
        raise ValueError(f"{who}: needs at least one MechanismSpec")
    for index, spec in enumerate(specs):
        if not isinstance(spec, MechanismSpec):
            raise ValueError(f"{who}: world {index} is a {type(spec).__name__}, expected MechanismSpec")
    config = config or SolverConfig()
    if not isinstance(config, SolverConfig):
        raise ValueError(f"{who}: config must be a SolverConfig, got {type(config).__name__}")
    try:
        dt_ok = not isinstance(dt, bool) and math.isfinite(float(dt)) and float(dt) > 0.0
    except (TypeError, ValueError):
        dt_ok = False
    if not dt_ok:
        raise ValueError(f"{who}: dt must be {dt_rule}, got {dt!r}")
    integral = isinstance(contact_capacity, (int, np.integer)) and not isinstance(contact_capacity, bool)
    if contact_capacity is not None and not (integral and contact_capacity >= 0):
        raise ValueError(f"{who}: contact_capacity must be a non-negative integer, got {contact_capacity!r}")
    return specs, config


def pack_worlds(specs: Sequence[MechanismSpec], device=None, *, config: SolverConfig | None = None,
                dt: float = 1.0e-3, contact_capacity: int | None = None, measure_only: bool = False) -> Model:
    """Pack one world per spec into a padded batch in maximal coordinates on ``device`` (the
    MAXIMAL plan's packer; engine.pack chooses the plan).

    Args:
        specs: the worlds; they may differ in bodies, joints and constraint rows.
        device: Warp device ("cpu", "cuda", "cuda:0", ...); None = Warp's default.
        config: SolverConfig (default settings when None).
        dt: initial time step of every world [s] (change it with Model.set_dt or step()).
        contact_capacity: contacts kept per world and step; None = the smaller of what the
            world's shape pairs can produce and 4 per shape + 8. A world that produces more is
            counted in model.work.contact_dropped (never silently wrong, never a crash).
        measure_only: a model that only measures states of these worlds (joint residuals, energy,
            tracked points: a reduced plan's gauge): no solver set-up (no sparse factor schedule).

    Returns:
        Model with arrays of shape (num_worlds, max_X) and per-world counts.
    """
    specs, config = _checked_arguments("pack_worlds", specs, config, dt, contact_capacity,
                                       "a positive finite time step [s]")
    tuning = config.tuning
    try:
        device = wp.get_device(device)
    except (RuntimeError, ValueError) as exc:  # Warp: unknown identifier, or CUDA not available
        raise ValueError(f"pack_worlds: device {device!r} is not available ('cpu', 'cuda' or 'cuda:N'): {exc}") from exc

    num_worlds = len(specs)
    max_bodies = max(len(s.bodies) for s in specs)
    max_joints = max(1, max(len(s.joints) for s in specs))
    max_points = max(1, max(len(s.points) for s in specs))
    pairs = [collision_pairs(s) for s in specs]
    worst = [contact_worst_case(s, p) for s, p in zip(specs, pairs)]
    if contact_capacity is None:
        capacity = max(min(w, 4 * len(s.shapes) + 8) for s, w in zip(specs, worst))
    else:
        capacity = min(int(contact_capacity), max(worst))
    if tuning.linear_solver == "dense":
        for index, spec in enumerate(specs):
            rows = spec.row_count + 3 * capacity
            if rows > MAX_DENSE_ROWS:
                raise ValueError(f"pack_worlds: world {index} ('{spec.name}') needs {rows} constraint rows "
                                 f"({spec.row_count} joint/drive/limit rows + 3 x {capacity} contacts); the dense "
                                 f"solver takes at most {MAX_DENSE_ROWS} per world: use Tuning(linear_solver='sparse') "
                                 f"or 'auto', lower contact_capacity or simplify the mechanism")
    max_pairs = max(len(p) for p in pairs)
    max_shapes = max(1, max(len(s.shapes) for s in specs))
    max_rows = max(1, max(s.row_count for s in specs) + 3 * capacity)
    max_rows = ROW_TILE * ((max_rows + ROW_TILE - 1) // ROW_TILE)
    dense = tuning.linear_solver == "dense" or (tuning.linear_solver == "auto" and max_rows <= MAX_DENSE_ROWS)
    sparse = not dense and tuning.linear_solver in ("auto", "sparse") and not measure_only

    W, B, J, R, P, S, Q = num_worlds, max_bodies, max_joints, max_rows, max_points, max_shapes, max(max_pairs, 1)
    f32 = np.float32
    h = {
        "body_count": np.zeros(W, np.int32), "joint_count": np.zeros(W, np.int32),
        "row_count": np.zeros(W, np.int32), "point_count": np.zeros(W, np.int32),
        "body_mass": np.zeros((W, B), f32), "body_inv_mass": np.zeros((W, B), f32),
        "body_inertia": np.tile(np.eye(3, dtype=f32), (W, B, 1, 1)),
        "body_inv_inertia": np.tile(np.eye(3, dtype=f32), (W, B, 1, 1)),
        "body_q_init": np.tile(np.array([0, 0, 0, 0, 0, 0, 1], f32), (W, B, 1)),
        "body_qd_init": np.zeros((W, B, 6), f32),
        "joint_type": np.zeros((W, J), np.int32), "joint_parent": np.full((W, J), -1, np.int32),
        "joint_child": np.zeros((W, J), np.int32),
        "joint_X_p": np.tile(np.array([0, 0, 0, 0, 0, 0, 1], f32), (W, J, 1)),
        "joint_X_c": np.tile(np.array([0, 0, 0, 0, 0, 0, 1], f32), (W, J, 1)),
        "joint_axis": np.zeros((W, J, 3), f32), "joint_axis2": np.zeros((W, J, 3), f32),
        "joint_row_start": np.zeros((W, J), np.int32), "joint_inertia_row": np.full((W, J), -1, np.int32),
        "joint_drive_row": np.full((W, J), -1, np.int32),
        "joint_armature": np.zeros((W, J), f32), "joint_damping": np.zeros((W, J), f32),
        "joint_stiffness": np.zeros((W, J), f32), "joint_drive_damping": np.zeros((W, J), f32),
        "joint_effort_limit": np.full((W, J), 1.0e30, f32),
        "joint_target_position_init": np.zeros((W, J), f32),
        "joint_target_velocity_init": np.zeros((W, J), f32),
        "row_kind": np.zeros((W, R), np.int32), "row_body_p": np.full((W, R), -1, np.int32),
        "row_body_c": np.full((W, R), -1, np.int32),
        "world_gravity": np.zeros((W, 3), f32), "world_dt": np.full(W, dt, f32),
        "point_body": np.zeros((W, P), np.int32), "point_local": np.zeros((W, P, 3), f32),
        "padmm_eta": np.full(W, tuning.eta, f32), "padmm_rho_init": np.full(W, tuning.rho_or(MAXIMAL_RHO), f32),
        "padmm_rho_free": np.full(W, tuning.free_rho if tuning.cap_joint_penalty else 0.0, f32),
        "padmm_tolerance": np.full(W, config.tolerance, f32),
        "joint_limit_lower": np.full((W, J), -1.0e30, f32), "joint_limit_upper": np.full((W, J), 1.0e30, f32),
        "joint_limit_lower_row": np.full((W, J), -1, np.int32), "joint_limit_upper_row": np.full((W, J), -1, np.int32),
        "shape_count": np.zeros(W, np.int32), "shape_type": np.zeros((W, S), np.int32),
        "shape_body": np.zeros((W, S), np.int32), "shape_X": np.tile(np.array([0, 0, 0, 0, 0, 0, 1], f32), (W, S, 1)),
        "shape_size": np.zeros((W, S, 3), f32), "shape_friction": np.zeros((W, S), f32),
        "shape_restitution": np.zeros((W, S), f32),
        "ground_normal": np.tile(np.array([0, 0, 1], f32), (W, 1)), "ground_offset": np.zeros(W, f32),
        "ground_friction": np.zeros(W, f32), "ground_restitution": np.zeros(W, f32),
        "pair_count": np.zeros(W, np.int32), "pair_shape_a": np.zeros((W, Q), np.int32),
        "pair_shape_b": np.full((W, Q), -1, np.int32), "contact_row_start": np.zeros(W, np.int32),
    }
    # bodies of all worlds at once
    counts = [len(spec.bodies) for spec in specs]
    bodies = [body for spec in specs for body in spec.bodies]
    at = (np.repeat(np.arange(W), counts), np.concatenate([np.arange(n) for n in counts]))
    mass = np.array([body.mass for body in bodies], float)
    inertia = np.array([body.inertia for body in bodies], float)
    orientation = np.array([body.orientation for body in bodies], float)
    com_world = np.array([body.position for body in bodies], float) + rotate(
        orientation, np.array([body.com for body in bodies], float))
    h["body_mass"][at] = mass
    h["body_inv_mass"][at] = 1.0 / mass
    h["body_inertia"][at] = inertia
    h["body_inv_inertia"][at] = np.linalg.inv(inertia)
    h["body_q_init"][at] = np.concatenate([com_world, orientation], axis=1)
    h["body_qd_init"][at] = np.concatenate([np.array([body.velocity for body in bodies], float),
                                            np.array([body.angular_velocity for body in bodies], float)], axis=1)
    for w, spec in enumerate(specs):
        index = spec.body_index
        coms = [body.com for body in spec.bodies]
        h["body_count"][w] = len(spec.bodies)
        h["joint_count"][w] = len(spec.joints)
        h["point_count"][w] = len(spec.points)
        h["world_gravity"][w] = spec.gravity
        row = _pack_joints(h, w, spec.joints, index, coms)
        h["row_count"][w] = row
        h["contact_row_start"][w] = row
        for k in range(capacity):  # contact rows: normal then two tangents; bodies are set per step
            h["row_kind"][w, row + 3 * k:row + 3 * k + 3] = (4, 5, 5)
        h["shape_count"][w] = len(spec.shapes)
        for s_index, shape in enumerate(spec.shapes):
            b = index[shape.body]
            h["shape_type"][w, s_index] = int(shape.type)
            h["shape_body"][w, s_index] = b
            h["shape_X"][w, s_index] = np.concatenate([shape.position - coms[b], shape.orientation])
            h["shape_size"][w, s_index] = shape.size
            h["shape_friction"][w, s_index] = shape.friction
            h["shape_restitution"][w, s_index] = shape.restitution
        if spec.ground is not None:
            if spec.ground.relief is not None and not measure_only:  # (engine.pack's plan refuses it first;
                # a gauge measures joints and energy, never the ground)
                raise ValueError(f"mechanism '{spec.name}': its ground has relief, which only the tabulated plan "
                                 f"simulates")
            h["ground_normal"][w] = spec.ground.normal
            h["ground_offset"][w] = spec.ground.offset
            h["ground_friction"][w] = spec.ground.friction
            h["ground_restitution"][w] = spec.ground.restitution
        h["pair_count"][w] = len(pairs[w])
        for p_index, (a, b) in enumerate(pairs[w]):
            h["pair_shape_a"][w, p_index], h["pair_shape_b"][w, p_index] = a, b
        for p, point in enumerate(spec.points):
            b = index[point.body]
            h["point_body"][w, p] = b
            h["point_local"][w, p] = point.position - coms[b]

    h["body_row_begin"], h["body_row_end"], h["body_row"] = body_row_lists(h["row_body_c"], h["row_body_p"],
                                                                          h["contact_row_start"], B)
    model = Model()
    model.device = device
    model.config = config
    model.specs = specs
    model.num_worlds, model.max_bodies, model.max_joints = W, B, J
    model.max_rows, model.max_points = R, P
    model.body_names = [[b.name for b in s.bodies] for s in specs]
    model.joint_names = [[j.name for j in s.joints] for s in specs]
    model.point_names = [[p.name for p in s.points] for s in specs]
    # engine.health's pack-time facts: how far from the origin each world lies (its FAR flag) and the
    # largest mass ratio across its joints (named in its reason when its joints come apart); the limits
    # they guard: benchmarks/results/README.md, "Limits: mass ratio and distance from the origin"
    extent = np.zeros(W)
    np.maximum.at(extent, at[0], np.abs(com_world).max(axis=1))
    ratio = np.ones(W)
    for w, spec in enumerate(specs):
        masses = {body.name: body.mass for body in spec.bodies}
        for joint in spec.joints:
            if joint.parent is None:
                extent[w] = max(extent[w], float(np.abs(joint.parent_position).max()))
            else:
                a, b = masses[joint.parent], masses[joint.child]
                ratio[w] = max(ratio[w], a / b, b / a)
    model.world_extent, model.world_mass_ratio = extent, ratio
    model.health_init = far_flags(extent, config.health_joint_tolerance)
    dtypes = {
        "body_inertia": wp.mat33, "body_inv_inertia": wp.mat33, "body_q_init": wp.transform,
        "body_qd_init": wp.spatial_vector, "joint_X_p": wp.transform, "joint_X_c": wp.transform,
        "joint_axis": wp.vec3, "joint_axis2": wp.vec3, "world_gravity": wp.vec3, "point_local": wp.vec3,
        "shape_X": wp.transform, "shape_size": wp.vec3, "ground_normal": wp.vec3,
    }
    forces = pack_forces(specs)
    dtypes.update(force_point_a=wp.vec3, force_point_b=wp.vec3, force_force=wp.vec3, force_torque=wp.vec3)
    for name, value in (*h.items(), *forces.items()):
        dtype = dtypes.get(name, wp.int32 if value.dtype == np.int32 else float)
        setattr(model, name, wp.array(value, dtype=dtype, device=device))
    model.max_forces = forces["force_kind"].shape[1]
    model.has_forces = bool(forces["force_count"].any())
    model.force_summary = force_summary(specs)
    model.undriven_effort_joints = int(sum(np.count_nonzero(forces["force_kind"][w, :n] == FORCE_JOINT_EFFORT_SLOT)
                                           for w, n in enumerate(forces["force_count"])))
    model._dt_host = h["world_dt"].copy()
    model.contact_capacity = capacity
    model.max_pairs = max_pairs
    model.has_contacts = capacity > 0
    model.has_limits = any(j.has_limits for s in specs for j in s.joints)
    model.has_unilateral_or_drive_rows = bool(np.any(h["row_kind"] >= 2))
    bilateral = np.array([sum(JOINT_ROW_COUNT[j.type] for j in s.joints) for s in specs], np.int32)
    model.bilateral_row_count = wp.array(bilateral, dtype=wp.int32, device=device)
    model.has_bilateral_rows = bool(bilateral.any())
    model.linear_solver = "dense" if dense else "sparse"
    fits = fused_fits(model.has_contacts, R, dense)
    if tuning.step_kernel == "fused" and not fits:
        raise ValueError(f"pack_worlds: step_kernel='fused' takes batches without contact shapes and with at most "
                         f"{FUSED_MAX_ROWS} dense rows per world; this batch has {R} rows"
                         f"{' and contacts' if model.has_contacts else ''} ({model.linear_solver} solver): use "
                         f"step_kernel='auto' or 'staged' (engine.Tuning)")
    fused = tuning.step_kernel == "fused" or (tuning.step_kernel == "auto" and fits)
    model.step_kernel = "fused" if fused else "staged"
    # the untimed fused kernel's (unused) cycle stamps: allocated here, as steps may be captured
    model._fused_no_stamps = wp.zeros((1, 1), dtype=wp.int64, device=device)
    # the fused step's knobs (engine.Tuning.fused_*), read by engine.fused at each step
    model.fused_block = tuning.fused_block  # threads per world (None: engine.fused.fused_block)
    # register cap per thread (None: the compiler's choice)
    model.fused_registers = FUSED_REGISTERS if tuning.fused_registers is None else (tuning.fused_registers or None)
    model.fused_inverse = tuning.fused_inverse  # solve through L^-1 (None: engine.fused.fused_inverse)
    model.fused_sharing = tuning.fused_sharing  # lanes sharing joints and bodies (None: engine.fused.fused_sharing)
    model.work = Workspace(W, B, R, device, max_pairs=max_pairs, contact_capacity=capacity, dense=dense and not measure_only)
    model.work.row_count.assign(h["row_count"])
    model.work.row_body_c = wp.clone(model.row_body_c)  # contact rows rewrite their bodies every step
    model.work.row_body_p = wp.clone(model.row_body_p)
    model.sparse_system = None
    model.sparse_projection = None
    model.sparse_body_nodes = False
    if sparse:  # one factor schedule per distinct topology (engine.linalg.sparse_analysis)
        rbc, rbp = factor_rows(specs, pairs, h)
        full = build_patterns(rbc, rbp, device, body_nodes=tuning.sparse_body_nodes, ordering=tuning.sparse_ordering)
        real = None  # with contact slots: rewritten every step (engine.linalg.sparse.prepare)
        if not model.has_contacts:  # each factor row stands for the joint row of its index, for good
            rows = np.arange(max(a.rows for a in full[1]))
            real = np.where(rows[None, :] < h["contact_row_start"][:, None], rows[None, :], -1)
        model.sparse_system = make_system(full, W, device, real=real)
        choice = tuning.sparse_projection_pattern
        if (choice != "never" and model.has_unilateral_or_drive_rows and model.has_bilateral_rows
                and config.position_iterations > 0):
            # the projection may factor the bilateral joint rows on a pattern of their own
            real, bc, bp = bilateral_factor_rows(h["row_kind"], h["row_body_c"], h["row_body_p"],
                                                 h["contact_row_start"])
            own = build_patterns(bc, bp, device, body_nodes=tuning.sparse_body_nodes, ordering=tuning.sparse_ordering)
            if choice == "always" or batch_schedule_cost(own[1]) < batch_schedule_cost(full[1]):
                model.sparse_projection = make_system(own, W, device, real=real, share=model.sparse_system)
        model.sparse_body_nodes = any(s.body_nodes for s in (model.sparse_system, model.sparse_projection) if s)
        model.work.sparse_root = wp.zeros((W, B), dtype=wp.mat33, device=device)
    return model
