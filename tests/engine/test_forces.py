"""Force elements (engine.forces) in the maximal plan, against analytic solutions: a mass on a
spring, a spring-held inverted pendulum's static deflection, a free body under a constant wrench,
a cable that does not push, a wheel spun by a joint torque (and by Control.joint_effort on an
undriven joint); the fused step bit-identical to the staged one; validation, pickling, the plan."""

import dataclasses
import math
import pickle

import numpy as np
import pytest
from scipy.optimize import brentq

import engine
from engine.reduced.model import ReducedModel
from engine import (Body, BodyWrench, Joint, JointSpring, JointTorque, LinearSpring, MechanismSpec, SolverConfig,
                    Tuning, step)
from engine.scenes import fourbar

CPU = "cpu"


def run(model, steps, control=None, record=None):
    """Step ``steps`` times; record(state) after every step when given. Returns the last state (a
    reduced plan steps one state in place)."""
    a = model.state()
    b = a if isinstance(model, ReducedModel) else model.state()
    for _ in range(steps):
        step(model, a, b, control)
        a, b = b, a
        if record is not None:
            record(a)
    return a


@pytest.mark.parametrize("coordinates", ["maximal", "tree", "tabulated"])
def test_mass_on_a_spring_oscillates_at_its_analytic_period(coordinates):
    m, k, rest, x0 = 2.0, 50.0, 0.5, 0.8
    spec = MechanismSpec([Body("mass", m, [0.01, 0.01, 0.01], position=(x0, 0.0, 0.0))], gravity=(0.0, 0.0, 0.0),
                         forces=[LinearSpring("spring", "mass", body_b=None, stiffness=k, rest_length=rest)])
    dt = 1.0e-3
    model = engine.pack([spec], device=CPU, dt=dt, coordinates=coordinates)
    xs = []
    run(model, 5000, record=lambda s: xs.append(s.body_q.numpy()[0, 0, :3].copy()))
    xs = np.array(xs)
    assert np.abs(xs[:, 1:]).max() == 0.0  # along one axis only
    u = xs[:, 0] - rest
    t = dt * np.arange(1, len(u) + 1)
    down = np.nonzero((u[:-1] > 0.0) & (u[1:] <= 0.0))[0]  # downward zero crossings, interpolated
    crossings = t[down] + dt * u[down] / (u[down] - u[down + 1])
    assert len(crossings) >= 3
    period = (crossings[-1] - crossings[0]) / (len(crossings) - 1)
    exact = 2.0 * math.pi * math.sqrt(m / k)
    print(f"spring period {period:.6f} s, analytic {exact:.6f} s, relative error {abs(period - exact) / exact:.2e}")
    assert abs(period - exact) / exact < 1.0e-3, (period, exact)
    amplitude = x0 - rest
    assert np.abs(u).max() < amplitude * 1.001  # no energy gain
    assert np.abs(u[-1500:]).max() > amplitude * 0.999  # nor loss over the last period


def inverted_pendulum(k, c, m=1.0, length=0.5, theta0=0.05):
    """A point-like mass on a massless rod hinged at the origin about y, upright at q = 0,
    held by a JointSpring (rest 0) against gravity."""
    half = 0.5 * theta0
    orientation = (0.0, math.sin(half), 0.0, math.cos(half))
    com = (length * math.sin(theta0), 0.0, length * math.cos(theta0))
    body = Body("bob", m, [1.0e-4, 1.0e-4, 1.0e-4], position=com, orientation=orientation)
    hinge = Joint("hinge", "revolute", None, "bob", child_position=(0.0, 0.0, -length), axis=(0.0, 1.0, 0.0))
    return MechanismSpec([body], [hinge], forces=[JointSpring("spring", "hinge", stiffness=k, damping=c)])


