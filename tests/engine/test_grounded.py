"""The grounded plan (engine.reduced.grounded): a fixed-base one-DoF linkage stepped in its one
coordinate, against independent oracles: the four-bar's float64 equations of motion (scipy's
DOP853, benchmarks.convergence.fourbar_reference), the maximal plan (other coordinates, rows and
solver) under a Control, a pendulum's energy, a batch of distinct designs against each alone, and
the refusals that keep other plans. CPU only."""

import dataclasses
import math

import numpy as np
import pytest

import engine
from benchmarks.convergence import crank_run, fourbar_reference
from engine import Body, Joint, MechanismSpec, TrackedPoint
from engine.forces import JointSpring, LinearSpring
from engine.scenes import fourbar
from tests.engine.test_forces import loaded_fourbar
from tests.engine.test_tree_control import run, set_control

TIMES = np.arange(101) * 0.02  # crank_run's records over 2 s


def _crank_error(plan: str, dt: float, reference: np.ndarray) -> float:
    angles, _ = crank_run(plan, dt, 2.0)
    return float(np.abs((angles - reference + math.pi) % (2 * math.pi) - math.pi).max())


def test_the_passive_fourbar_is_fourth_order_and_closer_than_the_other_plans():
    """Crank angle over 2 s against the float64 reference: at dt 1 ms within the tree plan's error
    and a fifth of the maximal plan's (measured 9.4e-8 rad, tree 1.8e-5, maximal 7.1e-5; the
    floor is the float32 tracked point the angle is read from), and 8x closer from dt 4 ms to 2 ms
    (the triple jump of implicit midpoint steps is fourth order: measured 1.4e-6 and 1.5e-7)."""
    reference = fourbar_reference(TIMES)
    grounded = {dt: _crank_error("grounded", dt, reference) for dt in (4e-3, 2e-3, 1e-3)}
    tree, maximal = _crank_error("tree", 1e-3, reference), _crank_error("maximal", 1e-3, reference)
    assert grounded[1e-3] <= tree and grounded[1e-3] <= 0.2 * maximal, (grounded, tree, maximal)
    assert grounded[4e-3] / grounded[2e-3] >= 8.0, grounded


def test_the_passive_fourbar_keeps_its_energy():
    """No drive, no damping: over 10 s at dt 1 ms the energy (engine.metrics on the body poses)
    stays within 1e-5 of what it can lose (measured 2.0e-6, the float32 gauge's floor)."""
    _, drift = crank_run("grounded", 1e-3, 10.0)
    assert np.abs(drift).max() < 1e-5, np.abs(drift).max()


def test_a_control_acts_as_on_the_maximal_plan():
    """joint_effort on the four-bar's undriven joints (one to the world, one between moving links,
    the loop-closing one) and body_f (force and torque) on its coupler: grounded and maximal plans
    within 1e-4 m after 0.5 s, both moved by the Control by more than 1e-3 m; a world without a
    Control's entries runs as without a Control."""
    dt, steps = 1.0e-3, 500
    spec = fourbar().spec
    names = [j.name for j in spec.joints]
    coupler = [b.name for b in spec.bodies].index("coupler")
    effort = {(0, names.index("coupler_rocker")): 0.05, (0, names.index("crank_coupler")): -0.03,
              (0, names.index("ground_rocker")): 0.02}
    wrench = {(0, coupler): ((0.5, 0.0, -1.0), (0.0, 0.02, 0.0))}
    bodies = {}
    for coordinates in ("grounded", "maximal"):
        model = engine.pack([spec, spec], device="cpu", dt=dt, coordinates=coordinates)
        assert model.plan.coordinates.value == coordinates
        control = set_control(model.control(), effort=effort, wrench=wrench)
        bodies[coordinates] = run(model, steps, control).body_q.numpy()[:, :, :3]
    plain = engine.pack([spec], device="cpu", dt=dt, coordinates="grounded")
    alone = run(plain, steps).body_q.numpy()[0, :, :3]
    gap = np.abs(bodies["grounded"][0] - bodies["maximal"][0]).max()
    moved = {c: np.abs(b[0] - b[1]).max() for c, b in bodies.items()}
    assert gap < 1.0e-4, gap
    assert min(moved.values()) > 1.0e-3, moved
    assert np.abs(bodies["grounded"][1] - alone).max() < 1e-6


