"""engine.legged (walkers in reduced coordinates) against independent oracles: the planar
kinematics and closed forms for the leg tables, the maximal-coordinate engine in free flight,
conservation laws, static equilibrium on the ground, and the evaluation and study plumbing."""

import dataclasses
import math
import pathlib
import textwrap

import numpy as np
import pytest

from engine import Integrator, SolverConfig, Tuning, pack_worlds, rollout
from engine.legged import (TILED_REGISTERS, legged_points, legged_rollout, legged_step_batch, pack_legged, step_kernel,
                           tiled_max_worlds)
from morphopt.evaluate import evaluate_dynamic
from morphopt.families import load_family
from morphopt.linkage.kinematics import solve_at
from morphopt.linkage.leg_table import leg_table
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec

WALKER = load_family("walker")
LEGS = ("jansen_leg", "klann_leg")
EULER = SolverConfig(integrator=Integrator.SEMI_IMPLICIT_EULER)


def unit_leg(name):
    """A leg family's default linkage (unit scale) and its table."""
    family = load_family(name)
    linkage = family.generate(family.space.default())
    return linkage, leg_table(linkage)


def wrap(angle):
    return np.angle(np.exp(1j * angle))


def exact_poses(linkage, psi):
    """Per link at crank angles psi (n,): (centre of mass x, z, planar angle) (n, K, 3), the foot
    (n, 2) and the nodes, from solve_at alone. Bars of one cross-section: a link's centre of mass
    is the length-weighted mean of its bars' midpoints (a bar between every pair of its nodes)."""
    solution = solve_at([linkage], np.asarray(psi, float)[None])[0]
    assert solution.feasible, solution.reason
    poses = []
    for link in linkage.links:
        pts = [solution.nodes[n] for n in link.nodes]
        bars = [(a, b) for i, a in enumerate(pts) for b in pts[i + 1:]]
        lengths = [np.linalg.norm(b - a, axis=1)[:, None] for a, b in bars]
        com = sum(w * 0.5 * (a + b) for w, (a, b) in zip(lengths, bars)) / sum(lengths)
        d = pts[1] - pts[0]
        poses.append(np.column_stack([com, np.arctan2(d[:, 1], d[:, 0])]))
    return np.stack(poses, axis=1), solution.nodes[linkage.points["foot"]], solution.nodes


@pytest.mark.parametrize("name", LEGS)
def test_leg_table_values_and_derivatives_match_the_kinematics(name):
    """At every sample angle the table's link poses and foot equal the exact kinematics (1e-9), and
    its FFT derivatives match central finite differences of the exact kinematics (h = 1e-4)."""
    linkage, table = unit_leg(name)
    n, h = table.samples, 1e-4
    psi = 2.0 * np.pi * np.arange(n) / n
    poses, foot, _ = exact_poses(linkage, psi)
    plus, foot_plus, _ = exact_poses(linkage, psi + h)
    minus, foot_minus, _ = exact_poses(linkage, psi - h)
    value = table.links - poses
    value[..., 2] = wrap(value[..., 2])
    assert np.abs(value).max() < 1e-9
    assert np.abs(table.foot[:, :2] - foot).max() < 1e-9 and not table.foot[:, 2].any()
    ahead, behind = plus - poses, poses - minus
    ahead[..., 2], behind[..., 2] = wrap(ahead[..., 2]), wrap(behind[..., 2])
    d1, d2 = (ahead + behind) / (2.0 * h), (ahead - behind) / h**2
    for c in (slice(0, 2), slice(2, 3)):  # centres of mass [m], angles [rad]
        scale1, scale2 = np.abs(d1[..., c]).max(), np.abs(d2[..., c]).max()
        assert np.abs(table.links_d1[..., c] - d1[..., c]).max() < 1e-6 * scale1
        assert np.abs(table.links_d2[..., c] - d2[..., c]).max() < 1e-5 * scale2
    assert np.abs(table.links_d1[:, 0, 2] - 1.0).max() < 1e-9  # the crank turns with psi
    foot_d1, foot_d2 = (foot_plus - foot_minus) / (2.0 * h), (foot_plus - 2.0 * foot + foot_minus) / h**2
    assert np.abs(table.foot_d1[:, :2] - foot_d1).max() < 1e-6 * np.abs(foot_d1).max()
    assert np.abs(table.foot_d2[:, :2] - foot_d2).max() < 1e-5 * np.abs(foot_d2).max()


