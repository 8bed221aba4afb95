"""run_study: ask -> evaluate (one batch of worlds) -> tell -> store, generation after generation.

Interrupting a run loses at most the generation in flight: each finished generation is stored
with the optimizer's checkpoint in one transaction, and resume=True continues from it (the
optimizer's random state included, so a resumed study ends where an uninterrupted one would).
"""

from __future__ import annotations

import math
import pickle
import time
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import load_family
from morphopt.optimizers import CMAES, OptunaSampler, RandomSearch
from morphopt.storage import StudyStorage
from morphopt.study_spec import StudySpec

__all__ = ["StudyResult", "run_study"]


@dataclass
class StudyResult:
    """Best design (all parameters), its objective value (natural sign), evaluations, seconds."""

    best_params: dict | None
    best_value: float
    evaluations: int
    generations: int
    seconds: float


def _make_optimizer(spec: StudySpec, space):
    if spec.optimizer == "cma":
        return CMAES(space, popsize=spec.worlds, sigma0=spec.sigma0, seed=spec.seed)
    if spec.optimizer == "optuna":
        return OptunaSampler(space, sampler=spec.sampler, seed=spec.seed)
    return RandomSearch(space, seed=spec.seed)


def objective_values(spec: StudySpec, evaluation) -> np.ndarray:
    """Values to minimize: the metric (negated when maximized); inf for failed designs."""
    sign = -1.0 if spec.direction == "maximize" else 1.0
    values = []
    for metrics, failure in zip(evaluation.metrics, evaluation.failures):
        value = metrics.get(spec.metric, math.nan) if not failure else math.nan
        values.append(sign * value if value is not None and math.isfinite(value) else math.inf)
    return np.array(values)


def _scalars(metrics: dict) -> dict:
    return {k: (float(v) if math.isfinite(v) else None) for k, v in metrics.items() if isinstance(v, (int, float))}


def run_study(spec: StudySpec, *, resume: bool = False, progress: bool = True) -> StudyResult:
    """Run (or resume) a study; returns the best design found."""
    family = load_family(spec.family)
    space = spec.design_space(family)
    storage = StudyStorage(spec.storage_url, spec.name)
    checkpoint = storage.checkpoint() if resume else None
    if resume and checkpoint is None:
        raise ValueError(f"study '{spec.name}' has nothing to resume in {spec.storage_url}")
    if checkpoint:
        done, state, seconds = checkpoint
        optimizer = pickle.loads(state)
        start = done + 1
    else:
        storage.clear()
        optimizer, start, seconds = _make_optimizer(spec, space), 0, 0.0
    sign = -1.0 if spec.direction == "maximize" else 1.0
    bar = tqdm(total=spec.generations, initial=start, desc=spec.name, unit="gen", disable=not progress)
    for generation in range(start, spec.generations):
        t0 = time.perf_counter()
        free = optimizer.ask(spec.worlds)
        params = [{**p, **spec.fixed} for p in free]
        if spec.mode == "kinematic":
            evaluation = evaluate_kinematic(family, params, samples=spec.samples)
        else:
            evaluation = evaluate_dynamic(family, params, duration=spec.duration, dt=spec.dt, device=spec.device,
                                          crank_speed=spec.crank_speed)
        values = objective_values(spec, evaluation)
        optimizer.tell(free, values.tolist())
        seconds += time.perf_counter() - t0
        storage.write_generation(generation, params, sign * values, [_scalars(m) for m in evaluation.metrics],
                                 evaluation.failures, pickle.dumps(optimizer), seconds)
        bar.update(1)
        rate = optimizer.evaluations / max(seconds, 1e-9)
        best = sign * optimizer.best_value if math.isfinite(optimizer.best_value) else float("nan")
        bar.set_postfix_str(f"{rate:,.0f} designs/s, best {spec.metric} {best:.6g}")
    bar.close()
    best = {**optimizer.best_params, **spec.fixed} if optimizer.best_params is not None else None
    value = sign * optimizer.best_value if math.isfinite(optimizer.best_value) else math.nan
    return StudyResult(best, value, optimizer.evaluations, spec.generations, seconds)
