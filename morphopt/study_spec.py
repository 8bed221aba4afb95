"""StudySpec: a study read from TOML and checked before anything runs.

    [study]       name (letters, digits, "_", "-", "."), family, mode ("kinematic" | "dynamic"),
                  seed (>= 0), generations, worlds, device ("cpu", "cuda", "cuda:N"), storage (path
                  relative to the spec file, or an SQLAlchemy URL)
    [objective]   metric (a metric name of the evaluation), direction ("minimize" | "maximize");
                  metric "path_error" also needs point (a tracked point) and target (a closed
                  curve [[x, y], ...] in metres)
    [[objectives]] several objectives instead of [objective], each with the keys of [objective]
                  and weight (>= 0, default 1). CMA-ES and random search minimize the weighted
                  score sum_k weight_k * (+-metric_k) (minus for maximized metrics); Optuna searches
                  the Pareto front of all of them (NSGA-II or TPE), and the weighted score only
                  ranks designs in `study show`. The stored value is that score (minimized).
    [optimizer]   name ("cma" | "optuna" | "random"), sigma0, restarts and restart_strategy
                  ("ipop" | "bipop") (cma), sampler
                  ("tpe" | "nsga2" | "random", optuna)
    [simulation]  duration [s], dt [s], crank_speed [rad/s] (dynamic mode; default: the design's
                  own, 2 pi for linkage families), samples (points per crank turn, kinematic mode);
                  the engine plans the coordinates itself (engine.pack; --verbose prints the plan)
    [solver]      engine settings of dynamic studies: any field of engine.SolverConfig (e.g.
                  max_iterations, tolerance); default: SolverConfig's own
    [solver.tuning] the solver's internal knobs, any field of engine.Tuning (e.g. linear_solver,
                  rho_update_interval); default: Tuning's own (None: the engine's plan chooses)
    [space]       per parameter: [low, high] to narrow the family's bounds
    [fixed]       per parameter: a value held fixed
    [constraints] per metric: [low, high]; a design outside fails with the reason (TOML has inf)
    [cluster]     address (a Ray cluster: "local", "auto" or host:port; morphopt.cluster), workers
                  (0: one per GPU, or per CPU core), gpus_per_worker (a CUDA study's share of a
                  GPU per worker, 0.0001 to 1: 0.5 puts two workers on each GPU), shard_timeout [s]
                  (0: ten times the median shard, at least 60 s); the results are the same as
                  without a cluster

``family`` is either the name of a family (a plain identifier such as "four_bar": a module in
./designs/ or a built-in one) or an explicit path to a .py file (relative paths are taken from
the spec file's folder); any other value is refused, so a study never loads code from elsewhere
(see morphopt.families).

A study file is data: it is parsed as TOML and checked, never executed. Every error names the
file, the key and what was expected. The checks run when the file is read and again after
command-line overrides, so every command (run, resume, show, export) refuses bad input before
any work:

- names: objective and [constraints] metrics must be metrics the family gives in the study's
  mode, and a "path_error" point one of its tracked points (morphopt.contract derives both from
  what the family builds; "path_error" itself cannot be constrained: it is computed after the
  constraints); the family's generate / build_spec must build its default design
  and return the right type.
- limits, each with its reason in the message:
    study.worlds          2 .. 65536: a generation is one batch, held in memory at once (the
                          largest measured is 16384 worlds)
    study.generations     1 .. 100000, and generations x worlds <= 10^8: every design is a row
                          of the study database
    study.seed            0 .. 2^32 - 1: the optimizers' random generators take 32-bit seeds
    study.storage         a file or a database server: SQLite in memory (":memory:",
                          "sqlite://", "sqlite:///:memory:") keeps nothing
    simulation.samples    8 .. 100000 per crank turn; kinematic mode: worlds x samples <= 10^8
                          (each sample of a design's turn is held in memory, 28 bytes and 16 per
                          tracked point)
    simulation.dt         1e-6 .. 0.1 s: below a microsecond a step moves a body by less than its
                          float32 position resolves
    simulation.duration   up to 3600 s; dynamic mode: at most 10^7 steps (duration / dt) and
                          2 x 10^7 recorded world-steps (worlds x steps / 10, held in memory:
                          ~0.6 KB each for a walker), and at least one crank turn (the stride and
                          step height are measured over the last whole turn)
    simulation.crank_speed  0.01 .. 1000 rad/s in magnitude; dynamic mode: at least 8 records (one
                          every 10 steps) per crank turn at the fastest drive
"""

