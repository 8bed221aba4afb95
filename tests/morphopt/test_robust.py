"""Robust design (morphopt.robust): scenarios reproducible by seed, different from each other and
common to every design of a generation; aggregates against NumPy; a four-bar near its Grashof limit
fails more often than a sturdy one under the same tolerance; the world perturbations applied to a
walker's spec; a kinematic robust study end to end and the [robustness] table's checks."""

import math
import pathlib
import pickle
import tempfile

import numpy as np
import pytest

from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import load_family
from morphopt.robust import (Aggregate, Distribution, Robustness, aggregate, draw, expand, robust_evaluation,
                             scenario_hook, scenario_hooks)
from morphopt.storage import read_designs
from morphopt.study import objective_values, run_study
from morphopt.study_spec import load_study_spec

FOUR_BAR = load_family("four_bar")
TOLERANCE = Robustness(samples=16, parameters={n: Distribution("normal", 0.0, 1e-3)
                                               for n in ("ground", "crank", "coupler", "rocker")})


def test_scenarios_are_reproducible_different_and_common_to_every_design():
    a, b = draw(TOLERANCE, seed=7, generation=3), draw(TOLERANCE, seed=7, generation=3)
    assert a == b
    assert draw(TOLERANCE, seed=8, generation=3) != a and draw(TOLERANCE, seed=7, generation=4) != a
    offsets = np.array([[s["offsets"][n] for n in ("ground", "crank")] for s in a])
    assert len(np.unique(offsets[:, 0])) == 16 and 0.5e-3 < offsets.std() < 2e-3
    designs = [FOUR_BAR.space.default(), {**FOUR_BAR.space.default(), "ground": 0.35}]
    batch = expand(designs, a, FOUR_BAR.space)
    assert len(batch) == 2 * 17 and batch[0] is designs[0] and batch[17] is designs[1]
    for k in range(16):  # the same offsets for both designs
        for name in ("ground", "crank", "coupler", "rocker"):
            assert batch[1 + k][name] - designs[0][name] == pytest.approx(batch[18 + k][name] - designs[1][name])


def test_aggregates_against_numpy():
    rng = np.random.default_rng(0)
    values = rng.normal(size=40)
    failed = np.zeros(40, bool)
    failed[[3, 17]] = True
    kept = np.sort(values[~failed])
    assert aggregate(values, failed, Aggregate.MEAN, 0.9) == pytest.approx(kept.mean())
    assert aggregate(values, failed, Aggregate.STD, 0.9) == pytest.approx(kept.std())
    assert aggregate(values, failed, Aggregate.WORST, 0.9) == kept[-1]
    assert aggregate(values, failed, Aggregate.QUANTILE, 0.75) == pytest.approx(np.quantile(kept, 0.75))
    # CVaR at 0.9 of 38 values: the mean of the worst ceil(3.8) = 4
    assert aggregate(values, failed, Aggregate.CVAR, 0.9) == pytest.approx(kept[-4:].mean())
    assert aggregate(values, failed, Aggregate.FAILURE_SHARE, 0.9) == pytest.approx(2 / 40)
    assert aggregate(values, np.ones(40, bool), Aggregate.MEAN, 0.9) == math.inf


