"""engine.reduced.chains on the linkages morphopt builds (morphopt.linkage.to_spec closes their loops with
inline joints: the child anchor held on the parent's axis line, two rows) against independent
oracles: the maximal-coordinate engine (pack_worlds + rollout: every body's pose, PADMM) for the
tracked points, finite differences for the inline rows, the maximal engine's joint residuals for
the loops."""

import dataclasses
import math

import numpy as np
import pytest

from engine import Joint, JointType, SolverConfig, compute_metrics, pack_worlds, rollout
from engine.reduced.chain_layout import chain_layout
from morphopt.build import build_spec
from morphopt.families import load_family
from tests.engine.test_chains import _maximal_reference, _quat_matrix, _reference_matrices, pack_tree, spatial_loop

LINKAGES = ("four_bar", "jansen_leg", "klann_leg", "watt_sixbar")


def linkage(name: str, driven: bool = True):
    """A linkage family's default design as morphopt builds it (its crank's velocity drive, inline
    loop closures, every body started at the crank's speed); driven False: the drive taken off."""
    family = load_family(name)
    spec = build_spec(family, family.space.default(), None)
    if not driven:
        spec = dataclasses.replace(spec, joints=[dataclasses.replace(j, drive=None) for j in spec.joints])
    return spec


def inline_between(seed: int = 7):
    """spatial_loop's six links hinged one to the next from the world about skew axes, its closing
    hinge replaced by an inline joint between links 1 and 4 about a skew axis: the first body turns
    about axes other than the inline axis and the anchors part along it as the chain moves."""
    spec = spatial_loop(seed)
    joints = [j for j in spec.joints if j.name != "close"]
    a, b = spec.bodies[1], spec.bodies[4]
    Ra, Rb = np.array(_quat_matrix(a.orientation)), np.array(_quat_matrix(b.orientation))
    point = np.asarray(b.position) + Rb @ np.array([0.1, 0.0, 0.02])
    joints.append(Joint("slide", "inline", a.name, b.name, parent_position=Ra.T @ (point - a.position),
                        child_position=Rb.T @ (point - b.position), axis=(0.3, 0.8, 0.5)))
    return dataclasses.replace(spec, joints=joints, name="inline_between")


def tracked(spec, body_q: np.ndarray) -> np.ndarray:
    """World positions (P, 3) of the spec's tracked points from COM poses body_q (B, 7)."""
    out = []
    for point in spec.points:
        b = spec.body_index[point.body]
        R = np.array(_quat_matrix(body_q[b, 3:]))
        out.append(body_q[b, :3] + R @ (np.asarray(point.position) - np.asarray(spec.bodies[b].com)))
    return np.array(out)


def chains_run(spec, duration: float, every: float, dt: float):
    """Tracked points at every ``every`` s (records, P, 3) and the maximal engine's joint residuals
    of the chains path's poses at each record (largest linear [m], angular [rad])."""
    model = pack_tree([spec], device="cpu", dt=dt)
    state = model.state()
    gauge = pack_worlds([spec], device="cpu")
    points, linear, angular = [tracked(spec, state.body_q.numpy()[0])], 0.0, 0.0
    for _ in range(round(duration / every)):
        for _ in range(round(every / dt)):
            model.step(state)
        points.append(tracked(spec, state.body_q.numpy()[0]))
        compute_metrics(gauge, state)
        linear = max(linear, float(gauge.work.violation_linear.numpy()[0]))
        angular = max(angular, float(gauge.work.violation_angular.numpy()[0]))
    assert model.failure_reasons() == [None]
    return np.array(points), linear, angular


def maximal_points(spec, duration: float, every: float, dt: float = 1e-4) -> np.ndarray:
    """The maximal engine's tracked points at every ``every`` s (engine.rollout)."""
    model = pack_worlds([spec], device="cpu", dt=dt)
    trace, _ = rollout(model, model.state(), model.control(), round(duration / dt), record_every=round(every / dt))
    assert not trace.diverged.any()
    return trace.points[:, 0]