from __future__ import annotations

import math
import pathlib
import re
import tomllib
from dataclasses import dataclass, field, replace

from morphopt.contract import RECORD_EVERY, family_metrics
from morphopt.design_space import Choice, DesignSpace, Int
from morphopt.families import load_family

__all__ = ["Objective", "StudySpec", "check_family_contract", "load_study_spec"]

SECTIONS = {
    "study": {"name": str, "family": str, "mode": str, "seed": int, "generations": int, "worlds": int,
              "device": str, "storage": str},
    "objective": {"metric": str, "direction": str, "point": str, "target": list},
    "objectives": None,
    "optimizer": {"name": str, "sigma0": float, "sampler": str, "restarts": int, "restart_strategy": str},
    "simulation": {"duration": float, "dt": float, "crank_speed": float, "samples": int},
    "solver": None,
    "space": None,
    "fixed": None,
    "constraints": None,
    "cluster": {"address": str, "workers": int, "gpus_per_worker": float, "shard_timeout": float},
    "robustness": None,
}
REQUIRED = {"study": ("name", "family")}
MIN_GPU_SHARE = 1e-4  # the finest fraction of a GPU Ray places
MAX_WORKERS = 4096  # Ray workers a study may ask for (and the most started when it names none)
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,199}")  # a study name is also its default file name
DEVICE_PATTERN = re.compile(r"cpu|cuda(:[0-9]+)?")
REMOVED_KEYS = {  # keys of earlier study files, and what took their place
    "simulation.model": "the engine chooses the coordinates of every batch itself (remove the key; "
                        "'morphopt study run --verbose' prints the plan)",
}
OBJECTIVE_KEYS = {"metric": str, "direction": str, "point": str, "target": list, "weight": float}
# Limits (the module docstring gives the reasons; the messages repeat them)
MAX_WORLDS = 65_536
MAX_GENERATIONS = 100_000
MAX_DESIGNS = 100_000_000  # generations x worlds
MAX_SEED = 2**32 - 1
MAX_SAMPLES = 100_000
MAX_SAMPLED = 100_000_000  # worlds x samples, kinematic mode
MIN_DT = 1e-6
MAX_DURATION = 3600.0
MAX_STEPS = 10_000_000  # duration / dt, dynamic mode
MAX_RECORDS = 20_000_000  # worlds x recorded steps, dynamic mode
CRANK_SPEEDS = (0.01, 1000.0)  # |crank_speed| [rad/s]
MIN_RECORDS_PER_TURN = 8
MEMORY_STORAGE = re.compile(r"(?i)\s*(:memory:|sqlite[a-z0-9+]*://(/(:memory:)?)?(\?.*)?|.*mode=memory.*"
                            r"|sqlite[a-z0-9+]*:///file::memory:.*)\s*")


@dataclass(frozen=True)
class Objective:
    """One objective term: a metric, its direction, its weight in the score, and for "path_error"
    the tracked point and target curve."""

    metric: str
    direction: str = "maximize"
    weight: float = 1.0
    point: str = ""
    target: tuple = ()

    @property
    def sign(self) -> float:
        """-1 for maximized metrics (values are minimized), else +1."""
        return -1.0 if self.direction == "maximize" else 1.0