def test_joint_spring_holds_an_inverted_pendulum_at_its_static_deflection():
    m, length, g, k = 1.0, 0.5, 9.81, 3.0
    spec = inverted_pendulum(k, 1.5, m, length)
    exact = brentq(lambda th: k * th - m * g * length * math.sin(th), 0.1, math.pi)
    model = engine.pack([spec], device=CPU, dt=2.0e-3)
    state = run(model, 4000)
    x, _, z = state.body_q.numpy()[0, 0, :3]
    theta = math.atan2(x, z)
    print(f"static deflection {theta:.6f} rad, analytic {exact:.6f} rad")
    assert abs(theta - exact) < 1.0e-3, (theta, exact)
    assert abs(math.hypot(x, z) - length) < 1.0e-4
    assert np.abs(state.body_qd.numpy()[0, 0]).max() < 1.0e-3  # settled


@pytest.mark.parametrize("integrator", ["moreau", "euler"])
def test_constant_body_wrench_moves_a_free_body_analytically(integrator):
    m, inertia, force, torque = 2.0, (0.1, 0.2, 0.3), np.array([3.0, 0.0, -1.0]), np.array([0.0, 0.0, 0.6])
    spec = MechanismSpec([Body("box", m, inertia)], gravity=(0.0, 0.0, 0.0),
                         forces=[BodyWrench("push", "box", force=force, torque=torque)])
    config = SolverConfig(integrator=integrator)
    dt, steps = 1.0e-3, 1000
    model = engine.pack([spec], device=CPU, config=config, dt=dt)
    state = run(model, steps)
    t = dt * steps
    q = state.body_q.numpy()[0, 0]
    u = state.body_qd.numpy()[0, 0]
    np.testing.assert_allclose(u[:3], force / m * t, rtol=1.0e-4, atol=1.0e-6)
    np.testing.assert_allclose(u[3:], torque / np.array(inertia) * t, rtol=1.0e-4, atol=1.0e-6)
    # Moreau-Jean's midpoint rule is exact for a constant acceleration; semi-implicit Euler runs
    # ahead by a relative dt / t (x_n = a dt^2 n (n + 1) / 2)
    tol = 1.0e-4 if integrator == "moreau" else 1.5 * dt / t
    np.testing.assert_allclose(q[:3], force * t * t / (2.0 * m), rtol=tol, atol=1.0e-6)
    angle = 2.0 * math.atan2(q[5], q[6])  # spin about the principal axis z: tau t^2 / 2 I
    exact = torque[2] * t * t / (2.0 * inertia[2])
    assert abs(angle - exact) < tol * exact, (angle, exact)


@pytest.mark.parametrize("coordinates", ["maximal", "tree"])
def test_tension_only_spring_does_not_push_and_pulls_when_stretched(coordinates):
    m, k, rest = 1.0, 40.0, 1.0
    dt, steps = 1.0e-3, 10

    def spec(x0, tension_only):
        return MechanismSpec([Body("mass", m, [0.01, 0.01, 0.01], position=(x0, 0.0, 0.0))], gravity=(0, 0, 0),
                             forces=[LinearSpring("cable", "mass", stiffness=k, rest_length=rest,
                                                  tension_only=tension_only)])

    # shorter than its rest length: the cable leaves the mass alone, a plain spring pushes it out
    model = engine.pack([spec(0.6, True), spec(0.6, False), spec(1.2, True)], device=CPU, dt=dt,
                        coordinates=coordinates)
    state = run(model, steps)
    v = state.body_qd.numpy()[:, 0, 0]
    x = state.body_q.numpy()[:, 0, 0]
    assert v[0] == 0.0 and x[0] == np.float32(0.6)
    t = dt * steps
    np.testing.assert_allclose(v[1], k * 0.4 / m * t, rtol=0.01)
    np.testing.assert_allclose(v[2], -k * 0.2 / m * t, rtol=0.01)  # stretched: it pulls


