"""engine.pack plans a batch itself: which coordinates each kind of mechanism gets (and why, in
print(model.plan)), that a forced plan that does not fit names the world and the reason, and that
engine.step / Stepper / rollout run every plan through one face with the same Trace, checked
against the maximal plan of the same worlds (an independent formulation: other coordinates, other
constraint rows, other solver)."""

import numpy as np
import pytest

import engine
from engine import Coordinates, SolverConfig, pack, rollout
from engine.scenes import make_scene
from engine.scenes_contact import CONTACT_SCENES
from morphopt.families import load_family


def family_spec(name, **overrides):
    family = load_family(name)
    return family.build_spec({**family.space.default(), **overrides}) if hasattr(family, "build_spec") else None


def linkage_spec(name):
    """A morphopt linkage family's default design as morphopt builds it (morphopt.linkage.to_spec:
    its loops closed by inline joints)."""
    from morphopt.build import build_specs
    family = load_family(name)
    [spec] = build_specs(family, [family.space.default()], workers=1)
    assert not isinstance(spec, str), spec
    return spec


@pytest.mark.parametrize("name", ["four_bar", "jansen_leg", "klann_leg", "watt_sixbar"])
def test_linkages_from_to_spec_get_the_grounded_plan_and_the_tree_plan_when_forced(name):
    spec = linkage_spec(name)
    model = pack([spec, spec])
    assert model.plan.coordinates is Coordinates.GROUNDED, str(model.plan)
    text = str(model.plan)
    assert "grounded coordinates (the fastest kind every world admits)" in text
    assert "PADMM iterations: skipped (no rows" in text
    tree = pack([spec, spec], coordinates="tree")
    text = str(tree.plan)
    assert "tree coordinates (forced by the caller)" in text
    assert "PADMM iterations: skipped (only bilateral rows" in text


def test_engine_scene_fourbar_gets_the_grounded_plan_and_maximal_when_forced():
    spec = make_scene("fourbar").spec
    assert pack([spec]).plan.coordinates is Coordinates.GROUNDED
    forced = pack([spec], coordinates="maximal")
    assert forced.plan.coordinates is Coordinates.MAXIMAL and forced.plan.forced
    assert isinstance(forced, engine.Model)
    assert "maximal coordinates (forced by the caller)" in str(forced.plan)


def test_walker_gets_the_tabulated_plan():
    walker = load_family("walker")
    specs = [walker.build_spec(walker.space.default()),
             walker.build_spec({**walker.space.default(), "leg_family": "klann_leg", "legs_per_side": 2})]
    model = pack(specs)
    assert model.plan.coordinates is Coordinates.TABULATED, str(model.plan)
    assert "tabulated coordinates" in str(model.plan)


@pytest.mark.parametrize("name, why", [
    ("fourbar_limits", "joint 'ground_rocker' has limits"),
    ("box_stack", "shapes 'box0' and 'box1' may touch each other"),
    ("ball_bounce", "restitution"),
])
def test_scenes_the_reduced_plans_cannot_model_stay_maximal_with_the_reasons(name, why):
    model = pack([CONTACT_SCENES[name]().spec])
    assert model.plan.coordinates is Coordinates.MAXIMAL
    text = str(model.plan)
    assert "not tabulated: world 0" in text and f"not tree: world 0 ({name}): " in text and why in text


def test_forcing_a_plan_that_does_not_fit_names_the_world_and_the_reason():
    fourbar = make_scene("fourbar").spec
    with pytest.raises(ValueError, match=r"coordinates 'tabulated' do not fit world 0 \(fourbar\): joint 'ground_crank' "):
        pack([fourbar, fourbar], coordinates=Coordinates.TABULATED)
    with pytest.raises(ValueError, match="coordinates must be one of"):
        pack([fourbar], coordinates="reduced")


