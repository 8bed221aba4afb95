"""Batched evaluation of designs: parameters -> linkages -> kinematics or dynamics -> metrics.

Kinematic-only questions (where does the foot go as the crank turns?) use the batched cycle
kinematics and never touch the dynamics. Dynamic evaluation converts every feasible design to
an engine world, packs them into one heterogeneous batch and rolls them out together. A design
that cannot be generated, cannot complete a crank turn or that the engine flags (engine.health:
diverged, joints come apart, too far from the origin, the solver stopped far from converged) is a
failed evaluation with a reason; the others in its batch carry on.
"""

from __future__ import annotations

import dataclasses
import functools
import operator
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from morphopt.build import build_prepared, no_collection
from morphopt.design_space import Float
from morphopt.linkage import Linkage
from morphopt.linkage.kinematics import crank_turn_failure, placement_name
from morphopt.linkage.kinematics_warp import LinkageTables, solve_tables
from morphopt.warp_setup import quiet_warp
from morphopt.metrics import gait_metrics, gait_metrics_batch

__all__ = ["Evaluation", "evaluate_dynamic", "evaluate_kinematic"]


def _walking_metrics(trace, world: int, torso: int, speeds: list, record_dt: float) -> dict:
    """Speed, heading drift and energy per distance of a walker's torso after a settling quarter."""
    start = len(trace.time) // 4
    path = trace.points[start:, world, torso]
    forward = path[-1, 0] - path[0, 0]
    sideways = path[-1, 1] - path[0, 1]
    elapsed = trace.time[-1] - trace.time[start]
    omega = max(speeds) if speeds else 0.0
    work = float(np.abs(trace.drive_torque[start + 1:, world]).sum() * omega * record_dt)
    distance = abs(forward)
    return {"walking_speed": float(distance / max(elapsed, 1e-9)),
            "heading_drift": float(abs(sideways) / max(distance, 1e-9)),
            "energy_per_distance": float(work / max(distance, 1e-9)) if distance > 1e-4 else float("inf")}


def _torso_tilt_height(points: np.ndarray, start: np.ndarray, torso: np.ndarray, up: np.ndarray) -> tuple:
    """Tilt [rad] of the torso's up axis and torso height as a fraction of its height in ``start``,
    per record and world ((T, W) each), from tracked points (T, W, P, 3) and record 0 (W, P, 3);
    torso, up (W,) point indices (-1 where a world is no walker: read as point 0)."""
    worlds = np.arange(points.shape[1])
    t, u = np.maximum(torso, 0), np.maximum(up, 0)
    centre = points[:, worlds, t]
    axis = points[:, worlds, u] - centre
    cos_tilt = axis[..., 2] / np.maximum(np.linalg.norm(axis, axis=-1), 1e-12)
    return np.arccos(np.clip(cos_tilt, -1.0, 1.0)), centre[..., 2] / np.maximum(start[worlds, t, 2], 1e-12)


def _fallen_worlds(points: np.ndarray, start: np.ndarray, torso: np.ndarray, up: np.ndarray, max_tilt: float,
                   min_height: float) -> np.ndarray:
    """(W,) bool: walkers (torso and up >= 0) whose torso has tilted past max_tilt or sunk below
    min_height of its starting height in the records ``points`` (see _torso_tilt_height)."""
    tilts, heights = _torso_tilt_height(points, start, torso, up)
    return (torso >= 0) & (up >= 0) & ((tilts > max_tilt) | (heights < min_height)).any(axis=0)