@pytest.mark.parametrize("name", LINKAGES)
def test_inline_joints_close_loops_with_their_two_rows(name):
    """Every inline joint of a morphopt linkage closes a loop (never a tree joint), and keeps
    exactly its two position rows normal to its axis (parts 0 and 1 of its turned anchor frame);
    the revolute joints to_spec keeps make the tree, one angle each."""
    spec = linkage(name)
    layout = chain_layout(spec)
    inline = [ji for ji, j in enumerate(spec.joints) if j.type == JointType.INLINE]
    revolute = [ji for ji, j in enumerate(spec.joints) if j.type == JointType.REVOLUTE]
    assert inline and sorted(layout.loops) == inline and list(layout.inline) == list(range(len(inline)))
    assert sorted(layout.joint) == revolute and layout.n == len(revolute)
    assert layout.rows.tolist() == [[li, part] for li in range(len(inline)) for part in (0, 1)]


@pytest.mark.parametrize("make, perturb", [(lambda: linkage("jansen_leg"), 0.0), (inline_between, 0.0),
                                           (inline_between, 0.15)])
def test_inline_rows_are_the_derivatives_of_their_errors(make, perturb):
    """The step's kept rows of inline loops equal finite differences of the loop errors (float64
    NumPy kinematics) to float32 rounding, and the layout's own float64 rows to 1e-6: at the
    initial pose, and with inline_between's angles moved off it (the loop open, its anchors apart
    along the axis while the first body turns about other axes: the rows' directions turn with it)."""
    spec = make()
    model = pack_tree([spec], device="cpu", dt=1e-3, config=SolverConfig(integrator="euler"))  # rows at q
    layout = model.layouts[0]
    q = layout.q0 + perturb * np.sin(np.arange(layout.n) + 1.0)
    state = model.state()
    state.q.assign(np.r_[q, state.q.numpy()[0, layout.n:]][None].astype(np.float32))
    model.step(state, record=True)
    _, dphi = _reference_matrices(layout, q)
    rows = 5 * layout.rows[:, 0] + layout.rows[:, 1]
    G = model.work.rows.numpy()[0, :len(rows), :layout.n]
    assert np.abs(G - dphi[rows]).max() < 1e-4 * np.abs(dphi[rows]).max()
    assert np.abs(layout.loop_rows(q)[0] - dphi).max() < 1e-6 * np.abs(dphi).max()
    if perturb:
        assert np.abs(layout.loop_rows(q)[1][rows]).max() > 1e-3  # the loop is open there


@pytest.mark.parametrize("name", ["four_bar", "jansen_leg"])
def test_driven_linkages_follow_the_maximal_engine(name):
    """Driven at the crank's speed (its velocity drive, as a study runs them), the tracked points
    of the chains path at dt 1 ms stay within 5e-5 m of the maximal engine's at dt 0.1 ms over 0.5 s
    (every 0.05 s; measured 1.2e-5 m four-bar, 1.7e-5 m Jansen), and the maximal engine's joint
    residuals of the chains path's poses stay below 1e-6 m (measured 1.2e-7 m; the tree joints have
    none: 0 rad)."""
    spec = linkage(name)
    reference = maximal_points(spec, 0.5, 0.05)
    points, linear, angular = chains_run(spec, 0.5, 0.05, 1e-3)
    assert np.linalg.norm(reference - reference[0], axis=2).max() > 1e-2  # the linkage moves
    assert np.linalg.norm(points - reference, axis=2).max() < 5e-5
    assert linear < 1e-6 and angular < 1e-5


@pytest.mark.parametrize("name", ["four_bar", "jansen_leg"])
def test_passive_linkages_converge_to_the_maximal_engine(name):
    """Without the drive (moving under gravity from the crank's speed), the tracked points converge
    to the maximal engine's at dt 0.1 ms at first order: within 1e-3 m at dt 1 ms over 0.5 s and at
    least 3x closer at dt 0.25 ms (measured 5.6e-4 -> 1.3e-4 m four-bar, 6.7e-5 -> 1.7e-5 m Jansen);
    loops closed to 1e-6 m."""
    spec = linkage(name, driven=False)
    reference = maximal_points(spec, 0.5, 0.05)
    errors = []
    for dt in (1e-3, 2.5e-4):
        points, linear, angular = chains_run(spec, 0.5, 0.05, dt)
        errors.append(np.linalg.norm(points - reference, axis=2).max())
        assert linear < 1e-6 and angular < 1e-5
    assert np.linalg.norm(reference - reference[0], axis=2).max() > 1e-2
    assert errors[0] < 1e-3 and errors[1] < errors[0] / 3