@dataclass(frozen=True)
class StudySpec:
    """A validated study (see the module docstring for the keys and their defaults)."""

    path: pathlib.Path
    name: str
    family: str
    mode: str = "kinematic"
    seed: int = 0
    generations: int = 10
    worlds: int = 64
    device: str = "cpu"
    storage: str = ""
    metric: str = "foot_stride"
    direction: str = "maximize"
    point: str = ""
    target: tuple = ()
    optimizer: str = "cma"
    sigma0: float = 0.25
    sampler: str = "tpe"
    restarts: int = 0
    restart_strategy: str = "ipop"
    duration: float = 2.0
    dt: float = 1e-3
    crank_speed: float | None = None
    samples: int = 360
    space_overrides: dict = field(default_factory=dict)
    fixed: dict = field(default_factory=dict)
    constraints: dict = field(default_factory=dict)
    objectives: tuple = ()
    solver: dict = field(default_factory=dict)
    cluster: str = ""  # a Ray address ("local", "auto", host:port); "": this process evaluates
    workers: int = 0  # Ray workers (0: one per GPU of a CUDA study, else one per CPU core)
    gpus_per_worker: float = 1.0  # a CUDA study's share of a GPU per Ray worker (0.5: two workers a GPU; CPU: unused)
    shard_timeout: float = 0.0  # [s] before a worker's shard runs again elsewhere (0: morphopt.cluster's rule)
    robustness: dict = field(default_factory=dict)  # the [robustness] table as written (morphopt.robust)

    def __post_init__(self):
        if not self.objectives:
            objective = Objective(self.metric, self.direction, 1.0, self.point, self.target)
            object.__setattr__(self, "objectives", (objective,))
        elif len(self.objectives) > 1:  # the stored value is the weighted score, minimized
            object.__setattr__(self, "metric", "score")
            object.__setattr__(self, "direction", "minimize")
        else:  # one [[objectives]] table is the [objective] table written another way
            only = self.objectives[0]
            for name in ("metric", "direction", "point", "target"):
                object.__setattr__(self, name, getattr(only, name))

    @property
    def multi_objective(self) -> bool:
        """Several objectives."""
        return len(self.objectives) > 1

    @property
    def pareto(self) -> bool:
        """Several objectives searched as a Pareto front (Optuna); else one value is minimized."""
        return self.multi_objective and self.optimizer == "optuna"

    @property
    def storage_url(self) -> str:
        """SQLAlchemy URL of the study database."""
        storage = self.storage or f"{self.name}.sqlite"
        if "://" in storage:
            return storage
        return f"sqlite:///{(self.path.parent / storage).resolve()}"

    def with_overrides(self, **changes) -> StudySpec:
        """A copy with command-line overrides (None values ignored), checked again."""
        changes = {k: v for k, v in changes.items() if v is not None}
        spec = replace(self, **changes)
        where = str(self.path)
        if changes:
            where += " (with " + ", ".join(f"{k}={v!r}" for k, v in changes.items()) + ")"
        _check_values(spec, where)
        return spec

    def solver_config(self):
        """The engine.SolverConfig of the [solver] table (None when the study sets nothing)."""
        if not self.solver:
            return None
        from engine import SolverConfig

        return SolverConfig(**self.solver)

    def robust(self, family, where: str | None = None):
        """The [robustness] table as a morphopt.robust.Robustness (None without one)."""
        if not self.robustness:
            return None
        from morphopt.robust import robustness_from_table

        from morphopt.design_space import Float

        numeric = {n for n, p in self.design_space(family).parameters.items() if isinstance(p, (Float, Int))}
        return robustness_from_table(self.robustness, where or str(self.path), numeric, self.mode == "dynamic")

    def design_space(self, family) -> DesignSpace:

        """The family's space narrowed by [space] and without the [fixed] parameters."""
        params = {}
        for name, parameter in family.space.parameters.items():
            if name in self.fixed:
                continue
            if name in self.space_overrides:
                low, high = self.space_overrides[name]
                default = parameter.default if parameter.default is not None and low <= parameter.default <= high else None
                parameter = replace(parameter, low=low, high=high, default=default)  # keeps log, unit and help
            params[name] = parameter
        return DesignSpace(params)


