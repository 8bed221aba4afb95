"""The plan: every choice engine.pack makes for a batch, and why, in one printable object.

The coordinates, fastest first: GROUNDED (a fixed-base planar linkage of mobility one: one
coordinate per world, every link read from tables of it), TABULATED (a floating base carrying one-DoF closed sub-chains,
each link a tabulated function of its sub-chain's driving angle: 6 + L coordinates per world),
TREE (one angle per joint of a spanning tree, every other joint a loop closed by rows) and MAXIMAL
(six coordinates per body, every joint its rows). ``fastest`` finds each world's fastest kind and
engine.pack runs worlds of different kinds in groups (MIXED: engine.grouped), so the user never
needs to know which path is fast; ``choose`` forces one kind (benchmarks, tests) and names the
world and the reason when it does not fit. After packing, describe_maximal / describe_reduced fill
in what the path decided: kernel, linear solver, stages, launch shape, register cap and accuracy.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass, field

import numpy as np

from engine.config import Integrator
from engine.spatial import rotate

__all__ = ["Coordinates", "Plan", "choose", "prepare"]


class Coordinates(enum.Enum):
    """How a plan describes the worlds' configuration (fastest first)."""

    GROUNDED = "grounded"  # fixed-base one-DoF planar linkage: its one coordinate, links read from tables
    TABULATED = "tabulated"  # floating base + one-DoF closed sub-chains read from tables of their driving angle
    TREE = "tree"  # spanning-tree joint angles (+ floating roots), loops closed by constraint rows
    MAXIMAL = "maximal"  # six coordinates per body, every joint a block of constraint rows
    MIXED = "mixed"  # groups of worlds, each in the fastest coordinates its worlds admit (engine.grouped)


ORDER = (Coordinates.GROUNDED, Coordinates.TABULATED, Coordinates.TREE, Coordinates.MAXIMAL)  # MIXED is no kind of its own
# unasked, the grounded plan takes a batch of at most this many distinct linkage geometries: each one's table
# costs 40-75 ms of host time (benchmarks/results/README.md, "The grounded plan")
GROUNDED_MAX_DISTINCT = 16
GROUNDED_TOO_MANY = ("{} distinct linkage geometries in the batch: building their tables (40-75 ms of host time "
                     f"each) would cost more than the tree plan's pack; the grounded plan is chosen for at most "
                     f"{GROUNDED_MAX_DISTINCT} (force it with coordinates='grounded')")


def _geometries(specs: list) -> int:
    """How many distinct geometries (joint graph, joint frames, body poses and centres of mass, to 1e-9)
    the batch's specs with a joint to the world have, counted up to GROUNDED_MAX_DISTINCT + 1: the
    tables a grounded plan would build at most (masses, inertias, drives and force elements do not
    change a table)."""
    seen = set()
    for spec in {id(s): s for s in specs}.values():
        if not any(j.parent is None for j in spec.joints):
            continue
        numbers = [np.ravel(getattr(b, f)) for b in spec.bodies for f in ("position", "orientation", "com")]
        numbers += [np.ravel(getattr(j, f)) for j in spec.joints
                    for f in ("parent_position", "parent_orientation", "child_position", "child_orientation", "axis")]
        graph = tuple((j.parent, j.child, j.type) for j in spec.joints)
        seen.add((graph, np.round(np.concatenate(numbers).astype(float), 9).tobytes()))
        if len(seen) > GROUNDED_MAX_DISTINCT:  # (past the limit the count no longer matters)
            break
    return len(seen)
# why a batch packed with a contact_capacity is not tabulated
CAPACITY_NOT_TABULATED = ("contact_capacity was given: the tabulated path keeps one contact slot per shape point "
                          "of every world")


