"""Force elements and a Control in the tabulated plan (engine.reduced.tabulated_forces): a floating
four-bar loaded by every force element kind, and one driven by a Control, against the maximal
plan (the oracle); an undamped spring-loaded one keeps its energy, springs included; a free base
under body_f follows F t^2 / (2 m); and the planner keeps such mechanisms tabulated."""

import dataclasses

import numpy as np
import pytest

import engine
from engine import BodyWrench, Integrator, JointSpring, JointTorque, LinearSpring, SolverConfig
from tests.engine.test_tabulated import four_bar
from tests.engine.test_tree_control import set_control

CPU = "cpu"


def run(model, steps, control=None):
    """``steps`` steps with engine.Stepper (every plan; the tabulated one steps its state in place)."""
    stepper = engine.Stepper(model, model.state(), control, chunk=steps)
    stepper.advance()
    return stepper.state


def weak_four_bar():
    """test_tabulated's floating four-bar with a weak crank drive (damping 0.01 N m s/rad toward
    3 rad/s: the tabulated plan needs a driving joint, and a weak one lets loads turn the crank)."""
    spec = four_bar()
    spec.joints = [dataclasses.replace(j, drive=dataclasses.replace(j.drive, damping=0.01)) if j.drive else j
                   for j in spec.joints]
    return spec


def loaded(damped=True, gravity=None):
    """The floating four-bar (weakly driven) with a spring from the base to the coupler, a cable from the
    rocker to a point in the world, a joint spring between coupler and rocker, a wrench on the
    coupler and a joint torque between crank and coupler (damped=False: springs alone, no damping,
    no wrench or torque)."""
    spec = weak_four_bar()
    c = 1.0 if damped else 0.0
    forces = [LinearSpring("spring", "coupler", (0.1, 0.0, 0.0), "base", (0.1, 0.0, 0.1), stiffness=3.0,
                           damping=0.05 * c, rest_length=0.05),
              LinearSpring("cable", "rocker", (0.05, 0.0, 0.0), None, (0.3, 0.0, 1.2), stiffness=2.0,
                           damping=0.02 * c, rest_length=0.15, tension_only=True),
              JointSpring("hinge", "B_coupler_rocker", stiffness=0.02, damping=1.0e-4 * c, rest_position=0.4)]
    if damped:
        forces += [BodyWrench("load", "coupler", force=(0.03, 0.0, 0.01), torque=(0.0, 0.002, 0.0)),
                   JointTorque("motor", "M_crank_coupler", effort=0.001)]
    spec.forces = forces
    if gravity is not None:
        spec.gravity = np.asarray(gravity, float)
    return spec


def positions(specs, coordinates, steps, dt=1.0e-3, control=None):
    model = engine.pack(specs, device=CPU, dt=dt, coordinates=coordinates)
    assert model.plan.coordinates.value == coordinates
    ctl = None if control is None else set_control(model.control(), **control)
    return run(model, steps, ctl).body_q.numpy()[:, :, :3], model


@pytest.mark.parametrize("integrator", [Integrator.MOREAU_JEAN, Integrator.SEMI_IMPLICIT_EULER])
def test_loaded_four_bar_matches_the_maximal_plan(integrator):
    """Every force element kind: the tabulated plan follows the maximal plan within 1e-4 m over
    0.3 s (the tables interpolate the linkage), while the forces move it by more than 1e-2 m."""
    steps = 300
    specs = [loaded(), weak_four_bar()]
    config = SolverConfig(integrator=integrator)
    out = {}
    for coordinates in ("tabulated", "maximal"):
        model = engine.pack(specs, device=CPU, dt=1.0e-3, coordinates=coordinates, config=config)
        out[coordinates] = run(model, steps).body_q.numpy()[:, :, :3]
    gap = np.abs(out["tabulated"][0] - out["maximal"][0]).max()
    moved = np.abs(out["maximal"][0] - out["maximal"][1]).max()
    print(f"{integrator.value}: tabulated - maximal {gap:.2e} m, moved by the forces {moved:.2e} m")
    assert gap < 1.0e-4, gap
    assert moved > 1.0e-2, moved
    assert np.abs(out["tabulated"][1] - out["maximal"][1]).max() < 1.0e-4


def test_control_matches_the_maximal_plan():
    """body_f on the coupler and joint_effort on the crank joint and on a joint between two
    links: tabulated and maximal within 1e-4 m after 0.3 s; the Control moved the linkage (the
    crank joint's effort adds to its drive's torque)."""
    spec = weak_four_bar()
    names = [j.name for j in spec.joints]
    crank, elbow = names.index("O_crank"), names.index("M_crank_coupler")
    control = dict(effort={(0, crank): 0.01, (0, elbow): -0.005},
                   wrench={(0, 2): ((0.1, 0.0, -0.05), (0.0, 0.005, 0.0))})
    tab, model = positions([spec, spec], "tabulated", 300, control=control)
    assert "body_f and joint_effort" in str(model.plan)
    maximal, _ = positions([spec, spec], "maximal", 300, control=control)
    gap = np.abs(tab - maximal).max()
    moved = np.abs(tab[0] - tab[1]).max()
    print(f"Control: tabulated - maximal {gap:.2e} m, moved {moved:.2e} m")
    assert gap < 1.0e-4, gap
    assert moved > 5.0e-3, moved