def test_reduced_plans_keep_their_dt_and_check_a_control():
    for coordinates in (None, "tree"):
        model = pack([make_scene("fourbar").spec], coordinates=coordinates)
        state = model.state()
        assert model.plan.coordinates is (Coordinates.GROUNDED if coordinates is None else Coordinates.TREE)
        engine.step(model, state, state, control=model.control())  # body_f and joint_effort (test_tree_control)
        with pytest.raises(ValueError, match="body_f"):
            engine.step(model, state, state, control=object())
        with pytest.raises(ValueError, match="dt it was packed with"):
            rollout(model, state, None, 10, dt=0.5 * model.dt)
    walker = load_family("walker")
    tabulated = pack([walker.build_spec(walker.space.default())])
    assert tabulated.plan.coordinates is Coordinates.TABULATED
    one = tabulated.state()  # (the tabulated plan steps its one state in place)
    engine.step(tabulated, one, one, control=tabulated.control())
    with pytest.raises(ValueError, match="the tabulated plan reads body_f"):
        engine.step(tabulated, one, one, control=object())
    with pytest.raises(ValueError, match="drive targets from the specs"):
        engine.Stepper(tabulated, tabulated.state(), pack([walker.build_spec(walker.space.default())],
                                                          coordinates="maximal").control())


@pytest.mark.parametrize("reduced", ["grounded", "tree"])
@pytest.mark.parametrize("name", ["four_bar", "jansen_leg"])
def test_reduced_plan_trace_matches_the_maximal_plan(name, reduced):
    """The same worlds on a reduced plan and forced MAXIMAL: tracked points within 1 mm over 0.5 s of
    a driven crank, loops closed (measured by the same gauge) and the drive torques alike."""
    spec = linkage_spec(name)
    dt, steps = 1e-3, 500
    traces = {}
    for kind in (reduced, "maximal"):
        model = pack([spec], dt=dt, coordinates=kind)
        traces[model.plan.coordinates], _ = rollout(model, model.state(), None, steps, record_every=50)
    tree, maximal = traces[Coordinates(reduced)], traces[Coordinates.MAXIMAL]
    assert tree.points.shape == maximal.points.shape
    assert np.abs(tree.points - maximal.points).max() < 1e-3
    assert tree.violation_linear.max() < 1e-5 and maximal.violation_linear.max() < 1e-5
    assert tree.health.ok.all() and maximal.health.ok.all()
    driven = [j for j, joint in enumerate(spec.joints) if joint.drive is not None]
    scale = np.abs(maximal.drive_torque[1:, 0, driven]).max()
    assert np.abs(tree.drive_torque[1:, 0, driven] - maximal.drive_torque[1:, 0, driven]).max() < 0.05 * scale + 1e-6


def test_step_and_stepper_agree_with_rollout_on_a_reduced_plan():
    spec = make_scene("fourbar").spec
    model = pack([spec, spec])
    a = model.state()
    for _ in range(20):
        engine.step(model, a, a)
    by_step = a.body_q.numpy().copy()
    stepper = engine.Stepper(model, model.state(), chunk=10)
    stepper.advance()
    stepper.advance()
    np.testing.assert_array_equal(stepper.state.body_q.numpy(), by_step)
    trace, final = rollout(model, model.state(), None, 20, record_every=10)
    np.testing.assert_array_equal(final.body_q.numpy(), by_step)
    assert trace.points.shape[:2] == (3, 2)


def test_distinct_states_step_from_state_in_into_state_out():
    model = pack([make_scene("fourbar").spec])
    a, b = model.state(), model.state()
    engine.step(model, a, b)
    start = model.state().body_q.numpy()
    np.testing.assert_array_equal(a.body_q.numpy(), start)  # state_in unchanged
    assert np.abs(b.body_q.numpy() - start).max() > 0.0


def test_halted_worlds_keep_their_state_and_no_failure():
    spec = make_scene("fourbar").spec
    model = pack([spec, spec])

    def halt(points, start):
        return np.array([True, False])

    trace, final = rollout(model, model.state(), None, 40, record_every=10, halt=halt)
    assert trace.halted_at[0] == pytest.approx(10 * model.dt) and trace.halted_at[1] < 0
    assert np.array_equal(trace.points[-1, 0], trace.points[1, 0])
    assert not np.array_equal(trace.points[-1, 1], trace.points[1, 1])
    assert trace.health.reasons() == ["", ""]