def _fall(trace, world: int, torso: int, up: int, max_tilt: float, min_height: float) -> tuple:
    """Largest tilt [rad] of the torso's up axis, lowest torso height (fraction of the start) and
    the failure reason ("" when the walker stayed up; else when it fell and how)."""
    points = trace.points[:, world:world + 1]
    tilts, heights = (a[:, 0] for a in _torso_tilt_height(points, points[0], np.array([torso]), np.array([up])))
    tilt, lowest = float(tilts.max()), float(heights.min())
    fallen = (tilts > max_tilt) | (heights < min_height)
    if not fallen.any():
        return tilt, lowest, ""
    first = int(np.argmax(fallen))
    when = f"fell after {trace.time[first]:.2f} s: the torso"
    if tilts[first] > max_tilt:
        return tilt, lowest, (f"{when} tilted by {np.degrees(tilts[first]):.1f} deg "
                              f"(more than {np.degrees(max_tilt):g})")
    return tilt, lowest, f"{when} sank to {heights[first]:.2f} of its starting height (less than {min_height:g})"


def _jam(trace, world: int, joints: list, stall_time: float, record_dt: float) -> str:
    """The failure reason of a jammed design ("" if none): a velocity drive with a finite effort
    limit that stays at >= 95 % of that limit while its joint turns at less than half of the
    target speed (or backwards) for stall_time [s] of consecutive records (a locked mechanism, a
    leg stuck in the ground, a load beyond the motor). Record 0, the initial state, is skipped."""
    needed = max(2, int(np.ceil(stall_time / record_dt)))
    for j, joint in enumerate(joints):
        drive = joint.drive
        if drive is None or drive.target_velocity == 0.0 or not np.isfinite(drive.effort_limit):
            continue
        torque = np.abs(trace.drive_torque[1:, world, j])
        speed = trace.drive_speed[1:, world, j] * np.sign(drive.target_velocity)
        stalled = (torque >= 0.95 * drive.effort_limit) & (speed < 0.5 * abs(drive.target_velocity))
        run = 0
        for k, flag in enumerate(stalled):
            run = run + 1 if flag else 0
            if run == needed:
                first = k - needed + 1
                revolute = joint.type.name == "REVOLUTE"
                unit = "N m" if revolute else "N"
                rate = "rad/s" if revolute else "m/s"
                return (f"jammed: the drive of joint '{joint.name}' stalled at its effort limit "
                        f"({drive.effort_limit:g} {unit}) from {trace.time[first + 1]:.2f} s, turning at "
                        f"{speed[first:k + 1].mean():.3g} of its {abs(drive.target_velocity):.3g} {rate} "
                        f"for {needed * record_dt:.2g} s")
    return ""


@dataclass
class Evaluation:
    """Results of one batch, in the order of ``params``.

    metrics: one dict per design (floats and, under "paths", tracked-point paths (N, 2) [m]);
    failures: "" for a feasible design, else the reason; timings: wall seconds per stage of the
    evaluation (dynamic: "build" (designs to MechanismSpecs), "pack", "simulate", "metrics";
    kinematic: "build" (designs to linkage tables), "kinematics" (kernels and metrics)); plan: the
    engine's plan of a dynamic batch (engine.plan.Plan; None when nothing was simulated).
    """

    params: list
    metrics: list = field(default_factory=list)
    failures: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    plan: object = None

    @property
    def feasible(self) -> np.ndarray:
        """(designs,) bool: True where the design has no failure reason."""
        return np.array([not reason for reason in self.failures])


def _path_metrics(paths: dict) -> dict:
    """Stride, full stride and step height of a rollout's tracked-point paths (its last crank turn's
    records: an open run, morphopt.metrics.gait_metrics with closed=False)."""
    metrics = {"paths": paths}
    for name, path in paths.items():
        stride, full, height = gait_metrics(path, closed=False)
        metrics[f"{name}_stride"] = stride
        metrics[f"{name}_stride_full"] = full
        metrics[f"{name}_step_height"] = height
    return metrics


