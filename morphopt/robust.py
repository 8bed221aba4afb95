"""Robust design: every design judged over K perturbed worlds of its own (a study's [robustness]).

Each generation draws K scenarios once, from the study's seed and the generation (common random
numbers: every design of the generation meets the same K), each a set of perturbations: additive
offsets of design parameters (manufacturing tolerances, in the parameters' units, clipped to their
bounds), and for dynamic studies a multiplier of the ground's friction coefficient (a contact's
coefficient is the geometric mean of its shape's and the ground's), a payload (the fraction of the
mass added to the body of the tracked point "torso", or of the first body), a ground slope (the
gravity turned about y: positive is uphill towards +x), a multiplier of every drive's target
speed, radial play in named revolute joints (with_clearance: the clearance-link model) and rough
ground: bumps of a drawn amplitude on the ground (engine.spec.Relief, ROUGHNESS_WAVELENGTH, phases
drawn per scenario; the mechanism lifted by the amplitude; simulated by the tabulated plan, the
walkers'). The batch holds each design's nominal world and its K scenarios next to each other (on a
cluster, shards of it: the scenarios travel as data and each worker applies its own); the
study's value is an aggregate of the objective over the scenarios that did not fail (mean, std,
quantile, CVaR, worst), a design fails when more than max_failure_share of its scenarios fail,
and the nominal metrics are stored with the aggregates (per-scenario values on request).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Aggregate", "Distribution", "Robustness", "aggregate", "draw", "expand", "robust_evaluation", "scenario_hook",
           "scenario_hooks"]


class Aggregate(enum.Enum):
    """How a design's scenario values become its value (all on the minimized scale)."""

    MEAN = "mean"
    STD = "std"
    QUANTILE = "quantile"  # the level-quantile of the minimized values (0.9: nine in ten are better)
    CVAR = "cvar"  # the mean of the worst (1 - level) share of the minimized values
    WORST = "worst"
    FAILURE_SHARE = "failure_share"


