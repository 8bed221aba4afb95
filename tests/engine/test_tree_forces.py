"""Force elements (engine.forces) in the tree plan (engine.reduced.chain_stages.apply_forces):
the same physics as test_forces checks on the maximal plan, where the tree applies: a spring-held
inverted pendulum's static deflection, a wheel spun by a joint torque (on a fixed axle and on a
free hub), a loaded four-bar against the maximal plan (the oracle),
joint elements on a joint the tree runs backwards and a spring on a welded body, the plan's choice."""

import dataclasses
import math

import numpy as np
from scipy.optimize import brentq

import engine
import engine.reduced.chain_layout
from engine import Body, BodyWrench, Joint, JointSpring, JointTorque, LinearSpring, MechanismSpec
from engine.scenes import fourbar
from tests.engine.test_forces import inverted_pendulum, loaded_fourbar, run, wheel_spec

CPU = "cpu"


def test_joint_spring_holds_an_inverted_pendulum_at_its_static_deflection():
    m, length, g, k = 1.0, 0.5, 9.81, 3.0
    spec = inverted_pendulum(k, 1.5, m, length)
    exact = brentq(lambda th: k * th - m * g * length * math.sin(th), 0.1, math.pi)
    model = engine.pack([spec], device=CPU, dt=2.0e-3, coordinates="tree")
    state = run(model, 4000)
    x, _, z = state.body_q.numpy()[0, 0, :3]
    theta = math.atan2(x, z)
    print(f"tree: static deflection {theta:.6f} rad, analytic {exact:.6f} rad")
    assert abs(theta - exact) < 1.0e-3, (theta, exact)
    assert abs(math.hypot(x, z) - length) < 1.0e-4
    assert np.abs(state.body_qd.numpy()[0, 0]).max() < 1.0e-3  # settled


def test_joint_torque_spins_an_undriven_wheel_at_tau_over_inertia():
    tau, dt, steps = 0.2, 1.0e-3, 500
    specs = [wheel_spec("element", tau), wheel_spec("nothing"), wheel_spec("hub", tau, parent_free=True)]
    model = engine.pack(specs, device=CPU, dt=dt, coordinates="tree")
    state = run(model, steps)
    w = state.body_qd.numpy()[:, :, 3:]
    t = dt * steps
    np.testing.assert_allclose(w[0, 0], [0.0, 0.0, tau / 0.05 * t], rtol=1.0e-4, atol=1.0e-6)
    assert np.abs(w[1]).max() == 0.0
    # equal and opposite on child and parent: the free hub turns back, angular momentum stays zero
    np.testing.assert_allclose(w[2, 0, 2], tau / 0.05 * t, rtol=1.0e-4)
    np.testing.assert_allclose(w[2, 1, 2], -tau / 0.2 * t, rtol=1.0e-4)


def test_loaded_fourbar_matches_the_maximal_plan():
    """Every force element kind on a four-bar (a spring between two bodies, a cable to the world,
    a joint spring on the loop joint, a body wrench, a joint torque on the crank): the tree plan
    follows the maximal plan (the oracle) within 1e-4 m over 0.5 s, and both move away from the
    unloaded four-bar by more than 1e-3 m."""
    dt, steps = 1.0e-3, 500
    bodies = {}
    for coordinates in ("tree", "maximal"):
        model = engine.pack([loaded_fourbar(), fourbar().spec], device=CPU, dt=dt, coordinates=coordinates)
        bodies[coordinates] = run(model, steps).body_q.numpy()[:, :, :3]
    gap = np.abs(bodies["tree"][0] - bodies["maximal"][0]).max()
    moved = {c: np.abs(b[0] - b[1]).max() for c, b in bodies.items()}
    print(f"loaded four-bar after {steps * dt:g} s: tree - maximal {gap:.2e} m; moved by the forces: {moved}")
    assert gap < 1.0e-4, gap
    assert min(moved.values()) > 1.0e-3, moved


def test_pack_chooses_the_tree_plan_for_a_fourbar_with_forces():
    model = engine.pack([loaded_fourbar()], device=CPU)
    assert model.plan.coordinates is engine.Coordinates.TREE
    text = str(model.plan)
    assert "forces: runs (2 spring-dampers" in text and "apply_forces" in text
    assert "forces: skipped (none)" in str(engine.pack([fourbar().spec], device=CPU, coordinates="tree").plan)


def test_joint_elements_on_a_joint_the_tree_takes_backwards_and_a_spring_on_a_welded_body():
    """A joint torque and spring where the tree's joint runs child to parent (the free wheel is the
    floating root, heavier than its hub) against the maximal plan; a spring to a point of a body
    welded to the world (its frame from the weld) and a wrench on that body (which goes nowhere)."""
    turn = (0.0, 0.0, math.sin(0.3), math.cos(0.3))  # 0.6 rad about z
    wheel = MechanismSpec([Body("wheel", 1.0, [0.025, 0.025, 0.05]), Body("hub", 0.5, [0.1, 0.1, 0.2])],
                          [Joint("axle", "revolute", "hub", "wheel", axis=(0.0, 0.0, 1.0))], gravity=(0.0, 0.0, 0.0),
                          forces=[JointTorque("motor", "axle", 0.2),
                                  JointSpring("return", "axle", stiffness=0.01, rest_position=0.2)])
    arm_at = (0.2 + 0.4 * math.cos(0.6), 0.1 + 0.4 * math.sin(0.6), 0.3)
    welded = MechanismSpec([Body("base", 1.0, [0.1, 0.1, 0.1], position=(0.2, 0.1, 0.0), orientation=turn),
                            Body("arm", 1.0, [0.01, 0.02, 0.02], position=arm_at, orientation=turn)],
                           [Joint("weld", "fixed", None, "base", parent_position=(0.2, 0.1, 0.0),
                                  parent_orientation=turn),
                            Joint("hinge", "revolute", "base", "arm", parent_position=(0.3, 0.0, 0.3),
                                  child_position=(-0.1, 0.0, 0.0), axis=(0.0, 1.0, 0.0))],
                           forces=[LinearSpring("spring", "arm", (0.1, 0.0, 0.0), "base", (0.0, 0.2, 0.5),
                                                stiffness=40.0, damping=0.3, rest_length=0.1),
                                   BodyWrench("held", "base", force=(5.0, 0.0, 0.0))])
    assert engine.reduced.chain_layout.chain_layout(wheel).tree_body[-1] == 1  # the hub: the tree joint reversed
    out = {}
    for coordinates in ("tree", "maximal"):
        model = engine.pack([wheel, welded, dataclasses.replace(welded, forces=[])], device=CPU, dt=1.0e-3,
                            coordinates=coordinates)
        state = run(model, 500)
        out[coordinates] = state.body_q.numpy()[:, :, :3], state.body_qd.numpy()[:, :, 3:]
    (q_t, w_t), (q_m, w_m) = out["tree"], out["maximal"]
    print(f"wheel spin tree - maximal {np.abs(w_t[0] - w_m[0]).max():.2e} rad/s; welded: bodies tree - maximal "
          f"{np.abs(q_t[1] - q_m[1]).max():.2e} m, moved by the spring {np.abs(q_t[1] - q_t[2]).max():.2e} m")
    np.testing.assert_allclose(w_t[0], w_m[0], rtol=1.0e-4, atol=1.0e-5)
    assert abs(w_t[0, 0, 2]) > 1.0 and w_t[0, 1, 2] < -0.1  # equal and opposite: wheel forward, hub back
    assert np.abs(q_t[1] - q_m[1]).max() < 1.0e-4 and np.abs(q_t[1] - q_t[2]).max() > 1.0e-2
