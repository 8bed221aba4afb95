"""Frictional contact and restitution against analytic results."""

import math

import numpy as np
import pytest

from engine import MechanismSpec, SolverConfig, pack_worlds, rollout
from engine.scenes_contact import ball_bounce, box_on_plane, box_slide, box_stack, solid_box, walker, walker_gait
from engine import GroundPlane, Shape, TrackedPoint

GRAVITY = 9.81


def test_box_settles_and_does_not_drift(device):
    """A box released 1 mm above the plane settles within 1 s (penetration < 1 mm, speed < 1e-3
    m/s) and then stays put for 10 s (< 0.1 mm)."""
    scene = box_on_plane(gap=0.001)
    model = pack_worlds([scene.spec], device=device)
    trace, state = rollout(model, model.state(), model.control(), 10000, dt=1e-3, record_every=100)
    half = 0.05
    centre = trace.points[:, 0, 0]
    assert half - centre[10:, 2].min() < 1e-3  # penetration after 1 s
    speeds = np.linalg.norm(np.diff(centre[10:], axis=0), axis=1) / 0.1
    assert speeds.max() < 1e-3
    assert np.abs(centre[-1] - centre[10]).max() < 1e-4
    assert np.linalg.norm(state.body_qd.numpy()[0, 0]) < 1e-3


def test_sliding_box_stops_at_the_coulomb_distance(device):
    """A box launched at v0 on the plane stops after v0^2 / (2 mu g) (within 2 %)."""
    speed, mu = 2.0, 0.5
    model = pack_worlds([box_slide(speed=speed, friction=mu).spec], device=device)
    trace, state = rollout(model, model.state(), model.control(), 800, dt=1e-3, record_every=800)
    distance = trace.points[-1, 0, 0, 0] - trace.points[0, 0, 0, 0]
    expected = speed**2 / (2 * mu * GRAVITY)
    assert abs(distance - expected) / expected < 0.02
    assert np.linalg.norm(state.body_qd.numpy()[0, 0]) < 1e-3  # stopped (and did not tip over)


def incline_box(theta, mu, half=0.05):
    """A box resting on a plane tilted by theta about +y (downhill = (cos theta, 0, -sin theta))."""
    normal = np.array([math.sin(theta), 0.0, math.cos(theta)])
    body = solid_box("box", (half,) * 3, 1.0, position=normal * (half + 1e-4),
                     orientation=(0.0, math.sin(theta / 2), 0.0, math.cos(theta / 2)))
    return MechanismSpec([body], shapes=[Shape("box", "box", "box", (half,) * 3, friction=mu)],
                         ground=GroundPlane(normal=normal, friction=mu), points=[TrackedPoint("c", "box")])


@pytest.mark.parametrize("offset_deg", [-2.0, 2.0], ids=["below_threshold", "above_threshold"])
def test_incline_sticks_below_and_slides_above_friction_angle(offset_deg, device):
    """With mu = 0.5 a box sticks on a plane 2 degrees below atan(mu) and slides 2 degrees above,
    accelerating at g (sin theta - mu cos theta) (within 5 %)."""
    mu = 0.5
    theta = math.atan(mu) + math.radians(offset_deg)
    model = pack_worlds([incline_box(theta, mu)], device=device)
    steps = 1000
    trace, _ = rollout(model, model.state(), model.control(), steps, dt=1e-3, record_every=100)
    downhill = np.array([math.cos(theta), 0.0, -math.sin(theta)])
    travel = (trace.points[:, 0, 0] - trace.points[1, 0, 0]) @ downhill  # from t = 0.1 s (settled)
    if offset_deg < 0:
        assert abs(travel[-1]) < 1e-3
    else:
        accel = GRAVITY * (math.sin(theta) - mu * math.cos(theta))
        expected = 0.5 * accel * (trace.time[-1] ** 2 - trace.time[1] ** 2)
        assert abs(travel[-1] - expected) / expected < 0.05