def _batch_world_metrics(trace, turn: np.ndarray, torso: np.ndarray, up: np.ndarray, effort: np.ndarray,
                         target: np.ndarray, fall_tilt: float, fall_height: float, stall_time: float,
                         record_dt: float) -> dict:
    """The costly parts of _world_metrics for every world of ``trace`` at once (NumPy over the
    worlds instead of one small call per world and path): per world and tracked point the stride,
    full stride and step height over the last ``turn`` (W,) records (gait_metrics' rule); per world
    the largest torso tilt, the lowest torso height and whether the walker fell (torso, up (W,)
    point indices; fall_tilt, fall_height: see _fall); whether a drive may have jammed (effort,
    target (W, J): effort limit and target speed per drive, target 0 for none; see _jam, which
    then words the reason). Returns arrays indexed by world; _world_metrics(pre=...) reads them
    and gives the same metrics."""
    points = trace.points
    T, W, P = points.shape[:3]
    window = np.where((turn <= 0) | (turn > T), T, turn)
    first = np.repeat(T - window, P)  # the paths as columns (world, point) of (T, W * P)
    stride, full, height = (a.reshape(W, P) for a in gait_metrics_batch(
        points[..., 0].reshape(T, W * P), points[..., 2].reshape(T, W * P), first, closed=False))
    tilts, heights = _torso_tilt_height(points, points[0], torso, up)
    needed = max(2, int(np.ceil(stall_time / record_dt)))
    driven = (target != 0.0) & np.isfinite(effort)
    columns = np.nonzero(driven.any(axis=0))[0]  # the joints driven in some world (the others never stall)
    effort, target, driven = effort[:, columns], target[:, columns], driven[:, columns]
    torque = np.abs(trace.drive_torque[1:][:, :, columns])
    dtype = torque.dtype  # compare in the records' precision, as _jam does
    speed = trace.drive_speed[1:][:, :, columns] * np.sign(target).astype(dtype)
    stalled = driven & (torque >= (0.95 * effort).astype(dtype)) & (speed < (0.5 * np.abs(target)).astype(dtype))
    runs = np.zeros((W, len(columns)), bool)
    if stalled.shape[0] >= needed:
        counts = np.concatenate([np.zeros((1, W, len(columns)), int), np.cumsum(stalled, axis=0)])
        runs = ((counts[needed:] - counts[:-needed]) >= needed).any(axis=0)
    return {"stride": stride, "stride_full": full, "height": height, "tilt": tilts.max(axis=0),
            "lowest": heights.min(axis=0),
            "fell": ((tilts > fall_tilt) | (heights < fall_height)).any(axis=0), "jam": runs.any(axis=1)}


def _generate_batched(family, params: Sequence[dict], **kwargs) -> tuple[list, list]:
    """Generate every design with one call of the family per topology.

    Designs are grouped by their integer and categorical values; each group's float parameters
    go to ``family.generate`` as (D,) arrays, which gives a batched linkage when the family is
    written with NumPy operations. The first design of the group is generated alone as well and
    must give the same numbers; otherwise (or when generate raises on arrays) the group falls back
    to one call per design. Returns [(indices, LinkageTables, point names -> node)] and the
    failure reasons ("" when generated).
    """
    space = family.space
    names = set(space.names)
    floats = [n for n, p in space.parameters.items() if isinstance(p, Float)]
    others = [n for n in space.names if n not in floats]
    failures = [""] * len(params)
    groups = defaultdict(list)
    for i, p in enumerate(params):
        if p.keys() != names:
            failures[i] = _validation_failure(space, p)
        else:
            try:
                groups[tuple(p[n] for n in others)].append(i)
            except TypeError:  # an unhashable value: let validation name it
                failures[i] = _validation_failure(space, p)
    batches = []
    for key, indices in groups.items():
        fixed = dict(zip(others, key))
        try:
            getter = operator.itemgetter(*floats)
            table = np.array([getter(params[i]) for i in indices], dtype=float).reshape(len(indices), len(floats))
            columns = {n: np.ascontiguousarray(table[:, k]) for k, n in enumerate(floats)}
        except (TypeError, ValueError):
            columns = None
        if columns is None or not all(space.parameters[n].contains(v) for n, v in fixed.items()):
            batches += _generate_each(family, params, indices, failures, kwargs)
            continue
        inside = np.ones(len(indices), bool)
        for n, values in columns.items():
            inside &= (values >= space.parameters[n].low) & (values <= space.parameters[n].high)
        for i in np.asarray(indices)[~inside]:
            failures[i] = _validation_failure(space, params[i])
        keep = [i for i, ok in zip(indices, inside) if ok]
        if not keep:
            continue
        tables = None
        try:
            batched = family.generate({**{n: v[inside] for n, v in columns.items()}, **fixed}, **kwargs)
            if isinstance(batched, Linkage) and batched.batch_size in (None, len(keep)):
                tables = LinkageTables.from_linkages(batched)
                alone = LinkageTables.from_linkages([family.generate(space.validate(params[keep[0]]), **kwargs)])
                if not _same_first_row(tables, alone):
                    tables = None
        except Exception:  # noqa: BLE001 - any failure on arrays means: generate design by design
            tables = None
        if tables is None:
            batches += _generate_each(family, params, keep, failures, kwargs)
        else:
            batches.append((keep, tables, dict(batched.points)))
    return batches, failures


