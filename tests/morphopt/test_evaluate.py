"""Batched evaluation: kinematic and dynamic paths agree, failures carry reasons, batches carry on."""

import time

import numpy as np

from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import load_family


def test_kinematic_batch_reports_failures_with_reasons_and_keeps_the_rest():
    """Jansen's leg, an out-of-range design and a leg that cannot close: the good one gets its
    flat-stance stride (~49 mm of its 68 mm foot travel), the others fail with a reason."""
    family = load_family("jansen_leg")
    good = family.space.default()
    broken = {**good, "m": good["m"] * 1.2, "j": good["j"] * 0.8, "b": good["b"] * 0.8}  # locks mid-turn
    outside = {**good, "m": 1.0}  # a 1 m crank is outside the design space
    evaluation = evaluate_kinematic(family, [good, outside, broken])
    assert evaluation.feasible.tolist() == [True, False, False]
    assert 0.045 < evaluation.metrics[0]["foot_stride"] < 0.052
    assert "'m' = 1.0 is outside" in evaluation.failures[1]
    assert "does not close at crank angle" in evaluation.failures[2]


def test_dynamic_evaluation_matches_kinematic_paths():
    """Driven at 2 pi rad/s for 1.5 s, the simulated coupler-point and foot paths over the last turn
    have the kinematic stride, full stride and step height (1 mm), and the crank torque is reported."""
    for name, point in (("four_bar", "coupler_point"), ("jansen_leg", "foot")):
        family = load_family(name)
        params = [family.space.default()]
        kinematic = evaluate_kinematic(family, params).metrics[0]
        dynamic = evaluate_dynamic(family, params, duration=1.5, record_every=5).metrics[0]
        for metric in (f"{point}_stride", f"{point}_stride_full", f"{point}_step_height"):
            assert abs(dynamic[metric] - kinematic[metric]) < 1e-3, (name, metric)
        assert dynamic["torque_peak"] > 0 and np.isfinite(dynamic["torque_rms"])
        assert dynamic["loop_violation_max"] < 1e-5


def test_torn_mechanisms_fail_as_diverged():
    """A design whose joints come apart by more than loop_tolerance fails with the distance in its
    reason (a torn mechanism can stay finite and score absurdly well); the same design passes
    under a tolerance above its real loop error."""
    family = load_family("four_bar")
    params = [family.space.default()]
    start = time.perf_counter()
    ok = evaluate_dynamic(family, params, duration=0.2, record_every=5)
    wall = time.perf_counter() - start
    assert ok.feasible.all()
    # the stages' wall times are all there and add up to no more than the call's
    assert set(ok.timings) == {"build", "pack", "simulate", "metrics"}
    assert min(ok.timings.values()) >= 0.0 and sum(ok.timings.values()) <= wall
    assert ok.timings["simulate"] > 0.0
    error = ok.metrics[0]["loop_violation_max"]
    assert 0.0 < error < 1e-5
    strict = evaluate_dynamic(family, params, duration=0.2, record_every=5, loop_tolerance=0.5 * error)
    assert not strict.feasible.any()
    assert "diverged: joints came apart by" in strict.failures[0] and "m tolerance" in strict.failures[0]


def test_batched_kinematic_evaluation_matches_the_numpy_reference():
    """evaluate_kinematic (families called once with parameter arrays, compiled kernels, the batch
    split over the CPU cores) gives the NumPy reference's feasibility, failure reasons, paths,
    stride, full stride, step height and transmission angle (1e-9) for 160 random designs of each
    family."""
    from morphopt.linkage import solve_cycles
    from morphopt.metrics import gait_metrics

    rng = np.random.default_rng(11)
    for name in ("jansen_leg", "klann_leg", "four_bar", "watt_sixbar"):
        family = load_family(name)
        params = family.space.sample(rng, 160)
        evaluation = evaluate_kinematic(family, params, samples=90)
        reference = solve_cycles([family.generate(p) for p in params], samples=90)
        assert evaluation.feasible.tolist() == [s.feasible for s in reference], name
        assert 0 < evaluation.feasible.sum(), name
        for metrics, failure, solution, p in zip(evaluation.metrics, evaluation.failures, reference, params):
            if not solution.feasible:
                assert failure == solution.reason
                continue
            linkage = family.generate(p)
            for point in linkage.points:
                path = solution.point(point, linkage)
                assert np.abs(metrics["paths"][point] - path).max() < 1e-9
                stride, full, height = gait_metrics(path)
                assert abs(metrics[f"{point}_stride"] - stride) < 1e-9
                assert abs(metrics[f"{point}_stride_full"] - full) < 1e-9
                assert abs(metrics[f"{point}_step_height"] - height) < 1e-9
            assert abs(metrics["transmission_angle_min"] - solution.transmission_angle_min) < 1e-9


