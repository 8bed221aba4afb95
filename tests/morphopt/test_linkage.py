"""Linkage kinematics against closed-form geometry, feasibility, and the conversion to the engine."""

import math

import numpy as np
import pytest

from engine import pack_worlds, rollout
from morphopt.families import load_family
from morphopt.linkage import solve_at, solve_cycles, to_spec


def circles(p0, r0, p1, r1):
    """Both intersections of two circles (independent closed form)."""
    d = np.linalg.norm(p1 - p0)
    a = (r0**2 - r1**2 + d**2) / (2 * d)
    h = math.sqrt(r0**2 - a**2)
    mid = p0 + a * (p1 - p0) / d
    perp = np.array([-(p1 - p0)[1], (p1 - p0)[0]]) / d
    return mid + h * perp, mid - h * perp


def jansen_foot(theta, n):
    """Jansen's foot from his numbers [mm] by explicit circle intersections, choosing each joint by
    its geometric position (above / below / outward), not by our branch signs."""
    A, M = np.array([-n["a"], -n["l"]]), n["m"] * np.array([math.cos(theta), math.sin(theta)])
    B = max(circles(M, n["j"], A, n["b"]), key=lambda p: p[1])  # upper joint: higher
    C = min(circles(M, n["k"], A, n["c"]), key=lambda p: p[1])  # lower joint: lower
    D = min(circles(B, n["e"], A, n["d"]), key=lambda p: p[0])  # top of the triangle: outward (left)
    E = min(circles(D, n["f"], C, n["g"]), key=lambda p: p[0])  # knee: outward (left)
    F = min(circles(E, n["h"], C, n["i"]), key=lambda p: p[1])  # foot: lowest
    return F


def test_jansen_foot_path_matches_closed_form():
    """Jansen's published dimensions assemble over a whole crank turn and the foot path equals the
    closed-form construction to 1e-6 m."""
    family = load_family("jansen_leg")
    linkage = family.generate(family.space.default())
    solution = solve_cycles([linkage], samples=360)[0]
    assert solution.feasible, solution.reason
    expected = np.array([jansen_foot(a, family.HOLY_NUMBERS) for a in solution.angles]) * 1e-3
    assert np.abs(solution.point("foot", linkage) - expected).max() < 1e-6
    stride = np.ptp(expected[:, 0])
    assert 0.06 < stride < 0.075  # the known ~68 mm stride of the 38-mm-crank leg


def test_grashof_crank_rocker_turns_and_non_grashof_is_infeasible():
    """A Grashof crank-rocker (s + l < p + q, crank shortest) completes a turn; a non-Grashof
    four-bar with the same ground is reported infeasible, naming the dyad and the crank angle."""
    family = load_family("four_bar")
    base = family.space.default()
    grashof = family.generate(base)  # 0.10 + 0.30 < 0.30 + 0.25
    non_grashof = family.generate({**base, "crank": 0.15, "coupler": 0.20, "rocker": 0.20})  # 0.15+0.30 > 0.40
    good, bad = solve_cycles([grashof, non_grashof], samples=360)
    assert good.feasible and good.transmission_angle_min > 0.3
    assert not bad.feasible
    assert "dyad 'C' does not close at crank angle" in bad.reason
    assert np.isnan(bad.nodes["C"]).all()


def test_batch_groups_topologies_and_keeps_order():
    """A mixed batch of Jansen legs and four-bars comes back in input order, each solved right."""
    jansen, four = load_family("jansen_leg"), load_family("four_bar")
    items = [four.generate(four.space.default()), jansen.generate(jansen.space.default()),
             four.generate({**four.space.default(), "crank": 0.08})]
    solutions = solve_cycles(items, samples=90)
    assert [s.feasible for s in solutions] == [True, True, True]
    assert "foot" in items[1].points and solutions[1].nodes["F"].shape == (90, 2)
    crank_tip = solutions[2].nodes["M"]
    assert np.allclose(np.linalg.norm(crank_tip, axis=1), 0.08)


@pytest.mark.parametrize("family_name, point", [("jansen_leg", "foot"), ("four_bar", "coupler_point"),
                                                ("watt_sixbar", "coupler_point")])
def test_slowly_driven_dynamics_follows_kinematics(family_name, point):
    """The linkage converted to the engine, driven slowly by its crank motor under gravity, keeps
    its tracked point on the kinematic path (at the simulated crank angle) to 1e-4 m."""
    family = load_family(family_name)
    linkage = family.generate(family.space.default(), crank_speed=1.0)
    spec = to_spec(linkage)
    assert len(spec.bodies) == len(linkage.links)
    model = pack_worlds([spec], device="cpu")
    state, angles, points = model.state(), [], []
    for _ in range(40):
        trace, state = rollout(model, state, model.control(), 25, dt=1e-3, record_every=25)
        q = state.body_q.numpy()[0, 0, 3:]  # the crank turns about -y
        angles.append(-2.0 * math.atan2(q[1], q[3]))
        points.append(trace.points[-1, 0, 0][[0, 2]])
    kinematic = solve_at([linkage], np.array([angles]))[0].point(point, linkage)
    assert np.abs(kinematic - np.array(points)).max() < 1e-4
    assert angles[-1] > 0.8  # the motor turned the crank (1 rad/s for 1 s)