def _validation_failure(space, params: dict) -> str:
    try:
        space.validate(params)
    except ValueError as exc:
        return f"cannot be generated: {exc}"
    return "cannot be generated: invalid parameters"


def _same_first_row(batch: LinkageTables, alone: LinkageTables) -> bool:
    """Same topology tables, and the batch's first design has the numbers of the design alone."""
    topology = ("ground_node", "kind", "node", "node_a", "node_b")
    numbers = ("ground_xy", "radius", "phase", "branch", "first", "second")
    return (batch.names == alone.names
            and all(np.array_equal(getattr(batch, k), getattr(alone, k)) for k in topology)
            and all(np.allclose(getattr(batch, k)[0], getattr(alone, k)[0], rtol=1e-12, atol=1e-15) for k in numbers))


def _generate_each(family, params, indices, failures, kwargs) -> list:
    """One generate call per design, grouped by topology into tables."""
    linkages, topologies = {}, defaultdict(list)
    for i in indices:
        try:
            linkage = family.generate(family.space.validate(params[i]), **kwargs)
        except ValueError as exc:
            failures[i] = f"cannot be generated: {exc}"
            continue
        linkages[i] = linkage
        topologies[linkage.topology].append(i)
    return [(group, LinkageTables.from_linkages([linkages[i] for i in group]), dict(linkages[group[0]].points))
            for group in topologies.values()]


def _collector_paused(function: Callable) -> Callable:
    """``function`` run without the cyclic garbage collector: a generation's specs, layouts and
    metrics are tens of thousands of live objects that every collection would walk again (0.15 s a
    generation of 1,024 walkers, 2-core CPU; 15 % of a kinematic evaluation of 4,096 Jansen legs);
    what they leave when dropped goes by reference count, and the collector runs again afterwards."""
    @functools.wraps(function)
    def paused(*args, **kwargs):
        with no_collection():
            return function(*args, **kwargs)
    return paused


