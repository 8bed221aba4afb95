"""Collision detection against analytic geometry, pair filtering, and what a scene skips."""

import importlib
import math

import numpy as np
import pytest

from engine import Body, Joint, MechanismSpec, pack_worlds, rollout
from engine.scenes import fourbar
from engine import GroundPlane, Shape
from engine.step import detect_contacts


def contacts(spec, device):
    """(distance, normal, point_a) of every contact of a one-world spec in its initial state."""
    model = pack_worlds([spec], device=device)
    state = model.state()
    detect_contacts(model, state.body_q, state.body_qd)
    work = model.work
    n = int(work.contact_count.numpy()[0])
    return (work.contact_distance.numpy()[0, :n], work.contact_normal.numpy()[0, :n],
            work.contact_point_a.numpy()[0, :n])


def ball(name, position, radius=0.1):
    return Body(name, 1.0, (0.004, 0.004, 0.004), position=position), Shape(name, "sphere", name, (radius,))


def box(name, position, half, orientation=(0, 0, 0, 1)):
    body = Body(name, 1.0, (0.01, 0.01, 0.01), position=position, orientation=orientation)
    return body, Shape(name, "box", name, half)


def capsule(name, position, radius, half_length, orientation=(0, 0, 0, 1)):
    body = Body(name, 1.0, (0.01, 0.01, 0.01), position=position, orientation=orientation)
    return body, Shape(name, "capsule", name, (radius, half_length))


def scene(*items, ground=None, joints=()):
    return MechanismSpec([b for b, _ in items], list(joints), shapes=[s for _, s in items], ground=ground)


Y90 = (0.0, math.sin(math.pi / 4), 0.0, math.cos(math.pi / 4))  # turns local z onto +x
X90 = (math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4))  # turns local z onto -y
Z45 = (0.0, 0.0, math.sin(math.pi / 8), math.cos(math.pi / 8))


def test_sphere_sphere(device):
    """Two spheres 0.205 m apart (radii 0.1): one contact at distance 0.005, normal along the line."""
    d, n, _ = contacts(scene(ball("a", (0.205, 0, 0)), ball("b", (0, 0, 0))), device)
    assert len(d) == 1 and abs(d[0] - 0.005) < 1e-6
    np.testing.assert_allclose(n[0], [1, 0, 0], atol=1e-6)


def test_sphere_on_plane_penetrating(device):
    """A sphere 2 mm into the plane: distance -0.002, normal +z, point at the sphere's bottom."""
    d, n, p = contacts(scene(ball("a", (0.3, 0, 0.098)), ground=GroundPlane()), device)
    assert len(d) == 1 and abs(d[0] + 0.002) < 1e-6
    np.testing.assert_allclose(p[0], [0.3, 0, -0.002], atol=1e-6)


def test_sphere_beside_capsule(device):
    """A sphere (r 0.1) 0.124 m from a capsule's segment (r 0.02): distance 0.004, normal radial."""
    d, n, _ = contacts(scene(ball("a", (0.05, 0.124, 0.0)), capsule("b", (0, 0, 0), 0.02, 0.2, Y90)), device)
    assert len(d) == 1 and abs(d[0] - 0.004) < 1e-6
    np.testing.assert_allclose(n[0], [0, 1, 0], atol=1e-6)


def test_crossed_capsules(device):
    """Capsules along x and y crossing 0.045 m apart (radii 0.02): distance 0.005 along z."""
    d, n, _ = contacts(scene(capsule("a", (0, 0, 0.045), 0.02, 0.2, Y90), capsule("b", (0, 0, 0), 0.02, 0.2, X90)),
                       device)
    assert abs(d.min() - 0.005) < 1e-6
    np.testing.assert_allclose(n[np.argmin(d)], [0, 0, 1], atol=1e-5)


def test_parallel_capsules_touch_along_a_line(device):
    """Two parallel capsules resting on each other give two contacts, one near each end."""
    d, _, p = contacts(scene(capsule("a", (0, 0, 0.041), 0.02, 0.2, Y90), capsule("b", (0, 0, 0), 0.02, 0.2, Y90)),
                       device)
    assert len(d) == 2 and np.allclose(d, 0.001, atol=1e-6)
    assert abs(p[0, 0] - p[1, 0]) > 0.3