def test_a_four_bar_near_its_grashof_limit_fails_more_often_than_a_sturdy_one(tmp_path):
    """Tolerances of 1 mm on every length: a crank-rocker 1 mm inside Grashof's s + l <= p + q
    fails to turn in the scenarios that leave it (about a third), one 150 mm inside in none; the
    failure shares equal Grashof's condition evaluated on each scenario's lengths."""
    sturdy = {**FOUR_BAR.space.default()}  # 0.1 + 0.3 against 0.3 + 0.25
    fragile = {**sturdy, "ground": 0.399, "coupler": 0.3, "rocker": 0.2}  # 0.1 + 0.399 against 0.5
    path = tmp_path / "s.toml"
    path.write_text('[study]\nname = "s"\nfamily = "four_bar"\nmode = "kinematic"\n[objective]\n'
                    'metric = "transmission_angle_min"\ndirection = "maximize"\n[simulation]\nsamples = 90\n')
    spec = load_study_spec(path)
    result, _ = robust_evaluation(spec, TOLERANCE, FOUR_BAR.space, [sturdy, fragile], 0,
                               lambda params, hooks: evaluate_kinematic(FOUR_BAR, params, samples=90),
                               lambda ev: objective_values(spec, ev))
    shares = [m["failure_share"] for m in result.metrics]
    # the oracle: Grashof's condition (the crank shortest, s + l <= p + q) for each scenario's lengths
    predicted = []
    for design in (sturdy, fragile):
        turns = []
        for scenario in draw(TOLERANCE, spec.seed, 0):
            n = {k: design[k] + scenario["offsets"][k] for k in ("ground", "crank", "coupler", "rocker")}
            lengths = sorted(n.values())
            turns.append(n["crank"] == lengths[0] and lengths[0] + lengths[3] <= lengths[1] + lengths[2])
        predicted.append(1.0 - np.mean(turns))
    print(f"failure share: sturdy {shares[0]:.3f}, fragile {shares[1]:.3f} (Grashof: {predicted})")
    assert shares == predicted
    assert shares[0] == 0.0 and shares[1] >= 0.1
    assert result.failures[0] == "" and "scenarios failed" in result.failures[1]


def test_world_perturbations_change_the_walkers_spec_as_documented():
    walker = load_family("walker")
    spec = walker.build_spec({**walker.space.default(), "legs_per_side": 3})
    torso = {p.name: p.body for p in spec.points}["torso"]
    scenario = {"offsets": {}, "friction": 0.5, "payload": 0.3, "slope": 5.0, "speed": 1.2}
    changed = scenario_hook(scenario)(spec, {})
    mass = {b.name: b.mass for b in spec.bodies}
    assert {b.name: b.mass for b in changed.bodies}[torso] == pytest.approx(1.3 * mass[torso])
    assert sum(b.mass for b in changed.bodies) == pytest.approx(sum(mass.values()) + 0.3 * mass[torso])
    g = np.linalg.norm(spec.gravity)
    np.testing.assert_allclose(changed.gravity, [-g * math.sin(math.radians(5)), 0, -g * math.cos(math.radians(5))],
                               atol=1e-12)
    assert changed.ground.friction == pytest.approx(0.5 * spec.ground.friction)
    speeds = [(a.drive.target_velocity, b.drive.target_velocity) for a, b in zip(spec.joints, changed.joints)
              if a.drive is not None]
    assert speeds and all(b == pytest.approx(1.2 * a) for a, b in speeds)
    assert spec.gravity[0] == 0.0  # the original is untouched


def test_rough_ground_puts_walkers_on_bumps_and_leaves_the_other_draws_alone():
    slope = Distribution("uniform", low=-5.0, high=5.0)
    plain = draw(Robustness(samples=6, slope=slope), seed=3, generation=1)
    rough_table = Robustness(samples=6, slope=slope, roughness=Distribution("uniform", low=0.0, high=0.02))
    rough = draw(rough_table, seed=3, generation=1)
    assert [s["slope"] for s in rough] == [s["slope"] for s in plain]  # drawn after them: a study keeps its draws
    assert all(s["roughness"] == 0.0 for s in plain)
    assert all(0.0 <= s["roughness"] <= 0.02 for s in rough) and len({s["roughness"] for s in rough}) == 6
    assert rough == draw(rough_table, seed=3, generation=1)
    walker = load_family("walker")
    params = {**walker.space.default(), "legs_per_side": 3}
    spec = walker.build_spec(params)
    changed = scenario_hook(rough[0])(spec, params)
    assert changed.ground.relief.amplitude == rough[0]["roughness"]
    np.testing.assert_array_equal(changed.ground.relief.phase, rough[0]["relief_phase"])
    lift = [b.position[2] - a.position[2] for a, b in zip(spec.bodies, changed.bodies)]
    np.testing.assert_allclose(lift, rough[0]["roughness"])  # above the crests
    assert spec.ground.relief is None  # the original is untouched
    # simulated on the tabulated plan: the same design on flat and on rough ground walks differently
    batch = [params, dict(params)]
    evaluation = evaluate_dynamic(walker, batch, duration=1.3, dt=0.005, device="cpu",
                                  spec_hook=scenario_hooks(batch, [None, rough[0]]))
    assert not any(evaluation.failures)
    assert "relief" in str(evaluation.plan)
    speeds = [m["walking_speed"] for m in evaluation.metrics]
    assert speeds[0] != speeds[1] and all(np.isfinite(speeds))