@_collector_paused
def evaluate_kinematic(family, params: Sequence[dict], *, samples: int = 360, device: str = "cpu",
                       keep_paths: bool = True) -> Evaluation:
    """Tracked-point paths over one crank turn, their stride, full stride and step height
    (morphopt.metrics.gait_metrics) and the transmission angle of every design, from the batched
    cycle kinematics alone (compiled Warp kernels on ``device``; the CPU splits the batch over its
    cores). keep_paths=False skips the paths (N, 2) in the metrics, which saves their copy from a
    GPU when only the scalar metrics are needed."""
    if not hasattr(family, "generate"):
        raise ValueError("this design family builds whole worlds (build_spec): evaluate it with mode = 'dynamic'")
    quiet_warp()
    t0 = time.perf_counter()
    batches, failures = _generate_batched(family, params)
    evaluation = Evaluation(list(params), [{} for _ in params], failures)
    t1 = time.perf_counter()
    for indices, tables, points in batches:
        names = list(points)
        result = solve_tables(tables, samples=samples, nodes=[points[n] for n in names], device=device,
                              keep_points=keep_paths)
        fail_step, fail_placement = result["fail_step"].tolist(), result["fail_placement"].tolist()
        transmission = result["transmission_angle_min"].tolist()
        stride, full, height = (result[k].tolist() for k in ("stride", "stride_full", "step_height"))
        for j, i in enumerate(indices):
            if fail_step[j] >= 0:
                angle = tables.phase[j] + 2.0 * np.pi * fail_step[j] / samples
                evaluation.failures[i] = crank_turn_failure(placement_name(tables, fail_placement[j]), angle)
                continue
            metrics = {"paths": {n: result["points"][j, :, k] for k, n in enumerate(names)}} if keep_paths else {}
            for k, n in enumerate(names):
                metrics[f"{n}_stride"] = stride[j][k]
                metrics[f"{n}_stride_full"] = full[j][k]
                metrics[f"{n}_step_height"] = height[j][k]
            metrics["transmission_angle_min"] = transmission[j]
            evaluation.metrics[i] = metrics
    evaluation.timings = {"build": t1 - t0, "kinematics": time.perf_counter() - t1}
    return evaluation