def test_sphere_over_box_face(device):
    """A sphere 3 mm above a box's top face: distance 0.003, normal +z."""
    d, n, _ = contacts(scene(ball("a", (0.02, 0.01, 0.2 + 0.1 + 0.003)), box("b", (0, 0, 0), (0.3, 0.3, 0.2))), device)
    assert len(d) == 1 and abs(d[0] - 0.003) < 1e-6
    np.testing.assert_allclose(n[0], [0, 0, 1], atol=1e-6)


def test_capsule_lying_on_box(device):
    """A capsule lying across a box's top face touches it at both ends of its segment."""
    d, n, _ = contacts(scene(capsule("a", (0, 0, 0.1 + 0.02 + 0.002), 0.02, 0.1, Y90),
                             box("b", (0, 0, 0), (0.3, 0.3, 0.1))), device)
    assert len(d) == 2 and np.allclose(d, 0.002, atol=1e-6)
    np.testing.assert_allclose(n, [[0, 0, 1]] * 2, atol=1e-6)


def test_turned_box_on_box_gives_four_corners(device):
    """A 0.1 m cube turned 45 degrees about z, 1 mm above a larger box: its 4 bottom corners."""
    d, n, p = contacts(scene(box("a", (0, 0, 0.05 + 0.1 + 0.001), (0.05,) * 3, Z45),
                             box("b", (0, 0, 0), (0.3, 0.3, 0.1))), device)
    assert len(d) == 4 and np.allclose(d, 0.001, atol=1e-6)
    np.testing.assert_allclose(n, [[0, 0, 1]] * 4, atol=1e-6)
    np.testing.assert_allclose(np.sort(np.linalg.norm(p[:, :2], axis=1)), [0.05 * math.sqrt(2)] * 4, atol=1e-6)


@pytest.mark.parametrize("upright", [True, False], ids=["upright", "on_its_side"])
def test_cylinder_on_plane(upright, device):
    """A cylinder 1 mm above the plane touches with 4 rim points upright and 2 on its side."""
    radius, half = 0.05, 0.1
    if upright:
        body = Body("c", 1.0, (0.01,) * 3, position=(0, 0, half + 0.001))
    else:
        body = Body("c", 1.0, (0.01,) * 3, position=(0, 0, radius + 0.001), orientation=Y90)
    spec = MechanismSpec([body], shapes=[Shape("c", "cylinder", "c", (radius, half))], ground=GroundPlane())
    d, _, _ = contacts(spec, device)
    assert len(d) == (4 if upright else 2) and np.allclose(d, 0.001, atol=1e-6)


def test_filters_skip_jointed_bodies_and_shared_groups():
    """Overlapping spheres on jointed bodies, or sharing a collision group, make no pair."""
    a, sa = ball("a", (0, 0, 0))
    b, sb = ball("b", (0.15, 0, 0))
    c, sc = ball("c", (0.0, 0.15, 0))
    sb.collision_group = sc.collision_group = 3
    hinge = Joint("hinge", "revolute", "a", "b", parent_position=(0.075, 0, 0), child_position=(-0.075, 0, 0))
    model = pack_worlds([MechanismSpec([a, b, c], [hinge], shapes=[sa, sb, sc])], device="cpu")
    pairs = {tuple(sorted(p)) for p in zip(model.pair_shape_a.numpy()[0, :model.pair_count.numpy()[0]],
                                           model.pair_shape_b.numpy()[0, :model.pair_count.numpy()[0]])}
    assert pairs == {(0, 2)}  # a-c only: a-b jointed, b-c share group 3


def test_fourbar_allocates_no_contact_rows_and_runs_no_collision(monkeypatch):
    """A batch without shapes has zero contact capacity, no contact or limit rows, and never calls
    the collision stage."""
    model = pack_worlds([fourbar().spec], device="cpu")
    assert model.contact_capacity == 0 and not model.has_contacts and not model.has_limits
    assert model.max_rows == 24 and model.row_count.numpy()[0] == 20

    def forbidden(*args, **kwargs):
        raise AssertionError("collision detection ran for a scene without shapes")

    monkeypatch.setattr(importlib.import_module("engine.step"), "detect_contacts", forbidden)
    trace, _ = rollout(model, model.state(), model.control(), 5, dt=1e-3)
    assert trace.violation_linear.max() < 1e-6
