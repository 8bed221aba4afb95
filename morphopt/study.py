"""run_study: ask -> evaluate (one batch of worlds) -> tell -> store, generation after generation.

Interrupting a run loses at most the generation in flight: each finished generation is stored
with the optimizer's log row and checkpoint in one transaction, and resume=True rebuilds the
optimizer by replaying the stored generations (morphopt.checkpoint), so a resumed study ends
where an uninterrupted one would, bit for bit.

A run never loses stored results: the spec, the family and the device are checked before the
storage is opened; a run on a study with results refuses unless it is a resume or ``fresh`` (the
earlier results are moved aside, never deleted); one process writes a study at a time (its lease,
morphopt.storage); the effective settings (command-line overrides included) are stored with the
study and a resume uses them, refusing a study file that changed since.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pathlib
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from tqdm.auto import tqdm

from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import load_family
from morphopt.metric_table import MetricTable
from morphopt.metrics import path_error
from morphopt.optimizers import CMAES, OptunaSampler, RandomSearch
from morphopt.robust import robust_evaluation, scenario_hooks
from morphopt import checkpoint
from morphopt.storage import StudyStorage, storage_exists
from morphopt.study_spec import StudySpec, check_family_contract
from morphopt.warp_setup import Kernels, announce_compile, compile_seconds, is_verbose, quiet_warp

__all__ = ["StudyResult", "objective_matrix", "objective_metric_names", "objective_values", "pareto_front", "run_study",
           "stored_spec", "study_settings"]


@dataclass
class StudyResult:
    """Best design (all parameters), its objective value (natural sign), evaluations, seconds
    (wall time of the generations run now and before a resume) and, of this run's time, the share
    spent outside the evaluation (sampling, telling, storage): ``overhead``. ``stages``: this run's
    wall seconds per stage, summed over its generations: "ask", the evaluation's own stages
    (morphopt.evaluate.Evaluation.timings; on a cluster the workers' seconds summed over the
    shards, which run at once), "objectives", "tell" and "storage"."""

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
    several such objectives, the metric is stored as path_error, path_error_1, ...). Metrics held
    as a MetricTable (a cluster's) are read column by column."""
    failed = np.array([bool(f) for f in evaluation.failures], dtype=bool)
    table = evaluation.metrics if isinstance(evaluation.metrics, MetricTable) else None
    columns = []
    for objective, name in zip(spec.objectives, objective_metric_names(spec)):
        if objective.metric == "path_error":
            target = np.asarray(objective.target, dtype=float)
            if table is not None:
                data, begin, end = table.paths.get(objective.point, (None, np.full(len(failed), -1), None))
                ok = ~failed & table.path_rows & (begin >= 0)
                errors = np.full(len(failed), np.nan)
                for i in np.flatnonzero(ok):
                    errors[i] = path_error(data[begin[i]:end[i]], target)
                table.set_column(name, errors, ok)
            else:
                for metrics, failure in zip(evaluation.metrics, evaluation.failures):
                    if not failure:
                        metrics[name] = path_error(metrics["paths"][objective.point], target)
        if table is not None:
            value = objective.sign * table.column(name)
            columns.append(np.where(~failed & np.isfinite(value), value, math.inf))
            continue
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
    if isinstance(evaluation.metrics, MetricTable):  # column by column; the first constraint broken is named
        for name, (low, high) in spec.constraints.items():
            value = evaluation.metrics.column(name)
            with np.errstate(invalid="ignore"):
                broken = ~((low <= value) & (value <= high))
            for k in np.flatnonzero(broken):
                if not evaluation.failures[k]:
                    evaluation.failures[k] = f"constraint {name} in [{low:g}, {high:g}] violated: {value[k]:.6g}"
        return
    for k, (metrics, failure) in enumerate(zip(evaluation.metrics, evaluation.failures)):
        if failure:
            continue
        for name, (low, high) in spec.constraints.items():
            value = metrics.get(name, math.nan)
            if not (low <= value <= high):
                evaluation.failures[k] = f"constraint {name} in [{low:g}, {high:g}] violated: {value:.6g}"
                break