@_collector_paused
def evaluate_dynamic(family, params: Sequence[dict], *, duration: float, dt: float = 1e-3, device: str = "cpu",
                     crank_speed: float | None = None, record_every: int = 10,
                     spec_hook: Callable | None = None, loop_tolerance: float | None = None,
                     fall_tilt: float = np.radians(45.0), fall_height: float = 0.5,
                     stall_time: float = 0.2, config=None, workers: int | None = None,
                     coordinates=None, progress: Callable | None = None) -> Evaluation:
    """Simulate every feasible design for ``duration`` [s] in one heterogeneous batch.

    Metrics: tracked-point paths over the last crank turn (planar, [m]), their stride, full stride
    and step height (morphopt.metrics.gait_metrics of the turn's records), crank torque peak and RMS
    [N m], loop-closure violation max [m]; with a tracked point named "torso" (walkers), over the
    last three quarters of the run: walking_speed [m/s], heading_drift (sideways per forward
    distance) and energy_per_distance [J/m] of the motors.
    crank_speed [rad/s] overrides the design's (linkage families default to 2 pi).
    spec_hook(spec, params) may add shapes, ground or change the spec before packing; a hook whose
    ``copies`` attribute is true promises to return a changed copy rather than change the spec in
    place, and designs of equal parameters are then built once (as they are without a hook).
    A world the engine flags (engine.health, Trace.health) fails with the engine's reason: its state
    turned non-finite, its joints came apart by more than loop_tolerance [m] at a record (a torn
    mechanism, which can still be finite and even "walk" fast; None: the config's
    health_joint_tolerance, 5 mm by default), it lies too far from the origin for float32, or its
    solver stopped unconverged at a large residual: its metrics would describe a broken
    simulation, not the design.
    A walker (tracked points "torso" and "torso_up", the latter above the torso centre) that tilts
    by more than fall_tilt [rad] or whose torso sinks below fall_height times its starting height
    fails as fallen (a tumbling or belly-sliding body can cover ground fast without walking); its
    torso_tilt_max [rad] and torso_height_min (fraction of the start) are metrics as well. A walker
    is frozen at the first record that shows it fallen (engine.rollout's halt): the rest of the
    batch runs on without it, and its metrics describe the run up to the fall.
    A design whose velocity drive stays at its effort limit while turning at less than half its
    target speed for stall_time [s] fails as jammed (it locks mid-cycle, or the motor cannot move
    it); the reason names the joint and when it stalled.
    config: the engine.SolverConfig of the batch (None: the defaults; a study's [solver] table).
    workers: processes that build the specs (morphopt.build.build_specs; None: one per core but
    one for batches of 256 designs or more).
    coordinates: None lets the engine plan the batch (engine.pack: a walker of one-DoF legs runs as a
    torso and one crank angle per leg, a linkage on its spanning tree); "maximal", "tree" or
    "tabulated" forces the engine's coordinates (benchmarks, tests). The metrics and failure rules
    are the same whatever the plan; the Evaluation's ``plan`` says which ran.
    progress(steps done, steps, worlds running, worlds fallen), if given, is called after every
    record (every record_every steps) from data already on the host.
    """
    quiet_warp()
    from engine import SolverConfig, pack, rollout

    if loop_tolerance is not None:  # the engine's joint check is the one test of torn mechanisms
        config = dataclasses.replace(config or SolverConfig(), health_joint_tolerance=float(loop_tolerance))
    t0 = time.perf_counter()
    # equal designs built once where the hook, if any, changes copies only (morphopt.robust's hooks)
    # the build workers also make the per-spec part of engine.pack's analysis where the plan may use it
    # and no hook changes the specs
    built, prepared = build_prepared(family, params, crank_speed=crank_speed, workers=workers,
                                     share=spec_hook is None or getattr(spec_hook, "copies", False),
                                     prepare=spec_hook is None and getattr(coordinates, "value", coordinates)
                                     in (None, "tabulated", "tree"))
    if spec_hook:
        built = [spec if isinstance(spec, str) else spec_hook(spec, p) for p, spec in zip(params, built)]
    evaluation, specs, owners = _built(params, built, t0)
    if not specs:
        return evaluation
    t1 = time.perf_counter()
    model = pack(specs, device=device, dt=dt, config=config, coordinates=coordinates,
                 prepared=None if prepared is None else [prepared[i] for i in owners])
    evaluation.plan = model.plan
    t2 = time.perf_counter()

    steps = max(record_every, int(round(duration / dt / record_every)) * record_every)
    torso = np.array([names.index("torso") if "torso" in names else -1 for names in model.point_names])
    up = np.array([names.index("torso_up") if "torso_up" in names else -1 for names in model.point_names])
    halt = None
    if ((torso >= 0) & (up >= 0)).any():  # a walker that fell has failed: stop simulating it
        def halt(points, start):
            return _fallen_worlds(points[None], start, torso, up, fall_tilt, fall_height)
    halt = _reporting(halt, progress, steps, record_every, model.num_worlds)
    trace, _ = rollout(model, model.state(), None, steps, record_every=record_every, halt=halt)
    t3 = time.perf_counter()
    record_dt = dt * record_every
    turn, effort, target = _drives(specs, record_dt, len(trace.time))
    pre = _batch_world_metrics(trace, turn, torso, up, effort, target, fall_tilt, fall_height, stall_time, record_dt)
    for world, i in enumerate(owners):
        _world_metrics(evaluation, i, trace, world, model.point_names[world], specs[world].joints, record_dt,
                       fall_tilt, fall_height, stall_time, pre=pre)
    evaluation.timings.update(pack=t2 - t1, simulate=t3 - t2, metrics=time.perf_counter() - t3)
    return evaluation


def _reporting(halt: Callable | None, progress: Callable | None, steps: int, record_every: int,
               worlds: int) -> Callable | None:
    """``halt`` (a rollout's, or None) that also calls progress(steps done, steps, worlds running,
    worlds fallen) after every record; ``halt`` itself when there is no progress to report."""
    if progress is None:
        return halt
    done = [0]
    fallen = np.zeros(worlds, bool)

    def report(points, start):
        marked = np.zeros(worlds, bool) if halt is None else np.asarray(halt(points, start), bool).reshape(worlds)
        fallen[marked] = True
        done[0] = min(done[0] + record_every, steps)
        count = int(fallen.sum())
        progress(done[0], steps, worlds - count, count)
        return marked

    return report