def load_study_spec(path) -> StudySpec:
    """Read and check a study TOML file; raise ValueError naming the file and key on any problem."""
    path = pathlib.Path(path)
    where = str(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ValueError(f"{where}: no such study file") from exc
    except OSError as exc:
        raise ValueError(f"{where}: cannot read the study file ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"{where}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{where}: not valid TOML ({exc})") from exc
    values = {}
    for section, content in data.items():
        if section not in SECTIONS:
            raise ValueError(f"{where}: unknown section [{section}]; expected one of {sorted(SECTIONS)}")
        if section == "objectives":
            continue  # a list of tables, checked by _objectives
        if not isinstance(content, dict):
            raise ValueError(f"{where}: '{section}' must be a [section] table")
        keys = SECTIONS[section]
        if keys is None:
            continue
        for key, value in _typed(content, keys, section, where).items():
            target = {("optimizer", "name"): "optimizer", ("objective", "metric"): "metric",
                      ("cluster", "address"): "cluster"}.get((section, key), key)
            values[target] = value
    for section, keys in REQUIRED.items():
        for key in keys:
            if key not in data.get(section, {}):
                raise ValueError(f"{where}: missing required key '{section}.{key}'")
    if ("objective" in data) == ("objectives" in data):
        raise ValueError(f"{where}: give either one [objective] table or several [[objectives]] tables")
    if "objective" in data and "metric" not in data["objective"]:
        raise ValueError(f"{where}: missing required key 'objective.metric'")
    if "target" in values:
        values["target"] = _curve(values["target"], "objective.target", where)
    family = values.get("family", "")
    if family.endswith(".py") and not pathlib.Path(family).is_absolute():
        values["family"] = str((path.parent / family).resolve())  # relative to the spec file
    if "objectives" in data:
        values["objectives"] = _objectives(data["objectives"], where)
    constraints = dict(data.get("constraints", {}))
    for name, bounds in constraints.items():
        if (not _numbers(bounds, 2) or any(math.isnan(b) for b in bounds) or bounds[0] > bounds[1]):
            raise ValueError(f"{where}: 'constraints.{name}' must be [low, high] with low <= high, got {bounds!r}")
    solver = dict(data.get("solver", {}))  # checked by _check_values, after everything that needs no engine
    spec = StudySpec(path=path, space_overrides=dict(data.get("space", {})), fixed=dict(data.get("fixed", {})),
                     constraints=constraints, solver=solver, robustness=dict(data.get("robustness", {})), **values)
    _check_values(spec, where)
    return spec


# the kind of value a [solver] or [solver.tuning] key takes, by the first word of its field's annotation
_KINDS = {"bool": bool, "int": int, "float": float, "str": str, "Integrator": str,  # enums are given by value
          "LinearSolver": str, "StepKernel": str, "ProjectionPattern": str, "SparseOrdering": str}


def _solver_keys(table: dict, cls, prefix: str, where: str) -> None:
    """Every key of ``table`` a field of ``cls`` (SolverConfig or Tuning; "tuning" checked apart), every
    value of that field's kind (a field that may be None: of its other kind)."""
    import dataclasses

    from engine.config import TUNING_FIELDS

    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key, value in table.items():
        if key not in fields:
            hint = ""
            if cls.__name__ == "SolverConfig" and key in TUNING_FIELDS:
                hint = f" ('{key}' is a field of engine.Tuning: put it under [solver.tuning])"
            raise ValueError(f"{where}: unknown key '{prefix}.{key}'{hint}; expected a field of "
                             f"engine.{cls.__name__}: {sorted(k for k in fields if k != 'tuning')}")
        if key == "tuning" and cls.__name__ == "SolverConfig":
            continue
        kind = _KINDS[str(fields[key].type).split("|")[0].strip()]
        ok = isinstance(value, kind) and not (kind is not bool and isinstance(value, bool))
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            ok = True
        if not ok:
            default = fields[key].default
            like = "left out: the plan's choice" if default is None else \
                f"like the default {getattr(default, 'value', default)!r}"
            raise ValueError(f"{where}: '{prefix}.{key}' must be {kind.__name__} ({like}), got {value!r}")


def _solver(table: dict, where: str) -> dict:
    """The [solver] table (and its [solver.tuning] sub-table) checked by building an
    engine.SolverConfig from it: every key a field of SolverConfig (of Tuning under tuning), every
    value of that field's kind and range."""
    from engine import SolverConfig, Tuning

    _solver_keys(table, SolverConfig, "solver", where)
    if "tuning" in table:
        if not isinstance(table["tuning"], dict):
            raise ValueError(f"{where}: 'solver.tuning' must be a [solver.tuning] table of engine.Tuning's fields, "
                             f"got {table['tuning']!r}")
        _solver_keys(table["tuning"], Tuning, "solver.tuning", where)
    try:
        SolverConfig(**table)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: [solver]: {exc}") from exc
    return dict(table)


def _numbers(value, count: int) -> bool:

    """True for a list of ``count`` numbers (ints or floats, not booleans)."""
    return (isinstance(value, list) and len(value) == count
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value))


def _curve(value, key: str, where: str) -> tuple:
    """A target curve [[x, y], ...] of finite numbers [m] as a tuple of (x, y) pairs."""
    if not isinstance(value, list) or not all(_numbers(p, 2) and all(map(math.isfinite, p)) for p in value):
        raise ValueError(f"{where}: '{key}' must be a list of [x, y] points (finite numbers, metres), got {value!r}")
    return tuple(tuple(float(c) for c in p) for p in value)


def _typed(table: dict, keys: dict, prefix: str, where: str) -> dict:
    """The table's values checked against ``keys`` (name -> type; ints pass as floats)."""
    out = {}
    for name, value in table.items():
        if f"{prefix}.{name}" in REMOVED_KEYS:
            raise ValueError(f"{where}: '{prefix}.{name}' is no longer a setting: {REMOVED_KEYS[f'{prefix}.{name}']}")
        if name not in keys:
            raise ValueError(f"{where}: unknown key '{prefix}.{name}'; expected one of {sorted(keys)}")
        expected = keys[name]
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, expected) or isinstance(value, bool):
            raise ValueError(f"{where}: '{prefix}.{name}' must be {expected.__name__}, got {value!r}")
        out[name] = value
    return out