def _check_device(spec: StudySpec) -> None:
    """ValueError naming the spec and 'study.device' when Warp cannot use the device."""
    wp = quiet_warp()
    try:
        wp.get_device(spec.device)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"{spec.path}: 'study.device' {spec.device!r} is not available here ({exc})") from exc


RUN_OVERRIDES = ("device", "worlds", "generations", "seed")  # what `study run` may override on the command line
# may differ between runs
RESUME_CHANGES = ("device", "generations", "cluster", "workers", "gpus_per_worker", "shard_timeout")


def study_settings(spec: StudySpec) -> dict:
    """The effective settings of a run (the study file with its command-line overrides) as JSON data."""
    data = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec) if f.name != "path"}
    data["objectives"] = [dataclasses.asdict(o) for o in spec.objectives]
    return json.loads(json.dumps(data, default=list))  # tuples as lists, as they read back


def stored_spec(spec: StudySpec, storage: StudyStorage | None = None, *, say: bool = False) -> StudySpec:
    """The spec of a stored study: the file's, with the command-line overrides its runs were made
    with (worlds, seed, generations, device), so that resume, show and export see what ran;
    ``say``: a line on stderr for each value of the file that the stored one replaces."""
    storage = storage or StudyStorage(spec.storage_url, spec.name)
    if not storage_exists(spec.storage_url):
        return spec
    settings = storage.info()["settings"]
    if not settings:
        return spec
    stored = {k: settings[k] for k in RUN_OVERRIDES if k in settings}
    for key, value in stored.items():
        kind = str if key == "device" else int
        if not isinstance(value, kind) or isinstance(value, bool):
            raise ValueError(f"{storage.where}: the stored settings are damaged ('{key}' = {str(value)[:40]!r})")
        if say and key != "device" and getattr(spec, key) != value:
            extend = "; 'study resume --generations N' extends it" if key == "generations" else ""
            print(f"{spec.name}: {key} = {value} as the study was run (the study file says {getattr(spec, key)})"
                  f"{extend}", file=sys.stderr)
    return spec.with_overrides(**stored)


def _nested_solver(solver):
    """A stored [solver] table as this morphopt writes it: studies stored before engine.Tuning kept
    the method's knobs beside the user's settings; they compare as the [solver.tuning] they are now."""
    if not isinstance(solver, dict):
        return solver
    from engine import SolverConfig

    public = {f.name for f in dataclasses.fields(SolverConfig)} - {"tuning"}
    out = {k: v for k, v in solver.items() if k in public}
    tuning = {**{k: v for k, v in solver.items() if k not in public and k != "tuning"}, **solver.get("tuning", {})}
    if tuning:
        out["tuning"] = tuning
    return out


def _say_plan(name: str, plan, first: bool) -> None:
    """The engine's plan on stderr: in full with --verbose, else its first line at the first generation."""
    if plan is None:
        return
    if is_verbose():
        tqdm.write(f"{name}: {plan}", file=sys.stderr)  # above the progress bars, not inside them
    elif first:
        tqdm.write(f"{name}: {str(plan).splitlines()[0]}", file=sys.stderr)


def family_digest(family) -> str:
    """SHA-256 of a family module's source: a study resumes only with the family it ran with."""
    return hashlib.sha256(pathlib.Path(family.__file__).read_bytes()).hexdigest()