def _built(params: Sequence[dict], built: list, t0: float) -> tuple:
    """The Evaluation of a batch whose worlds were built (``built``: per design its world, or the
    reason it cannot be built), its "build" time since t0, the worlds and their designs' indices."""
    failures = [spec if isinstance(spec, str) else "" for spec in built]
    owners = [i for i, spec in enumerate(built) if not isinstance(spec, str)]
    evaluation = Evaluation(list(params), [{} for _ in params], failures)
    evaluation.timings = {"build": time.perf_counter() - t0}
    return evaluation, [built[i] for i in owners], owners


def _world_metrics(evaluation: Evaluation, i: int, trace, world: int, names: list, joints: list, record_dt: float,
                   fall_tilt: float, fall_height: float, stall_time: float, pre: dict | None = None) -> None:
    """Metrics or the failure reason of design i, simulated as ``world`` of ``trace``; joints: the
    spec's joints (trace.drive_torque's last axis). pre: the batch's _batch_world_metrics (the same
    metrics, computed for every world at once). A world the engine flags (trace.health: diverged,
    joints open past the config's tolerance, ...) fails with the engine's reason."""
    flagged = trace.health.reason(world)
    if flagged:
        evaluation.failures[i] = flagged
        return
    jammed = _jam(trace, world, joints, stall_time, record_dt) if pre is None or pre["jam"][world] else ""
    if jammed:
        evaluation.failures[i] = jammed
        return
    speeds = [abs(j.drive.target_velocity) for j in joints if j.drive is not None]
    turn = int(round(2.0 * np.pi / max(speeds + [1e-9]) / record_dt)) if speeds else len(trace.time)
    paths = {name: trace.points[-turn:, world, k][:, [0, 2]] for k, name in enumerate(names)}
    if pre is None:
        metrics = _path_metrics(paths)
    else:
        metrics = {"paths": paths}
        for k, name in enumerate(names):
            metrics[f"{name}_stride"] = float(pre["stride"][world, k])
            metrics[f"{name}_stride_full"] = float(pre["stride_full"][world, k])
            metrics[f"{name}_step_height"] = float(pre["height"][world, k])
    if "torso" in names:
        metrics.update(_walking_metrics(trace, world, names.index("torso"), speeds, record_dt))
    if "torso" in names and "torso_up" in names:
        if pre is None or pre["fell"][world]:
            fell = _fall(trace, world, names.index("torso"), names.index("torso_up"), fall_tilt, fall_height)
        else:
            fell = float(pre["tilt"][world]), float(pre["lowest"][world]), ""
        metrics["torso_tilt_max"], metrics["torso_height_min"], reason = fell
        if reason:
            evaluation.failures[i] = reason
            return
    driven = [j for j, joint in enumerate(joints) if joint.drive is not None]
    drive = trace.drive_torque[1:, world][:, driven] if driven else np.zeros((1, 1))  # record 0: the start
    metrics["torque_peak"] = float(np.abs(drive).max())
    metrics["torque_rms"] = float(np.sqrt(np.mean(drive**2)))  # over the driven joints
    metrics["loop_violation_max"] = float(trace.violation_linear[:, world].max())
    evaluation.metrics[i] = metrics


def _drives(specs: list, record_dt: float, records: int) -> tuple:
    """For _batch_world_metrics: per world the records of a crank turn at its fastest drive (all
    ``records`` without one), and every joint's drive effort limit and target speed (W, J; zero
    for joints without a drive)."""
    J = max(1, max(len(spec.joints) for spec in specs))
    effort, target = np.zeros((len(specs), J)), np.zeros((len(specs), J))
    for world, spec in enumerate(specs):
        for j, joint in enumerate(spec.joints):
            if joint.drive is not None:
                effort[world, j], target[world, j] = joint.drive.effort_limit, joint.drive.target_velocity
    fastest = np.abs(target).max(axis=1)
    turn = np.where(fastest > 0.0, np.round(2.0 * np.pi / np.maximum(fastest, 1e-9) / record_dt), records)
    return turn.astype(int), effort, target
