"""Joint limits as unilateral rows in the same solve as the loops."""

import math

import numpy as np

from engine import Body, Joint, MechanismSpec, pack_worlds, rollout
from engine.scenes_contact import fourbar_limits


def rocker_angle(body_q):
    """Angle of a bar turned about +y from its quaternion (x, y, z, w)."""
    return 2.0 * np.arctan2(body_q[..., 4], body_q[..., 6])


def test_fourbar_rocker_limit_holds_and_loop_stays_closed(device):
    """The passive four-bar's rocker hits its upper limit every swing: over 5 s it never passes
    the limit by more than 1 mm at its 0.25 m tip (0.004 rad) and the loop stays closed to 1e-5 m."""
    scene = fourbar_limits()
    limit = scene.spec.joints[3].limit_upper
    model = pack_worlds([scene.spec], device=device)
    state, control = model.state(), model.control()
    angles, closure = [], []
    for _ in range(1000):
        trace, state = rollout(model, state, control, 5, dt=1e-3, record_every=5)
        angles.append(rocker_angle(state.body_q.numpy()[0, 2]))
        closure.append(trace.violation_linear.max())
    angles = np.array(angles)
    hits = np.count_nonzero((angles[1:] > limit - 0.005) & (angles[:-1] <= limit - 0.005))
    assert hits >= 3, "the rocker did not reach its limit every swing"
    assert angles.max() - limit < 0.004
    assert max(closure) < 1e-5


def test_prismatic_slider_rests_on_its_lower_limit(device):
    """A slider on a vertical prismatic joint falls onto its lower limit at -0.1 m and rests
    there within 1 mm (no tunnelling at 1.4 m/s impact speed)."""
    slider = Body("slider", 0.5, (1e-3, 1e-3, 1e-3))
    rail = Joint("rail", "prismatic", None, "slider", axis=(0, 0, 1), limit_lower=-0.1)
    model = pack_worlds([MechanismSpec([slider], [rail])], device=device)
    assert model.has_limits and model.row_count.numpy()[0] == 6
    state, heights = model.state(), []
    for _ in range(200):
        _, state = rollout(model, state, model.control(), 5, dt=1e-3, record_every=5)
        heights.append(state.body_q.numpy()[0, 0, 2])
    assert abs(heights[-1] + 0.1) < 1e-3
    assert min(heights) > -0.101


def test_revolute_limit_stops_a_pendulum(device):
    """A pendulum released horizontally with a limit at 30 degrees past vertical swings to the
    limit and no further (within 0.004 rad)."""
    length = 0.3
    rod = Body("rod", length, (1e-5, length**2 / 12, length**2 / 12), com=(length / 2, 0, 0))
    limit = math.radians(120.0)  # rod starts along +x (angle 0), hangs at 90 degrees
    hinge = Joint("hinge", "revolute", None, "rod", axis=(0, 1, 0), limit_upper=limit)
    model = pack_worlds([MechanismSpec([rod], [hinge])], device=device)
    state = model.state()
    angles = []
    for _ in range(100):
        _, state = rollout(model, state, model.control(), 10, dt=1e-3, record_every=10)
        angles.append(rocker_angle(state.body_q.numpy()[0, 0]))
    # rotation about +y by a positive angle swings the +x bar downwards (u = (cos, 0, -sin))
    assert max(angles) > limit - 0.05
    assert max(angles) - limit < 0.004
