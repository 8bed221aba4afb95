"""A Control in the tree plan (engine.reduced.chain_stages.apply_control): joint_effort on an
undriven wheel against tau / I and the maximal plan (also on a joint the tree runs backwards),
joint_effort on a four-bar's loop-closing and tree joints with body_f on its coupler against the
maximal plan, a free body under body_f against F t^2 / (2 m), and a None Control bit-identical to
the plain step (the tabulated plan's Control: test_tabulated_forces)."""

import math

import numpy as np
import pytest

import engine
import engine.reduced.chain_layout
from engine import Body, Joint, MechanismSpec
from engine.scenes import fourbar

CPU = "cpu"


def run(model, steps, control=None):
    """Step ``steps`` times with engine.step; the last state."""
    a, b = model.state(), model.state()
    for _ in range(steps):
        engine.step(model, a, b, control)
        a, b = b, a
    return a


def wheel_spec(hub=False):
    """A wheel (I_zz 0.05) on an undriven revolute joint about z through its COM, to the world or
    to a free hub heavier than it (the tree's root: the joint taken child to parent)."""
    bodies, parent = [Body("wheel", 1.0, [0.025, 0.025, 0.05])], None
    if hub:
        bodies.append(Body("hub", 0.5, [0.1, 0.1, 0.2]))
        parent = "hub"
    return MechanismSpec(bodies, [Joint("axle", "revolute", parent, "wheel", axis=(0.0, 0.0, 1.0))],
                         gravity=(0.0, 0.0, 0.0))


def set_control(control, effort=None, wrench=None):
    """Fill a Control's joint_effort {(world, joint): tau} and body_f {(world, body): (f, t)}."""
    if effort:
        a = np.zeros(control.joint_effort.shape, np.float32)
        for at, tau in effort.items():
            a[at] = tau
        control.joint_effort.assign(a)
    if wrench:
        a = np.zeros((*control.body_f.shape, 6), np.float32)
        for at, (f, t) in wrench.items():
            a[at] = (*f, *t)
        control.body_f.assign(a)
    return control


def test_joint_effort_spins_an_undriven_wheel_at_tau_over_inertia():
    tau, dt, steps = 0.2, 1.0e-3, 200
    specs = [wheel_spec(), wheel_spec(), wheel_spec(hub=True)]
    assert engine.reduced.chain_layout.chain_layout(specs[2]).tree_body[-1] == 1  # the tree joint reversed
    spins = {}
    for coordinates in ("tree", "maximal"):
        model = engine.pack(specs, device=CPU, dt=dt, coordinates=coordinates)
        assert model.plan.coordinates.value == coordinates
        control = set_control(model.control(), effort={(0, 0): tau, (2, 0): tau})
        spins[coordinates] = run(model, steps, control).body_qd.numpy()[:, :, 3:]
    w = spins["tree"]
    t = dt * steps
    print(f"wheel after {t:g} s: {w[0, 0, 2]:.7f} rad/s (tau t / I {tau / 0.05 * t:.7f}); tree - maximal "
          f"{np.abs(w - spins['maximal']).max():.2e} rad/s")
    np.testing.assert_allclose(w[0, 0], [0.0, 0.0, tau / 0.05 * t], rtol=1.0e-4, atol=1.0e-6)
    assert np.abs(w[1]).max() == 0.0  # a world without effort
    np.testing.assert_allclose(w[2, 0, 2], tau / 0.05 * t, rtol=1.0e-4)  # the wheel forward,
    np.testing.assert_allclose(w[2, 1, 2], -tau / 0.2 * t, rtol=1.0e-4)  # its hub back
    np.testing.assert_allclose(w, spins["maximal"], rtol=1.0e-4, atol=1.0e-5)


def test_fourbar_efforts_and_coupler_wrench_match_the_maximal_plan():
    """joint_effort on the four-bar's loop-closing joint (coupler_rocker, undriven) and on a tree
    joint between two moving bodies (crank_coupler), body_f on the coupler: tree and maximal plans
    within 1e-4 m after 0.5 s, both moved by the Control by more than 1e-3 m."""
    dt, steps = 1.0e-3, 500
    spec = fourbar().spec
    lay = engine.reduced.chain_layout.chain_layout(spec)
    names = [j.name for j in spec.joints]
    loop, tree_joint = names.index("coupler_rocker"), names.index("crank_coupler")
    assert lay.loops == [loop] and tree_joint in lay.joint and spec.joints[loop].drive is None
    coupler = [b.name for b in spec.bodies].index("coupler")
    bodies = {}
    for coordinates in ("tree", "maximal"):
        model = engine.pack([spec, spec], device=CPU, dt=dt, coordinates=coordinates)
        assert model.plan.coordinates.value == coordinates
        control = set_control(model.control(), effort={(0, loop): 0.05, (0, tree_joint): -0.03},
                              wrench={(0, coupler): ((0.5, 0.0, -1.0), (0.0, 0.02, 0.0))})
        bodies[coordinates] = run(model, steps, control).body_q.numpy()[:, :, :3]
    gap = np.abs(bodies["tree"][0] - bodies["maximal"][0]).max()
    moved = {c: np.abs(b[0] - b[1]).max() for c, b in bodies.items()}
    print(f"four-bar under a Control after {steps * dt:g} s: tree - maximal {gap:.2e} m; moved: {moved}")
    assert gap < 1.0e-4, gap
    assert min(moved.values()) > 1.0e-3, moved


