"""What a design family promises a study, checked before any work: its functions return what the
evaluation needs, and the metrics and tracked points a study names are ones the evaluation gives.

Families declare no list of metrics: the names are derived from what the family builds, by the
rules of morphopt.evaluate (tests/morphopt/test_study_file_checks.py runs the evaluation and
compares, so the two cannot drift apart):

    kinematic  per tracked point P of generate's linkage: P_stride, P_stride_full, P_step_height; and
               transmission_angle_min
    dynamic    per tracked point P of the world (build_spec, or generate's linkage
               made a world): P_stride, P_stride_full, P_step_height; torque_peak, torque_rms,
               loop_violation_max; with a point "torso": walking_speed, heading_drift,
               energy_per_distance; with "torso" and "torso_up": torso_tilt_max, torso_height_min

"path_error" is no metric of the evaluation: the study computes it for an objective from the path
of a tracked point and a target curve.

What each metric means, with its unit, is said once, in DEFINITIONS: `morphopt families show`
prints it and the README's metric list is its markdown (metric_table; a test compares them).

The contract: the function the study's mode uses (generate, or build_spec) builds the family's own
default design without raising and returns a Linkage or an engine.MechanismSpec; otherwise one ValueError names the family
file, the function and what it did (the exception's type, message and line).

The designs built to find these names (probes) are the study's: the defaults of its design space
with its [fixed] values, one per topology (each combination of the free integer and choice
parameters, at most MAX_PROBES), since a topology can change the tracked points (a walker's
legs_per_side). A metric must be given by every probe.
"""

from __future__ import annotations

import enum
import itertools
import math
from dataclasses import dataclass, field

from morphopt.design_space import Choice, DesignSpace, Int
from morphopt.families import describe_exception

__all__ = ["DEFINITIONS", "Definition", "FamilyMetrics", "Mode", "RECORD_EVERY", "check_default_design",
           "definition", "family_metrics", "metric_table", "point_metrics"]


class Mode(enum.StrEnum):
    """A study's evaluation: one crank turn of kinematics, or a simulation."""

    KINEMATIC = "kinematic"
    DYNAMIC = "dynamic"


POINT_METRICS = ("stride", "stride_full", "step_height")
KINEMATIC_METRICS = ("transmission_angle_min",)
DYNAMIC_METRICS = ("torque_peak", "torque_rms", "loop_violation_max")
WALKING_METRICS = ("walking_speed", "heading_drift", "energy_per_distance")  # with a point "torso"
UPRIGHT_METRICS = ("torso_tilt_max", "torso_height_min")  # with points "torso" and "torso_up"
RECORD_EVERY = 10  # a study's rollouts record every 10th step (evaluate_dynamic's default)
MAX_PROBES = 32
VALUES_PER_PARAMETER = 8  # an integer parameter of a wider range is probed at 8 values, ends included




@dataclass(frozen=True)
class Definition:
    """What a metric means: its unit ("1": a ratio), the modes that give it, one line of meaning;
    ``per_point``: the name is "<point>_<name>", one per tracked point."""

    name: str
    unit: str
    modes: tuple
    meaning: str
    per_point: bool = False

    @property
    def label(self) -> str:
        """The name as users write it ("<point>_stride" for a per-point metric)."""
        return f"<point>_{self.name}" if self.per_point else self.name


BOTH, KINEMATIC, DYNAMIC = (Mode.KINEMATIC, Mode.DYNAMIC), (Mode.KINEMATIC,), (Mode.DYNAMIC,)
DEFINITIONS = {d.label: d for d in (
    Definition("stride", "m", BOTH, "flat-stance stride: horizontal extent of the part of the point's path within 2 % "
               "of its step height above its lowest point, over a crank turn (dynamic: the last turn's records); "
               "band edges and extrema interpolated between samples", per_point=True),
    Definition("stride_full", "m", BOTH, "full stride: the path's whole horizontal extent over a crank turn (the "
               "stride quoted for Jansen's leg: 67.9 mm at his numbers, of which 49.3 mm flat)", per_point=True),
    Definition("step_height", "m", BOTH, "vertical extent of the point's path over a crank turn", per_point=True),
    Definition("transmission_angle_min", "rad", KINEMATIC, "smallest transmission angle of any dyad over the crank "
               "turn, folded into [0, pi/2] (pi/2 is ideal, 0 locks)"),
    Definition("torque_peak", "N m", DYNAMIC, "largest absolute torque of the driven joints over the run"),
    Definition("torque_rms", "N m", DYNAMIC, "RMS torque of the driven joints over the run"),
    Definition("loop_violation_max", "m", DYNAMIC, "largest joint separation over the run (the loop-closure "
               "error, measured whatever coordinates the engine planned)"),
    Definition("walking_speed", "m/s", DYNAMIC, "walkers (a point 'torso'): forward distance of the torso over the "
               "last three quarters of the run, per second"),
    Definition("heading_drift", "1", DYNAMIC, "walkers: sideways per forward distance of the torso over the last "
               "three quarters of the run"),
    Definition("energy_per_distance", "J/m", DYNAMIC, "walkers: the motors' work (absolute torque x crank speed x time) "
               "per metre walked over the last three quarters of the run (inf below 0.1 mm)"),
    Definition("torso_tilt_max", "rad", DYNAMIC, "walkers (points 'torso' and 'torso_up'): largest tilt of the "
               "torso's up axis from vertical (more than 45 degrees: fallen, a failure)"),
    Definition("torso_height_min", "1", DYNAMIC, "walkers: lowest torso height as a fraction of its starting height "
               "(below 0.5: fallen, a failure)"),
    Definition("path_error", "m", BOTH, "objectives only (with a point and a target curve): RMS distance between the "
               "point's path and the target, both resampled by arc length, the best over start and direction"),
)}