def test_body_f_on_the_base_moves_the_centre_of_mass_by_f_t2_over_2m():
    """The base pushed at its centre of mass in zero gravity while the drive turns the crank: the
    mechanism's centre of mass moves by F t^2 / (2 m_total) more than without the push (the drive's
    torques are internal; the linkage starts with the momentum of its crank's speed)."""
    spec = weak_four_bar()
    spec.gravity = np.zeros(3)
    force, dt, steps = np.array([0.3, 0.0, -0.2]), 1.0e-3, 400
    mass = np.array([b.mass for b in spec.bodies])
    moved = []
    for push in (force, np.zeros(3)):
        model = engine.pack([spec], device=CPU, dt=dt, coordinates="tabulated")
        start = mass @ model.state().body_q.numpy()[0, :, :3]
        state = run(model, steps, set_control(model.control(), wrench={(0, 0): (push, (0.0, 0.0, 0.0))}))
        moved.append((mass @ state.body_q.numpy()[0, :, :3] - start) / mass.sum())
    t = dt * steps
    expected = force * t * t / (2 * mass.sum())
    print(f"centre of mass moved {moved[0] - moved[1]} by the push, F t^2 / 2m {expected}")
    np.testing.assert_allclose(moved[0] - moved[1], expected, atol=1.0e-6)


def _rotation(quat):
    x, y, z, w = quat
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def initial_energy(spec):
    """The spec's energy at rest in NumPy: gravity's potential of every centre of mass and 1/2 k s^2
    of each spring at the spec's poses (a joint spring's angle from its anchor frames)."""
    bodies = {b.name: b for b in spec.bodies}
    frame = {n: (_rotation(b.orientation), np.asarray(b.position, float)) for n, b in bodies.items()}
    energy = -sum(b.mass * np.dot(spec.gravity, frame[n][1] + frame[n][0] @ b.com) for n, b in bodies.items())
    joints = {j.name: j for j in spec.joints}
    for f in spec.forces:
        if isinstance(f, LinearSpring):
            a = frame[f.body_a][1] + frame[f.body_a][0] @ f.point_a
            b = np.asarray(f.point_b) if f.body_b is None else frame[f.body_b][1] + frame[f.body_b][0] @ f.point_b
            s = np.linalg.norm(b - a) - f.rest_length
            energy += 0.5 * f.stiffness * (max(s, 0.0) if f.tension_only else s) ** 2
        elif isinstance(f, JointSpring):
            j = joints[f.joint]
            Rp = frame[j.parent][0] @ _rotation(j.parent_orientation)
            Rc = frame[j.child][0] @ _rotation(j.child_orientation)
            Rr = Rp.T @ Rc
            sin = 0.5 * np.dot(j.axis, [Rr[2, 1] - Rr[1, 2], Rr[0, 2] - Rr[2, 0], Rr[1, 0] - Rr[0, 1]])
            s = np.arctan2(sin, 0.5 * (np.trace(Rr) - 1.0)) - f.rest_position
            energy += 0.5 * f.stiffness * np.arctan2(np.sin(s), np.cos(s)) ** 2
    return energy


def test_undamped_springs_keep_the_energy():
    """Springs without damping on the floating four-bar in zero gravity, its crank free (a drive of
    zero damping): the record's energy exceeds the spring-free four-bar's by the springs' NumPy
    potential at the start, and drifts over 1 s, while they swing the linkage, by no more than the
    spring-free four-bar's own energy wanders (the drive's compliance, the tables) plus a tenth of it."""
    def free(spec):
        spec.gravity = np.zeros(3)
        spec.joints = [dataclasses.replace(j, drive=dataclasses.replace(j.drive, damping=0.0)) if j.drive else j
                       for j in spec.joints]
        return spec

    energy = []
    for spec in (free(loaded(damped=False)), free(weak_four_bar())):
        model = engine.pack([spec], device=CPU, dt=5.0e-4, coordinates="tabulated")
        energy.append(engine.rollout(model, model.state(), None, 2000, record_every=20)[0].energy[:, 0])
    springs = initial_energy(loaded(damped=False)) - initial_energy(weak_four_bar())
    drift = np.abs(energy[0] - energy[0][0]).max()
    print(f"springs at the start {energy[0][0] - energy[1][0]:.6f} J (NumPy {springs:.6f} J), drift {drift:.2e} J, "
          f"range of the spring-free energy {np.ptp(energy[1]):.2e} J")
    assert springs > 1.0e-3
    assert abs((energy[0][0] - energy[1][0]) - springs) < 1.0e-5 * max(1.0, springs)
    assert drift < np.ptp(energy[1]) + 0.1 * springs


def test_planner_keeps_a_loaded_mechanism_tabulated_and_names_the_forces():
    model = engine.pack([loaded()], device=CPU)
    assert model.plan.coordinates is engine.Coordinates.TABULATED
    text = str(model.plan)
    assert "forces: runs" in text and "applied_forces" in text
    plain = engine.pack([four_bar()], device=CPU)
    assert "forces: skipped (none)" in str(plain.plan)


def test_cuda_steps_forces_and_a_control_like_the_cpu():
    """The tiled CUDA step with force elements and a Control against the CPU's per-thread step."""
    import warp as wp
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device on this machine")
    control = dict(effort={(0, 1): -0.005}, wrench={(0, 2): ((0.1, 0.0, -0.05), (0.0, 0.005, 0.0))})
    out = {}
    for device in ("cpu", "cuda"):
        model = engine.pack([loaded(), weak_four_bar()], device=device, dt=1.0e-3, coordinates="tabulated")
        assert model.inner.tiled == (device == "cuda")
        stepper = engine.Stepper(model, model.state(), set_control(model.control(), **control), chunk=200)
        stepper.advance()
        out[device] = stepper.state.body_q.numpy()[:, :, :3]
    gap = np.abs(out["cpu"] - out["cuda"]).max()
    print(f"CUDA - CPU after 0.2 s: {gap:.2e} m")
    assert gap < 1.0e-4, gap