ROBUST = """[study]
name = "robust"
family = "jansen_leg"
mode = "kinematic"
seed = 0
generations = 2
worlds = 8
device = "cpu"
[objective]
metric = "foot_stride"
direction = "maximize"
[simulation]
samples = 90
[fixed]
m = 0.015
[robustness]
samples = 3
aggregate = "{aggregate}"
level = 0.5
max_failure_share = 1.0
store_scenarios = true
[robustness.parameters]
a = {{ normal = [0.0, 0.0002] }}
"""


def test_a_kinematic_robust_study_stores_the_aggregate_and_the_nominal_metrics(tmp_path):
    path = tmp_path / "robust.toml"
    path.write_text(ROBUST.format(aggregate="worst"))
    spec = load_study_spec(path)
    run_study(spec, progress=False)
    frame = read_designs(spec.storage_url, spec.name)
    assert len(frame) == 16
    ok = frame[frame.failure == ""]
    assert len(ok)
    scenarios = ok[[f"metric_foot_stride_s{k}" for k in range(3)]].to_numpy()
    worst = np.nanmin(scenarios, axis=1)  # the least stride of the scenarios that turned
    np.testing.assert_allclose(ok["metric_foot_stride_worst"].to_numpy(), worst)
    np.testing.assert_allclose(ok["value"].to_numpy(), worst)  # the stored value is the aggregate (natural sign)
    assert ok["metric_foot_stride"].notna().all()  # and the nominal metric beside it


@pytest.mark.parametrize("table, error", [
    ("[robustness]\nsamples = 0\n", "'robustness.samples' must be an integer in 1 .. 1024"),
    ("[robustness]\nsamples = 4\naggregate = \"median\"\n", "'robustness.aggregate' must be one of"),
    ("[robustness]\nsamples = 4\n[robustness.parameters]\nzz = { normal = [0, 1] }\n",
     "'robustness.parameters.zz' is not a numeric design parameter"),
    ("[robustness]\nsamples = 4\nslope = { uniform = [-5.0, 5.0] }\n", "perturbs the simulated world"),
    ("[robustness]\nsamples = 4\n[robustness.parameters]\na = { normal = [0, -1] }\n", "std >= 0"),
    ("[robustness]\nsamples = 4\nlevel = 1.5\n", "'robustness.level' must be in"),
    ("[robustness]\nsamples = 4\nroughness = { uniform = [-0.01, 0.02] }\n", "'robustness.roughness' is the bumps'"),
])
def test_the_robustness_table_is_checked_before_any_work(tmp_path, table, error):
    path = tmp_path / "q.toml"
    path.write_text(ROBUST.split("[robustness]")[0].format() + table)
    with pytest.raises(ValueError, match=error.replace("(", r"\(").replace(".", r"\.")):
        load_study_spec(path)


def test_a_categorical_parameter_takes_no_tolerance_and_a_spread_is_stored_as_it_is(tmp_path):
    """leg_family (a choice) is refused as a tolerance; a maximized study whose aggregate is the
    scenarios' standard deviation stores and minimizes it as it is (not negated)."""
    walker = """[study]
name = "w"
family = "walker"
mode = "dynamic"
seed = 0
generations = 1
worlds = 4
device = "cpu"
[objective]
metric = "walking_speed"
direction = "maximize"
[simulation]
duration = 1.3
dt = 0.005
[fixed]
legs_per_side = 3
[robustness]
samples = 2
aggregate = "std"
max_failure_share = 1.0
payload = { uniform = [0.0, 0.3] }
"""
    path = tmp_path / "w.toml"
    path.write_text(walker + "[robustness.parameters]\nleg_family = { normal = [0, 1] }\n")
    with pytest.raises(ValueError, match="'robustness.parameters.leg_family' is not a numeric design parameter"):
        load_study_spec(path)
    path.write_text(walker)
    spec = load_study_spec(path)
    run_study(spec, progress=False)
    frame = read_designs(spec.storage_url, spec.name)
    ok = frame[frame.failure == ""]
    assert len(ok) and (ok["value"] >= 0.0).all()
    np.testing.assert_allclose(ok["value"].to_numpy(), ok["metric_walking_speed_std"].to_numpy())