@dataclass(frozen=True)
class Distribution:
    """A perturbation: "normal" (mean, std, clipped to [low, high]) or "uniform" (low, high)."""

    kind: str
    mean: float = 0.0
    std: float = 0.0
    low: float = -math.inf
    high: float = math.inf

    def sample(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """``count`` draws from ``rng``."""
        if self.kind == "uniform":
            return rng.uniform(self.low, self.high, count)
        return np.clip(rng.normal(self.mean, self.std, count), self.low, self.high)


@dataclass(frozen=True)
class Robustness:
    """A study's [robustness] table (checked by morphopt.study_spec)."""

    samples: int
    aggregate: Aggregate = Aggregate.MEAN
    level: float = 0.9
    max_failure_share: float = 0.0
    parameters: dict = field(default_factory=dict)  # name -> Distribution of an additive offset
    friction: Distribution | None = None  # multiplier
    payload: Distribution | None = None  # added fraction of the torso's mass
    slope: Distribution | None = None  # [deg]
    speed: Distribution | None = None  # multiplier of the drives' target speeds
    roughness: Distribution | None = None  # the ground's bumps' amplitude [m] (engine.spec.Relief)
    store_scenarios: bool = False
    clearance: tuple | None = None  # (joint names, radius [m]): play in those joints (with_clearance)


def draw(robust: Robustness, seed: int, generation: int) -> list[dict]:
    """The generation's K scenarios: dicts of parameter offsets ("offsets") and the world's
    perturbations ("friction", "payload", "slope", "speed", "roughness" with "relief_phase"), the
    same for every design."""
    rng = np.random.default_rng([int(seed), int(generation), 0x5CE4A])
    K = robust.samples
    offsets = {name: d.sample(rng, K) for name, d in sorted(robust.parameters.items())}
    world = {name: (getattr(robust, name).sample(rng, K) if getattr(robust, name) is not None else np.full(K, base))
             for name, base in (("friction", 1.0), ("payload", 0.0), ("slope", 0.0), ("speed", 1.0),
                                ("roughness", 0.0))}
    # the bumps' phases, drawn last (a study without roughness draws what it drew before)
    phases = rng.uniform(0.0, 2.0 * math.pi, (K, 2)) if robust.roughness is not None else np.zeros((K, 2))
    return [{"offsets": {n: float(v[k]) for n, v in offsets.items()}, **{n: float(v[k]) for n, v in world.items()},
             "relief_phase": [float(x) for x in phases[k]], "clearance": robust.clearance} for k in range(K)]


def expand(params: list, scenarios: list, space) -> list:
    """Per design its nominal params then one per scenario (offsets added, clipped to the space)."""
    out = []
    for p in params:
        out.append(p)
        for s in scenarios:
            q = dict(p)
            for name, offset in s["offsets"].items():
                parameter = space.parameters.get(name)
                value = q[name] + offset
                if parameter is not None and hasattr(parameter, "low"):
                    value = min(max(value, parameter.low), parameter.high)
                    if type(parameter).__name__ == "Int":
                        value = int(round(value))
                q[name] = value
            out.append(q)
    return out


def scenario_hooks(params: list, scenarios: list):
    """One spec_hook for a batch: each world's scenario (scenarios[i] for params[i]; None: nominal)
    applied to its spec, found by the identity of its params dict."""
    by_world = {id(p): scenario_hook(s) for p, s in zip(params, scenarios) if s is not None}

    def hook(spec, p):
        return by_world[id(p)](spec, p) if id(p) in by_world else spec

    hook.copies = True  # scenario_hook changes a copy: a design's worlds may share its one built spec
    return hook


def scenario_hook(scenario: dict):
    """spec_hook(spec, params) applying a scenario's world perturbations to a built MechanismSpec."""
    def hook(spec, params):
        spec = dataclasses.replace(spec)
        if scenario.get("clearance"):
            joints, radius = scenario["clearance"]
            for joint in joints:
                spec = with_clearance(spec, joint, radius)
        if scenario["friction"] != 1.0 and spec.ground is not None:
            spec.ground = dataclasses.replace(spec.ground, friction=spec.ground.friction * scenario["friction"])
        if scenario["payload"] != 0.0:
            names = {p.name: p.body for p in spec.points}
            body = names.get("torso", spec.bodies[0].name)
            scale = 1.0 + scenario["payload"]
            spec.bodies = [dataclasses.replace(b, mass=b.mass * scale, inertia=np.asarray(b.inertia) * scale)
                           if b.name == body else b for b in spec.bodies]
        if scenario["slope"] != 0.0:
            a = math.radians(scenario["slope"])
            g = np.asarray(spec.gravity, float)
            spec.gravity = np.array([g[0] * math.cos(a) + g[2] * math.sin(a), g[1],
                                     -g[0] * math.sin(a) + g[2] * math.cos(a)])
        roughness = max(0.0, scenario.get("roughness", 0.0))  # (scenarios stored before roughness: none)
        if roughness > 0.0 and spec.ground is not None:
            from engine.spec import Relief
            spec.ground = dataclasses.replace(spec.ground, relief=Relief(roughness, ROUGHNESS_WAVELENGTH,
                                                                         scenario["relief_phase"]))
            spec.bodies = [dataclasses.replace(b, position=np.asarray(b.position, float) + (0.0, 0.0, roughness))
                           for b in spec.bodies]  # above the bumps' crests
        if scenario["speed"] != 1.0:
            spec.joints = [dataclasses.replace(j, drive=dataclasses.replace(
                j.drive, target_velocity=j.drive.target_velocity * scenario["speed"])) if j.drive else j
                for j in spec.joints]
        return spec
    return hook


def aggregate(values: np.ndarray, failed: np.ndarray, kind: Aggregate, level: float) -> float:
    """The aggregate of one design's minimized scenario values over those not ``failed``."""
    if kind is Aggregate.FAILURE_SHARE:
        return float(np.mean(failed))
    kept = np.sort(np.asarray(values, float)[~np.asarray(failed, bool)])
    if not len(kept):
        return math.inf
    if kind is Aggregate.MEAN:
        return float(kept.mean())
    if kind is Aggregate.STD:
        return float(kept.std())
    if kind is Aggregate.WORST:
        return float(kept[-1])
    if kind is Aggregate.QUANTILE:
        return float(np.quantile(kept, level))
    tail = max(1, int(math.ceil((1.0 - level) * len(kept) - 1e-9)))  # CVaR: the worst (1 - level) share
    return float(kept[-tail:].mean())


def robust_evaluation(spec, robust: Robustness, space, params: list, generation: int, evaluate, values_of):
    """Evaluate every design of ``params`` over its scenarios: evaluate(params, scenarios) runs one
    batch (scenarios: per params entry its scenario dict, or None for a nominal world; scenario_hook
    applies one to a built spec) and values_of(evaluation) gives the minimized
    objective per world. Returns (an Evaluation of the designs: the nominal world's metrics plus
    <metric>_<aggregate>, failure_share (and <metric>_s<k> per scenario where store_scenarios), and
    the failures (a design whose nominal world fails, or more than max_failure_share of its
    scenarios, fails with the first reason); the designs' aggregates to minimize, inf where failed)."""
    from morphopt.evaluate import Evaluation

    scenarios = draw(robust, spec.seed, generation)
    K = len(scenarios)
    batch = expand(params, scenarios, space)
    per_world = [None if k == 0 else scenarios[k - 1] for _ in params for k in range(K + 1)]
    evaluation = evaluate(batch, per_world)
    values = np.asarray(values_of(evaluation), float).reshape(len(params), K + 1)
    failures = np.asarray(evaluation.failures, dtype=object).reshape(len(params), K + 1)
    metrics, reasons, aggregates = [], [], []
    name = spec.metric
    sign = -1.0 if spec.direction == "maximize" else 1.0
    for d in range(len(params)):
        failed = np.array([bool(f) for f in failures[d, 1:]])
        share = float(failed.mean())
        value = aggregate(values[d, 1:], failed, robust.aggregate, robust.level)
        m = dict(evaluation.metrics[d * (K + 1)] or {})
        m[f"{name}_{robust.aggregate.value}"] = sign * value if robust.aggregate not in (
            Aggregate.STD, Aggregate.FAILURE_SHARE) else value
        m["failure_share"] = share
        if robust.store_scenarios:
            for k in range(K):
                m[f"{name}_s{k}"] = sign * values[d, 1 + k] if not failed[k] else math.nan
        reason = failures[d, 0]
        if not reason and (share > robust.max_failure_share or share == 1.0):
            first = next(f for f in failures[d, 1:] if f)
            limit = "all of them" if share == 1.0 else f"more than {robust.max_failure_share:g}"
            reason = f"{int(failed.sum())} of {K} scenarios failed ({limit}): {first}"
        metrics.append(m)
        reasons.append(reason or "")
        aggregates.append(math.inf if reason else value)
    return Evaluation(list(params), metrics, reasons, evaluation.timings, evaluation.plan), np.array(aggregates)


WORLD = ("friction", "payload", "slope", "speed", "roughness")
ROUGHNESS_WAVELENGTH = 0.4  # [m] of the rough ground's bumps (about a walker's stride)
TABLE_KEYS = {"samples", "aggregate", "level", "max_failure_share", "store_scenarios", "parameters", "clearance", *WORLD}


def _distribution(value, key: str, where: str) -> Distribution:
    """{normal = [mean, std], low = .., high = ..} or {uniform = [low, high]}."""
    def numbers(v, count):
        return (isinstance(v, list) and len(v) == count and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                              and math.isfinite(x) for x in v))
    if not isinstance(value, dict) or len({"normal", "uniform"} & set(value)) != 1 \
            or set(value) - {"normal", "uniform", "low", "high"}:
        raise ValueError(f"{where}: 'robustness.{key}' must be {{normal = [mean, std]}} (optionally with low and "
                         f"high bounds) or {{uniform = [low, high]}}, got {value!r}")
    if "uniform" in value:
        if not numbers(value["uniform"], 2) or value["uniform"][0] > value["uniform"][1] or set(value) != {"uniform"}:
            raise ValueError(f"{where}: 'robustness.{key}.uniform' must be [low, high] with low <= high, "
                             f"got {value['uniform']!r}")
        return Distribution("uniform", low=float(value["uniform"][0]), high=float(value["uniform"][1]))
    if not numbers(value["normal"], 2) or value["normal"][1] < 0:
        raise ValueError(f"{where}: 'robustness.{key}.normal' must be [mean, std] with std >= 0, got {value['normal']!r}")
    low, high = float(value.get("low", -math.inf)), float(value.get("high", math.inf))
    if not low <= high:
        raise ValueError(f"{where}: 'robustness.{key}': low must be <= high, got {low}, {high}")
    return Distribution("normal", float(value["normal"][0]), float(value["normal"][1]), low, high)