def test_an_inline_joint_between_turning_bodies_converges_to_the_maximal_engine():
    """inline_between (the anchors slide apart along a skew axis whose body turns about others):
    every body within 5e-4 m of the maximal engine's (dt 0.1 ms, converged to 3e-7 m) after 0.3 s
    at dt 0.5 ms, and at least 3x closer with each 4x smaller step unless within 2e-6 m already
    (measured 1.4e-6, 5.1e-7 m: the reference's floor; 3.4e-4, 8.5e-5, 2.2e-5 m at first order;
    rows without their directions' turn stalled at 5.5e-5 m); loop closed to 1e-6 m."""
    spec = inline_between()
    reference = _maximal_reference(spec, 0.3)
    errors = []
    for dt in (5e-4, 1.25e-4, 3.125e-5):
        model = pack_tree([spec], device="cpu", dt=dt)
        state = model.state()
        for _ in range(round(0.3 / dt)):
            model.step(state)
        errors.append(np.linalg.norm(state.body_q.numpy()[0, :, :3] - reference, axis=1).max())
        gauge = pack_worlds([spec], device="cpu")
        compute_metrics(gauge, state)
        assert gauge.work.violation_linear.numpy()[0] < 1e-6
    assert np.linalg.norm(reference - np.array([b.position for b in spec.bodies]), axis=1).max() > 0.1
    assert errors[0] < 5e-4 and errors[1] < max(errors[0] / 3, 2e-6) and errors[2] < max(errors[1] / 3, 2e-6)


def walker(legs_per_side: int, leg: str = "jansen_leg"):
    family = load_family("walker")
    return build_spec(family, dict(family.space.default(), legs_per_side=legs_per_side, leg_family=leg), None)


def test_walkers_are_refused_only_where_they_outgrow_the_kernel():
    """A walker (a floating box torso, inline loop closures, capsule feet on the ground) is refused
    by its size alone, with the count named: the default (3 Jansen legs a side) has 36 loop rows,
    4 legs a side 62 coordinates. Its shapes are modelled: a smaller walker packs."""
    with pytest.raises(ValueError, match="36 independent loop rows .* at most 32 rows"):
        chain_layout(walker(3))
    with pytest.raises(ValueError, match="62 tree coordinates, at most 48"):
        chain_layout(walker(4))
    layout = chain_layout(walker(1))
    assert layout.n == 6 + 14 and len(layout.rows) == 12 and len(layout.shapes) == 3


@pytest.mark.slow
@pytest.mark.parametrize("leg", ["jansen_leg", "klann_leg"])
def test_a_small_walker_walks_as_in_the_maximal_engine(leg):
    """One leg a side, dropped on the ground and walking for 1 s at dt 1 ms: the torso and the
    feet within 5e-3 m of the maximal engine's at the same dt (measured with the second-order tree
    step: 3.1e-3 m Jansen, first order: 1.0e-3; both, and the maximal engine itself, lie 2.2-2.5e-2 m
    from the maximal engine at dt 0.25 ms: on contact this compares two runs at one dt, not
    accuracy), while it falls 0.15-0.33 m and walks 9 cm; loops closed to 1e-6 m, no world stopped. The cranks' effort limits lifted in both engines: started at rest against their 5 rad/s
    velocity drives (damping 5), they would need 25 N m, past the 20 N m limit, from the first step,
    and the tree plan, which checks limits without enforcing them, refuses such a world."""
    spec = walker(1, leg)
    spec = dataclasses.replace(spec, joints=[j if j.drive is None else dataclasses.replace(
        j, drive=dataclasses.replace(j.drive, effort_limit=math.inf)) for j in spec.joints])
    model = pack_tree([spec], device="cpu", dt=1e-3)
    state = model.state()
    for _ in range(1000):
        model.step(state)
    maximal = pack_worlds([spec], device="cpu", dt=1e-3)
    trace, _ = rollout(maximal, maximal.state(), maximal.control(), 1000, record_every=1000)
    ours = tracked(spec, state.body_q.numpy()[0])
    assert np.linalg.norm(trace.points[-1, 0] - trace.points[0, 0], axis=1).max() > 0.05
    assert np.linalg.norm(ours - trace.points[-1, 0], axis=1).max() < 5e-3
    assert model.failure_reasons() == [None]
    gauge = pack_worlds([spec], device="cpu")
    compute_metrics(gauge, state)
    assert gauge.work.violation_linear.numpy()[0] < 1e-6