def test_compiled_kinematics_match_numpy():
    """The Warp kernels (float64) give the NumPy reference's feasibility, failure reasons, paths
    (to 1e-9 m) and transmission angles on random Jansen legs, four-bars and six-bars in one mixed
    call."""
    rng = np.random.default_rng(5)
    linkages = []
    for name in ("jansen_leg", "four_bar", "watt_sixbar"):
        family = load_family(name)
        linkages += [family.generate(p) for p in family.space.sample(rng, 40)]
    reference = solve_cycles(linkages, samples=120)
    compiled = solve_cycles(linkages, samples=120, device="cpu")
    assert [s.feasible for s in compiled] == [s.feasible for s in reference]
    assert 0 < sum(s.feasible for s in reference) < len(linkages)  # both outcomes occur
    for fast, slow in zip(compiled, reference):
        if slow.feasible:
            for node, path in slow.nodes.items():
                assert np.abs(fast.nodes[node] - path).max() < 1e-9, node
            assert abs(fast.transmission_angle_min - slow.transmission_angle_min) < 1e-9
        else:
            assert fast.reason == slow.reason


def test_link_mass_properties_match_trimesh():
    """The analytic mass, centre of mass and inertia of a ternary link made of three bars equal the
    mass properties trimesh integrates over the same boxes (to 1e-9 relative)."""
    from morphopt.linkage.to_spec import BarStyle, _matrix, link_body, link_mesh

    style = BarStyle(width=0.012, thickness=0.004, density=2700.0)
    points = [np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.0, 0.1]), np.array([0.1, 0.0, -0.2])]
    body = link_body("plate", points, style)
    mesh = link_mesh(points, style)
    mesh.density = style.density
    assert abs(body.mass - mesh.mass) < 1e-9 * mesh.mass
    rotation = _matrix(body.orientation)
    com_world = points[0] + rotation @ body.com
    assert np.abs(com_world - mesh.center_mass).max() < 1e-9
    inertia_world = rotation @ body.inertia @ rotation.T
    assert np.abs(inertia_world - mesh.moment_inertia).max() < 1e-9 * np.abs(mesh.moment_inertia).max()


def _bilateral_jacobian(spec):
    """Dense Jacobian (rows x 6 bodies) of the joint rows of one spec at its initial pose, and the
    number of bilateral rows."""
    import warp as wp

    from engine import pack_worlds
    from engine.joints import compute_joint_rows
    from engine.model import ROW_ANGULAR, ROW_LINEAR

    model = pack_worlds([spec], device="cpu")
    state = model.state()
    compute_joint_rows(model, state.body_q, state.body_qd, model.control())
    wp.synchronize()
    n = int(model.row_count.numpy()[0])
    kind = model.row_kind.numpy()[0, :n]
    rows = np.nonzero((kind == ROW_LINEAR) | (kind == ROW_ANGULAR))[0]
    J = np.zeros((len(rows), 6 * model.max_bodies))
    for r, i in enumerate(rows):
        for side in ("c", "p"):
            body = int(getattr(model.work, f"row_body_{side}").numpy()[0, i])
            if body >= 0:
                J[r, 6 * body:6 * body + 6] += getattr(model.work, f"row_J_{side}").numpy()[0, i]
    return J


@pytest.mark.parametrize("family_name", ["four_bar", "jansen_leg", "klann_leg"])
def test_loop_closures_add_no_redundant_rows(family_name):
    """Every loop of a planar linkage closes with an inline joint (two in-plane rows), so the joint
    rows are independent: the Jacobian has full row rank, where revolute closures would repeat
    three rows per loop (checked on the same linkage with its closures made revolute)."""
    import dataclasses

    from engine import MechanismSpec

    family = load_family(family_name)
    spec = to_spec(family.generate(family.space.default()))
    loops = sum(1 for j in spec.joints if j.type.name == "INLINE")
    assert loops == len(spec.joints) - len(spec.bodies) >= 1  # one closure per independent loop
    J = _bilateral_jacobian(spec)
    assert np.linalg.matrix_rank(J, tol=1e-6 * np.abs(J).max()) == J.shape[0]
    revolute = MechanismSpec(spec.bodies, [dataclasses.replace(j, type="revolute") for j in spec.joints],
                             points=spec.points, shapes=spec.shapes)
    J = _bilateral_jacobian(revolute)
    assert J.shape[0] - np.linalg.matrix_rank(J, tol=1e-6 * np.abs(J).max()) == 3 * loops