def test_worlds_past_the_speed_guard_fail_with_the_reason():
    spec = make_scene("fourbar").spec
    model = pack([spec, spec], config=SolverConfig(max_speed=1e-3))  # every moving world trips the guard
    trace, _ = rollout(model, model.state(), None, 20, record_every=10)
    assert trace.diverged.all()
    assert all(r.startswith("diverged") for r in trace.health.reasons())


def test_a_motor_started_past_its_effort_limit_gets_a_plan_that_enforces_it():
    """The tree plan checks effort limits without enforcing them: a velocity drive that starts from
    rest against a low limit would stop its world at once, so the tree plan refuses such a world
    (the grounded plan, which clamps the drive, takes it; without it, maximal); the same arm started
    at its drive's speed (as morphopt builds linkages) takes the tree plan."""
    from engine import Body, Joint, JointDrive, MechanismSpec, TrackedPoint

    def arm(spin):
        body = Body("arm", mass=0.2, inertia=(1e-5, 1e-3, 1e-3), com=(0.1, 0, 0), angular_velocity=(0, spin, 0))
        motor = Joint("motor", "revolute", None, "arm", axis=(0, 1, 0),
                      drive=JointDrive(damping=5.0, target_velocity=6.0, effort_limit=2.0))
        return MechanismSpec([body], [motor], [TrackedPoint("tip", "arm", (0.2, 0, 0))])

    assert pack([arm(0.0)]).plan.coordinates is Coordinates.GROUNDED
    with pytest.raises(ValueError, match=r"joint 'motor': its drive starts past its effort limit \(30 > 2 N m\)"):
        pack([arm(0.0)], coordinates="tree")
    at_speed = pack([arm(6.0)], coordinates="tree")
    assert "effort limits checked, not enforced" in str(at_speed.plan)
    torques = []
    for kind in ("grounded", "maximal"):
        at_rest = pack([arm(0.0)], coordinates=kind)
        trace, _ = rollout(at_rest, at_rest.state(), None, 100, record_every=10)
        torques.append(trace.drive_torque[1:, 0, 0])
        assert trace.health.ok.all() and np.abs(torques[-1]).max() <= 2.0 + 1e-4, (kind, torques[-1])
    assert np.abs(torques[0] - torques[1]).max() < 0.01  # (at speed: the drive holds the arm against gravity)


def test_pack_checks_its_arguments_whatever_the_plan():
    walker = load_family("walker")
    spec = walker.build_spec(walker.space.default())
    for bad in (0.0, -1e-3, float("nan"), "x"):
        with pytest.raises(ValueError, match=r"^pack: dt must be a positive number of seconds"):
            pack([spec], dt=bad)
    with pytest.raises(ValueError, match=r"^pack: contact_capacity must be a non-negative integer"):
        pack([spec], contact_capacity=-1)
    capped = pack([spec], contact_capacity=8)  # fixed contact slots cannot honour a cap: not tabulated
    assert capped.plan.coordinates is not Coordinates.TABULATED
    assert "not tabulated: contact_capacity was given" in str(capped.plan)


def test_a_mechanism_far_from_the_origin_keeps_the_compensated_maximal_plan():
    from engine.scenes import shifted

    near, far = make_scene("fourbar").spec, shifted(make_scene("fourbar").spec, 500.0)
    assert pack([near], coordinates="tree").plan.coordinates is Coordinates.TREE
    model = pack([far], coordinates="maximal")
    assert model.plan.coordinates is Coordinates.MAXIMAL
    with pytest.raises(ValueError, match="lies 500 m from the origin"):
        pack([far], coordinates="tree")
    trace, _ = rollout(model, model.state(), None, 200, record_every=50)
    assert trace.health.ok.all()


@pytest.mark.parametrize("standing", [False, True])
def test_dr_legs_gets_the_tree_plan(standing):
    """DR Legs hanging (welded pelvis, 6 loops) and standing (its boxes on the ground, as the
    benchmark and both Newton peers run it) plan in tree coordinates unasked."""
    from benchmarks.scenes import dr_legs, dr_legs_path

    if dr_legs_path() is None:
        pytest.skip("the DR Legs asset is not beside this checkout (shared/assets)")
    model = pack(dr_legs(standing).specs)
    assert model.plan.coordinates is Coordinates.TREE, str(model.plan)
    assert ("collision: runs" in str(model.plan)) == standing