def _check_unchanged(spec: StudySpec, settings: dict | None, family_sha256: str) -> None:
    """ValueError naming the key when the study file (or its family's source) no longer describes
    the stored study."""
    if not settings:
        return
    now = {**study_settings(spec), "family_sha256": family_sha256}
    if settings.get("family_sha256", family_sha256) != family_sha256:
        raise ValueError(f"{spec.path}: the family {spec.family} is not the source study '{spec.name}' was run "
                         f"with (the file changed, or another file of that name was found first); restore it, or "
                         f"start over with 'morphopt study run {spec.path} --fresh'")
    settings = {**settings, "solver": _nested_solver(settings.get("solver"))}
    for key in now:
        if key in RESUME_CHANGES or key == "storage" or key not in settings or now[key] == settings[key]:
            continue  # where the database is may change (a moved file, another URL to it)
        if key == "family" and pathlib.Path(now[key]).name == pathlib.Path(str(settings[key])).name:
            continue  # the same family file in a moved folder
        raise ValueError(f"{spec.path}: the study file changed since study '{spec.name}' was run: '{key}' was "
                         f"{settings[key]!r}, is now {now[key]!r}; restore it, or start over with "
                         f"'morphopt study run {spec.path} --fresh'")


def _stored_told(spec: StudySpec, space, frame) -> list:
    """The optimizer log of a study stored without one (an earlier morphopt): per generation the
    digest of its designs and the values the optimizer was told, from the designs table."""
    log = []
    names = objective_metric_names(spec)
    for generation, rows in frame.groupby("generation", sort=True):
        designs = _designs(space, rows)
        sign = -1.0 if spec.direction == "maximize" else 1.0
        values = np.where(rows["value"].notna(), sign * rows["value"].to_numpy(dtype=float), math.inf)
        columns = [values]
        if spec.pareto:
            failed = rows["failure"].to_numpy() != ""
            for objective, name in zip(spec.objectives, names):
                metric = objective.sign * rows[f"metric_{name}"].to_numpy(dtype=float)
                columns.append(np.where(failed | ~np.isfinite(metric), math.inf, metric))
        log.append((int(generation), checkpoint.designs_digest(designs), np.column_stack(columns)))
    return log


def _designs(space, rows) -> list[dict]:
    """The free parameters of a generation's stored designs, as the optimizer asked for them."""
    return [{n: _plain(v) for n, v in zip(space.names, row)} for row in rows[space.names].itertuples(index=False)]


def _plain(value):
    return value.item() if hasattr(value, "item") else value


def _read_checkpoint(spec: StudySpec, space, storage: StudyStorage, state: bytes, trust: bool) -> dict | None:
    """The checkpoint's header checked against the spec (None: a pickle of an earlier morphopt, to be
    rebuilt from the stored designs, which needs ``trust``)."""
    if checkpoint.is_legacy_pickle(state) and trust:
        return None
    header, arrays = checkpoint.decode(state, storage.where)
    if header.get("optimizer") != spec.optimizer:
        raise ValueError(f"{storage.where}: the checkpoint holds optimizer '{header.get('optimizer')}', the spec asks "
                         f"for optimizer '{spec.optimizer}'; start over with 'study run --fresh'")
    if header.get("space") != checkpoint.space_description(space):
        raise ValueError(f"{storage.where}: the checkpoint was made for another design space than the spec's "
                         f"(its [space] or [fixed] changed); start over with 'study run --fresh'")
    return {"header": header, "arrays": arrays}


def _rebuilt_optimizer(spec: StudySpec, space, storage: StudyStorage, stored: dict | None, done: int,
                       progress: bool):
    """A fresh optimizer brought to the stored state by replaying the study's generations."""
    optimizer = _make_optimizer(spec, space)
    stored_designs = stored is not None and getattr(optimizer, "takes_stored_designs", False)
    frame = storage.designs() if stored is None or stored_designs else None
    log = storage.optimizer_log() if stored is not None else _stored_told(spec, space, frame)
    if [g for g, _, _ in log] != list(range(done + 1)):
        raise ValueError(f"{storage.where}: the stored optimizer log does not hold generations 0 to {done}; "
                         f"start over with 'study run --fresh'")
    if progress and log:
        print(f"{spec.name}: rebuilding the optimizer from {len(log)} stored generations", file=sys.stderr)
    designs = None
    if stored_designs:  # TPE takes the stored designs instead of sampling them again, then its random states
        designs = [_designs(space, rows) for _, rows in frame.groupby("generation", sort=True)]
    checkpoint.replay(optimizer, log, storage.where, designs)
    if stored is not None:
        if designs is not None:
            checkpoint.restore_random_states(optimizer, stored["arrays"], storage.where)
        checkpoint.check_summary(optimizer, stored["arrays"], storage.where)
    if stored is not None:
        return optimizer, []
    logged = {g for g, _, _ in storage.optimizer_log()}  # a study converted before keeps its rows
    return optimizer, [row for row in log if row[0] not in logged]