def wheel_spec(name, torque=None, parent_free=False):
    """A wheel on a revolute joint about z, through its COM (to the world, or to a free hub)."""
    wheel = Body("wheel", 1.0, [0.025, 0.025, 0.05])
    bodies, parent = [wheel], None
    if parent_free:
        bodies.append(Body("hub", 2.0, [0.1, 0.1, 0.2]))
        parent = "hub"
    joints = [Joint("axle", "revolute", parent, "wheel", axis=(0.0, 0.0, 1.0))]
    forces = [] if torque is None else [JointTorque("motor", "axle", torque)]
    return MechanismSpec(bodies, joints, gravity=(0.0, 0.0, 0.0), name=name, forces=forces)


def test_joint_torque_and_joint_effort_spin_an_undriven_wheel_at_tau_over_inertia():
    tau, dt, steps = 0.2, 1.0e-3, 500
    specs = [wheel_spec("element", tau), wheel_spec("control"), wheel_spec("nothing"),
             wheel_spec("hub", tau, parent_free=True)]
    model = engine.pack(specs, device=CPU, dt=dt, coordinates="maximal")  # a Control: the maximal plan
    assert model.undriven_effort_joints == 4
    control = model.control()
    effort = np.zeros(control.joint_effort.shape, np.float32)
    effort[1, 0] = tau  # Control.joint_effort on a joint without a drive
    control.joint_effort.assign(effort)
    state = run(model, steps, control)
    w = state.body_qd.numpy()[:, :, 3:]
    t = dt * steps
    for world in (0, 1):
        np.testing.assert_allclose(w[world, 0], [0.0, 0.0, tau / 0.05 * t], rtol=1.0e-4, atol=1.0e-6)
    assert np.abs(w[2]).max() == 0.0
    # equal and opposite on child and parent: the hub turns back, angular momentum stays zero
    np.testing.assert_allclose(w[3, 0, 2], tau / 0.05 * t, rtol=1.0e-4)
    np.testing.assert_allclose(w[3, 1, 2], -tau / 0.2 * t, rtol=1.0e-4)


def loaded_fourbar():
    """The four-bar with every kind of force element (and an undriven joint left for Control.joint_effort)."""
    spec = fourbar().spec
    forces = [LinearSpring("spring", "crank", (0.01, 0.0, 0.0), "rocker", (0.0, 0.0, 0.02), stiffness=30.0,
                           damping=0.2, rest_length=0.05),
              LinearSpring("cable", "coupler", (0.0, 0.0, 0.0), None, (0.1, 0.0, 0.4), stiffness=20.0, damping=0.1,
                           rest_length=0.2, tension_only=True),
              JointSpring("return", "coupler_rocker", stiffness=0.5, damping=0.01, rest_position=0.3),
              BodyWrench("load", "coupler", force=(0.5, 0.0, -1.0), torque=(0.0, 0.02, 0.0)),
              JointTorque("motor", "ground_crank", 0.3)]
    return dataclasses.replace(spec, forces=forces)


@pytest.mark.parametrize("integrator", ["moreau", "euler"])
def test_fused_step_with_forces_matches_the_staged_step(integrator):
    """The force wrenches of a step are bit-identical in both paths (one function, same inputs,
    same order); the trajectories agree as test_fused's do (the solvers' substitutions round
    differently: within 2e-6 with the projection's velocity update off), PADMM iterations equal."""
    specs = [loaded_fourbar(), fourbar().spec]
    results = []
    for kernel in ("staged", "fused"):
        config = SolverConfig(integrator=integrator, tuning=Tuning(step_kernel=kernel,
                                                                   projection_velocity_update=False))
        model = engine.pack(specs, device=CPU, config=config, dt=2.0e-3, coordinates="maximal")
        assert model.step_kernel == kernel and model.has_forces
        control = model.control()
        effort = np.zeros(control.joint_effort.shape, np.float32)
        effort[:, 3] = 0.1  # ground_rocker: undriven
        control.joint_effort.assign(effort)
        run(model, 1, control)
        wrenches = model.work.body_f_total.numpy().copy()  # (a view of the array on the CPU)
        iterations = []
        state = run(model, 100, control, record=lambda s: iterations.append(model.work.iterations.numpy().copy()))
        results.append((wrenches, state.body_q.numpy(), state.body_qd.numpy(), iterations))
    (f_s, q_s, u_s, it_s), (f_f, q_f, u_f, it_f) = results
    np.testing.assert_array_equal(f_s, f_f)
    print(f"{integrator}: staged - fused after 101 steps: poses {np.abs(q_s - q_f).max():.2e}, "
          f"twists {np.abs(u_s - u_f).max():.2e}")
    assert np.abs(f_s[0]).max() > 0.1 and np.abs(f_s[1, :, 3:]).max() > 0.0  # forces and the effort acted
    assert np.abs(q_s - q_f).max() <= 2.0e-6 and np.abs(u_s - u_f).max() <= 1.0e-5, np.abs(q_s - q_f).max()
    np.testing.assert_array_equal(it_s, it_f)
    assert np.abs(q_s[0] - q_s[1]).max() > 1.0e-3  # the forces moved the loaded world