@pytest.mark.parametrize("name", LEGS)
def test_leg_table_between_samples_places_pivots_within_its_closure_error(name):
    """closure_error < 1e-5 m at unit scale, and LegTable.at between samples (midpoints and random
    fractions) places every link's pivots, rebuilt from its centre of mass and angle, within
    closure_error of the exact nodes; at the midpoints the error reaches at least half of it."""
    linkage, table = unit_leg(name)
    assert 0.0 < table.closure_error < 1e-5
    poses0, _, nodes0 = exact_poses(linkage, [0.0])
    offsets = []  # per link: its nodes relative to its centre of mass, in the link frame
    for k, link in enumerate(linkage.links):
        c, s = math.cos(poses0[0, k, 2]), math.sin(poses0[0, k, 2])
        offsets.append([np.array([[c, s], [-s, c]]) @ (nodes0[m][0] - poses0[0, k, :2]) for m in link.nodes])
    n = table.samples
    rng = np.random.default_rng(7)
    steps = np.concatenate([np.arange(n) + 0.5, rng.uniform(0, n, 64)])
    psi = 2.0 * np.pi * steps / n
    _, _, exact = exact_poses(linkage, psi)
    errors = np.zeros(len(psi))
    for i, angle in enumerate(psi):
        links, foot = table.at(angle)
        foot_only, foot_angle = table.foot_at(angle)  # what a walker's build reads
        assert np.array_equal(foot_only, foot) and abs(foot_angle - links[table.foot_link, 2]) < 1e-12
        for k, link in enumerate(linkage.links):
            c, s = math.cos(links[k, 2]), math.sin(links[k, 2])
            for m, off in zip(link.nodes, offsets[k]):
                placed = links[k, :2] + np.array([[c, -s], [s, c]]) @ off
                errors[i] = max(errors[i], np.abs(placed - exact[m][i]).max())
    assert errors.max() <= table.closure_error * (1.0 + 1e-9), (errors.max(), table.closure_error)
    assert errors[:n].max() >= 0.5 * table.closure_error