def _pendulum(length: float, angle: float) -> MechanismSpec:
    """A rod on a revolute joint to the world about y, its centre of mass ``length`` from the pivot,
    released at ``angle`` from the horizontal (x axis)."""
    c, s = math.cos(angle), math.sin(angle)
    rod = Body("rod", 1.0, (1e-4, 2e-3, 2e-3), position=(length * c, 0.0, -length * s),
               orientation=(0.0, -math.sin(-angle / 2), 0.0, math.cos(-angle / 2)))
    pin = Joint("pin", "revolute", None, "rod", axis=(0.0, 1.0, 0.0), child_position=(-length, 0.0, 0.0))
    return MechanismSpec([rod], [pin], [TrackedPoint("tip", "rod", (length, 0.0, 0.0))], name=f"rod_{length:g}")


def test_a_batch_of_distinct_linkages_runs_each_world_as_alone_and_swings_like_a_pendulum():
    """Rods of three lengths and a four-bar in one batch: every world's tracked points
    after 0.3 s equal those of its world packed alone, bit for bit; a rod released from the
    horizontal reaches the bottom at the speed energy conservation gives (m g l = (m l^2 + I) w^2 / 2)
    within 1e-6 relative."""
    specs = [_pendulum(0.1, 0.0), _pendulum(0.2, 0.3), fourbar().spec, _pendulum(0.1, 0.0), _pendulum(0.15, 1.0)]
    model = engine.pack(specs, device="cpu", dt=1e-3)
    assert model.plan.coordinates is engine.Coordinates.GROUNDED
    # the rods share one unit-scale table; the two rods of 0.1 m share their mass and potential splines
    assert "2 distinct link tables, 4 distinct mass and potential splines" in str(model.plan)
    trace, _ = engine.rollout(model, model.state(), None, 300, record_every=100)
    for w, spec in enumerate(specs):
        alone = engine.pack([spec], device="cpu", dt=1e-3)
        ref, _ = engine.rollout(alone, alone.state(), None, 300, record_every=100)
        P = len(spec.points)
        np.testing.assert_array_equal(trace.points[:, w, :P], ref.points[:, 0, :P])
    # the first rod's bottom: the fastest rate over a fine sweep of its first quarter swing
    rod = engine.pack([_pendulum(0.1, 0.0)], device="cpu", dt=1e-4)
    state = rod.state()
    fastest = 0.0
    for _ in range(3000):
        rod.advance(state, 1)
        fastest = max(fastest, abs(float(state.inner.v.numpy()[0])))
    expected = math.sqrt(2.0 * 9.81 * 0.1 / (0.1 ** 2 + 2e-3))
    assert abs(fastest - expected) < 1e-6 * expected + 2e-5, (fastest, expected)


@pytest.mark.parametrize("change, why", [
    ("cable", "force element 'cable': a tension-only spring with damping is not in the grounded plan"),
    ("limit", "joint 'ground_rocker' has limits"),
    ("floating", "no joint to the world"),
])
def test_what_the_grounded_plan_cannot_model_keeps_another_plan_with_the_reason(change, why):
    spec = fourbar().spec
    if change == "cable":
        spec = dataclasses.replace(spec, forces=[LinearSpring("cable", "coupler", body_b=None, point_b=(0.1, 0.0, 0.4),
                                                              stiffness=20.0, damping=0.1, tension_only=True)])
    elif change == "limit":
        joints = [dataclasses.replace(j, limit_lower=-1.0, limit_upper=1.0) if j.name == "ground_rocker" else j
                  for j in spec.joints]
        spec = dataclasses.replace(spec, joints=joints)
    else:
        spec = dataclasses.replace(spec, joints=[j for j in spec.joints if j.parent is not None])
    model = engine.pack([spec], device="cpu", dt=1e-3)
    assert model.plan.coordinates is not engine.Coordinates.GROUNDED
    assert f"not grounded: world 0 ({spec.name}): {why}" in str(model.plan)
    with pytest.raises(ValueError, match=r"coordinates 'grounded' do not fit world 0"):
        engine.pack([spec], device="cpu", dt=1e-3, coordinates="grounded")