def _objectives(tables, where: str) -> tuple:
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise ValueError(f"{where}: 'objectives' must be one or more [[objectives]] tables")
    objectives = []
    for k, table in enumerate(tables):
        key = f"objectives[{k}]"
        table = _typed(table, OBJECTIVE_KEYS, key, where)
        if "metric" not in table:
            raise ValueError(f"{where}: missing required key '{key}.metric'")
        if table.get("direction", "maximize") not in ("minimize", "maximize"):
            raise ValueError(f"{where}: '{key}.direction' must be 'minimize' or 'maximize'")
        if not (math.isfinite(table.get("weight", 1.0)) and table.get("weight", 1.0) >= 0.0):
            raise ValueError(f"{where}: '{key}.weight' must be a finite number >= 0")
        target = _curve(table["target"], f"{key}.target", where) if "target" in table else ()
        objectives.append(Objective(table["metric"], table.get("direction", "maximize"), table.get("weight", 1.0),
                                    table.get("point", ""), target))
    return tuple(objectives)


def _check_values(spec: StudySpec, where: str) -> None:
    checks = [
        ("study.name", isinstance(spec.name, str) and NAME_PATTERN.fullmatch(spec.name) is not None,
         "1 to 200 letters, digits, '_', '-' or '.' (it names the storage file), not starting with '.', '_' or '-'"),
        ("study.device", isinstance(spec.device, str) and DEVICE_PATTERN.fullmatch(spec.device) is not None,
         "'cpu', 'cuda' or 'cuda:N'"),
        ("study.seed", spec.seed >= 0, "an integer >= 0"),
        ("study.mode", spec.mode in ("kinematic", "dynamic"), "'kinematic' or 'dynamic'"),
        ("objective.direction", spec.direction in ("minimize", "maximize"), "'minimize' or 'maximize'"),
        ("optimizer.name", spec.optimizer in ("cma", "optuna", "random"), "'cma', 'optuna' or 'random'"),
        ("optimizer.sampler", spec.sampler in ("tpe", "nsga2", "random"), "'tpe', 'nsga2' or 'random'"),
        ("optimizer.restarts", spec.restarts >= 0, "an integer >= 0 (restarts of CMA-ES)"),
        ("optimizer.restart_strategy", spec.restart_strategy in ("ipop", "bipop"), "'ipop' or 'bipop'"),
        ("study.generations", spec.generations >= 1, "an integer >= 1"),
        ("study.worlds", spec.worlds >= 2, "an integer >= 2"),
        ("cluster.workers", 0 <= spec.workers <= MAX_WORKERS,
         f"an integer in 0 .. {MAX_WORKERS} (0: one per GPU or CPU core)"),
        ("cluster.gpus_per_worker", MIN_GPU_SHARE <= spec.gpus_per_worker <= 1.0,
         f"a share of a GPU in [{MIN_GPU_SHARE:g}, 1] (a CUDA study's; a CPU study's workers take CPU cores)"),
        ("cluster.shard_timeout", 0.0 <= spec.shard_timeout <= 86400.0 and math.isfinite(spec.shard_timeout),
         "0 (the automatic timeout) or seconds up to a day"),
        ("cluster.address", spec.cluster == "" or spec.cluster.strip() == spec.cluster != "",
         "'local', 'auto' or a Ray address host:port"),
        ("study.seed", spec.seed <= MAX_SEED,
         f"at most 2**32 - 1 = {MAX_SEED}: the optimizers' random generators take 32-bit seeds"),
        ("study.generations", spec.generations <= MAX_GENERATIONS,
         f"at most {MAX_GENERATIONS}: every generation is a transaction of the study database and a step of the "
         f"optimizer; search longer with more worlds a generation"),
        ("study.worlds", spec.worlds <= MAX_WORLDS,
         f"at most {MAX_WORLDS}: a generation is one batch of worlds held in memory at once (the largest "
         f"measured is 16384)"),
        ("optimizer.sigma0", 0.0 < spec.sigma0 <= 1.0, "a number in (0, 1]"),
        ("simulation.duration", 0.0 < spec.duration <= MAX_DURATION,
         f"a positive number of seconds, at most {MAX_DURATION:g} (an hour simulated per design)"),
        ("simulation.dt", MIN_DT <= spec.dt <= 0.1,
         f"a time step in [{MIN_DT:g}, 0.1] s: below a microsecond a step moves a body by less than its float32 "
         f"position resolves"),
        ("simulation.crank_speed", spec.crank_speed is None or (spec.crank_speed != 0.0 and math.isfinite(spec.crank_speed)),
         "a non-zero speed"),
        ("simulation.crank_speed", spec.crank_speed is None or CRANK_SPEEDS[0] <= abs(spec.crank_speed) <= CRANK_SPEEDS[1],
         f"{CRANK_SPEEDS[0]:g} to {CRANK_SPEEDS[1]:g} rad/s in magnitude (one turn in 10 minutes to ~9500 rpm)"),
        ("simulation.samples", spec.samples >= 8, "an integer >= 8"),
        ("simulation.samples", spec.samples <= MAX_SAMPLES,
         f"at most {MAX_SAMPLES} points per crank turn (one every {360 / MAX_SAMPLES:g} degrees)"),
    ]
    for key, ok, expected in checks:
        if not ok:
            raise ValueError(f"{where}: '{key}' must be {expected}")
    _check_work(spec, where)
    for k, objective in enumerate(spec.objectives):
        key = "objective" if not spec.multi_objective else f"objectives[{k}]"
        if objective.metric == "path_error" and not (objective.point and len(objective.target) >= 3):
            raise ValueError(f"{where}: metric 'path_error' needs '{key}.point' and '{key}.target' "
                             f"as at least three [x, y] points")
    _solver(spec.solver, where)  # the first check that imports the engine (and Warp)
    try:
        family = load_family(spec.family)
    except ValueError as exc:
        raise ValueError(f"{where}: 'study.family': {exc}") from exc
    if spec.mode == "kinematic" and not hasattr(family, "generate"):
        raise ValueError(f"{where}: 'study.mode' must be 'dynamic' for family '{spec.family}': it builds whole "
                         f"worlds (build_spec), which have no kinematic evaluation")
    for section, table in (("space", spec.space_overrides), ("fixed", spec.fixed)):
        for name, value in table.items():
            if name not in family.space.parameters:
                raise ValueError(f"{where}: '{section}.{name}' is not a parameter of family '{spec.family}' "
                                 f"(parameters: {', '.join(family.space.names)})")
            parameter = family.space.parameters[name]
            if section == "space":
                if isinstance(parameter, Choice):
                    raise ValueError(f"{where}: 'space.{name}' cannot narrow a choice among {list(parameter.options)}; "
                                     f"hold it with [fixed] instead")
                integers = isinstance(parameter, Int)
                if (not _numbers(value, 2) or not all(map(math.isfinite, value))
                        or (integers and not all(isinstance(v, int) for v in value))):
                    kind = "integers" if integers else "finite numbers"
                    raise ValueError(f"{where}: 'space.{name}' must be [low, high] ({kind}), got {value!r}")
                if not value[0] < value[1]:
                    raise ValueError(f"{where}: 'space.{name}' has inverted bounds {value}")
                if value[0] < parameter.low or value[1] > parameter.high:
                    raise ValueError(f"{where}: 'space.{name}' {value} leaves the family's range "
                                     f"[{parameter.low}, {parameter.high}]")
            elif not parameter.contains(value):
                expected = (f"one of {list(parameter.options)}" if isinstance(parameter, Choice)
                            else f"in [{parameter.low}, {parameter.high}]")
                raise ValueError(f"{where}: 'fixed.{name}' = {value!r} is outside the family's range: expected "
                                 f"{expected}")
    if len(spec.fixed) == len(family.space.parameters):
        raise ValueError(f"{where}: every parameter is fixed; nothing to optimize")
    check_family_contract(spec, family, where)