def robustness_from_table(table: dict, where: str, parameter_names, dynamic: bool) -> Robustness:
    """The Robustness of a study file's [robustness] table, every key checked (ValueError naming
    the file and key); parameter_names: the design parameters a tolerance may perturb."""
    if not isinstance(table, dict):
        raise ValueError(f"{where}: 'robustness' must be a [robustness] table")
    unknown = sorted(set(table) - TABLE_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown key 'robustness.{unknown[0]}'; expected {sorted(TABLE_KEYS)}")
    samples = table.get("samples")
    if not isinstance(samples, int) or isinstance(samples, bool) or not 1 <= samples <= 1024:
        raise ValueError(f"{where}: 'robustness.samples' must be an integer in 1 .. 1024 (worlds per design beside "
                         f"its nominal one), got {samples!r}")
    try:
        kind = Aggregate(table.get("aggregate", "mean"))
    except ValueError:
        raise ValueError(f"{where}: 'robustness.aggregate' must be one of {[a.value for a in Aggregate]}, got "
                         f"{table.get('aggregate')!r}") from None
    level = table.get("level", 0.9)
    if not isinstance(level, (int, float)) or isinstance(level, bool) or not 0.0 <= level < 1.0:
        raise ValueError(f"{where}: 'robustness.level' must be in [0, 1), got {level!r}")
    share = table.get("max_failure_share", 0.0)
    if not isinstance(share, (int, float)) or isinstance(share, bool) or not 0.0 <= share <= 1.0:
        raise ValueError(f"{where}: 'robustness.max_failure_share' must be in [0, 1], got {share!r}")
    store = table.get("store_scenarios", False)
    if not isinstance(store, bool):
        raise ValueError(f"{where}: 'robustness.store_scenarios' must be true or false, got {store!r}")
    parameters = table.get("parameters", {})
    if not isinstance(parameters, dict):
        raise ValueError(f"{where}: 'robustness.parameters' must be a table of design parameters")
    for name in parameters:
        if name not in parameter_names:
            raise ValueError(f"{where}: 'robustness.parameters.{name}' is not a numeric design parameter of the "
                             f"study (a tolerance is added to it); expected one of {sorted(parameter_names)}")
    world = {key: _distribution(table[key], key, where) for key in WORLD if key in table}
    if "roughness" in world and world["roughness"].low < 0.0:
        raise ValueError(f"{where}: 'robustness.roughness' is the bumps' amplitude [m]: give it a low bound >= 0 "
                         f"(uniform = [low, high], or normal with low = 0), got {table['roughness']!r}")
    clearance = None
    if "clearance" in table:
        value = table["clearance"]
        joints, radius = (value.get("joints"), value.get("radius")) if isinstance(value, dict) else (None, None)
        if not (isinstance(value, dict) and set(value) == {"joints", "radius"} and isinstance(joints, list) and joints
                and all(isinstance(j, str) and j for j in joints) and isinstance(radius, (int, float))
                and not isinstance(radius, bool) and 0.0 < radius <= 0.01):
            raise ValueError(f"{where}: 'robustness.clearance' must be {{joints = [\"name\", ...], radius = R}} with "
                             f"0 < R <= 0.01 m (play in those undriven revolute joints), got {value!r}")
        clearance = (tuple(joints), float(radius))
    if clearance and "roughness" in world:
        raise ValueError(f"{where}: 'robustness.roughness' needs the tabulated plan, which a world with "
                         f"'robustness.clearance' leaves (the clearance link is a loop the tables do not hold)")
    perturbs = sorted(world) + (["clearance"] if clearance else [])
    if perturbs and not dynamic:
        raise ValueError(f"{where}: 'robustness.{perturbs[0]}' perturbs the simulated world: a dynamic study's "
                         f"(a kinematic one takes 'robustness.parameters' only)")
    return Robustness(samples, kind, float(level), float(share),
                      {n: _distribution(d, f"parameters.{n}", where) for n, d in parameters.items()},
                      store_scenarios=store, clearance=clearance, **world)


def with_clearance(spec, joint: str, radius: float, mass_fraction: float = 0.01):
    """``spec`` with radial play of ``radius`` [m] in its undriven revolute joint ``joint``, by the
    clearance-link model: the pin's centre is held at ``radius`` from the hole's by a light link
    (mass_fraction of the child's mass) turning freely about the joint axis at both ends, so the
    pin rides on the hole's wall and crosses to the opposite wall when the load reverses (the
    contact-mode model of joint clearance: no free flight, no impact). The link starts across the
    joint, one radius off: the first step closes that gap."""
    from engine.reduced.tabulated_layout import matrix_quat
    from engine.spatial import quat_matrix

    found = [j for j in spec.joints if j.name == joint]
    if not found:
        raise ValueError(f"clearance: no joint '{joint}' in mechanism '{spec.name}'")
    j = found[0]
    if j.type.name != "REVOLUTE" or j.drive is not None:
        raise ValueError(f"clearance: joint '{joint}' must be an undriven revolute joint (a drive's angle would "
                         f"straddle the play)")
    bodies = {b.name: b for b in spec.bodies}
    child = bodies[j.child]
    if j.parent is None:
        R_p, p_p = np.eye(3), np.zeros(3)
    else:
        parent = bodies[j.parent]
        R_p, p_p = quat_matrix(parent.orientation), np.asarray(parent.position, float)
    R_anchor = R_p @ quat_matrix(j.parent_orientation)
    anchor = p_p + R_p @ np.asarray(j.parent_position, float)
    axis = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    if np.linalg.norm(side) < 1e-6:
        side = np.cross(axis, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    mass = mass_fraction * child.mass
    play = dataclasses.replace(child, name=f"{joint}_play", mass=mass, inertia=np.eye(3) * mass * max(radius, 0.01)**2,
                               com=np.zeros(3), position=anchor, orientation=matrix_quat(R_anchor),
                               velocity=np.zeros(3), angular_velocity=np.zeros(3))
    hole = dataclasses.replace(j, name=f"{joint}_hole", child=play.name, child_position=np.zeros(3),
                               child_orientation=(0.0, 0.0, 0.0, 1.0))
    pin = dataclasses.replace(j, name=f"{joint}_pin", parent=play.name, parent_position=radius * side,
                              parent_orientation=(0.0, 0.0, 0.0, 1.0))
    joints = [x for k in spec.joints for x in ((hole, pin) if k is j else (k,))]
    return dataclasses.replace(spec, bodies=[*spec.bodies, play], joints=joints)