@pytest.mark.parametrize("name, dt", [("jansen_leg", 1e-3), ("klann_leg", 5e-4)])
def test_free_flight_matches_the_maximal_engine(name, dt):
    """Without ground the reduced walker follows the maximal-coordinate walker for 0.3 s (semi-
    implicit Euler both): torso points within 2e-4 m, feet (the crank angles) within 1e-3 m. The
    Klann walker runs at dt 5e-4: at 1e-3 both engines' first-order errors (1.3e-3 m each against
    dt 1.25e-4) leave them 6.6e-4 m (torso) and 4.5e-3 m (feet) apart."""
    params = {**WALKER.space.default(), "leg_family": name}
    reduced = pack_legged([dataclasses.replace(WALKER.build_legged(params), ground=False)], dt=dt, config=EULER)
    maximal = pack_worlds([dataclasses.replace(WALKER.build_spec(params), shapes=[], ground=None)], device="cpu",
                          dt=dt, config=EULER)
    steps = round(0.3 / dt)
    trace = legged_rollout(reduced, steps, record_every=steps // 10)
    reference, _ = rollout(maximal, maximal.state(), maximal.control(), steps, record_every=steps // 10)
    names = trace.point_names[0]
    ours = trace.points[:, 0, :len(names)]
    theirs = reference.points[:, 0, [reference.point_names[0].index(p) for p in names]]
    assert np.abs(ours[-1, 2:] - ours[0, 2:]).max() > 0.05  # the legs turned
    torso, feet = np.abs(ours[:, :2] - theirs[:, :2]).max(), np.abs(ours[:, 2:] - theirs[:, 2:]).max()
    assert torso < 2e-4 and feet < 1e-3, (torso, feet)


def centre_of_mass(model, spec):
    """The whole walker's centre of mass [m] from the state: the torso and every link, its centre
    R (leg origin + scale * table centre (psi)) from the torso's centre."""
    x, y, z, w = model.orientation.numpy()[0].astype(float)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    p = model.position.numpy()[0].astype(float)
    psi = model.psi.numpy()[0]
    moment, mass = spec.torso_mass * p, spec.torso_mass
    for index, leg in enumerate(spec.legs):
        links, _ = leg.table.at(float(psi[index]))
        for k, m in enumerate(leg.link_mass):
            local = np.asarray(leg.origin) + leg.scale * np.array([links[k, 0], 0.0, links[k, 1]])
            moment = moment + m * (p + R @ local)
            mass += m
    return moment / mass


def test_internal_drives_leave_the_centre_of_mass_in_place():
    """Zero gravity, no ground, at rest: the crank drives spin the legs up against the torso; the
    torso moves in reaction, the centre of mass stays within 1e-4 m over 0.5 s."""
    spec = dataclasses.replace(WALKER.build_legged(WALKER.space.default()), ground=False, gravity=(0.0, 0.0, 0.0))
    model = pack_legged([spec], dt=1e-3)
    start, torso = centre_of_mass(model, spec), model.position.numpy()[0].copy()
    drift = []
    for _ in range(10):
        legged_step_batch(model, 50)
        drift.append(np.abs(centre_of_mass(model, spec) - start).max())
    assert np.abs(model.psi_dot.numpy()[0, :6] - 5.0).max() < 0.05  # the cranks reached their speed
    assert np.abs(model.position.numpy()[0] - torso).max() > 2e-4  # and pushed the torso about
    assert max(drift) < 1e-4, drift


def test_free_legs_conserve_energy_and_momentum():
    """Zero gravity, no ground, drives off (effort limit 0), torso at rest and cranks set turning at
    3..8 rad/s: the energy stays within 1 % over 0.5 s (dt 5e-4) and the centre of mass moves
    in a straight line at constant speed (within 0.5 % of its travel)."""
    base = WALKER.build_legged(WALKER.space.default())
    spec = dataclasses.replace(base, ground=False, gravity=(0.0, 0.0, 0.0),
                               legs=[dataclasses.replace(leg, effort_limit=0.0) for leg in base.legs])
    model = pack_legged([spec], dt=5e-4)
    rates = np.zeros((1, 8), np.float32)
    rates[0, :6] = [3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    model.psi_dot.assign(rates)
    _, energy0 = legged_points(model)
    energies, centres = [], [centre_of_mass(model, spec)]
    for _ in range(10):
        legged_step_batch(model, 100)
        energies.append(legged_points(model)[1][0])
        centres.append(centre_of_mass(model, spec))
    assert not model.drive_torque.numpy().any()
    assert np.abs(np.array(energies) / energy0[0] - 1.0).max() < 0.01, (energy0, energies)
    centres = np.array(centres)
    line = centres[0] + np.linspace(0.0, 1.0, len(centres))[:, None] * (centres[-1] - centres[0])
    travel = np.linalg.norm(centres[-1] - centres[0])
    assert travel > 1e-3 and np.abs(centres - line).max() < 0.005 * travel, (travel, np.abs(centres - line).max())


def test_standing_walker_rests_with_its_weight_on_the_contacts():
    """Cranks held (target speed 0, damping raised to 1e3 N m s/rad so that the weight cannot
    back-drive them; at the walker's own 5 the torso creeps at ~2e-3 m/s): after 1 s at dt 2e-3
    the torso is at rest and the normal contact impulses per step carry the total weight (2 %)."""
    dt = 2e-3
    base = WALKER.build_legged(WALKER.space.default(), crank_speed=0.0)
    spec = dataclasses.replace(base, legs=[dataclasses.replace(leg, damping=1e3) for leg in base.legs])
    model = pack_legged([spec], dt=dt)
    crank_rate = 0.0
    for _ in range(10):
        legged_step_batch(model, 50)
        crank_rate = max(crank_rate, float(np.abs(model.psi_dot.numpy()[0]).max()))
    weight = (spec.torso_mass + sum(leg.link_mass.sum() for leg in spec.legs)) * 9.81
    normals = model.impulse.numpy()[0][8 + 3 * np.arange(8 + 2 * len(spec.legs))]
    points, _ = legged_points(model)
    up = points[0, 1] - points[0, 0]
    speed, support = float(np.linalg.norm(model.velocity.numpy()[0])), normals.sum() / dt / weight
    state = (f"speed {speed:.3g} m/s, support {support:.4f} of the weight, tilt "
             f"{np.degrees(np.arccos(up[2] / np.linalg.norm(up))):.2f} deg, crank rate max {crank_rate:.3g} rad/s")
    assert speed < 1e-3, state
    assert abs(support - 1.0) < 0.02, state


def test_tiled_and_per_thread_steps_agree():
    """The tiled step (a block of lanes per world; one lane on the CPU) and the one-thread step
    compute the same walk: two walkers on the ground, 0.4 s at dt 2e-3."""
    specs = [WALKER.build_legged(WALKER.space.default()),
             WALKER.build_legged({**WALKER.space.default(), "leg_family": "klann_leg", "legs_per_side": 2})]
    models = [pack_legged(specs, dt=2e-3, tiled=tiled) for tiled in (True, False)]
    assert [m.tiled for m in models] == [True, False]
    # the tiled step is held to TILED_REGISTERS registers per thread on CUDA (the CPU ignores it);
    # without the cap (None) it is the same kernel otherwise
    assert models[0].max_registers == TILED_REGISTERS == 64
    assert tiled_max_worlds("cpu") == 0 and not pack_legged(specs).tiled  # the CPU steps a thread per world
    assert step_kernel(True, "all", models[0].max_registers).options["cuda_max_registers"] == 64
    uncapped = pack_legged(specs, dt=2e-3, tiled=True)
    uncapped.max_registers = None
    assert step_kernel(True, "all", None).options.get("cuda_max_registers") is None
    for m in (*models, uncapped):
        legged_step_batch(m, 200)
    assert np.array_equal(uncapped.position.numpy(), models[0].position.numpy())
    tiled, plain = models
    assert np.abs(tiled.position.numpy() - plain.position.numpy()).max() < 1e-6
    assert np.abs(tiled.psi.numpy() - plain.psi.numpy()).max() < 1e-5
    assert np.abs(tiled.impulse.numpy() - plain.impulse.numpy()).max() < 1e-6
    assert np.linalg.norm(plain.position.numpy()[0] - specs[0].torso_position) > 1e-3  # it moved


def test_cuda_tiled_step_matches_the_cpu():
    """On CUDA the tiled step's 32 lanes share what one lane does on the CPU: the rows of the
    Woodbury inverse (through a tile), the impulses of the velocity update, one reduction of the
    residuals and the merit. Walkers of both leg families on the ground, with their contacts and
    PADMM iterations: after one step and after five, CUDA tiled and CUDA one thread per world give
    the CPU's result to float32 rounding (a lane reading the wrong row or entry would not), and the
    register cap changes nothing, bit for bit."""
    import warp as wp

    if not wp.is_cuda_available():
        pytest.skip("no CUDA device on this machine")
    default = WALKER.space.default()
    specs = [WALKER.build_legged(p) for p in (
        default, {**default, "leg_family": "klann_leg", "legs_per_side": 2},
        {**default, "legs_per_side": 2, "stance": 0.8}, {**default, "leg_family": "klann_leg", "scale": 3.5})]
    study = load_study_spec(pathlib.Path(__file__).resolve().parents[2] / "studies" / "walker.toml")
    for steps in (1, 5):
        runs = {}
        for name, device, tiled, registers in (("cpu", "cpu", True, TILED_REGISTERS),
                                               ("tiled", "cuda", True, TILED_REGISTERS),
                                               ("uncapped", "cuda", True, None), ("thread", "cuda", False, None)):
            model = pack_legged(specs, device=device, dt=study.dt, config=study.solver_config(), tiled=tiled)
            model.max_registers = registers
            legged_step_batch(model, steps)
            assert model.tiled == tiled and not model.diverged.numpy().any()
            runs[name] = {"velocity": model.velocity.numpy(), "rates": model.psi_dot.numpy(),
                          "impulse": model.impulse.numpy(), "position": model.position.numpy(),
                          "iterations": model.iterations.numpy(), "contacts": model.contacts.numpy()}
        cpu = runs["cpu"]
        assert cpu["contacts"].min() > 0 and cpu["iterations"].min() > 0  # contacts and PADMM in every world
        for name in ("tiled", "thread"):
            run = runs[name]
            assert np.abs(run["velocity"] - cpu["velocity"]).max() < 1e-4, (steps, name)
            assert np.abs(run["rates"] - cpu["rates"]).max() < 1e-2, (steps, name)
            assert np.abs(run["impulse"] - cpu["impulse"]).max() < 1e-4 * max(1.0, np.abs(cpu["impulse"]).max())
        for key in ("position", "velocity", "rates", "impulse"):
            assert np.array_equal(runs["uncapped"][key], runs["tiled"][key]), key


def test_evaluate_dynamic_reduced():
    """model="reduced": the default walker gets finite metrics with loop_violation_max = the Jansen
    table's closure error times the scale; the Klann walker gets metrics or a reason; a design out
    of bounds cannot be built while the others are evaluated."""
    default = WALKER.space.default()
    params = [default, {**default, "leg_family": "klann_leg"}, {**default, "scale": 100.0}]
    evaluation = evaluate_dynamic(WALKER, params, duration=1.0, dt=2e-3, model="reduced")
    assert all(isinstance(reason, str) for reason in evaluation.failures)
    assert evaluation.failures[2].startswith("cannot be built"), evaluation.failures[2]
    assert evaluation.failures[0] == "", evaluation.failures[0]
    for p, metrics, reason in zip(params[:2], evaluation.metrics, evaluation.failures):
        if reason:
            assert not metrics
            continue
        assert np.isfinite(metrics["walking_speed"])
        closure = unit_leg(p["leg_family"])[1].closure_error * p["scale"]
        assert metrics["loop_violation_max"] == pytest.approx(closure, rel=1e-9)


def test_reduced_walks_as_fast_as_maximal():
    """The default walker's walking speed in reduced coordinates is within 30 % of the maximal
    engine's (2 s at dt 2e-3, rho_update_interval 8 for both)."""
    config = SolverConfig(tuning=Tuning(rho_update_interval=8))
    default = WALKER.space.default()
    runs = {model: evaluate_dynamic(WALKER, [default], duration=2.0, dt=2e-3, config=config, model=model)
            for model in ("maximal", "reduced")}
    assert runs["maximal"].failures == [""], runs["maximal"].failures
    assert runs["reduced"].failures == [""], runs["reduced"].failures
    fast, ours = runs["maximal"].metrics[0]["walking_speed"], runs["reduced"].metrics[0]["walking_speed"]
    assert fast > 0.1 and abs(ours - fast) < 0.3 * fast, (ours, fast)


def study_file(tmp_path, name, family, model, extra=""):
    path = tmp_path / f"{name}.toml"
    path.write_text(textwrap.dedent(f"""
        [study]
        name = "{name}"
        family = "{family}"
        mode = "dynamic"
        generations = 1
        worlds = 2
        seed = 1
        [objective]
        metric = "{'walking_speed' if family == 'walker' else 'torque_rms'}"
        direction = "maximize"
        [optimizer]
        name = "cma"
        [simulation]
        duration = 1.3  # one crank turn at least: 1.26 s at the walker's 5 rad/s, 1 s for the four-bar
        dt = 0.002
        model = "{model}"
        {extra}
    """))
    return path


def test_study_simulation_model(tmp_path):
    """[simulation] model: "bogus" is refused naming simulation.model; "reduced" for a family
    without build_legged is refused by run_study; a reduced walker study runs and stores its
    designs, their loop violation the tables' closure error times the scale (reduced worlds)."""
    with pytest.raises(ValueError, match="simulation.model"):
        load_study_spec(study_file(tmp_path, "bogus", "walker", "bogus"))
    four_bar = load_study_spec(study_file(tmp_path, "four", "four_bar", "reduced"))
    with pytest.raises(ValueError, match="build_legged"):
        run_study(four_bar, progress=False)
    kinematic = study_file(tmp_path, "kin", "four_bar", "reduced").read_text().replace('mode = "dynamic"',
                                                                                      'mode = "kinematic"')
    (tmp_path / "kin.toml").write_text(kinematic)
    with pytest.raises(ValueError, match="simulation.model"):
        load_study_spec(tmp_path / "kin.toml")
    with pytest.raises(ValueError, match="spec_hook"):
        evaluate_dynamic(WALKER, [WALKER.space.default()], duration=0.02, dt=2e-3, model="reduced",
                         spec_hook=lambda spec, params: spec)
    from morphopt.storage import StudyStorage

    # three legs a side, as in studies/walker.toml: walkers on one or two fall within the crank turn a study runs
    spec = load_study_spec(study_file(tmp_path, "walk", "walker", "reduced", extra="[fixed]\nlegs_per_side = 3"))
    assert spec.model == "reduced"
    result = run_study(spec, progress=False)
    assert result.evaluations == 2
    frame = StudyStorage(spec.storage_url, spec.name).designs()
    assert len(frame) == 2 and (tmp_path / "walk.sqlite").exists()
    ok = frame[frame["failure"] == ""]
    assert len(ok) >= 1, frame["failure"].tolist()
    for _, row in ok.iterrows():
        closure = unit_leg(row["leg_family"])[1].closure_error * row["scale"]
        assert row["metric_loop_violation_max"] == pytest.approx(closure, rel=1e-9)
        assert np.isfinite(row["metric_walking_speed"])