class _SimulationBar:
    """A second progress line inside a dynamic generation: steps simulated, worlds still running,
    walkers fallen so far (evaluate_dynamic's progress)."""

    def __init__(self, shown: bool):
        self.shown, self.bar = bool(shown), None

    def report(self, done: int, total: int, running: int, fallen: int) -> None:
        if self.bar is None:
            self.bar = tqdm(total=total, desc="  simulating", unit="step", leave=False, position=1)
        elif done <= self.bar.n or self.bar.total != total:  # a new generation's rollout
            self.bar.reset(total=total)
        self.bar.set_postfix_str(f"{running} worlds running, {fallen} fell", refresh=False)
        self.bar.update(done - self.bar.n)
        if done >= total:  # a generation faster than tqdm's refresh interval still shows its end
            self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _checkpoint_blob(spec: StudySpec, space, optimizer, generation: int) -> bytes:
    header = {"optimizer": spec.optimizer, "study": spec.name, "generation": generation,
              "space": checkpoint.space_description(space)}
    return checkpoint.encode(header, checkpoint.summary(optimizer))


def run_study(spec: StudySpec, *, resume: bool = False, fresh: bool = False, steal: bool = False,
              trust_checkpoint: bool = False, progress: bool = True,
              on_generation: Callable | None = None) -> StudyResult:
    """Run (or resume) a study; returns the best design found.

    A run on a study that has stored results refuses unless ``fresh`` (the earlier results are
    moved aside as '<name>.before-<time>' in the transaction of the first new generation) or
    ``resume``. ``steal`` takes the study's lease from another writer (one that is gone);
    ``trust_checkpoint`` rebuilds the optimizer of a study stored by an earlier morphopt (a pickled
    checkpoint, never unpickled) from its stored designs. on_generation(generation, seconds, stages),
    if given, is called once each generation is stored: the study's seconds so far (a resumed
    study's earlier runs included) and this run's seconds by stage so far (StudyResult.stages),
    e.g. to time generations after the first."""
    family = load_family(spec.family)
    space = spec.design_space(family)
    check_family_contract(spec, family)
    _check_device(spec)
    if resume and not storage_exists(spec.storage_url):
        raise ValueError(f"study '{spec.name}' has nothing to resume: no database {spec.storage_url}")
    storage = StudyStorage(spec.storage_url, spec.name)
    digest = family_digest(family)
    if storage_exists(spec.storage_url):
        _plan(spec, space, storage, resume, fresh, trust_checkpoint, digest)  # refuse before writing anything
    settings = {**study_settings(spec), "family_sha256": digest}
    storage.acquire(settings, steal=steal)
    try:  # under the lease, the same checks again: what they read can no longer change
        plan = _plan(spec, space, storage, resume, fresh, trust_checkpoint, digest)
        return _generations(spec, family, space, storage, plan, settings, progress, on_generation)
    finally:
        storage.release()