@dataclass
class Plan:
    """What engine.pack chose for a batch. ``print(model.plan)`` shows it.

    coordinates: Coordinates; forced: whether the caller chose them; worlds, device; refused:
    (kind, reason) for every faster kind the batch did not admit; analysis: per-world facts the
    choice rests on (e.g. the sub-chains found); kernel, linear_solver, launch, registers: how a
    step runs; stages: stage -> whether it runs, with the reason; integrator; control: what
    drives the joints; accuracy: what the plan guarantees or measured at packing.
    """

    coordinates: Coordinates
    worlds: int
    device: str
    forced: bool = False
    refused: list = field(default_factory=list)
    analysis: list = field(default_factory=list)
    kernel: str = ""
    linear_solver: str = ""
    launch: str = ""
    registers: int | None = None
    stages: dict = field(default_factory=dict)
    integrator: str = ""
    control: str = ""
    accuracy: str = ""
    groups: list = field(default_factory=list)  # MIXED: (worlds, Plan) per group

    def __str__(self) -> str:
        if self.coordinates is Coordinates.MIXED:
            head = (f"plan for {self.worlds} worlds on {self.device}: {len(self.groups)} groups, each in the "
                    f"fastest coordinates its worlds admit")
            parts = [head] + [f"group of {n} world{'s' if n != 1 else ''}: " + "\n  ".join(str(p).splitlines())
                              for n, p in self.groups]
            return "\n".join(parts)
        why = "forced by the caller" if self.forced else "the fastest kind every world admits"
        lines = [f"plan for {self.worlds} world{'s' if self.worlds != 1 else ''} on {self.device}: "
                 f"{self.coordinates.value} coordinates ({why})"]
        for kind, reason in self.refused:
            lines.append(f"  not {kind.value}: {reason}")
        lines += [f"  {fact}" for fact in self.analysis]
        lines.append(f"  kernel: {self.kernel}")
        lines.append(f"  linear solver: {self.linear_solver}")
        lines.append(f"  launch: {self.launch}" + (f", at most {self.registers} registers per thread"
                                                   if self.registers else ""))
        for stage, (runs, reason) in self.stages.items():
            lines.append(f"  {stage}: {'runs' if runs else 'skipped'} ({reason})")
        lines.append(f"  integrator: {self.integrator}")
        lines.append(f"  control: {self.control}")
        lines.append(f"  accuracy: {self.accuracy}")
        return "\n".join(lines)


def _tabulated_ready(specs: list, prepared=None) -> dict:
    """The tabulated layouts of the batch's distinct specs, analysed together (a generation's
    walkers share their topology: engine.reduced.tabulated_layout.tabulated_layouts, equal to one
    analysis per spec): id(spec) -> its TabulatedLayout or the ValueError that refuses it.
    prepared: per spec what engine.prepare gave for it, or None."""
    from engine.reduced.tabulated_layout import tabulated_layouts

    unique = {}
    for i, s in enumerate(specs):
        unique.setdefault(id(s), (s, None if prepared is None or prepared[i] is None else prepared[i][0]))
    distinct = list(unique.values())
    analyses = None if prepared is None else [p for _, p in distinct]
    made = tabulated_layouts([s for s, _ in distinct], analyses=analyses)
    return {id(s): m for (s, _), m in zip(distinct, made)}


def prepare(specs) -> list:
    """What engine.pack works out from each spec alone, made ahead: per spec a small picklable
    entry for ``engine.pack(specs, prepared=...)``. A process that builds specs for another to
    pack (morphopt.build's workers) makes it beside them, so that the packing process, the one
    that holds the GPU, spends its time on what only it can do. An entry holds the tabulated
    plan's per-spec analysis (engine.reduced.tabulated_layout.tabulated_analyses) and, for a spec
    that plan does not take as it is, the tree plan's layout (chain_layout); pack checks each
    against its spec's structure, body masses and positions, and analyses a spec whose entry
    does not match itself. Valid only while the specs stay as they were."""
    from engine.reduced.tabulated_layout import tabulated_analyses

    specs = list(specs)
    return [(entry, _tree_ahead(spec) if entry is None or entry[2] is None else None)
            for spec, entry in zip(specs, tabulated_analyses(specs))]


def _tree_ahead(spec):
    """(the spec's tie, its chain_layout without the spec) or None where the tree plan refuses it."""
    from engine.reduced.chain_layout import chain_layout
    from engine.reduced.tabulated_layout import spec_tie

    try:
        layout = chain_layout(spec)
    except Exception:  # noqa: BLE001 - a head start only: engine.pack analyses this spec itself, and says why
        return None
    return spec_tie(spec), dataclasses.replace(layout, spec=None)