def test_spec_validation_names_the_element_and_field():
    body = Body("b", 1.0, [0.1, 0.1, 0.1])
    ball = Joint("ball", "spherical", None, "b")
    hinge = Joint("hinge", "revolute", None, "b")
    cases = [
        (dict(forces=[LinearSpring("s", "ghost", stiffness=1.0)]), "LinearSpring 's': body_a: body 'ghost'"),
        (dict(forces=[BodyWrench("w", "ghost")]), "BodyWrench 'w': body: body 'ghost'"),
        (dict(joints=[hinge], forces=[JointSpring("j", "nope")]), "JointSpring 'j': joint: joint 'nope'"),
        (dict(joints=[ball], forces=[JointTorque("t", "ball", 1.0)]), "JointTorque 't': joint: joint 'ball' is "
                                                                      "spherical"),
        (dict(forces=[BodyWrench("w", "b"), BodyWrench("w", "b")]), "duplicate force element name 'w'"),
        (dict(forces=["spring"]), "in the force list, got str"),
        (dict(forces=LinearSpring("s", "b")), "the force list must be a list"),
    ]
    for kwargs, message in cases:
        with pytest.raises(ValueError, match=message.replace("(", r"\(")):
            MechanismSpec([body], **kwargs)
    for make, message in [
        (lambda: LinearSpring("s", "b", stiffness=-1.0), "linear spring 's': stiffness"),
        (lambda: LinearSpring("s", "b", body_b="b"), "linear spring 's': body_b: must differ"),
        (lambda: LinearSpring("s", "b", point_a=(1.0, 2.0)), "linear spring 's': point_a"),
        (lambda: LinearSpring("s", "b", tension_only="yes"), "linear spring 's': tension_only"),
        (lambda: JointSpring("j", "hinge", damping=float("nan")), "joint spring 'j': damping"),
        (lambda: BodyWrench("w", "b", torque=(0.0, math.inf, 0.0)), "body wrench 'w': torque"),
        (lambda: JointTorque("t", "", 1.0), "joint torque 't': joint"),
    ]:
        with pytest.raises(ValueError, match=message):
            make()


def test_specs_with_forces_pickle_round_trip():
    spec = loaded_fourbar()
    back = pickle.loads(pickle.dumps(spec))
    assert [type(f) for f in back.forces] == [type(f) for f in spec.forces]
    for a, b in zip(spec.forces, back.forces):
        for name in a.__dataclass_fields__:
            assert np.array_equal(getattr(a, name), getattr(b, name)), (a.name, name)
    assert [b.name for b in back.bodies] == [b.name for b in spec.bodies]
    assert pickle.loads(pickle.dumps(fourbar().spec)).forces == []