def definition(name: str, points=()) -> Definition | None:
    """The Definition of metric ``name`` ("foot_stride" is "<point>_stride" for a point "foot" of
    ``points``), None for a name it does not know."""
    if name in DEFINITIONS:
        return DEFINITIONS[name]
    for point in sorted(points, key=len, reverse=True):  # the longest point that prefixes the name
        if name.startswith(point + "_") and f"<point>_{name[len(point) + 1:]}" in DEFINITIONS:
            return DEFINITIONS[f"<point>_{name[len(point) + 1:]}"]
    return None


def metric_table() -> str:
    """Every metric as a markdown table (name, unit, modes, meaning): the README's list."""
    rows = [f"| `{d.label}` | {d.unit} | {', '.join(d.modes)} | {d.meaning} |" for d in DEFINITIONS.values()]
    return "\n".join(["| metric | unit | modes | meaning |", "|---|---|---|---|", *rows])


def point_metrics(points, mode: str) -> list[str]:
    """The metric names the evaluation gives a design with these tracked points in ``mode``."""
    names = [f"{p}_{m}" for p in points for m in POINT_METRICS]
    if mode == "kinematic":
        return names + list(KINEMATIC_METRICS)
    names += DYNAMIC_METRICS
    if "torso" in points:
        names += WALKING_METRICS
        if "torso_up" in points:
            names += UPRIGHT_METRICS
    return names


@dataclass(frozen=True)
class FamilyMetrics:
    """What the study's designs give: the metrics and tracked points of every probe (in order);
    ``lacking``: for a metric or point of some probes only, a probe without it (its topology);
    in dynamic mode the slowest and fastest crank speed of the probes [rad/s] (None: no drive)."""

    metrics: tuple
    points: tuple
    lacking: dict = field(default_factory=dict)
    slowest: float | None = None
    fastest: float | None = None


def _module_file(family) -> str:
    return str(getattr(family, "__file__", None) or getattr(family, "__name__", "<family>"))


def _call(family, function: str, params: dict, what: str, **kwargs):
    """family.<function>(params, **kwargs); an exception other than ValueError (which says: this
    design cannot be built) is _Broken, naming the family file, the function and the line."""
    try:
        return getattr(family, function)(params, **kwargs)
    except ValueError:
        raise
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - a broken family, reported by type and line
        raise _Broken(f"design family {_module_file(family)}: {function}({what}) raised "
                      f"{describe_exception(exc, _module_file(family))}") from None


class _Broken(ValueError):
    """The family broke its contract (as opposed to: this design cannot be built)."""


def _expect(value, kind, family, function: str, what: str, expected: str):
    if not isinstance(value, kind):
        text = repr(value)
        raise _Broken(f"design family {_module_file(family)}: {function}({what}) returned {type(value).__name__} "
                      f"{text if len(text) <= 40 else text[:37] + '...'}, expected {expected}")
    return value


def _build(family, params: dict, mode: str, crank_speed, what: str) -> tuple:
    """What the evaluation builds of one design in ``mode``: (tracked point
    names, the fastest crank drive's speed [rad/s] or None). ValueError: the design cannot be
    built; _Broken: the family returned the wrong thing or raised something else."""
    from morphopt.linkage import Linkage

    if mode == "kinematic":
        linkage = _expect(_call(family, "generate", params, what), Linkage, family, "generate", what,
                          "a morphopt.linkage.Linkage")
        return list(linkage.points), None
    from engine import MechanismSpec

    if hasattr(family, "build_spec"):  # morphopt.build.build_spec prefers a family's own world
        return _world(_expect(_call(family, "build_spec", params, what, crank_speed=crank_speed), MechanismSpec,
                              family, "build_spec", what, "an engine.MechanismSpec"))
    from morphopt.linkage import to_spec

    speed = crank_speed or 2.0 * math.pi  # morphopt.build.build_spec's default for linkage families
    linkage = _expect(_call(family, "generate", params, what, crank_speed=speed), Linkage, family, "generate", what,
                      "a morphopt.linkage.Linkage")
    return _world(to_spec(linkage))