def _admits(kind: Coordinates, spec, ready: dict | None = None, tree=None):
    """The kind's layout of ``spec`` (raises ValueError with the reason when it does not fit);
    ready: the batch's tabulated layouts (_tabulated_ready); tree: the spec's tree entry of
    engine.prepare, or None."""
    if kind is Coordinates.GROUNDED:
        from engine.reduced.grounded import grounded_layout
        return grounded_layout(spec)
    if kind is Coordinates.TABULATED:
        made = (ready or {}).get(id(spec))
        if made is None:
            from engine.reduced.tabulated_layout import tabulated_layout
            return tabulated_layout(spec)
        if isinstance(made, ValueError):
            raise ValueError(str(made))
        return made
    if _has_relief(spec):
        raise ValueError(RELIEF_ONLY_TABULATED)
    if kind is Coordinates.TREE:
        from engine.pack import collision_pairs
        from engine.reduced.chain_layout import chain_layout
        for a, b in collision_pairs(spec):
            if b >= 0:
                raise ValueError(f"shapes '{spec.shapes[a].name}' and '{spec.shapes[b].name}' may touch each other: "
                                 f"the tree path has ground contacts only (give them a common collision group)")
        _effort_limits_clear(spec)
        _near_the_origin(spec)
        if tree is not None:
            from engine.reduced.tabulated_layout import spec_tie
            if tree[0] == spec_tie(spec):
                return dataclasses.replace(tree[1], spec=spec)
        return chain_layout(spec)
    return None


RELIEF_ONLY_TABULATED = ("its ground has relief (engine.spec.Relief), which only the tabulated plan simulates "
                         "(floating-base mechanisms)")


def _has_relief(spec) -> bool:
    return spec.ground is not None and spec.ground.relief is not None


def _maximal_admits(specs: list, first: int = 0) -> None:
    """ValueError naming the first world with ground relief (the maximal plan has none; ``first``:
    the index of specs[0] in the batch), with why the tabulated plan refuses that world."""
    for index, spec in enumerate(specs, start=first):
        if _has_relief(spec):
            try:
                _admits(Coordinates.TABULATED, spec)
                why = "a tabulated plan was not allowed (a contact capacity, or coordinates forced)"
            except ValueError as exc:
                why = str(exc)
            raise ValueError(f"engine.pack: world {index} ({spec.name}): {RELIEF_ONLY_TABULATED}; not tabulated: {why}")


def _effort_limits_clear(spec) -> None:
    """ValueError where a velocity drive starts past its effort limit: the tree path checks effort
    limits without enforcing them (a world whose drive passes its limit stops), so a drive whose
    limit binds from the first step (a motor started from rest against a low limit) keeps the
    maximal path, which enforces it."""
    bodies = spec.body_index
    for joint in spec.joints:
        drive = joint.drive
        if drive is None or not np.isfinite(drive.effort_limit) or drive.damping <= 0.0:
            continue
        child = spec.bodies[bodies[joint.child]]
        parent = None if joint.parent is None else spec.bodies[bodies[joint.parent]]
        axis = rotate(np.asarray(joint.parent_orientation, float), np.asarray(joint.axis, float))
        if parent is not None:
            axis = rotate(np.asarray(parent.orientation, float), axis)
        rate = np.asarray(child.angular_velocity, float) - (0.0 if parent is None else
                                                            np.asarray(parent.angular_velocity, float))
        torque = drive.damping * abs(drive.target_velocity - float(axis @ rate))
        if torque > drive.effort_limit:
            raise ValueError(f"joint '{joint.name}': its drive starts past its effort limit ({torque:.3g} > "
                             f"{drive.effort_limit:g} N m), which the tree path checks but does not enforce")


# farthest a tree world may lie from the origin [m]: the tree path keeps float32 positions without
# compensation (a four-bar diverged from 500 m on, CPU)
TREE_EXTENT = 100.0


def _near_the_origin(spec) -> None:
    """ValueError where a body or a world anchor lies farther than TREE_EXTENT from the origin."""
    far = max([float(np.abs(b.position).max()) for b in spec.bodies] +
              [float(np.abs(j.parent_position).max()) for j in spec.joints if j.parent is None])
    if far > TREE_EXTENT:
        raise ValueError(f"it lies {far:.3g} m from the origin; the tree path keeps float32 positions without "
                         f"compensation and is used within {TREE_EXTENT:g} m")