def test_ball_rebounds_to_e_squared_height(device):
    """A ball dropped from 1 m with restitution 0.5 rebounds to 0.25 m (within 5 %)."""
    height, e, radius = 1.0, 0.5, 0.05
    model = pack_worlds([ball_bounce(radius=radius, height=height, restitution=e).spec], device=device)
    trace, _ = rollout(model, model.state(), model.control(), 1200, dt=1e-3, record_every=2)
    bottom = trace.points[:, 0, 0, 2] - radius
    impact = int(np.argmin(bottom[:300]))
    rebound = bottom[impact:].max()
    assert abs(rebound - e**2 * height) / (e**2 * height) < 0.05
    assert bottom.min() > -1e-3


def test_five_box_stack_stands(device):
    """Five stacked cubes stand for 10 s: no box moves more than 1 mm."""
    scene = box_stack(count=5, gap=0.0)
    model = pack_worlds([scene.spec], device=device)
    trace, _ = rollout(model, model.state(), model.control(), 10000, dt=1e-3, record_every=200)
    moved = np.linalg.norm(trace.points[:, 0] - trace.points[0, 0], axis=-1)
    assert moved.max() < 1e-3
    assert model.work.contact_dropped.numpy()[0] == 0


def test_contact_overflow_is_reported_per_world(device):
    """With room for 4 contacts, the 5-box stack (20 contacts) reports its dropped contacts while
    the ball in the same batch is unaffected (same trajectory as alone)."""
    stack, ball = box_stack(count=5, gap=0.0).spec, ball_bounce(height=0.2).spec
    batch = pack_worlds([stack, ball], device=device, contact_capacity=4)
    rollout(batch, batch.state(), batch.control(), 1, dt=1e-3)
    assert batch.work.contact_dropped.numpy().tolist() == [16, 0]  # 4 kept of the 20 touching corners
    trace, _ = rollout(batch, batch.state(), batch.control(), 300, dt=1e-3, record_every=300)
    assert batch.work.contact_dropped.numpy()[0] > 0 and batch.work.contact_dropped.numpy()[1] == 0
    alone = pack_worlds([ball], device=device, contact_capacity=4)
    trace_alone, _ = rollout(alone, alone.state(), alone.control(), 300, dt=1e-3, record_every=300)
    assert np.abs(trace.points[-1, 1, 0] - trace_alone.points[-1, 0, 0]).max() < 1e-6


def test_warm_start_matches_contacts_across_steps(device):
    """Contact impulses carried by key make a resting box converge in fewer PADMM iterations
    than a cold start, and the stored impulses carry the box's weight."""
    iterations = {}
    for warm in (True, False):
        model = pack_worlds([box_on_plane(gap=0.0).spec], device=device, config=SolverConfig().tuned(warmstart=warm))
        trace, state = rollout(model, model.state(), model.control(), 200, dt=1e-3, record_every=1)
        iterations[warm] = trace.iterations[100:, 0].mean()
        if warm:
            impulse = state.contact_impulse.numpy()[0, :state.contact_count.numpy()[0]].sum(axis=0)
            assert abs(impulse[2] - 1.0 * GRAVITY * 1e-3) < 1e-6
    assert iterations[True] < iterations[False]


def test_walker_stands_and_steps(device):
    """The four-legged walker stands on its PD-held legs (torso within 1 cm of its start height
    over 1 s) and, following the gait, keeps its hips assembled with no divergence."""
    scene = walker()
    model = pack_worlds([scene.spec] * 2, device=device)
    control = model.control()
    state = model.state()
    z0 = state.body_q.numpy()[0, 0, 2]
    targets = np.zeros((2, model.max_joints), np.float32)
    worst = 0.0
    for chunk in range(10):
        targets[1, :4] = walker_gait(chunk * 0.1)
        control.joint_target_position.assign(targets)
        trace, state = rollout(model, state, control, 100, dt=1e-3, record_every=100)
        worst = max(worst, trace.violation_linear.max())
    torso = state.body_q.numpy()[:, 0, :3]
    assert abs(torso[0, 2] - z0) < 1e-2
    assert np.all(np.isfinite(torso)) and not trace.diverged.any()
    assert worst < 1e-4