def test_a_batch_of_many_distinct_linkages_keeps_the_tree_plan_unless_forced():
    """Unasked, more than GROUNDED_MAX_DISTINCT distinct linkage geometries (a study's generation of
    new designs) keep the tree plan, whose pack builds no tables, and the plan says why; as many
    specs of one geometry that differ in masses and springs (one table) take the grounded plan."""
    from engine.plan import GROUNDED_MAX_DISTINCT

    n = GROUNDED_MAX_DISTINCT + 1
    many = [fourbar(crank=0.08 + 1e-4 * k).spec for k in range(n)]
    model = engine.pack(many, device="cpu", dt=1e-3)
    assert model.plan.coordinates is engine.Coordinates.TREE
    assert f"not grounded: more than {GROUNDED_MAX_DISTINCT} distinct linkage geometries in the batch" in str(model.plan)
    one = fourbar().spec
    varied = [dataclasses.replace(one, bodies=[dataclasses.replace(b, mass=b.mass * (1 + 0.01 * k)) for b in one.bodies],
                                  forces=[JointSpring("spring", "ground_rocker", stiffness=0.1 * k)]) for k in range(n)]
    model = engine.pack(varied, device="cpu", dt=1e-3)
    assert model.plan.coordinates is engine.Coordinates.GROUNDED
    assert f"1 distinct link table, {n} distinct mass and potential splines" in str(model.plan)


def test_force_elements_act_as_on_the_maximal_plan():
    """The loaded four-bar (a spring-damper between two links, a cable to the world, a joint spring-
    damper on the loop joint, a wrench with a torque on the coupler, a joint torque on the crank),
    its cable undamped (a damped cable keeps the tree plan): grounded and maximal plans within 1e-4 m
    after 0.5 s, both moved by the forces by more than 1e-3 m."""
    spec = loaded_fourbar()
    forces = [dataclasses.replace(f, damping=0.0) if f.name == "cable" else f for f in spec.forces]
    loaded = dataclasses.replace(spec, forces=forces)
    bodies = {}
    for coordinates in ("grounded", "maximal"):
        model = engine.pack([loaded, fourbar().spec], device="cpu", dt=1e-3, coordinates=coordinates)
        bodies[coordinates] = run(model, 500).body_q.numpy()[:, :, :3]
    gap = np.abs(bodies["grounded"][0] - bodies["maximal"][0]).max()
    moved = {c: np.abs(b[0] - b[1]).max() for c, b in bodies.items()}
    assert gap < 1.0e-4, gap
    assert min(moved.values()) > 1.0e-3, moved


def _rod_on_a_spring(k: float, c: float) -> MechanismSpec:
    """A rod (I about its pivot 2e-3 + 1 * 0.1^2) on a joint spring-damper, no gravity, released at
    0.5 rad, 0.4 rad from its rest position 0.1 rad."""
    spec = _pendulum(0.1, 0.5)
    return dataclasses.replace(spec, gravity=(0.0, 0.0, 0.0), name="sprung",
                               forces=[JointSpring("spring", "pin", stiffness=k, damping=c, rest_position=0.1)])


def test_a_joint_spring_damper_rings_at_its_analytic_frequency_and_decay():
    """A rod on a torsional spring-damper without gravity: the angle q(t) = rest + A e^(-zeta w t)
    cos(w_d t) with w = sqrt(k / I), zeta = c / (2 sqrt(k I)); over 1 s at dt 1 ms within 1e-8 rad
    undamped (the triple jump; measured 2.2e-10) and 2e-5 rad damped (single midpoint steps, the
    damping at the step's mean momentum; measured 4.8e-6)."""
    I, k = 2e-3 + 0.1**2, 0.5
    for c in (0.0, 0.01):
        spec = _rod_on_a_spring(k, c)
        model = engine.pack([spec], device="cpu", dt=1e-3)
        assert model.plan.coordinates is engine.Coordinates.GROUNDED
        state = model.state()
        q0 = float(state.inner.q.numpy()[0])
        worst = 0.0
        w, zeta = math.sqrt(k / I), c / (2.0 * math.sqrt(k * I))
        wd = w * math.sqrt(1.0 - zeta**2)
        for n in range(1, 1001):
            model.advance(state, 1)
            t = n * 1e-3
            exact = 0.1 + 0.4 * math.exp(-zeta * w * t) * (math.cos(wd * t) + zeta * w / wd * math.sin(wd * t))
            got = q0 - 0.5 + float(state.inner.q.numpy()[0])  # the joint's angle: its coordinate, from the start
            worst = max(worst, abs(math.remainder(got - exact, 2 * math.pi)))
        assert worst < (1e-8 if c == 0.0 else 2e-5), (c, worst)