def test_joint_clearance_gives_the_backlash_geometry_predicts():
    """A four-bar with its crank welded and 0.5 mm of radial play in the coupler-rocker pin
    (with_clearance), its rocker loaded one way then the other: the rocker turns by the backlash
    of the first-order estimate 2 c / (L_rocker sin mu), mu the angle between coupler and rocker,
    within 20 % (measured: within 0.1 %); without the play it does not move."""
    import dataclasses

    import engine
    from engine import JointSpring, JointType
    from engine.scenes import fourbar, fourbar_configuration
    from morphopt.robust import with_clearance

    c, tau = 5e-4, 0.05
    results = []
    for play in (True, False):
        spec = fourbar().spec
        crank = {b.name: b for b in spec.bodies}["crank"]
        spec.gravity = np.zeros(3)
        spec.bodies = [dataclasses.replace(b, velocity=np.zeros(3), angular_velocity=np.zeros(3)) for b in spec.bodies]
        spec.joints = [dataclasses.replace(j, type=JointType.FIXED, parent_orientation=crank.orientation)
                       if j.name == "ground_crank" else j for j in spec.joints]
        spec.forces = [JointSpring("settle", "ground_rocker", damping=0.02)]
        if play:
            spec = with_clearance(spec, "coupler_rocker", c)
            spec.forces = [*spec.forces, JointSpring("settle_pin", "coupler_rocker_hole", damping=1e-5)]
        model = engine.pack([spec], device="cpu", dt=1e-3, coordinates="maximal")
        control = model.control()
        joint = [j.name for j in spec.joints].index("ground_rocker")
        rocker = [b.name for b in spec.bodies].index("rocker")
        a, b = model.state(), model.state()
        angles = []
        for load in (tau, -tau):
            effort = np.zeros(control.joint_effort.shape, np.float32)
            effort[0, joint] = load
            control.joint_effort.assign(effort)
            for _ in range(5000):
                engine.step(model, a, b, control)
                a, b = b, a
            q = a.body_q.numpy()[0, rocker, 3:]
            angles.append(2.0 * math.atan2(q[1], q[3]))
        results.append(abs(angles[1] - angles[0]))
    s = fourbar_configuration(0.30, 0.10, 0.30, 0.25, math.radians(45.0), 0.0)
    cb, cd = s["C"] - s["B"], s["C"] - s["D"]
    mu = math.acos(abs(cb @ cd) / (np.linalg.norm(cb) * np.linalg.norm(cd)))
    expected = 2.0 * c / (0.25 * math.sin(mu))
    print(f"backlash {results[0]:.6f} rad, first-order estimate {expected:.6f} rad; without play {results[1]:.2e}")
    assert abs(results[0] - expected) < 0.2 * expected
    assert results[1] < 0.02 * expected


def test_the_clearance_key_is_checked_on_the_familys_default_design():
    """A clearance joint the family's designs do not have is refused before any work, naming it;
    a radius past 1 cm is refused; a kinematic study takes no clearance."""
    text = ROBUST.split("[robustness]")[0].format().replace('mode = "kinematic"', 'mode = "dynamic"')
    text = text.replace("[simulation]\nsamples = 90", "[simulation]\nduration = 1.0\ndt = 0.001")
    folder = pathlib.Path(tempfile.mkdtemp())
    for table, error in (('clearance = { joints = ["nope"], radius = 0.0005 }', "clearance: no joint 'nope'"),
                         ('clearance = { joints = ["nope"], radius = 0.5 }', "0 < R <= 0.01 m")):
        path = folder / "c.toml"
        path.write_text(text + "[robustness]\nsamples = 2\n" + table + "\n")
        with pytest.raises(ValueError, match=error):
            load_study_spec(path)
    kinematic = folder / "k.toml"
    kinematic.write_text(ROBUST.split("[robustness]")[0].format()
                         + '[robustness]\nsamples = 2\nclearance = { joints = ["x"], radius = 0.0005 }\n')
    with pytest.raises(ValueError, match="'robustness.clearance' perturbs the simulated world"):
        load_study_spec(kinematic)