def test_families_that_need_floats_are_generated_design_by_design():
    """A family whose generate works only on floats (math functions, float()) and one that quietly
    ignores its parameter arrays both fall back to one generate call per design and give the same
    results as the NumPy-written four-bar; a NaN or string parameter fails with its name."""
    import math
    import types

    from morphopt.linkage import Linkage

    four_bar = load_family("four_bar")

    def floats_only(params, **kwargs):
        assert all(isinstance(v, float) for v in params.values())
        return four_bar.generate({k: float(v) for k, v in params.items()}, **kwargs)

    frozen = four_bar.generate(four_bar.space.default())

    def ignores_arrays(params, **kwargs):
        if np.ndim(params["crank"]) > 0:
            return frozen  # wrong for every design but the default: must be caught
        return four_bar.generate(params, **kwargs)

    rng = np.random.default_rng(2)
    params = four_bar.space.sample(rng, 130)
    expected = evaluate_kinematic(four_bar, params, samples=60)
    for generate in (floats_only, ignores_arrays):
        family = types.SimpleNamespace(space=four_bar.space, generate=generate)
        evaluation = evaluate_kinematic(family, params, samples=60)
        assert evaluation.failures == expected.failures
        for got, want in zip(evaluation.metrics, expected.metrics):
            if want:
                assert abs(got["coupler_point_stride"] - want["coupler_point_stride"]) < 1e-12
    assert isinstance(frozen, Linkage) and math.isfinite(frozen.crank.radius)
    bad = [{**params[0], "rocker": float("nan")}, {**params[0], "crank": "long"}, params[1]]
    evaluation = evaluate_kinematic(four_bar, bad, samples=60)
    assert "'rocker' = nan is outside" in evaluation.failures[0]
    assert "'crank' = 'long' is outside" in evaluation.failures[1]
    assert evaluation.failures[2] == expected.failures[1]


def test_drive_speed_matches_the_crank_angle_rate():
    """Trace.drive_speed of the four-bar's velocity-driven crank equals the central-difference rate
    of the crank tip's angle about its pivot (to 1 %), is near its 2 pi rad/s target, and joints
    without a drive read 0."""
    import dataclasses

    from engine import TrackedPoint, pack_worlds, rollout
    from morphopt.linkage import to_spec

    family = load_family("four_bar")
    params = family.space.default()
    spec = to_spec(family.generate(params))
    tip = TrackedPoint("crank_tip", "crank", (params["crank"], 0.0, 0.0))
    spec = dataclasses.replace(spec, points=[*spec.points, tip])
    model = pack_worlds([spec], device="cpu", dt=1e-3)
    trace, _ = rollout(model, model.state(), model.control(), 300, record_every=1)
    xyz = trace.points[:, 0, len(spec.points) - 1]
    pivot = trace.points[0, 0, len(spec.points) - 1] - params["crank"] * np.array([1.0, 0.0, 0.0])
    angle = np.unwrap(np.arctan2(-(xyz[:, 2] - pivot[2]), xyz[:, 0] - pivot[0]))
    rate = (angle[2:] - angle[:-2]) / (trace.time[2:] - trace.time[:-2])
    speed = trace.drive_speed[1:-1, 0, 0]
    assert np.allclose(np.abs(rate), speed, rtol=1e-2)
    assert np.allclose(speed, 2.0 * np.pi, rtol=0.05)
    assert np.all(trace.drive_speed[:, 0, 1:] == 0.0)