def _coerce(coordinates) -> Coordinates | None:
    if coordinates is Coordinates.MIXED or coordinates == "mixed":
        raise ValueError("engine.pack: coordinates 'mixed' is what the plan chooses for a batch whose worlds "
                         "differ; force one of 'grounded', 'tabulated', 'tree' or 'maximal', or leave it None")
    if coordinates is None or isinstance(coordinates, Coordinates):
        return coordinates
    try:
        return Coordinates(str(coordinates))
    except ValueError:
        names = ", ".join(repr(k.value) for k in Coordinates)
        raise ValueError(f"engine.pack: coordinates must be one of {names} or None (automatic), "
                         f"got {coordinates!r}") from None


def choose(specs: list, device, coordinates=None, contact_capacity: int | None = None,
           prepared=None) -> tuple[Plan, list | None]:
    """The coordinates of a batch and their per-world layouts (None for MAXIMAL).

    Tries the kinds fastest first and keeps the first that every world admits; a world that
    refuses a kind ends that kind's check (its reason is kept); a contact_capacity rules out the
    tabulated kind (its contact slots are fixed by the shapes). ``coordinates`` forces a kind:
    a world that does not admit it raises ValueError naming the world and the reason.
    """
    forced = _coerce(coordinates)
    refused = []
    for kind in ([forced] if forced is not None else ORDER):
        if kind is Coordinates.TABULATED and contact_capacity is not None:
            if forced is not None:
                raise ValueError(f"engine.pack: coordinates 'tabulated' do not fit: {CAPACITY_NOT_TABULATED}")
            refused.append((kind, CAPACITY_NOT_TABULATED))
            continue
        if kind is Coordinates.MAXIMAL:
            _maximal_admits(specs)
            return Plan(kind, len(specs), str(device), forced=forced is not None, refused=refused), None
        layouts, seen = [], {}  # a batch often repeats one spec object: its layout is made once
        ready = _tabulated_ready(specs, prepared) if kind is Coordinates.TABULATED else None
        for index, spec in enumerate(specs):
            try:
                if id(spec) not in seen:
                    seen[id(spec)] = _admits(kind, spec, ready, _tree_entry(prepared, index))
                layouts.append(seen[id(spec)])
            except ValueError as exc:
                reason = f"world {index} ({spec.name}): {exc}"
                if forced is not None:
                    raise ValueError(f"engine.pack: coordinates {kind.value!r} do not fit {reason}") from None
                refused.append((kind, reason))
                break
        else:
            return Plan(kind, len(specs), str(device), forced=forced is not None, refused=refused), layouts
    raise AssertionError("unreachable: MAXIMAL admits every world")


def _tree_entry(prepared, index: int):
    return None if prepared is None or prepared[index] is None else prepared[index][1]


def fastest(specs: list, contact_capacity: int | None = None, prepared=None) -> tuple[list, list, list]:
    """Per world the fastest kind it admits, its layout there, and the refusals on the way
    ((kind, 'world i (name): reason'), the first world per kind). A batch repeating one spec
    object analyses it once."""
    kinds, layouts, refused, seen, noted = [], [], [], {}, set()
    ready = _tabulated_ready(specs, prepared) if contact_capacity is None else None
    distinct = _geometries(specs)
    for index, spec in enumerate(specs):
        if id(spec) not in seen:
            found = None
            for kind in ORDER:
                if kind is Coordinates.MAXIMAL:
                    found = (kind, None)
                    break
                if kind is Coordinates.GROUNDED and distinct > GROUNDED_MAX_DISTINCT:
                    if kind not in noted:
                        noted.add(kind)
                        refused.append((kind, GROUNDED_TOO_MANY.format(f"more than {GROUNDED_MAX_DISTINCT}")))
                    continue
                if kind is Coordinates.TABULATED and contact_capacity is not None:
                    if kind not in noted:
                        noted.add(kind)
                        refused.append((kind, CAPACITY_NOT_TABULATED))
                    continue
                try:
                    found = (kind, _admits(kind, spec, ready, _tree_entry(prepared, index)))
                    break
                except ValueError as exc:
                    if kind not in noted:
                        noted.add(kind)
                        refused.append((kind, f"world {index} ({spec.name}): {exc}"))
            seen[id(spec)] = found
        kind, layout = seen[id(spec)]
        if kind is Coordinates.MAXIMAL and _has_relief(spec):
            _maximal_admits([spec], index)
        kinds.append(kind)
        layouts.append(layout)
    return kinds, layouts, refused