def test_worlds_that_admit_different_coordinates_run_in_groups_each_as_alone():
    """A batch of a walker, two four-bars and a box stack: three groups (tabulated, grounded, maximal),
    the plan prints each; a grouped rollout gives every world the trace of its group's plan run
    alone (the worlds never interact), in the batch's world order; step and Stepper run it too."""
    walker = load_family("walker")
    walk = walker.build_spec(walker.space.default())
    four = make_scene("fourbar").spec
    stack = CONTACT_SCENES["box_stack"]().spec
    specs = [four, walk, stack, four]
    model = pack(specs, dt=2e-3)
    assert model.plan.coordinates is Coordinates.MIXED
    text = str(model.plan)
    assert text.startswith("plan for 4 worlds on cpu: 3 groups")
    assert "group of 1 world: plan for 1 world on cpu: tabulated coordinates" in text
    assert "group of 2 worlds: plan for 2 worlds on cpu: grounded coordinates" in text
    assert "group of 1 world: plan for 1 world on cpu: maximal coordinates" in text
    trace, final = rollout(model, model.state(), None, 40, record_every=10)
    assert trace.points.shape[:2] == (5, 4) and trace.point_names[1] == [p.name for p in walk.points]
    for w, spec in enumerate(specs):
        alone = pack([spec], dt=2e-3)
        ref, _ = rollout(alone, alone.state(), None, 40, record_every=10)
        P = len(spec.points)
        np.testing.assert_array_equal(trace.points[:, w, :P], ref.points[:, 0, :P])
        assert trace.health.reason(w) == ref.health.reason(0)
    stepper = engine.Stepper(model, model.state(), chunk=10)
    for _ in range(4):
        stepper.advance()
    for part, ours in zip(stepper.state.parts, final.parts):
        np.testing.assert_array_equal(part.body_q.numpy(), ours.body_q.numpy())
    with pytest.raises(ValueError, match="coordinates 'mixed' is what the plan chooses"):
        pack(specs, coordinates="mixed")


def test_a_grouped_batch_takes_one_control_in_world_order():
    """A GroupedControl (body_f and joint_effort for the whole batch, world order) gives each world of
    a walker, four-bar and box-stack batch what its own plan gives it alone under the same rows:
    rollout, step and Stepper alike; the Control moves every world."""
    walker = load_family("walker")
    specs = [make_scene("fourbar").spec, walker.build_spec(walker.space.default()),
             CONTACT_SCENES["box_stack"]().spec]
    model = pack(specs, dt=2e-3)
    assert model.plan.coordinates is Coordinates.MIXED
    control = model.control()
    rows = np.zeros((*control.body_f.shape, 6), np.float32)
    rows[:, 1] = (0.5, 0.0, 1.0, 0.0, 0.02, 0.0)  # each world's second body
    efforts = np.zeros(control.joint_effort.shape, np.float32)
    efforts[0, 1] = 0.05
    control.body_f.assign(rows)
    control.joint_effort.assign(efforts)
    trace, final = rollout(model, model.state(), control, 40, record_every=10)
    plain, _ = rollout(model, model.state(), None, 40, record_every=10)
    for w, spec in enumerate(specs):
        alone = pack([spec], dt=2e-3)
        own = alone.control()
        own.body_f.assign(rows[w:w + 1, :own.body_f.shape[1]])
        own.joint_effort.assign(efforts[w:w + 1, :own.joint_effort.shape[1]])
        ref, _ = rollout(alone, alone.state(), own, 40, record_every=10)
        P = len(spec.points)
        np.testing.assert_array_equal(trace.points[:, w, :P], ref.points[:, 0, :P])
        assert np.abs(trace.points[-1, w, :P] - plain.points[-1, w, :P]).max() > 1e-4, w
    stepper = engine.Stepper(model, model.state(), control, chunk=10)
    for _ in range(4):
        stepper.advance()
    for part, ours in zip(stepper.state.parts, final.parts):
        np.testing.assert_array_equal(part.body_q.numpy(), ours.body_q.numpy())
    with pytest.raises(ValueError, match="GroupedControl"):
        rollout(model, model.state(), object(), 10, record_every=10)