def _check_work(spec: StudySpec, where: str) -> None:
    """Storage that keeps the results, and the memory and steps a generation needs in the study's mode."""
    if spec.storage and MEMORY_STORAGE.fullmatch(spec.storage):
        raise ValueError(f"{where}: 'study.storage' = {spec.storage!r} keeps nothing (an in-memory SQLite "
                         f"database ends with the process); give a file path or a database URL")
    if spec.generations * spec.worlds > MAX_DESIGNS:
        raise ValueError(f"{where}: 'study.generations' x 'study.worlds' ({spec.generations} x {spec.worlds}) must be at "
                         f"most {MAX_DESIGNS:.0e} designs: every design is a row of the study database")
    # a robust study's batch holds every design's nominal world and its scenarios
    scenarios = spec.robustness.get("samples", 0) if isinstance(spec.robustness.get("samples"), int) else 0
    worlds = spec.worlds * (1 + max(0, scenarios))
    if spec.mode == "kinematic" and worlds * spec.samples > MAX_SAMPLED:
        raise ValueError(f"{where}: 'simulation.samples' x 'study.worlds' ({spec.samples} x {worlds}) must be at "
                         f"most {MAX_SAMPLED:.0e}: every sample of a generation's crank turns is held in memory "
                         f"(28 bytes, and 16 per tracked point)")
    if spec.mode == "dynamic":
        steps = spec.duration / spec.dt
        if steps > MAX_STEPS:
            raise ValueError(f"{where}: 'simulation.duration' / 'simulation.dt' ({spec.duration:g} s / {spec.dt:g} s = "
                             f"{steps:.3g} steps) must be at most {MAX_STEPS:.0e} steps: every world of a generation "
                             f"takes them all")
        records = steps / RECORD_EVERY * worlds
        if records > MAX_RECORDS:
            raise ValueError(f"{where}: 'simulation.duration' / 'simulation.dt' x 'study.worlds'"
                             f"{' x (1 + robustness.samples)' if scenarios else ''} / {RECORD_EVERY} "
                             f"({records:.3g} recorded world-steps) must be at most {MAX_RECORDS:.0e}: a generation's "
                             f"records are held in memory (~0.6 KB each for a walker); shorten the run, or use "
                             f"fewer worlds or a larger dt")