def test_free_body_under_body_f_follows_f_t2_over_2m():
    m, force, dt, steps = 2.0, (0.6, -0.4, 0.2), 1.0e-3, 400
    spec = MechanismSpec([Body("block", m, [0.01, 0.02, 0.03], position=(0.1, 0.2, 0.3))], gravity=(0.0, 0.0, 0.0))
    model = engine.pack([spec], device=CPU, dt=dt, coordinates="tree")
    assert model.plan.coordinates is engine.Coordinates.TREE
    state = run(model, steps, set_control(model.control(), wrench={(0, 0): (force, (0.0, 0.0, 0.0))}))
    t = dt * steps
    x = state.body_q.numpy()[0, 0, :3]
    expected = np.array([0.1, 0.2, 0.3]) + np.array(force) * t * t / (2.0 * m)
    print(f"free body after {t:g} s: {x} (F t^2 / 2m: {expected})")
    np.testing.assert_allclose(x, expected, rtol=0.0, atol=2.0e-5)  # (first-order in dt: F dt t / 2m = 6e-5 m)
    np.testing.assert_allclose(state.body_qd.numpy()[0, 0, :3], np.array(force) * t / m, rtol=1.0e-4)
    assert np.abs(state.body_qd.numpy()[0, 0, 3:]).max() == 0.0


def test_none_control_is_bit_identical_and_a_zero_control_changes_nothing_but_rounding():
    spec = fourbar().spec
    out = []
    for control in (False, None, True):
        model = engine.pack([spec], device=CPU, dt=1.0e-3, coordinates="tree")
        state = model.state()
        if control is False:  # the plain path: the model stepped directly
            for _ in range(100):
                model.step(state, state)
        else:
            stepper = engine.Stepper(model, state, model.control() if control else None, chunk=50)
            stepper.advance()
            stepper.advance()
            state = stepper.state
        out.append((state.body_q.numpy().copy(), state.body_qd.numpy().copy()))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    np.testing.assert_allclose(out[2][0], out[0][0], rtol=0.0, atol=1.0e-6)


def test_rollout_takes_a_control_and_the_tree_control_checks_its_arrays():
    spec = fourbar().spec
    model = engine.pack([spec], device=CPU, dt=1.0e-3, coordinates="tree")
    control = set_control(model.control(), wrench={(0, 1): ((5.0, 0.0, -10.0), (0.0, 0.0, 0.0))})
    trace, final = engine.rollout(model, model.state(), control, 100, record_every=50)
    plain, _ = engine.rollout(model, model.state(), None, 100, record_every=50)
    assert trace.health.ok.all()
    assert np.abs(trace.points[-1] - plain.points[-1]).max() > 1.0e-4
    with pytest.raises(ValueError, match="body_f"):
        engine.step(model, final, final, control=object())
    assert "body_f and joint_effort" in str(model.plan)
    assert not hasattr(model.control(), "joint_target_position")  # drive targets come from the specs
    maximal = engine.pack([spec], device=CPU, dt=1.0e-3, coordinates="maximal")
    with pytest.raises(ValueError, match="drive targets from the specs"):  # its targets would not be read
        engine.rollout(model, model.state(), maximal.control(), 10, record_every=10)
    assert math.isfinite(float(trace.energy[-1, 0]))


def test_two_controls_on_one_model_each_act_with_their_own_arrays():
    """The step kernel reads a Control's arrays through a loads struct made per Control: alternating
    two Controls gives each its own torque (tau t / I over the steps it was used)."""
    tau, dt = 0.2, 1.0e-3
    model = engine.pack([wheel_spec()], device=CPU, dt=dt, coordinates="tree")
    forward = set_control(model.control(), effort={(0, 0): tau})
    back = set_control(model.control(), effort={(0, 0): -0.5 * tau})
    a, b = model.state(), model.state()
    for k in range(200):
        engine.step(model, a, b, forward if k % 2 == 0 else back)
        a, b = b, a
    spin = a.body_qd.numpy()[0, 0, 5]
    np.testing.assert_allclose(spin, (tau - 0.5 * tau) / 0.05 * 100 * dt, rtol=1.0e-4)
    engine.step(model, a, b, None)  # and without one: no torque at all
    assert b.body_qd.numpy()[0, 0, 5] == pytest.approx(spin, rel=1e-6)
