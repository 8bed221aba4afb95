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
                  own, 2 pi for linkage families), samples (points per crank turn, kinematic mode),
                  model ("maximal", the default, or "reduced": walkers in reduced coordinates,
                  engine.legged, for families with build_legged)
    [solver]      engine settings of dynamic studies: any field of engine.SolverConfig (e.g.
                  max_iterations, tolerance, linear_solver); default: SolverConfig's own
    [space]       per parameter: [low, high] to narrow the family's bounds
    [fixed]       per parameter: a value held fixed
    [constraints] per metric: [low, high]; a design outside fails with the reason (TOML has inf)

``family`` is either the name of a module in designs/ (a plain identifier such as "four_bar")
or an explicit path to a .py file (relative paths are taken from the spec file's folder); any
other value is refused, so a study never loads code from elsewhere (see morphopt.families).

A study file is data: it is parsed as TOML and checked, never executed. Every error names the
file, the key and what was expected.
"""

from __future__ import annotations

import math
import pathlib
import re
import tomllib
from dataclasses import dataclass, field, replace

from morphopt.design_space import Choice, DesignSpace, Float, Int
from morphopt.families import load_family

__all__ = ["Objective", "StudySpec", "load_study_spec"]

SECTIONS = {
    "study": {"name": str, "family": str, "mode": str, "seed": int, "generations": int, "worlds": int,
              "device": str, "storage": str},
    "objective": {"metric": str, "direction": str, "point": str, "target": list},
    "objectives": None,
    "optimizer": {"name": str, "sigma0": float, "sampler": str, "restarts": int, "restart_strategy": str},
    "simulation": {"duration": float, "dt": float, "crank_speed": float, "samples": int, "model": str},
    "solver": None,
    "space": None,
    "fixed": None,
    "constraints": None,
}
REQUIRED = {"study": ("name", "family")}
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,199}")  # a study name is also its default file name
DEVICE_PATTERN = re.compile(r"cpu|cuda(:[0-9]+)?")
OBJECTIVE_KEYS = {"metric": str, "direction": str, "point": str, "target": list, "weight": float}


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
    model: str = "maximal"
    space_overrides: dict = field(default_factory=dict)
    fixed: dict = field(default_factory=dict)
    constraints: dict = field(default_factory=dict)
    objectives: tuple = ()
    solver: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.objectives:
            objective = Objective(self.metric, self.direction, 1.0, self.point, self.target)
            object.__setattr__(self, "objectives", (objective,))
        elif len(self.objectives) > 1:  # the stored value is the weighted score, minimized
            object.__setattr__(self, "metric", "score")
            object.__setattr__(self, "direction", "minimize")

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

    def design_space(self, family) -> DesignSpace:

        """The family's space narrowed by [space] and without the [fixed] parameters."""
        params = {}
        for name, parameter in family.space.parameters.items():
            if name in self.fixed:
                continue
            if name in self.space_overrides:
                low, high = self.space_overrides[name]
                kind = Int if isinstance(parameter, Int) else Float
                default = parameter.default if parameter.default is not None and low <= parameter.default <= high else None
                parameter = kind(low, high, default=default) if kind is Int else Float(low, high, default=default,
                                                                                         log=parameter.log)
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
            target = {("optimizer", "name"): "optimizer", ("objective", "metric"): "metric"}.get((section, key), key)
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
    solver = _solver(data.get("solver", {}), where)
    spec = StudySpec(path=path, space_overrides=dict(data.get("space", {})), fixed=dict(data.get("fixed", {})),
                     constraints=constraints, solver=solver, **values)
    _check_values(spec, where)
    return spec


def _solver(table: dict, where: str) -> dict:
    """The [solver] table checked by building an engine.SolverConfig from it: every key a field of
    SolverConfig, every value of that field's kind and range."""
    import dataclasses

    from engine import SolverConfig

    fields = {f.name: f for f in dataclasses.fields(SolverConfig)}
    for key, value in table.items():
        if key not in fields:
            raise ValueError(f"{where}: unknown key 'solver.{key}'; expected a field of engine.SolverConfig: "
                             f"{sorted(fields)}")
        default = getattr(SolverConfig, key)
        kind = bool if isinstance(default, bool) else int if isinstance(default, int) else (
            float if isinstance(default, float) else str)
        ok = isinstance(value, kind) and not (kind is not bool and isinstance(value, bool))
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            ok = True
        if not ok:
            raise ValueError(f"{where}: 'solver.{key}' must be {kind.__name__} "
                             f"(like the default {default!r}), got {value!r}")
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
        ("optimizer.sigma0", 0.0 < spec.sigma0 <= 1.0, "a number in (0, 1]"),
        ("simulation.duration", 0.0 < spec.duration < math.inf, "a positive finite number of seconds"),
        ("simulation.dt", 0.0 < spec.dt <= 0.1, "a time step in (0, 0.1] s"),
        ("simulation.crank_speed", spec.crank_speed is None or (spec.crank_speed != 0.0 and math.isfinite(spec.crank_speed)),
         "a non-zero speed"),
        ("simulation.samples", spec.samples >= 8, "an integer >= 8"),
        ("simulation.model", spec.model in ("maximal", "reduced"),
         "'maximal' (every link a body) or 'reduced' (a walker's torso and crank angles: engine.legged)"),
        ("simulation.model", spec.model == "maximal" or spec.mode == "dynamic",
         "'maximal' in kinematic mode (the reduced model simulates dynamics)"),
    ]
    for key, ok, expected in checks:
        if not ok:
            raise ValueError(f"{where}: '{key}' must be {expected}")
    for k, objective in enumerate(spec.objectives):
        key = "objective" if not spec.multi_objective else f"objectives[{k}]"
        if objective.metric == "path_error" and not (objective.point and len(objective.target) >= 3):
            raise ValueError(f"{where}: metric 'path_error' needs '{key}.point' and '{key}.target' "
                             f"as at least three [x, y] points")
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