def _plan(spec, space, storage, resume: bool, fresh: bool, trust: bool, family_sha256: str) -> dict:
    """What a run starts from (the stored study, its checkpoint), or ValueError when it must not run."""
    info = storage.info()
    info["found"] = info["stored"] = None
    if resume:
        found = storage.checkpoint()
        if found is None:
            raise ValueError(f"study '{spec.name}' has nothing to resume in {spec.storage_url}")
        info["stored"] = _read_checkpoint(spec, space, storage, found[1], trust)
        info["found"] = found
        _check_unchanged(spec, info["settings"], family_sha256)
        if spec.generations < found[0] + 1:
            raise ValueError(f"study '{spec.name}' has {found[0] + 1} generations stored; 'study.generations' "
                             f"(--generations) must be at least that, got {spec.generations}")
    elif (info["designs"] or info["checkpoint"]) and not fresh:
        raise ValueError(f"study '{spec.name}' already has {info['designs']} designs in {info['generations']} "
                         f"generations in {spec.storage_url}; continue it with 'morphopt study resume {spec.path}', "
                         f"or start over with 'morphopt study run {spec.path} --fresh' (which keeps the earlier "
                         f"results under another name)")
    return info


def _world_values(spec: StudySpec, evaluation) -> np.ndarray:
    """Each world's minimized objective after the study's constraints (a robust batch's worlds)."""
    apply_constraints(spec, evaluation)
    return objective_values(spec, evaluation)


def _batch_evaluator(spec: StudySpec, family, steps, cluster):
    """evaluate(params, scenarios): one batch of a robust study, each world with its scenario (or
    None), here or on the cluster."""
    def evaluate(params, scenarios):
        if cluster is not None:
            return cluster.evaluate(params, scenarios)
        if spec.mode == "kinematic":
            return evaluate_kinematic(family, params, samples=spec.samples, device=spec.device,
                                      keep_paths=any(o.metric == "path_error" for o in spec.objectives))
        return evaluate_dynamic(family, params, duration=spec.duration, dt=spec.dt, device=spec.device,
                                crank_speed=spec.crank_speed, config=spec.solver_config(),
                                spec_hook=scenario_hooks(params, scenarios),
                                progress=steps.report if steps.shown else None)
    return evaluate