def _world(spec) -> tuple:
    """Tracked points and fastest drive speed of an engine.MechanismSpec (as evaluate_dynamic reads them)."""
    speeds = [abs(j.drive.target_velocity) for j in spec.joints if j.drive is not None and j.drive.target_velocity]
    return [p.name for p in spec.points], max(speeds) if speeds else None


def check_default_design(family, mode: str, crank_speed=None) -> tuple:
    """Build the family's own default design as the study will (``mode``); any
    exception or a result of the wrong type is a ValueError naming the family file and the
    function. Returns what _build returns."""
    params = family.space.default()
    try:
        return _build(family, params, mode, crank_speed, "default design")
    except _Broken:
        raise
    except ValueError as exc:
        raise ValueError(f"design family {_module_file(family)}: its default design cannot be built "
                         f"({' '.join(str(exc).split())})") from None


def _probes(space: DesignSpace, fixed: dict) -> list[dict]:
    """The study's designs to build: its space's defaults with [fixed], one per topology."""
    base = {**space.default(), **fixed}
    choices = []
    for name, parameter in space.parameters.items():
        if isinstance(parameter, Choice):
            values = list(parameter.options)
        elif isinstance(parameter, Int):
            count = int(parameter.high - parameter.low) + 1
            values = (list(range(int(parameter.low), int(parameter.high) + 1)) if count <= VALUES_PER_PARAMETER else
                      sorted({int(round(parameter.low + k * (parameter.high - parameter.low) / (VALUES_PER_PARAMETER - 1)))
                              for k in range(VALUES_PER_PARAMETER)}))
        else:
            continue
        choices.append((name, values))
    if not choices:
        return [base]
    if math.prod(len(values) for _, values in choices) <= MAX_PROBES:
        names = [name for name, _ in choices]
        return [{**base, **dict(zip(names, combo))} for combo in itertools.product(*(v for _, v in choices))]
    probes = [base] + [{**base, name: value} for name, values in choices for value in values if value != base[name]]
    return probes[:MAX_PROBES]


def _describe(params: dict, space: DesignSpace) -> str:
    """A probe by its topology (the free integer and choice values)."""
    parts = [f"{name}={params[name]!r}" for name, p in space.parameters.items() if isinstance(p, (Int, Choice))]
    return "the study's design with " + ", ".join(parts) if parts else "the study's default design"


def _union(lists) -> list:
    """Every name of ``lists``, once, in order of first appearance."""
    return list(dict.fromkeys(name for names in lists for name in names))


def family_metrics(family, space: DesignSpace, fixed: dict, mode: str,
                   crank_speed=None) -> FamilyMetrics:
    """Check the family's default design (check_default_design), then build the study's probes
    (``space``: the study's design space, ``fixed``: its [fixed] values) and collect what they
    give. A probe that cannot be built (ValueError) is skipped; with none left, the default
    design's names are used. A few ms for a walker's 8 topologies, microseconds for a linkage."""
    default_points, default_speed = check_default_design(family, mode, crank_speed)
    built = []
    for params in _probes(space, fixed):
        what = _describe(params, space)
        if params == family.space.default():  # built above: the family is called once for it
            built.append((what, default_points, default_speed))
            continue
        try:
            points, speed = _build(family, family.space.validate(params), mode, crank_speed, what)
        except _Broken:
            raise
        except ValueError:  # this design cannot be built: the evaluation reports it as failed
            continue
        built.append((what, points, speed))
    if not built:
        built = [("the default design", default_points, default_speed)]
    every = [point_metrics(points, mode) for _, points, _ in built]
    metrics = [m for m in _union(every) if all(m in names for names in every)]
    points = [p for p in _union([b[1] for b in built]) if all(p in b[1] for b in built)]
    lacking = {}
    for (what, names_of_points, _), names in zip(built, every):
        for name in [*_union(every), *_union([b[1] for b in built])]:
            if name not in names and name not in names_of_points:
                lacking.setdefault(name, what)
    speeds = [speed for _, _, speed in built if speed]
    return FamilyMetrics(tuple(metrics), tuple(points), lacking, min(speeds) if speeds else None,
                         max(speeds) if speeds else None)