def test_jammed_designs_fail_with_the_drive_and_the_time_and_short_stalls_do_not():
    """A velocity drive held at its effort limit below half its target speed for stall_time fails
    the design as jammed; the same stall for less than stall_time (a transient) does not."""
    from types import SimpleNamespace

    from engine import Joint, JointDrive
    from morphopt.evaluate import _jam

    drive = JointDrive(damping=10.0, target_velocity=2.0, effort_limit=5.0)
    joints = [Joint("crank", "revolute", None, "a", drive=drive), Joint("pin", "revolute", "a", "b")]
    records = 60
    time = np.arange(records) * 0.01
    torque = np.zeros((records, 1, 2))
    speed = np.zeros((records, 1, 2))
    speed[:, 0, 0] = 2.0
    torque[10:40, 0, 0] = -5.0  # at the limit, the wrong way round is still the limit
    speed[10:40, 0, 0] = 0.3
    trace = SimpleNamespace(time=time, drive_torque=torque, drive_speed=speed)
    reason = _jam(trace, 0, joints, stall_time=0.2, record_dt=0.01)
    assert reason.startswith("jammed: the drive of joint 'crank'") and "(5 N m) from 0.10 s" in reason
    assert _jam(trace, 0, joints, stall_time=0.35, record_dt=0.01) == ""
    speed[10:40, 0, 0] = 1.2  # slowed down but above half the target: a heavy load, not a jam
    assert _jam(trace, 0, joints, stall_time=0.2, record_dt=0.01) == ""


def test_batched_walker_metrics_equal_the_per_world_ones():
    """_batch_world_metrics (every world at once, as evaluate_dynamic uses it) gives each walker the
    metrics and failure reasons of the per-world computation (_world_metrics without pre): on six
    walkers simulated as evaluate_dynamic simulates them (engine.pack's automatic plan: TABULATED),
    with one world's records edited into a jam, one into a fall, one into a non-finite foot path
    and one with a crank speed of zero."""
    import dataclasses
    import math

    from engine import Coordinates, SolverConfig, pack, rollout
    from morphopt.evaluate import Evaluation, _batch_world_metrics, _drives, _world_metrics

    walker = load_family("walker")
    params = [walker.space.default()] + walker.space.sample(np.random.default_rng(3), 5)
    params = [{**p, "legs_per_side": 3} for p in params]
    specs = [walker.build_spec(walker.space.validate(p)) for p in params]
    specs[5] = dataclasses.replace(specs[5], joints=[
        j if j.drive is None else dataclasses.replace(j, drive=dataclasses.replace(j.drive, target_velocity=0.0))
        for j in specs[5].joints])
    cranks = [[j for j, joint in enumerate(s.joints) if joint.drive is not None] for s in specs]  # one per leg
    assert [len(c) for c in cranks] == [6] * 6
    names = [point.name for point in specs[0].points]
    assert all([point.name for point in s.points] == names for s in specs)
    torso, up, foot = names.index("torso"), names.index("torso_up"), names.index("left2_foot")
    dt, every = 5e-3, 4
    model = pack(specs, device="cpu", dt=dt,
                 config=SolverConfig(tolerance=1e-4, relative_tolerance=1e-3, max_iterations=30))
    assert model.plan.coordinates is Coordinates.TABULATED, str(model.plan)
    trace, _ = rollout(model, model.state(), None, 160, record_every=every)
    record_dt = dt * every
    stalled = specs[1].joints[cranks[1][2]].drive  # leg 2 of world 1 stalls at its limit
    trace.drive_torque[5:30, 1, cranks[1][2]] = stalled.effort_limit
    trace.drive_speed[5:30, 1, cranks[1][2]] = 0.1 * stalled.target_velocity
    trace.points[20:, 2, up] = trace.points[20:, 2, torso] + np.array([0.3, 0.0, 0.01])  # world 2 tips over
    trace.points[-3, 3, foot, 0] = np.nan  # a foot of world 3 leaves no finite path
    turn, effort, target = _drives(specs, record_dt, len(trace.time))
    assert list(turn[:5]) == [round(2.0 * np.pi / abs(spec.joints[c[0]].drive.target_velocity) / record_dt)
                              for spec, c in zip(specs[:5], cranks)]
    assert turn[5] == len(trace.time)
    assert effort[0, cranks[0][5]] == specs[0].joints[cranks[0][5]].drive.effort_limit
    assert effort[0, cranks[0][5] + 1] == 0.0
    pre = _batch_world_metrics(trace, turn, np.full(6, torso), np.full(6, up), effort, target, np.radians(45.0), 0.5,
                               0.2, record_dt)
    assert list(np.flatnonzero(pre["jam"])) == [1] and list(np.flatnonzero(pre["fell"])) == [2]
    assert np.isnan(pre["stride"][3, foot]) and np.isfinite(pre["stride"][[0, 1, 2, 4, 5]]).all()
    batched, single = Evaluation(params, [None] * 6, [""] * 6), Evaluation(params, [None] * 6, [""] * 6)
    for w, spec in enumerate(specs):
        for evaluation, extra in ((batched, {"pre": pre}), (single, {})):
            _world_metrics(evaluation, w, trace, w, names, spec.joints, record_dt, np.radians(45.0), 0.5, 0.2, **extra)
    assert batched.failures == single.failures
    assert batched.failures[1].startswith(f"jammed: the drive of joint '{specs[1].joints[cranks[1][2]].name}'"), \
        batched.failures[1]
    assert batched.failures[2].startswith("fell after"), batched.failures[2]
    for w in range(6):
        a, b = batched.metrics[w], single.metrics[w]
        assert (a is None) == (b is None)
        if a is None:
            continue
        assert a.keys() == b.keys()
        for key in a:
            if key == "paths":
                continue
            same = (math.isnan(a[key]) and math.isnan(b[key])) or abs(a[key] - b[key]) <= 1e-6 * max(1.0, abs(b[key]))
            assert same, (w, key, a[key], b[key])
    assert math.isnan(batched.metrics[3]["left2_foot_stride"])
    assert batched.metrics[5] is not None and batched.metrics[0] is not None