def _rows(model) -> str:
    return f"{model.max_rows} rows per world (padded)"


def _integrator(config) -> str:
    return "Moreau-Jean midpoint" if config.integrator is Integrator.MOREAU_JEAN else "semi-implicit Euler"


def _forces(model) -> str:
    """The force elements of a maximal batch and where they are evaluated (engine.dynamics)."""
    text = model.force_summary
    if model.undriven_effort_joints:
        text += f"; Control.joint_effort on {model.undriven_effort_joints} undriven joints"
    if model.has_forces:
        point = ("midpoint poses, starting twists" if model.config.integrator is Integrator.MOREAU_JEAN
                 else "starting poses and twists")
        text += f"; body wrenches beside Control.body_f, at the {point}"
    return text


def _tree_forces(specs, cfg) -> str:
    """The force elements of a tree batch and where the step kernel evaluates them."""
    from engine.pack import force_summary
    point = ("midpoint poses and rates extrapolated to the midpoint" if cfg.integrator is Integrator.MOREAU_JEAN
             else "starting poses and rates")
    return (f"{force_summary(specs)}; wrenches on the tree's bodies before the subtree sums "
            f"(chain_stages.apply_forces), at the {point}")


def describe_maximal(plan: Plan, model) -> Plan:
    """Fill ``plan`` from a packed maximal Model (engine.pack_worlds's choices)."""
    from engine.fused import FUSED_MAX_ROWS, fused_block, fused_inverse, sharing_used
    from engine.pack import MAX_DENSE_ROWS

    cfg, device = model.config, model.device
    if model.step_kernel == "fused":
        block = fused_block(device) if model.fused_block is None else model.fused_block
        inverse = fused_inverse(device, model.max_rows) if model.fused_inverse is None else model.fused_inverse
        plan.kernel = (f"fused: the whole step in one launch (dense rows, no contacts, at most {FUSED_MAX_ROWS} "
                       f"rows; {_rows(model)})")
        plan.launch = (f"one block of {block} lane{'s' if block != 1 else ''} per world"
                       + (f", lanes share joints and bodies (flags {sharing_used(model)})" if sharing_used(model) else ""))
        plan.registers = model.fused_registers if device.is_cuda else None
        plan.linear_solver = ("dense Cholesky per world in shared memory" +
                              (", solves through the inverse factor" if inverse else ", substitution"))
    else:
        plan.kernel = f"staged: one launch per stage ({_rows(model)})"
        plan.launch = "one thread or tile per world and stage"
        if model.linear_solver == "dense":
            plan.linear_solver = f"dense tile Cholesky per world (at most {MAX_DENSE_ROWS} rows)"
        else:
            plan.linear_solver = (f"sparse LDL^T on one factor schedule per topology (more than {MAX_DENSE_ROWS} "
                                  f"rows or asked for)" +
                                  ("; the projection factors its own pattern" if model.sparse_projection else ""))
    plan.stages = {
        "collision": (model.has_contacts, "the batch has shapes" if model.has_contacts else "no shapes"),
        "contact rows": (model.has_contacts, f"up to {model.contact_capacity} contacts per world"
                         if model.has_contacts else "no shapes"),
        "limit rows": (model.has_limits, "joints with limits" if model.has_limits else "no joint limits"),
        "position projection": (cfg.position_iterations > 0 and model.has_bilateral_rows,
                                f"{cfg.position_iterations} Gauss-Newton iterations" if model.has_bilateral_rows
                                else "no bilateral joint rows"),
        "forces": (model.has_forces, _forces(model)),
    }
    plan.integrator = _integrator(cfg)
    plan.control = "engine.Control: drive targets, efforts and body wrenches per step"
    plan.accuracy = ("joints held by constraint rows and a position projection; violations measured per record "
                     "(Trace.violation_*, Trace.health)")
    return plan