def test_a_robust_study_resumed_stores_what_an_uninterrupted_one_does(tmp_path):
    """The scenarios come from the seed and the generation: a resume draws the same ones, and the
    optimizer replays the stored aggregates."""
    text = ROBUST.format(aggregate="cvar").replace("generations = 2", "generations = 3")
    whole, split = tmp_path / "whole.toml", tmp_path / "split.toml"
    whole.write_text(text.replace('name = "robust"', 'name = "whole"'))
    split.write_text(text.replace('name = "robust"', 'name = "split"'))
    run_study(load_study_spec(whole), progress=False)
    first = load_study_spec(split)
    run_study(first.with_overrides(generations=2), progress=False)
    run_study(first, resume=True, progress=False)
    a = read_designs(load_study_spec(whole).storage_url, "whole")
    b = read_designs(first.storage_url, "split")
    assert len(a) == len(b) == 24
    np.testing.assert_array_equal(a["value"].to_numpy(), b["value"].to_numpy())
    np.testing.assert_array_equal(a["metric_foot_stride_cvar"].to_numpy(), b["metric_foot_stride_cvar"].to_numpy())


def test_roughness_on_a_family_the_tabulated_plan_cannot_take_is_refused_before_any_work(tmp_path):
    path = tmp_path / "rough.toml"
    path.write_text(ROBUST.split("[robustness]")[0].format().replace('mode = "kinematic"', 'mode = "dynamic"')
                    .replace("[simulation]\nsamples = 90", "[simulation]\nduration = 1.3\ndt = 0.005")
                    + "[robustness]\nsamples = 2\nroughness = { uniform = [0.0, 0.01] }\n")
    with pytest.raises(ValueError, match=r"'robustness\.roughness': rough ground is simulated by the tabulated plan "
                                         r"only.*needs a floating base"):
        load_study_spec(path)


def test_a_design_s_scenario_worlds_share_its_built_spec_and_a_hook_that_changes_in_place_gets_its_own():
    """evaluate_dynamic builds equal designs once where the hook changes copies only
    (scenario_hooks): the same metrics, to the last bit, as with every world built on its own;
    a hook without that promise that changes its spec in place touches its own world only."""
    walker = load_family("walker")
    design = {**walker.space.default(), "legs_per_side": 1}
    scenarios = [{"offsets": {}, "friction": 0.7, "payload": 0.2, "slope": 3.0, "speed": 1.0},
                 {"offsets": {}, "friction": 1.0, "payload": 0.0, "slope": -4.0, "speed": 1.1}]
    batch = [dict(design) for _ in range(3)]
    hook = scenario_hooks(batch, [None, *scenarios])
    assert hook.copies

    def unshared(spec, p):  # the same changes, without the promise: every world built on its own
        return hook(spec, p)

    kwargs = dict(duration=0.1, dt=5e-3, record_every=5)
    shared = evaluate_dynamic(walker, batch, spec_hook=hook, **kwargs)
    each = evaluate_dynamic(walker, batch, spec_hook=unshared, **kwargs)
    assert shared.failures == each.failures == ["", "", ""]
    assert all(_same_metrics(x, y) for x, y in zip(shared.metrics, each.metrics))
    assert shared.metrics[1]["walking_speed"] != shared.metrics[2]["walking_speed"]

    def heavier_in_place(spec, p):
        if p is batch[1]:
            for body in spec.bodies:
                body.mass *= 3.0
        return spec

    heavy = evaluate_dynamic(walker, batch, spec_hook=heavier_in_place, **kwargs)
    plain = evaluate_dynamic(walker, batch[:1], **kwargs)
    assert _same_metrics(heavy.metrics[0], plain.metrics[0]) and _same_metrics(heavy.metrics[2], plain.metrics[0])
    assert not _same_metrics(heavy.metrics[1], plain.metrics[0])


def _same_metrics(a: dict, b: dict) -> bool:
    """Two designs' metric dicts equal to the last bit (keys, order, every number and array)."""
    return pickle.dumps(a) == pickle.dumps(b)