def check_family_contract(spec: StudySpec, family, where: str | None = None) -> None:
    """Refuse, before any work, a family that breaks its contract for the study's mode (its
    default design must build, each function return the right type) and every metric, constraint
    or path_error point the study's designs do not give; in dynamic mode a duration shorter than
    a crank turn and a dt that records a turn fewer than 8 times. ValueError naming the file
    (``where``, default the spec's path) and the key."""
    where = where or str(spec.path)
    if spec.robustness:
        robust = spec.robust(family, where)  # its keys, distributions and parameter names
        if robust.clearance:  # the joints named, on the family's default design
            from morphopt.build import build_specs
            from morphopt.robust import with_clearance

            built = build_specs(family, [{**spec.design_space(family).default(), **spec.fixed}], workers=1)[0]
            for joint in ([] if isinstance(built, str) else robust.clearance[0]):
                try:
                    with_clearance(built, joint, robust.clearance[1])
                except ValueError as exc:
                    raise ValueError(f"{where}: 'robustness.clearance': {exc}") from None
        if robust.roughness is not None:  # rough ground needs the tabulated plan: the default design must fit it
            from engine.plan import Coordinates, _admits
            from morphopt.build import build_specs

            built = build_specs(family, [{**spec.design_space(family).default(), **spec.fixed}], workers=1)[0]
            if not isinstance(built, str):
                try:
                    _admits(Coordinates.TABULATED, built)
                except ValueError as exc:
                    raise ValueError(f"{where}: 'robustness.roughness': rough ground is simulated by the tabulated "
                                     f"plan only, and the family's default design does not fit it ({exc})") from None
        if spec.multi_objective:
            raise ValueError(f"{where}: 'robustness' takes one objective: its aggregate is the study's value")
    try:
        given = family_metrics(family, spec.design_space(family), spec.fixed, spec.mode, spec.crank_speed)
    except ValueError as exc:
        raise ValueError(f"{where}: 'study.family': {exc}") from None
    for k, objective in enumerate(spec.objectives):
        key = "objective" if not spec.multi_objective else f"objectives[{k}]"
        if objective.metric == "path_error":
            if objective.point not in given.points:
                raise ValueError(f"{where}: '{key}.point' = {objective.point!r} is not a tracked point of "
                                 f"{_designs(spec, given, objective.point)}; expected one of: {', '.join(given.points)}")
            continue
        if objective.point or objective.target:
            raise ValueError(f"{where}: '{key}.{'point' if objective.point else 'target'}' is read only by metric "
                             f"'path_error'; metric '{objective.metric}' takes neither point nor target")
        if objective.metric not in given.metrics:
            raise ValueError(_unknown_metric(spec, given, f"{key}.metric", objective.metric, where))
    for name in spec.constraints:
        if name == "path_error":
            raise ValueError(f"{where}: 'constraints.path_error' cannot be constrained: path_error is computed for an "
                             f"objective after the constraints are applied; constrain a metric of the evaluation: "
                             f"{', '.join(given.metrics)}")
        if name not in given.metrics:
            raise ValueError(_unknown_metric(spec, given, f"constraints.{name}", name, where))
    if spec.mode == "dynamic":
        _check_crank_turn(spec, given, where)