def _generations(spec, family, space, storage, info, settings, progress, on_generation=None) -> StudyResult:
    """The ask -> evaluate -> tell -> store loop of run_study, under the study's lease."""
    archive = backfill = None
    if info["found"] is not None:
        done, _, seconds = info["found"]
        optimizer, backfill = _rebuilt_optimizer(spec, space, storage, info["stored"], done, progress)
        start = done + 1
    else:
        optimizer, start, seconds = _make_optimizer(spec, space), 0, 0.0
        if info["designs"] or info["checkpoint"]:
            archive = storage.archive_name()
    sign = -1.0 if spec.direction == "maximize" else 1.0
    robust = spec.robust(family)
    if robust is not None and robust.aggregate.value in ("std", "failure_share"):
        sign = 1.0  # a spread or a share is minimized and stored as it is, whatever the metric's direction
    evaluating = outside = compiling = 0.0
    cluster = None
    if spec.cluster:
        from morphopt.cluster import ClusterEvaluator

        cluster = ClusterEvaluator(spec, space, address=spec.cluster, workers=spec.workers,
                                   gpus_per_worker=spec.gpus_per_worker, shard_timeout=spec.shard_timeout,
                                   log=lambda line: tqdm.write(line, file=sys.stderr))
        tqdm.write(f"{spec.name}: {cluster.workers} Ray workers at {spec.cluster!r}", file=sys.stderr)
    stages = {}
    announce_compile(Kernels.KINEMATIC if spec.mode == "kinematic" else Kernels.DYNAMIC, spec.device)
    bar = tqdm(total=spec.generations, initial=start, desc=spec.name, unit="gen", disable=not progress)
    steps = _SimulationBar(spec.mode == "dynamic" and progress)
    batch = _batch_evaluator(spec, family, steps, cluster) if robust is not None else None
    try:  # the bar ends its line before any error is printed
        for generation in range(start, spec.generations):
            if storage.lease_lost:  # the heartbeat found another writer: compute nothing it cannot store
                raise ValueError(f"{storage.where}: this run lost the study's lease (--steal); it stops before "
                                 f"generation {generation}")
            compiled_before = compile_seconds()
            t0 = time.perf_counter()
            free = optimizer.ask(spec.worlds)
            params = [{**p, **spec.fixed} for p in free]
            t1 = time.perf_counter()
            if robust is not None:  # the constraints and objective applied to every world inside
                evaluation, robust_values = robust_evaluation(spec, robust, space, params, generation, batch,
                                                              lambda ev: _world_values(spec, ev))
            elif cluster is not None:
                evaluation = cluster.evaluate(params)
                _say_plan(spec.name, evaluation.plan, generation == start and progress)
                if is_verbose():
                    tqdm.write(f"{spec.name}: generation {generation}: {cluster.report()}", file=sys.stderr)
            elif spec.mode == "kinematic":
                evaluation = evaluate_kinematic(family, params, samples=spec.samples, device=spec.device,
                                                keep_paths=any(o.metric == "path_error" for o in spec.objectives))
            else:
                evaluation = evaluate_dynamic(family, params, duration=spec.duration, dt=spec.dt, device=spec.device,
                                              crank_speed=spec.crank_speed, config=spec.solver_config(),
                                              progress=steps.report if steps.shown else None)
                _say_plan(spec.name, evaluation.plan, generation == start and progress)
            t_objectives = time.perf_counter()
            if robust is not None:  # the scenarios' aggregate (morphopt.robust), the nominal metrics stored beside
                values = robust_values
            else:
                apply_constraints(spec, evaluation)
                values = objective_values(spec, evaluation)
            told = values[:, None]
            t2 = time.perf_counter()
            if spec.pareto:
                matrix = objective_matrix(spec, evaluation)
                optimizer.tell(free, values.tolist(), matrix)
                told = np.column_stack([values, matrix])
            else:
                optimizer.tell(free, values.tolist())
            t_told = time.perf_counter()
            first = generation == start
            storage.write_generation(generation, params, sign * values, evaluation.metrics, evaluation.failures,
                                     _checkpoint_blob(spec, space, optimizer, generation),
                                     seconds + time.perf_counter() - t0, asked=checkpoint.designs_digest(free), told=told,
                                     settings=settings if first else None, archive=archive if first else None,
                                     backfill=backfill if first else None,
                                     workers=cluster.last if cluster is not None else None)
            if first and archive:
                print(f"{spec.name}: the earlier results were moved aside as study '{archive}' in {spec.storage_url}",
                      file=sys.stderr)
            t3 = time.perf_counter()
            seconds += t3 - t0
            evaluating += t2 - t1
            outside += (t1 - t0) + (t3 - t2)
            for stage, spent in (("ask", t1 - t0), *evaluation.timings.items(), ("objectives", t2 - t_objectives),
                                 ("tell", t_told - t2), ("storage", t3 - t_told)):
                stages[stage] = stages.get(stage, 0.0) + spent
            compiled = compile_seconds() - compiled_before
            compiling += compiled
            if compiled > 0.0 and not bar.disable:  # Warp compiled kernels in this generation: not in the ETA
                bar.start_t += compiled
                bar.last_print_t += compiled
            bar.update(1)
            if on_generation is not None:
                on_generation(generation, seconds, dict(stages))
            rate = optimizer.evaluations / max(seconds - compiling, 1e-9)
            best = sign * optimizer.best_value if math.isfinite(optimizer.best_value) else float("nan")
            shown = f"{rate:,.0f}" if rate >= 100 else f"{rate:.3g}"
            bar.set_postfix_str(f"{shown} designs/s, best {spec.metric} {best:.6g}")
    finally:
        steps.close()
        bar.close()
        if cluster is not None:
            tqdm.write(f"{spec.name}: {cluster.report()}", file=sys.stderr)
            cluster.close()
    best = {**optimizer.best_params, **spec.fixed} if optimizer.best_params is not None else None
    value = sign * optimizer.best_value if math.isfinite(optimizer.best_value) else math.nan
    return StudyResult(best, value, optimizer.evaluations, spec.generations, seconds,
                       outside / max(evaluating + outside, 1e-12), stages)
