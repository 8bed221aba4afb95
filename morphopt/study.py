"""run_study: ask -> evaluate (one batch of worlds) -> tell -> store, generation after generation.

Interrupting a run loses at most the generation in flight: each finished generation is stored
with the optimizer's checkpoint in one transaction, and resume=True continues from it (the
optimizer's random state included, so a resumed study ends where an uninterrupted one would).

A run that fails leaves the stored results as they were: the spec, the family and the device are
checked before the storage is opened; a fresh run removes the earlier designs only in the
transaction that stores its first generation; resume reads the optimizer only from the study's
own checkpoint row (morphopt.storage.load_checkpoint) and refuses one of another optimizer or
design space.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from tqdm.auto import tqdm

from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import load_family
from morphopt.metrics import path_error
from morphopt.optimizers import CMAES, OptunaSampler, RandomSearch
from morphopt.storage import StudyStorage, dump_checkpoint, load_checkpoint, storage_exists
from morphopt.study_spec import StudySpec

__all__ = ["StudyResult", "objective_matrix", "objective_metric_names", "objective_values", "pareto_front", "run_study"]


@dataclass
class StudyResult:
    """Best design (all parameters), its objective value (natural sign), evaluations, seconds
    (wall time of the generations run now and before a resume) and, of this run's time, the share
    spent outside the evaluation (sampling, telling, storage): ``overhead``. ``stages``: this run's
    wall seconds per stage, summed over its generations: "ask", the evaluation's own stages
    (morphopt.evaluate.Evaluation.timings), "objectives", "tell" and "storage"."""

    best_params: dict | None
    best_value: float
    evaluations: int
    generations: int
    seconds: float
    overhead: float = 0.0
    stages: dict = field(default_factory=dict)


def _make_optimizer(spec: StudySpec, space):
    if spec.optimizer == "cma":
        return CMAES(space, popsize=spec.worlds, sigma0=spec.sigma0, seed=spec.seed, restarts=spec.restarts,
                     restart_strategy=spec.restart_strategy)
    if spec.optimizer == "optuna":
        directions = ["minimize"] * len(spec.objectives) if spec.pareto else None
        return OptunaSampler(space, sampler=spec.sampler, seed=spec.seed, directions=directions)
    return RandomSearch(space, seed=spec.seed)


def objective_matrix(spec: StudySpec, evaluation) -> np.ndarray:
    """(designs, objectives) values to minimize: each metric, negated when maximized; inf for
    failed designs. A "path_error" objective compares the path of its point with its target (with
    several such objectives, the metric is stored as path_error, path_error_1, ...)."""
    columns = []
    for objective, name in zip(spec.objectives, objective_metric_names(spec)):
        if objective.metric == "path_error":
            target = np.asarray(objective.target, dtype=float)
            for metrics, failure in zip(evaluation.metrics, evaluation.failures):
                if not failure:
                    metrics[name] = path_error(metrics["paths"][objective.point], target)
        column = []
        for metrics, failure in zip(evaluation.metrics, evaluation.failures):
            value = metrics.get(name, math.nan) if not failure else math.nan
            column.append(objective.sign * value if value is not None and math.isfinite(value) else math.inf)
        columns.append(column)
    return np.array(columns, dtype=float).T.reshape(len(evaluation.failures), len(spec.objectives))


def objective_metric_names(spec: StudySpec) -> list[str]:
    """The stored metric of every objective (a second "path_error" objective is "path_error_1", ...)."""
    names = []
    for k, objective in enumerate(spec.objectives):
        name = objective.metric
        if name == "path_error" and name in names:
            name = f"path_error_{k}"
        names.append(name)
    return names


def objective_values(spec: StudySpec, evaluation) -> np.ndarray:
    """One value per design to minimize: the metric (negated when maximized), or with several
    objectives the weighted score sum_k weight_k * value_k; inf for failed designs."""
    matrix = objective_matrix(spec, evaluation)
    if not spec.multi_objective:
        return matrix[:, 0]
    weights = np.array([o.weight for o in spec.objectives])
    with np.errstate(invalid="ignore"):
        score = matrix @ weights
    return np.where(np.isfinite(matrix).all(axis=1), score, math.inf)


def nondominated(values) -> np.ndarray:
    """True for the rows of ``values`` (designs x objectives, every objective minimized) that no
    other row dominates (all objectives at least as good, one better)."""
    values = np.asarray(values, dtype=float)
    keep = np.ones(len(values), dtype=bool)
    for i in range(len(values)):
        better_or_equal = (values <= values[i]).all(axis=1)
        strictly = (values < values[i]).any(axis=1)
        keep[i] = not bool(np.any(better_or_equal & strictly))
    return keep


def pareto_front(frame, spec: StudySpec):
    """The feasible designs of a stored study that no other feasible design dominates, best
    score first."""
    feasible = frame[frame["failure"] == ""]
    columns = [f"metric_{name}" for name in objective_metric_names(spec)]
    values = feasible[columns].to_numpy(dtype=float) * np.array([o.sign for o in spec.objectives])
    keep = np.isfinite(values).all(axis=1)
    values, feasible = values[keep], feasible[keep]
    return feasible[nondominated(values)].sort_values("value")


def apply_constraints(spec: StudySpec, evaluation) -> None:
    """Mark designs whose metrics leave the [constraints] bounds as failed, with the reason."""
    for k, (metrics, failure) in enumerate(zip(evaluation.metrics, evaluation.failures)):
        if failure:
            continue
        for name, (low, high) in spec.constraints.items():
            value = metrics.get(name, math.nan)
            if not (low <= value <= high):
                evaluation.failures[k] = f"constraint {name} in [{low:g}, {high:g}] violated: {value:.6g}"
                break


OPTIMIZER_CLASSES = {"cma": CMAES, "optuna": OptunaSampler, "random": RandomSearch}


def _check_device(spec: StudySpec) -> None:
    """ValueError naming the spec and 'study.device' when Warp cannot use the device."""
    import warp as wp

    try:
        wp.get_device(spec.device)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"{spec.path}: 'study.device' {spec.device!r} is not available here ({exc})") from exc


def _resumed_optimizer(spec: StudySpec, space, storage: StudyStorage, state: bytes):
    """The checkpointed optimizer, checked against the spec: same optimizer, same design space."""
    optimizer = load_checkpoint(state, storage.where)
    expected = OPTIMIZER_CLASSES[spec.optimizer]
    if type(optimizer) is not expected:
        raise ValueError(f"{storage.where}: the checkpoint holds a {type(optimizer).__name__}, the spec asks for "
                         f"optimizer '{spec.optimizer}' ({expected.__name__}); start afresh with 'study run'")
    if getattr(getattr(optimizer, "space", None), "parameters", None) != space.parameters:
        raise ValueError(f"{storage.where}: the checkpoint was made for another design space than the spec's "
                         f"(its [space] or [fixed] changed); start afresh with 'study run'")
    return optimizer


def run_study(spec: StudySpec, *, resume: bool = False, progress: bool = True) -> StudyResult:
    """Run (or resume) a study; returns the best design found."""
    family = load_family(spec.family)
    space = spec.design_space(family)
    _check_device(spec)
    if spec.mode == "dynamic" and spec.model == "reduced" and not hasattr(family, "build_legged"):
        raise ValueError(f"{spec.path}: 'simulation.model' = 'reduced' needs a family with build_legged "
                         f"(a walker of one-DoF legs); family '{spec.family}' has none")
    if resume and not storage_exists(spec.storage_url):
        raise ValueError(f"study '{spec.name}' has nothing to resume: no database {spec.storage_url}")
    storage = StudyStorage(spec.storage_url, spec.name)
    checkpoint = storage.checkpoint() if resume else None
    if resume and checkpoint is None:
        raise ValueError(f"study '{spec.name}' has nothing to resume in {spec.storage_url}")
    if checkpoint:
        done, state, seconds = checkpoint
        optimizer = _resumed_optimizer(spec, space, storage, state)
        start = done + 1
    else:
        optimizer, start, seconds = _make_optimizer(spec, space), 0, 0.0
    fresh = not checkpoint
    sign = -1.0 if spec.direction == "maximize" else 1.0
    evaluating = outside = 0.0
    stages = {}
    bar = tqdm(total=spec.generations, initial=start, desc=spec.name, unit="gen", disable=not progress)
    for generation in range(start, spec.generations):
        t0 = time.perf_counter()
        free = optimizer.ask(spec.worlds)
        params = [{**p, **spec.fixed} for p in free]
        t1 = time.perf_counter()
        if spec.mode == "kinematic":
            evaluation = evaluate_kinematic(family, params, samples=spec.samples, device=spec.device,
                                            keep_paths=any(o.metric == "path_error" for o in spec.objectives))
        else:
            evaluation = evaluate_dynamic(family, params, duration=spec.duration, dt=spec.dt, device=spec.device,
                                          crank_speed=spec.crank_speed, config=spec.solver_config(), model=spec.model)
        t_objectives = time.perf_counter()
        apply_constraints(spec, evaluation)
        values = objective_values(spec, evaluation)
        t2 = time.perf_counter()
        if spec.pareto:
            optimizer.tell(free, values.tolist(), objective_matrix(spec, evaluation))
        else:
            optimizer.tell(free, values.tolist())
        t_told = time.perf_counter()
        storage.write_generation(generation, params, sign * values, evaluation.metrics,
                                 evaluation.failures, dump_checkpoint(optimizer), seconds + time.perf_counter() - t0,
                                 replace=fresh)
        fresh = False
        t3 = time.perf_counter()
        seconds += t3 - t0
        evaluating += t2 - t1
        outside += (t1 - t0) + (t3 - t2)
        for stage, spent in (("ask", t1 - t0), *evaluation.timings.items(), ("objectives", t2 - t_objectives),
                             ("tell", t_told - t2), ("storage", t3 - t_told)):
            stages[stage] = stages.get(stage, 0.0) + spent
        bar.update(1)
        rate = optimizer.evaluations / max(seconds, 1e-9)
        best = sign * optimizer.best_value if math.isfinite(optimizer.best_value) else float("nan")
        shown = f"{rate:,.0f}" if rate >= 100 else f"{rate:.3g}"
        bar.set_postfix_str(f"{shown} designs/s, best {spec.metric} {best:.6g}")
    bar.close()
    best = {**optimizer.best_params, **spec.fixed} if optimizer.best_params is not None else None
    value = sign * optimizer.best_value if math.isfinite(optimizer.best_value) else math.nan
    return StudyResult(best, value, optimizer.evaluations, spec.generations, seconds,
                       outside / max(evaluating + outside, 1e-12), stages)