def _designs(spec: StudySpec, given, name: str) -> str:
    """Whose metrics or points were asked for, in words (the probe without ``name`` if some have it)."""
    if name in given.lacking:
        return f"every design of the study ({given.lacking[name]} has none)"
    return f"family '{spec.family}' in {spec.mode} mode"


def _unknown_metric(spec: StudySpec, given, key: str, name: str, where: str) -> str:
    return (f"{where}: '{key}' = {name!r} is not a metric of {_designs(spec, given, name)}; expected one of: "
            f"{', '.join(given.metrics)} (or 'path_error' as an objective, with a point and a target)")


def _check_crank_turn(spec: StudySpec, given, where: str) -> None:
    """A dynamic run long enough for one crank turn at the slowest drive, and recorded often
    enough (every RECORD_EVERY steps) for MIN_RECORDS_PER_TURN records a turn at the fastest."""
    source = "'simulation.crank_speed'" if spec.crank_speed is not None else "the design's own crank speed"
    if given.slowest:
        turn = 2.0 * math.pi / given.slowest
        if spec.duration < turn * (1.0 - 1e-9):
            raise ValueError(f"{where}: 'simulation.duration' = {spec.duration:g} s is shorter than one crank turn "
                             f"({turn:.4g} s at {given.slowest:.4g} rad/s, {source}): the stride and step height "
                             f"are measured over the last whole turn")
    if given.fastest:
        turn = 2.0 * math.pi / given.fastest
        records = turn / (RECORD_EVERY * spec.dt)
        if records < MIN_RECORDS_PER_TURN:
            raise ValueError(f"{where}: 'simulation.dt' = {spec.dt:g} s records a crank turn ({turn:.4g} s at "
                             f"{given.fastest:.4g} rad/s, {source}) {records:.3g} times (once every {RECORD_EVERY} "
                             f"steps): at least {MIN_RECORDS_PER_TURN} records a turn are needed for its stride and "
                             f"step height; use dt <= {turn / (RECORD_EVERY * MIN_RECORDS_PER_TURN):.3g} s or a "
                             f"slower crank")