def test_plan_lists_forces_in_every_plan():
    body = Body("b", 1.0, [0.1, 0.1, 0.1])
    spec = MechanismSpec([body, Body("c", 1.0, [0.1, 0.1, 0.1], position=(1, 0, 0))],
                         [Joint("hinge", "revolute", None, "b", axis=(0, 1, 0))],
                         forces=[LinearSpring("s1", "b", body_b="c", stiffness=1.0),
                                 LinearSpring("s2", "c", stiffness=1.0), BodyWrench("w", "b")])
    model = engine.pack([spec], device=CPU)  # the tree plan takes force elements (tests/engine/test_tree_forces.py)
    text = str(model.plan)
    assert model.plan.coordinates is engine.Coordinates.TREE
    # not tabulated for its joint to the world, not for its forces (tests/engine/test_tabulated_forces.py)
    assert "not tabulated: world 0 (mechanism): joint 'hinge' holds body 'b' to the world" in text
    assert "force" not in text.split("not tabulated:")[1].splitlines()[0]
    maximal = engine.pack([spec], device=CPU, coordinates="maximal")
    assert maximal.plan.coordinates is engine.Coordinates.MAXIMAL
    assert "forces: runs (2 spring-dampers, 1 body wrench" in str(maximal.plan)
    plain = engine.pack([MechanismSpec([body])], device=CPU, coordinates="maximal")
    assert "forces: skipped (none)" in str(plain.plan)


def test_energy_counts_the_springs_potential():
    """engine.metrics' energy includes 1/2 k s^2 of every spring: a mass on an undamped linear
    spring under gravity and a pendulum on an undamped joint spring keep their total energy within
    1e-3 of the energy they exchange (measured 1.3e-5 and 1.7e-5 over 1 s at dt 0.5 ms; without the
    springs' term the first would swing by all of it), the potential equals 1/2 k s^2 computed on
    the host, and a slack tension-only cable stores none."""
    from engine.metrics import compute_metrics

    m, k, rest = 2.0, 50.0, 0.5
    hanging = MechanismSpec([Body("mass", m, [0.01, 0.01, 0.01], position=(0.0, 0.0, -0.8))],
                            forces=[LinearSpring("spring", "mass", body_b=None, stiffness=k, rest_length=rest)])
    arm = Body("arm", 1.0, [1e-3, 1e-3, 1e-3], com=(0.4, 0.0, 0.0), position=(0.0, 0.0, 0.0))
    swinging = MechanismSpec([arm], [Joint("hinge", "revolute", None, "arm", axis=(0, 1, 0))],
                             forces=[JointSpring("coil", "hinge", stiffness=8.0, rest_position=0.6)])
    slack = MechanismSpec([Body("mass", m, [0.01, 0.01, 0.01], position=(0.0, 0.0, -0.3))], gravity=(0.0, 0.0, 0.0),
                          forces=[LinearSpring("cable", "mass", body_b=None, stiffness=k, rest_length=rest,
                                               tension_only=True)])
    model = engine.pack([hanging, swinging, slack], device=CPU, dt=5.0e-4, coordinates="maximal")
    state = model.state()
    compute_metrics(model, state)
    start = model.work.energy.numpy().copy()
    stretch = 0.8 - rest
    assert start[0] == pytest.approx(0.5 * k * stretch ** 2 + m * 9.81 * (-0.8), rel=1e-5)  # m g z, z = -0.8
    assert start[1] == pytest.approx(0.5 * 8.0 * 0.6 ** 2 - 1.0 * 9.81 * 0.0, rel=1e-5)  # the com on z = 0
    assert start[2] == 0.0  # at rest, no gravity, the cable slack
    energies, kinetic = [], []

    def record(s):
        compute_metrics(model, s)
        energies.append(model.work.energy.numpy().copy())
        kinetic.append(0.5 * m * float(np.sum(s.body_qd.numpy()[0, 0, :3] ** 2)))

    run(model, 2000, record=record)
    energies = np.array(energies)
    exchanged = max(kinetic)
    assert exchanged > 0.2  # 1/2 k (0.392 - 0.3)^2 = 0.21 J swing between the spring, gravity and motion
    assert np.abs(energies[:, 0] - start[0]).max() < 1e-3 * exchanged
    assert np.abs(energies[:, 1] - start[1]).max() < 1e-3 * 0.5 * 8.0 * 0.6 ** 2
