"""Ground relief (engine.spec.Relief) on the tabulated plan, against analytic results: a ball resting on
a crest at the surface's height, a frictionless ball oscillating in a trough with the period of the
surface's curvature; zero amplitude is the flat ground exactly; the other plans refuse relief by name."""

import math

import numpy as np
import pytest

import engine
from engine import Body, GroundPlane, MechanismSpec, Relief, Shape, TrackedPoint

AMPLITUDE, WAVELENGTH = 0.02, 0.5
RELIEF = Relief(AMPLITUDE, WAVELENGTH, (0.0, math.pi / 2))  # h = A sin(k x) cos(k y): along y = 0, A sin(k x)
K = 2.0 * math.pi / WAVELENGTH


def _ball(x, relief, radius=0.05, friction=1.0, lift=0.001):
    """A free ball above (x, 0) of the ground, ``lift`` above its surface."""
    h = 0.0 if relief is None else float(relief.height(x, 0.0))
    inertia = 0.4 * radius * radius * np.eye(3)
    return MechanismSpec(bodies=[Body("ball", 1.0, inertia, position=(x, 0.0, h + radius + lift))],
                         shapes=[Shape("s", "sphere", "ball", (radius,), friction=friction)],
                         ground=GroundPlane(friction=friction, relief=relief),
                         points=[TrackedPoint("centre", "ball")], name="ball")


def _centres(specs, steps, dt=0.001, every=1):
    model = engine.pack(specs, "cpu", dt=dt)
    assert model.plan.coordinates is engine.Coordinates.TABULATED
    trace, _ = engine.rollout(model, model.state(), None, steps, record_every=every)
    return trace.points[:, :, 0]  # (T, W, 3)


def test_ball_rests_on_a_crest_at_the_surface_height():
    crest = WAVELENGTH / 4  # sin(k x) = 1
    centres = _centres([_ball(crest, RELIEF)], 600, dt=0.002, every=100)
    assert abs(centres[-1, 0, 2] - (AMPLITUDE + 0.05)) < 2e-5
    assert abs(centres[-1, 0, 0] - crest) < 1e-4  # no slope there: it stays


def test_frictionless_ball_oscillates_with_the_trough_period():
    """Small oscillations of a frictionless ball (it slides, never turns) in the trough x0 = -lambda/4:
    its centre follows the surface's offset curve, of radius 1 / kappa - r with kappa = A k^2 at the
    bottom, so omega^2 = g / (1 / kappa - r)."""
    radius, x0 = 0.01, -WAVELENGTH / 4
    centres = _centres([_ball(x0 + 0.003, RELIEF, radius=radius, friction=0.0)], 3000)
    x = centres[:, 0, 0] - x0
    crossings = np.flatnonzero(np.sign(x[1:]) != np.sign(x[:-1]))
    assert len(crossings) >= 4
    t = (crossings + x[crossings] / (x[crossings] - x[crossings + 1])) * 0.001  # interpolated zeros
    period = 2.0 * float(np.mean(np.diff(t)))
    kappa = AMPLITUDE * K * K
    expected = 2.0 * math.pi * math.sqrt((1.0 / kappa - radius) / 9.81)
    assert abs(period / expected - 1.0) < 0.005, (period, expected)  # (0.06 % off at this amplitude)
    assert np.abs(x[-500:]).max() > 0.0029  # not damped
    assert centres[:, 0, 2].min() > -AMPLITUDE + radius - 1e-4  # never through the surface


def test_zero_amplitude_is_the_flat_ground():
    flat = _ball(0.1, None, lift=0.05)
    level = _ball(0.1, Relief(0.0, WAVELENGTH, (0.3, 0.2)), lift=0.05)
    bumpy = _ball(0.0, RELIEF)  # compiles the relief's code into the batch's step
    centres = _centres([flat, level, bumpy], 300)
    np.testing.assert_array_equal(centres[:, 0], centres[:, 1])


def test_other_plans_refuse_relief_by_name():
    with pytest.raises(ValueError, match="relief"):
        engine.pack([_ball(0.0, RELIEF)], "cpu", dt=0.001, coordinates="tree")
    with pytest.raises(ValueError, match="relief"):
        engine.pack([_ball(0.0, RELIEF)], "cpu", dt=0.001, coordinates="maximal")
    grounded = _ball(0.0, RELIEF)
    grounded.joints = [engine.Joint("pin", "revolute", None, "ball", parent_position=(0.0, 0.0, 0.2))]
    with pytest.raises(ValueError, match=r"world 0 \(ball\): its ground has relief.*not tabulated"):
        engine.pack([grounded], "cpu", dt=0.001)


def test_relief_is_checked():
    with pytest.raises(ValueError, match="wavelength"):
        Relief(0.01, 0.0)
    with pytest.raises(ValueError, match="phase"):
        Relief(0.01, 0.5, (0.0,))
    with pytest.raises(ValueError, match="horizontal"):
        GroundPlane(normal=(0.0, 0.1, 1.0), relief=Relief(0.01))


def test_a_relief_batch_measures_its_joints_and_names_each_worlds_reason():
    model = engine.pack([_ball(0.1, RELIEF)], "cpu", dt=0.001)
    assert model.gauge is not None  # the joints' gauge packs without the ground
    flat, bumpy = _ball(0.0, None), _ball(0.0, RELIEF)
    flat.joints = [engine.Joint("pin", "revolute", None, "ball", parent_position=(0.0, 0.0, 0.2))]
    bumpy.name = "bumpy"
    bumpy.bodies = [engine.Body("wheel", 1.0, np.eye(3) * 1e-3, position=(0.0, 0.0, 0.1)), *bumpy.bodies]
    bumpy.joints = [engine.Joint("axle", "revolute", "wheel", "ball")]
    with pytest.raises(ValueError, match=r"world 1 \(bumpy\): its ground has relief.*not tabulated: (?!world 0)"):
        engine.pack([flat, bumpy], "cpu", dt=0.001)