def describe_reduced(plan: Plan, model) -> Plan:
    """Fill ``plan`` from a packed reduced model (engine.reduced.model)."""
    inner, cfg, cuda = model.inner, model.config, model.device.is_cuda
    plan.control = "the specs' drive targets (no engine.Control)"
    if plan.coordinates is Coordinates.TREE:
        from engine.reduced.chain_kernel import CHAIN_BLOCK
        plan.control = ("a Control's body_f and joint_effort per step (TreeModel.control; compiled in only when "
                        "stepped with one), the specs' drive targets")
        coords = max(lay.n for lay in inner.layouts)
        rows = max(len(lay.rows) + len(lay.soft) for lay in inner.layouts)
        plan.analysis.append(f"largest world: {coords} tree coordinates, {rows} independent loop rows")
        plan.kernel = "fused: the whole step in one launch (the TREE kernel)"
        plan.linear_solver = ("mass matrix factored along the tree (no fill), loop rows' matrix by dense Cholesky "
                              "in shared memory")
        plan.launch = f"one block of {CHAIN_BLOCK if cuda else 1} lane{'s' if cuda else ''} per world"
        plan.registers = inner.max_registers if cuda else None
        contacts = inner.tile_contacts > 0
        plan.stages = {
            "collision": (contacts, "shapes against the ground plane" if contacts else "no shapes"),
            "PADMM iterations": (contacts, f"contact rows only, up to {inner.contact_capacity} contacts per world"
                                 if contacts else "only bilateral rows: the loops are solved directly"),
            "limit rows": (False, "no joint limits"),
            "position projection": (cfg.position_iterations > 0 and rows > 0,
                                    f"{cfg.position_iterations} Gauss-Newton iterations on the loop rows" if rows
                                    else "no loops"),
            "forces": (inner.forces, _tree_forces(model.specs, cfg) if inner.forces else "none"),
        }
        plan.integrator = _integrator(cfg)
        plan.accuracy = ("loops closed by their rows at every step (velocities exactly, positions projected), "
                         "joint errors measured at every record through a maximal gauge (Trace.health); the motion "
                         "is second order in dt with Moreau-Jean (passive four-bar, dt 1 ms: crank angle 1.8e-5 rad off "
                         "a float64 reference, the maximal plan 7.1e-5), first order where drives, damping or "
                         "contact impulses act")
        if any(np.isfinite(j.drive.effort_limit) for spec in model.specs for j in spec.joints if j.drive):
            plan.control += ("; effort limits checked, not enforced: a world whose drive passes its limit stops "
                             "there (health EFFORT_LIMIT)")
    elif plan.coordinates is Coordinates.GROUNDED:
        _describe_grounded(plan, model)
    else:
        from engine.reduced.tabulated import describe
        describe(plan, inner)
    return plan


def _describe_grounded(plan: Plan, model) -> None:
    """The GROUNDED plan's choices (engine.reduced.grounded)."""
    inner = model.inner
    tables, splines = inner.distinct
    plan.analysis.append(f"one coordinate per world (a fixed-base linkage of mobility one); {tables} distinct link "
                         f"table{'s' if tables != 1 else ''}, {splines} distinct mass and potential spline"
                         f"{'s' if splines != 1 else ''}")
    plan.kernel = "one launch per advance: every step of it for a world in one thread (the GROUNDED kernel)"
    plan.linear_solver = "none: the mass matrix is one tabulated number M(q)"
    plan.launch = "one thread per world"
    plan.stages = {
        "collision": (False, "no shapes over a ground"),
        "PADMM iterations": (False, "no rows: the loops are closed by the tables"),
        "limit rows": (False, "no joint limits"),
        "position projection": (False, "nothing to project: every link is a function of the coordinate"),
        "forces": (any(spec.forces for spec in model.specs),
                   "springs, dampers and loads tabulated over the turn as a generalized force and damping, at the "
                   "step's midpoint" if any(spec.forces for spec in model.specs) else "none"),
    }
    plan.integrator = ("implicit midpoint in (q, M(q) q') in float64, iterated to 1e-14 rad; without drive damping "
                       "three of them per step (triple jump, fourth order); the config's integrator does not apply")
    plan.control = ("a Control's body_f and joint_effort at the step's midpoint (compiled in only when stepped with "
                    "one), the specs' velocity drives implicit at the end rate and clamped to their effort limits")
    plan.accuracy = (f"loops closed by construction (tables' Hermite splines, linear closure error "
                     f"{inner.closure_error:.1e} m); the motion is the splines' Lagrangian system, symplectic (energy bounded), "
                     f"fourth order in dt where no drive acts, first order where one does")
