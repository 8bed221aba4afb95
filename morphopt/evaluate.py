"""Batched evaluation of designs: parameters -> linkages -> kinematics or dynamics -> metrics.

Kinematic-only questions (where does the foot go as the crank turns?) use the batched cycle
kinematics and never touch the dynamics. Dynamic evaluation converts every feasible design to
an engine world, packs them into one heterogeneous batch and rolls them out together. A design
that cannot be generated, cannot complete a crank turn or diverges is a failed evaluation with a
reason; the others in its batch carry on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from morphopt.linkage import solve_cycles, to_spec
from morphopt.metrics import stride_and_step_height

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


@dataclass
class Evaluation:
    """Results of one batch, in the order of ``params``.

    metrics: one dict per design (floats and, under "paths", tracked-point paths (N, 2) [m]);
    failures: "" for a feasible design, else the reason.
    """

    params: list
    metrics: list = field(default_factory=list)
    failures: list = field(default_factory=list)

    @property
    def feasible(self) -> np.ndarray:
        return np.array([not reason for reason in self.failures])


def _generate(family, params: Sequence[dict], **kwargs):
    linkages, failures = [], []
    for p in params:
        try:
            linkages.append(family.generate(family.space.validate(p), **kwargs))
            failures.append("")
        except ValueError as exc:
            linkages.append(None)
            failures.append(f"cannot be generated: {exc}")
    return linkages, failures


def _path_metrics(paths: dict) -> dict:
    metrics = {"paths": paths}
    for name, path in paths.items():
        stride, height = stride_and_step_height(path)
        metrics[f"{name}_stride"] = float(stride)
        metrics[f"{name}_step_height"] = float(height)
    return metrics


def evaluate_kinematic(family, params: Sequence[dict], *, samples: int = 360) -> Evaluation:
    """Tracked-point paths over one crank turn, stride, step height and transmission angle of
    every design, from the batched kinematics alone."""
    if not hasattr(family, "generate"):
        raise ValueError("this design family builds whole worlds (build_spec): evaluate it with mode = 'dynamic'")
    linkages, failures = _generate(family, params)
    ok = [i for i, linkage in enumerate(linkages) if linkage is not None]
    solutions = dict(zip(ok, solve_cycles([linkages[i] for i in ok], samples=samples)))
    evaluation = Evaluation(list(params))
    for i, linkage in enumerate(linkages):
        if linkage is None:
            evaluation.metrics.append({})
            evaluation.failures.append(failures[i])
            continue
        solution = solutions[i]
        paths = {name: solution.point(name, linkage) for name in linkage.points}
        metrics = _path_metrics(paths)
        metrics["transmission_angle_min"] = solution.transmission_angle_min
        evaluation.metrics.append(metrics)
        evaluation.failures.append(solution.reason)
    return evaluation


def evaluate_dynamic(family, params: Sequence[dict], *, duration: float, dt: float = 1e-3, device: str = "cpu",
                     crank_speed: float | None = None, record_every: int = 10,
                     spec_hook: Callable | None = None, loop_tolerance: float = 5e-3) -> Evaluation:
    """Simulate every feasible design for ``duration`` [s] in one heterogeneous batch.

    Metrics: tracked-point paths over the last crank turn (planar, [m]), their stride and step
    height, crank torque peak and RMS [N m], loop-closure violation max [m]; with a tracked point
    named "torso" (walkers), over the last three quarters of the run: walking_speed [m/s],
    heading_drift (sideways per forward distance) and energy_per_distance [J/m] of the motors.
    crank_speed [rad/s] overrides the design's (linkage families default to 2 pi).
    spec_hook(spec, params) may add shapes, ground or change the spec before packing.
    A design whose state turns non-finite, or whose joints come apart by more than loop_tolerance
    [m] at any recorded step (a torn mechanism, which can still be finite and even "walk" fast),
    fails as diverged: its metrics would describe a broken simulation, not the design.
    """
    from engine import pack_worlds, rollout

    specs, owners, failures = [], [], []
    for i, p in enumerate(params):
        try:
            if hasattr(family, "build_spec"):
                spec = family.build_spec(family.space.validate(p), crank_speed=crank_speed)
            else:
                spec = to_spec(family.generate(family.space.validate(p), crank_speed=crank_speed or 2.0 * np.pi))
        except ValueError as exc:
            failures.append(f"cannot be built: {exc}")
            continue
        spec = spec_hook(spec, p) if spec_hook else spec
        failures.append("")
        specs.append(spec)
        owners.append(i)
    evaluation = Evaluation(list(params), [{} for _ in params], failures)
    if not specs:
        return evaluation
    model = pack_worlds(specs, device=device, dt=dt)
    steps = max(record_every, int(round(duration / dt / record_every)) * record_every)
    trace, _ = rollout(model, model.state(), model.control(), steps, record_every=record_every)
    record_dt = dt * record_every
    for world, i in enumerate(owners):
        if trace.diverged[world]:
            evaluation.failures[i] = "diverged: the simulation produced a non-finite state"
            continue
        torn = float(trace.violation_linear[:, world].max())
        if torn > loop_tolerance:
            evaluation.failures[i] = (f"diverged: joints came apart by {torn:.3g} m "
                                      f"(more than the {loop_tolerance:g} m tolerance)")
            continue
        speeds = [abs(j.drive.target_velocity) for j in specs[world].joints if j.drive is not None]
        turn = int(round(2.0 * np.pi / max(speeds + [1e-9]) / record_dt)) if speeds else len(trace.time)
        names = model.point_names[world]
        paths = {name: trace.points[-turn:, world, k][:, [0, 2]] for k, name in enumerate(names)}
        metrics = _path_metrics(paths)
        if "torso" in names:
            metrics.update(_walking_metrics(trace, world, names.index("torso"), speeds, record_dt))
        drive = trace.drive_torque[1:, world]  # record 0 is the initial state
        metrics["torque_peak"] = float(np.abs(drive).max())
        metrics["torque_rms"] = float(np.sqrt(np.mean(drive**2)))
        metrics["loop_violation_max"] = float(trace.violation_linear[:, world].max())
        evaluation.metrics[i] = metrics
    return evaluation