def test_walkers_are_planned_tabulated_and_score_as_in_maximal_coordinates():
    """evaluate_dynamic lets engine.pack plan walkers: a torso and one crank angle per leg
    (TABULATED; evaluation.plan says so). Forced into maximal coordinates, the same walkers score
    alike over a 1.5 s walk at dt 2 ms, within what two discretizations of a contact-rich walk
    allow: the default walker's speed within 35 % (measured 11 % with Moreau-Jean in both plans),
    every foot's full stride within 10 % (measured at most 5 %), its lowest torso height within 2 %
    (measured 0.3 %) and its crank torque RMS within 25 % (measured 11 %; recorded every step: the
    torque spikes at foot impacts, and every fifth step's samples moved the maximal plan's own RMS
    from 0.22 to 0.47 N m between dt 2 and 1 ms), loops closed to 1e-5 m in maximal coordinates and to the
    legs' table closure error (1.3e-5 m at scale 3) in tabulated ones; a Klann walker on two
    legs a side falls in both (measured at 0.52 s in both)."""
    from engine import Coordinates

    family = load_family("walker")
    params = [family.space.default(), {**family.space.default(), "leg_family": "klann_leg", "legs_per_side": 2}]
    runs = {c: evaluate_dynamic(family, params, duration=1.5, dt=2e-3, record_every=1, coordinates=c)
            for c in (None, "maximal")}
    assert runs[None].plan.coordinates is Coordinates.TABULATED, str(runs[None].plan)
    assert runs["maximal"].plan.coordinates is Coordinates.MAXIMAL
    for run in runs.values():
        assert run.failures[0] == "" and run.failures[1].startswith("fell after"), run.failures
    ours, theirs = runs[None].metrics[0], runs["maximal"].metrics[0]

    def close(key, tolerance):
        assert abs(ours[key] - theirs[key]) <= tolerance * abs(theirs[key]), (key, ours[key], theirs[key])

    assert theirs["walking_speed"] > 0.1
    close("walking_speed", 0.35)
    feet = [key for key in theirs if key.endswith("_foot_stride_full")]
    assert len(feet) == 6
    for key in feet:
        close(key, 0.10)
    close("torso_height_min", 0.02)
    close("torque_rms", 0.25)
    assert ours["loop_violation_max"] < 3e-5 and theirs["loop_violation_max"] < 1e-5  # ours: the table's bound
