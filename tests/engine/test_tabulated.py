"""engine.reduced.tabulated (a floating base carrying tabulated one-DoF sub-chains, found in a plain
MechanismSpec) against independent oracles: morphopt's planar kinematics for the tables, the
maximal engine, conservation laws, static equilibrium, and the mobility analysis's refusals."""

import dataclasses
import math

import numpy as np
import pytest

from engine import (Body, GroundPlane, Integrator, Joint, JointDrive, MechanismSpec, Shape, SolverConfig, pack_worlds,
                    rollout)
from engine.reduced import tabulated_tables as tables_module
from engine.reduced.tabulated import pack_tabulated, rollout_tabulated
from engine.reduced.tabulated_kernel import MAX_GROUPS, TILED_REGISTERS, tiled_max_worlds
from engine.reduced.tabulated_layout import tabulated_layout
from engine.reduced.tabulated_step import step_kernel
from engine.reduced.tabulated_tables import wrap
from morphopt.families import load_family
from morphopt.linkage import Crank, Dyad, Link, Linkage
from morphopt.linkage.kinematics import solve_at
from morphopt.linkage.leg_table import leg_table
from morphopt.linkage.to_spec import BarStyle, linkage_parts

WALKER = load_family("walker")
LEGS = ("jansen_leg", "klann_leg")
EULER = SolverConfig(integrator=Integrator.SEMI_IMPLICIT_EULER)


def walker(family="jansen_leg", crank_speed=None, **params):
    """The walker family's MechanismSpec (build_spec), and None where the walker's reduced spec
    was (engine.legged, removed once this path replaced it; its checks are in git history)."""
    p = {**WALKER.space.default(), "leg_family": family, **params}
    return WALKER.build_spec(p, crank_speed=crank_speed), None


def four_bar(crank=0.05, coupler=0.2, rocker=0.1, ground=0.2, *, drive=True):
    """A box base (1 kg) at 1 m carrying one four-bar (ground pivots O, A on the base), crank at 0."""
    base = Body("base", 1.0, np.diag([0.01, 0.02, 0.02]), position=(0.0, 0.0, 1.0))
    linkage = Linkage("four_bar", ground={"O": (0.0, 0.0), "A": (ground, 0.0)},
                      crank=Crank("O", "M", crank, speed=3.0),
                      dyads=[Dyad("B", "M", coupler, "A", rocker)],
                      links=[Link("crank", ("O", "M")), Link("coupler", ("M", "B")), Link("rocker", ("A", "B"))],
                      points={"tip": "B"})
    bodies, joints, points = linkage_parts(linkage, base=base, origin=(0.0, 0.0, 1.0), style=BarStyle(),
                                           crank_damping=5.0, effort_limit=10.0)
    if not drive:
        joints = [dataclasses.replace(j, drive=None) for j in joints]
    return MechanismSpec([base, *bodies], joints, points, name="four_bar")


def replace_joint(spec, name, **changes):
    return dataclasses.replace(spec, joints=[dataclasses.replace(j, **changes) if j.name == name else j
                                             for j in spec.joints])


# -- tables ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("family", LEGS)
def test_tables_match_morphopt_kinematics(family):
    """The engine's table of a walker's leg, solved from the MechanismSpec alone, against
    morphopt.linkage.leg_table (an independent planar solver with FFT derivatives) for the
    family's default leg at the walker's scale 3: link centres within 1e-9 m and angles within
    1e-9 rad at every sample, first derivatives within 1e-9 (m or rad per rad), second within
    1e-8 relative to their largest value; the contact centre (the shoe's, at the foot node) within
    1e-9 m of the foot. The closure error is leg_table's (1e-6 relative; below 3e-5 m) and the
    links read between samples place every node (joints and foot) within it of morphopt's exact
    nodes, reaching at least half of it at the midpoints."""
    spec, _ = walker(family)
    lay = tabulated_layout(spec)
    chain = lay.groups[0]
    table, s = chain.table, chain.scale
    F = load_family(family)
    reference = leg_table(F.generate(F.space.default()))
    assert table.samples == reference.samples == 512
    assert [spec.bodies[i].name for i in chain.bodies] == [f"left0_{name}" for name in reference.link_names]
    assert np.abs(table.links[..., :2] * s - reference.links[..., :2] * 3.0).max() < 1e-9
    assert np.abs(wrap(table.links[..., 2] - reference.links[..., 2])).max() < 1e-9
    assert np.abs(table.links_d1[..., :2] * s - reference.links_d1[..., :2] * 3.0).max() < 1e-9
    assert np.abs(table.links_d1[..., 2] - reference.links_d1[..., 2]).max() < 1e-9
    for c, unit in ((slice(0, 2), 3.0 / s), (slice(2, 3), 1.0)):
        ours, theirs = table.links_d2[..., c], reference.links_d2[..., c] * unit
        assert np.abs(ours - theirs).max() < 1e-8 * np.abs(theirs).max()
    assert table.contact_link == reference.foot_link
    assert np.abs(table.contact[:, :2] * s - reference.foot[:, :2] * 3.0).max() < 1e-9
    # the same closure error as morphopt's table (both place every link node halfway between samples)
    assert 0.0 < chain.closure_error < 3e-5
    assert chain.closure_error == pytest.approx(reference.closure_error * 3.0, rel=1e-6)
    # between samples (midpoints and random fractions): every node of every link (its joints and
    # the foot) placed by the link read as the kernels read it, against morphopt's exact nodes
    linkage = F.generate({k: 3.0 * v for k, v in F.space.default().items()})
    nodes0 = solve_at([linkage], np.zeros((1, 1)))[0].nodes
    offsets = []  # per link: its nodes relative to its centre of mass, in its table frame
    for k, link in enumerate(linkage.links):
        c, sn = math.cos(table.links[0, k, 2]), math.sin(table.links[0, k, 2])
        offsets.append([np.array([[c, sn], [-sn, c]]) @ (nodes0[m][0] - s * table.links[0, k, :2])
                        for m in link.nodes])
    n = table.samples
    steps = np.concatenate([np.arange(n) + 0.5, np.random.default_rng(7).uniform(0, n, 64)])
    psi = 2.0 * np.pi * steps / n
    exact = solve_at([linkage], psi[None])[0].nodes
    errors = np.zeros(len(psi))
    for i, angle in enumerate(psi):
        links, _ = table.at(angle)
        for k, link in enumerate(linkage.links):
            c, sn = math.cos(links[k, 2]), math.sin(links[k, 2])
            for m, off in zip(link.nodes, offsets[k]):
                placed = s * links[k, :2] + np.array([[c, -sn], [sn, c]]) @ off
                errors[i] = max(errors[i], np.abs(placed - exact[m][i]).max())
    assert errors.max() <= chain.closure_error * (1.0 + 1e-6), (errors.max(), chain.closure_error)
    assert errors[:n].max() >= 0.5 * chain.closure_error


def test_tables_are_shared_and_cached():
    """Sub-chains of one geometry up to scale share one table: 8 walkers (2 families x 2 scales,
    twice; 48 legs) tabulate twice (once per family) from an empty cache, and not again to pack."""
    calls = []
    original = tables_module.tabulate_sub_chain

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    saved = dict(tables_module._TABLES)
    tables_module._TABLES.clear()
    try:
        tables_module.tabulate_sub_chain = counting
        specs = [walker(f, scale=sc, legs_per_side=3)[0] for f in LEGS for sc in (2.5, 4.0)] * 2
        layouts = [tabulated_layout(spec) for spec in specs]
        assert len(calls) == 2, calls
        model = pack_tabulated(specs)
        assert len(calls) == 2 and model.links[0].shape[0] == 2  # two distinct tables in the batch
        tables = {id(chain.table) for lay in layouts for chain in lay.groups}
        assert len(tables) == 2
    finally:
        tables_module.tabulate_sub_chain = original
        tables_module._TABLES.update(saved)


def test_a_table_is_the_same_whichever_design_made_it():
    """A table depends on its cache key alone (tabulated_tables.canonical): walkers of one family at
    other scales, crank speeds and phases, tabulated from an empty cache in two orders, give tables
    equal to the last bit, so a study's results do not depend on batch order or process history."""
    specs = [walker("jansen_leg", scale=sc, crank_speed=w, side_phase=ph)[0]
             for sc, w, ph in ((2.5, 4.0, 0.1), (4.0, 6.5, 0.7), (3.3, 5.0, 0.4))]
    saved = dict(tables_module._TABLES)
    made = []
    try:
        for order in (specs, specs[::-1]):
            tables_module._TABLES.clear()
            table = tabulated_layout(order[0]).groups[0].table
            assert all(chain.table is table for spec in order for chain in tabulated_layout(spec).groups)
            made.append(table)
    finally:
        tables_module._TABLES.clear()
        tables_module._TABLES.update(saved)
    for name in ("links", "links_d1", "links_d2", "contact", "contact_d1"):
        np.testing.assert_array_equal(getattr(made[0], name), getattr(made[1], name), err_msg=name)


# -- mobility analysis -----------------------------------------------------------------------------


@pytest.mark.parametrize("family", LEGS)
@pytest.mark.parametrize("legs", [1, 2, 3, 4])
def test_layout_accepts_walkers(family, legs):
    """Every walker.build_spec walker (1..4 legs a side, both families) is a base (the torso, body
    0) carrying 2 x legs sub-chains, each turned by its crank joint; its point names are the
    spec's own, its contact slots the torso box's 8 corners and one shoe (capsule) per leg."""
    spec, _ = walker(family, legs_per_side=legs)
    lay = tabulated_layout(spec)
    assert lay.base == 0 and len(lay.groups) == 2 * legs
    assert lay.point_names == [p.name for p in spec.points]
    assert len(lay.base_slots) == 8 and all(chain.shape is not None for chain in lay.groups)
    driven = [j for j, joint in enumerate(spec.joints) if joint.drive is not None]
    assert sorted(chain.joint for chain in lay.groups) == driven
    assert len({id(chain.table) for chain in lay.groups}) == 1
    assert np.allclose(lay.frame, [0.0, 0.0, 0.0, 1.0])  # the legs turn about the torso's y axis


def test_layout_refuses_with_the_reason():
    """Clear counter-examples are refused with one line naming what prevents them."""
    spec = four_bar()
    lay = tabulated_layout(spec)
    assert len(lay.groups) == 1 and len(lay.groups[0].bodies) == 3
    closing = next(j for j in spec.joints if j.type.name == "INLINE")
    cases = [
        # two DoF: the loop's closing joint removed
        (dataclasses.replace(spec, joints=[j for j in spec.joints if j is not closing]), r"mobility 3 n - 2 j = 3 \* 3"),
        (replace_joint(spec, spec.joints[1].name, limit_lower=-1.0), f"joint '{spec.joints[1].name}' has limits"),
        (dataclasses.replace(spec, shapes=[Shape("plate", "box", "coupler", (0.01, 0.01, 0.01))],
                             ground=GroundPlane()), "shape 'plate' is a box"),
        (dataclasses.replace(spec, joints=[*spec.joints, Joint("pin", "revolute", None, "base")]),
         "joint 'pin' holds body 'base' to the world"),
        (four_bar(drive=False), "0 driven joints"),
        (replace_joint(spec, spec.joints[1].name, axis=(1.0, 0.0, 0.0)), "one plane normal per world"),
        (replace_joint(spec, spec.joints[0].name, drive=JointDrive(stiffness=10.0, damping=1.0)), "stiffness"),
        # a non-Grashof four-bar: its crank cannot make a full turn
        (four_bar(crank=0.1, coupler=0.12, rocker=0.1, ground=0.2), "cannot make a full turn"),
    ]
    for bad, reason in cases:
        with pytest.raises(ValueError, match=reason) as info:
            tabulated_layout(bad)
        assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"^world 1 \(four_bar\): .*has limits"):
        pack_tabulated([spec, cases[1][0]])


@pytest.mark.parametrize("family, dt", [("jansen_leg", 1e-3), ("klann_leg", 5e-4)])
def test_free_flight_matches_the_maximal_engine(family, dt):
    """Without ground the tabulated walker follows the maximal-coordinate walker (the same spec)
    for 0.3 s (semi-implicit Euler both): torso points within 2e-4 m, feet within 1e-3 m (the
    tolerances of engine.legged's test: both engines' first-order errors, Klann at dt 5e-4)."""
    spec, _ = walker(family)
    free = dataclasses.replace(spec, shapes=[], ground=None)
    ours = pack_tabulated([free], dt=dt, config=EULER)
    maximal = pack_worlds([free], device="cpu", dt=dt, config=EULER)
    steps = round(0.3 / dt)
    trace = rollout_tabulated(ours, steps, record_every=steps // 10)
    reference, final = rollout(maximal, maximal.state(), maximal.control(), steps, record_every=steps // 10)
    names = trace.point_names[0]
    mine = trace.points[:, 0, :len(names)]
    theirs = reference.points[:, 0, [reference.point_names[0].index(p) for p in names]]
    assert np.abs(mine[-1, 2:] - mine[0, 2:]).max() > 0.05  # the legs turned
    torso, feet = np.abs(mine[:, :2] - theirs[:, :2]).max(), np.abs(mine[:, 2:] - theirs[:, 2:]).max()
    assert torso < 2e-4 and feet < 1e-3, (torso, feet)
    # every body's centre of mass from the reduced state against the maximal bodies
    body_q, _ = ours.body_poses()
    assert np.abs(body_q[0, :, :3] - final.body_q.numpy()[0][:, :3]).max() < 1e-3


def test_walks_as_fast_as_the_maximal_engine():
    """The default walker on the ground for 2 s (dt 2e-3, rho_update_interval 8 for both): the
    torso's speed over the last 1.5 s within 30 % of the maximal engine's on the same spec."""
    config = SolverConfig().tuned(rho_update_interval=8)
    spec, _ = walker()
    ours = rollout_tabulated(pack_tabulated([spec], dt=2e-3, config=config), 1000, record_every=10)
    maximal = pack_worlds([spec], device="cpu", dt=2e-3, config=config)
    theirs, _ = rollout(maximal, maximal.state(), maximal.control(), 1000, record_every=10)
    speeds = []
    for trace in (ours, theirs):
        torso = trace.points[:, 0, trace.point_names[0].index("torso")]
        speeds.append(abs(torso[-1, 0] - torso[25, 0]) / (trace.time[-1] - trace.time[25]))
    assert not ours.diverged.any()
    assert speeds[1] > 0.1 and abs(speeds[0] - speeds[1]) < 0.3 * speeds[1], speeds


# -- the state's readers ---------------------------------------------------------------------------


def test_start_matches_the_spec_and_reports_by_spec_index():
    """At the start body_poses gives every spec body's centre of mass (within 1e-5 m: the
    interpolated tables and float32) and orientation (1e-5), record() the spec's tracked points;
    the drive torque and speed arrays are indexed by spec joint (zero off the crank joints)."""
    spec, _ = walker("klann_leg", legs_per_side=2)
    model = pack_tabulated([spec])
    body_q, body_qd = model.body_poses()
    for b, body in enumerate(spec.bodies):
        x, y, z, w = body.orientation
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        assert np.abs(body_q[0, b, :3] - (body.position + R @ body.com)).max() < 1e-5, body.name
        q = body_q[0, b, 3:]
        assert min(np.abs(q - body.orientation).max(), np.abs(q + body.orientation).max()) < 1e-5, body.name
    assert not body_qd.any()
    points, energy, torque, speed = model.record()
    for p, point in enumerate(spec.points):
        b = spec.body_index[point.body]
        x, y, z, w = body_q[0, b, 3:]
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        body = spec.bodies[b]
        expected = body_q[0, b, :3] + R @ (point.position - body.com)
        assert np.abs(points[0, p] - expected).max() < 1e-5, point.name
    assert torque.shape == speed.shape == (1, len(spec.joints)) and np.isfinite(energy).all()
    model.step(20)
    _, _, torque, speed = model.record()
    driven = np.array([j.drive is not None for j in spec.joints])
    assert np.abs(torque[0, driven]).min() > 0.0 and not torque[0, ~driven].any() and not speed[0, ~driven].any()
    _, body_qd = model.body_poses()
    assert np.abs(body_qd[0, 1:]).max() > 0.0  # the links move


def turned_base(spec, angle=0.5 * math.pi):
    """``spec`` with its base (body 0) given another body frame, turned by ``angle`` about its z:
    the same mechanism, its joints now turning about the base frame's x axis."""
    c, s = math.cos(angle), math.sin(angle)
    G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    g = np.array([0.0, 0.0, math.sin(0.5 * angle), math.cos(0.5 * angle)])

    def mul(a, b):
        av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
        return np.concatenate([aw * bv + bw * av + np.cross(av, bv), [aw * bw - av @ bv]])

    g_inv = g * np.array([-1.0, -1.0, -1.0, 1.0])
    base = spec.bodies[0]
    bodies = [dataclasses.replace(base, orientation=mul(base.orientation, g), com=G.T @ base.com,
                                  inertia=G.T @ base.inertia @ G), *spec.bodies[1:]]
    joints = []
    for j in spec.joints:
        if j.parent == base.name:
            j = dataclasses.replace(j, parent_position=G.T @ j.parent_position,
                                    parent_orientation=mul(g_inv, j.parent_orientation))
        if j.child == base.name:
            j = dataclasses.replace(j, child_position=G.T @ j.child_position,
                                    child_orientation=mul(g_inv, j.child_orientation))
        joints.append(j)
    shapes = [dataclasses.replace(sh, position=G.T @ sh.position, orientation=mul(g_inv, sh.orientation))
              if sh.body == base.name else sh for sh in spec.shapes]
    points = [dataclasses.replace(p, position=G.T @ p.position) if p.body == base.name else p for p in spec.points]
    return dataclasses.replace(spec, bodies=bodies, joints=joints, shapes=shapes, points=points)


def test_base_frame_turned_gives_the_same_motion():
    """The plane normal may be any axis of the base frame: the default walker re-expressed with its
    torso frame turned a quarter turn about z (its legs now turn about the torso's x axis) has a
    state frame turned accordingly and walks the same: tracked points within 1e-4 m over 0.2 s."""
    spec, _ = walker()
    turned = turned_base(spec)
    lay = tabulated_layout(turned)
    assert not np.allclose(lay.frame, [0.0, 0.0, 0.0, 1.0])
    traces = [rollout_tabulated(pack_tabulated([s], dt=2e-3), 100, record_every=10) for s in (spec, turned)]
    assert np.abs(traces[0].points - traces[1].points).max() < 1e-4
    assert np.abs(traces[0].energy - traces[1].energy).max() < 1e-3 * np.abs(traces[0].energy).max()


# -- conservation and equilibrium (ported from test_legged) ----------------------------------------


def centre_of_mass(model, spec):
    body_q, _ = model.body_poses()
    masses = np.array([b.mass for b in spec.bodies])
    return (masses[:, None] * body_q[0, :, :3]).sum(axis=0) / masses.sum()


def test_internal_drives_leave_the_centre_of_mass_in_place():
    """Zero gravity, no ground, at rest: the crank drives spin the legs up against the torso; the
    torso moves in reaction, the centre of mass (from body_poses) stays within 1e-4 m over 0.5 s."""
    spec, _ = walker()
    spec = dataclasses.replace(spec, ground=None, shapes=[], gravity=(0.0, 0.0, 0.0))
    model = pack_tabulated([spec], dt=1e-3)
    start, torso = centre_of_mass(model, spec), model.position.numpy()[0].copy()
    drift = []
    for _ in range(10):
        model.step(50)
        drift.append(np.abs(centre_of_mass(model, spec) - start).max())
    assert np.abs(model.coord_rate.numpy()[0, :6] - 5.0).max() < 0.05  # the cranks reached their speed
    assert np.abs(model.position.numpy()[0] - torso).max() > 2e-4  # and pushed the torso about
    assert max(drift) < 1e-4, drift


def test_free_legs_conserve_energy_and_momentum():
    """Zero gravity, no ground, drives all but off (effort limit 1e-12 N m), torso at rest and
    cranks set turning at 3..8 rad/s: the energy stays within 1 % over 0.5 s (dt 5e-4) and the
    centre of mass moves in a straight line at constant speed (within 0.5 % of its travel)."""
    spec, _ = walker()
    joints = [dataclasses.replace(j, drive=dataclasses.replace(j.drive, effort_limit=1e-12)) if j.drive else j
              for j in spec.joints]
    spec = dataclasses.replace(spec, joints=joints, ground=None, shapes=[], gravity=(0.0, 0.0, 0.0))
    model = pack_tabulated([spec], dt=5e-4)
    rates = np.zeros((1, MAX_GROUPS), np.float32)
    rates[0, :6] = [3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    model.coord_rate.assign(rates)
    energy0 = model.record()[1][0]
    energies, centres = [], [centre_of_mass(model, spec)]
    for _ in range(10):
        model.step(100)
        energies.append(model.record()[1][0])
        centres.append(centre_of_mass(model, spec))
    assert np.abs(model.drive_torque.numpy()).max() < 1e-9
    assert np.abs(np.array(energies) / energy0 - 1.0).max() < 0.01, (energy0, energies)
    centres = np.array(centres)
    line = centres[0] + np.linspace(0.0, 1.0, len(centres))[:, None] * (centres[-1] - centres[0])
    travel = np.linalg.norm(centres[-1] - centres[0])
    assert travel > 1e-3 and np.abs(centres - line).max() < 0.005 * travel, (travel, np.abs(centres - line).max())


def test_standing_walker_rests_with_its_weight_on_the_contacts():
    """Cranks held (target speed 0, damping 1e3 N m s/rad): after 1 s at dt 2e-3 the torso is at
    rest and the normal contact impulses per step carry the total weight (2 %)."""
    dt = 2e-3
    spec, _ = walker(crank_speed=0.0)
    joints = [dataclasses.replace(j, drive=dataclasses.replace(j.drive, damping=1e3)) if j.drive else j
              for j in spec.joints]
    spec = dataclasses.replace(spec, joints=joints)
    model = pack_tabulated([spec], dt=dt)
    model.step(500)
    weight = sum(b.mass for b in spec.bodies) * 9.81
    normals = model.impulse.numpy()[0][MAX_GROUPS + 3 * np.arange(8 + 2 * MAX_GROUPS)]
    speed, support = float(np.linalg.norm(model.velocity.numpy()[0])), normals.sum() / dt / weight
    assert speed < 1e-3, speed
    assert abs(support - 1.0) < 0.02, support


# -- batches, kernels, failures --------------------------------------------------------------------


def test_heterogeneous_batch_steps_each_world_as_alone():
    """Walkers of both families, 1 to 4 legs a side and two scales in one batch (different
    sub-chain counts, two tables) step exactly as each packed alone (0.4 s at dt 2e-3)."""
    specs = [walker("jansen_leg")[0], walker("klann_leg", legs_per_side=2)[0],
             walker("jansen_leg", legs_per_side=1, scale=4.0)[0], walker("klann_leg", legs_per_side=4, scale=2.5)[0]]
    batch = pack_tabulated(specs, dt=2e-3)
    assert batch.group_count.numpy().tolist() == [6, 4, 2, 8] and batch.links[0].shape[0] == 2
    batch.step(200)
    points, energy, torque, _ = batch.record()
    for w, spec in enumerate(specs):
        alone = pack_tabulated([spec], dt=2e-3)
        alone.step(200)
        p, e, t, _ = alone.record()
        count = len(spec.points)
        assert np.array_equal(points[w, :count], p[0, :count]), w
        assert np.array_equal(torque[w, :len(spec.joints)], t[0]), w
    assert batch.point_names == [[p.name for p in s.points] for s in specs]
    assert batch.failure_reasons() == [""] * 4


def test_tiled_and_per_thread_steps_agree():
    """The tiled step (a block of lanes per world; one lane on the CPU) and the one-thread step
    compute the same walk: two walkers on the ground, 0.4 s at dt 2e-3; the tiled step is held to
    TILED_REGISTERS registers per thread on CUDA (the CPU ignores it)."""
    specs = [walker()[0], walker("klann_leg", legs_per_side=2)[0]]
    models = [pack_tabulated(specs, dt=2e-3, config=SolverConfig().tuned(tabulated_tiled=tiled))
              for tiled in (True, False)]
    assert [m.tiled for m in models] == [True, False]
    assert models[0].max_registers == TILED_REGISTERS == 64
    assert tiled_max_worlds("cpu") == 0 and not pack_tabulated(specs).tiled
    assert step_kernel(True, "all", models[0].max_registers).options["cuda_max_registers"] == 64
    for m in models:
        m.step(200)
    tiled, plain = models
    assert np.abs(tiled.position.numpy() - plain.position.numpy()).max() < 1e-6
    assert np.abs(tiled.coord.numpy() - plain.coord.numpy()).max() < 1e-5
    assert np.abs(tiled.impulse.numpy() - plain.impulse.numpy()).max() < 1e-6
    assert np.linalg.norm(plain.position.numpy()[0] - tiled.layouts[0].position) > 1e-3  # it moved


def test_failure_reasons_and_halt():
    """A world whose state turns non-finite, and one whose base outruns SolverConfig.max_speed, are
    flagged with their reason and frozen; the others run on; a halted world keeps its state."""
    spec = walker()[0]
    model = pack_tabulated([spec, spec, spec, spec], dt=2e-3, config=SolverConfig(max_speed=50.0))
    velocity = model.velocity.numpy()
    velocity[0, 2] = np.nan
    velocity[1, 0] = 100.0
    model.velocity.assign(velocity)
    model.halt([False, False, True, False])
    before = model.position.numpy().copy()  # (a view of the array on the CPU)
    model.step(10)
    reasons = model.failure_reasons()
    assert reasons[0] == "diverged: the state turned non-finite"
    assert reasons[1].startswith("diverged: the base moved faster than 50 m/s")
    assert reasons[2:] == ["", ""]
    after = model.position.numpy()
    assert np.array_equal(after[2], before[2]) and not np.array_equal(after[3], before[3])
    trace = rollout_tabulated(model, 10, record_every=10)
    assert trace.diverged.tolist() == [True, True, False, False]


def test_cuda_tiled_step_matches_the_cpu():
    """On CUDA the tiled step's 32 lanes share what one lane does on the CPU: walkers of both
    families on the ground, after one step and after five, CUDA tiled and one thread per world
    give the CPU's result to float32 rounding, and the register cap changes nothing, bit for bit."""
    import warp as wp

    if not wp.is_cuda_available():
        pytest.skip("no CUDA device on this machine")
    specs = [walker()[0], walker("klann_leg", legs_per_side=2)[0], walker(legs_per_side=2, stance=0.8)[0],
             walker("klann_leg", scale=3.5)[0]]
    config = SolverConfig().tuned(rho_update_interval=8)
    for steps in (1, 5):
        runs = {}
        for name, device, tiled, registers in (("cpu", "cpu", True, TILED_REGISTERS),
                                               ("tiled", "cuda", True, TILED_REGISTERS),
                                               ("uncapped", "cuda", True, None), ("thread", "cuda", False, None)):
            model = pack_tabulated(specs, device=device, dt=2e-3, config=config.tuned(tabulated_tiled=tiled))
            model.max_registers = registers
            model.step(steps)
            assert model.tiled == tiled and not model.diverged.numpy().any()
            runs[name] = {"velocity": model.velocity.numpy(), "rates": model.coord_rate.numpy(),
                          "impulse": model.impulse.numpy(), "position": model.position.numpy(),
                          "iterations": model.iterations.numpy(), "contacts": model.contacts.numpy()}
        cpu = runs["cpu"]
        assert cpu["contacts"].min() > 0 and cpu["iterations"].min() > 0
        for name in ("tiled", "thread"):
            run = runs[name]
            assert np.abs(run["velocity"] - cpu["velocity"]).max() < 1e-4, (steps, name)
            assert np.abs(run["rates"] - cpu["rates"]).max() < 1e-2, (steps, name)
            assert np.abs(run["impulse"] - cpu["impulse"]).max() < 1e-4 * max(1.0, np.abs(cpu["impulse"]).max())
        for key in ("position", "velocity", "rates", "impulse"):
            assert np.array_equal(runs["uncapped"][key], runs["tiled"][key]), key


def test_base_shapes_rest_on_the_ground():
    """A lone base (no sub-chain: 6 coordinates) with a box (off its centre of mass, turned a
    quarter turn about z), a capsule lying along x, or a sphere, dropped from 5 cm onto the ground
    at z = 0.1: after 1 s it rests with its lowest surface on the ground (1e-3 m) and its contact
    impulses carry its weight (2 %); the box fills its 8 base slots, the capsule 2, the sphere 1."""
    turn = (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))
    shapes = {"box": (Shape("s", "box", "base", (0.1, 0.05, 0.02), position=(0.2, 0.0, 0.0), orientation=turn), 0.02, 8),
              "capsule": (Shape("s", "capsule", "base", (0.03, 0.1), orientation=(0.0, math.sin(math.pi / 4), 0.0,
                                                                                  math.cos(math.pi / 4))), 0.03, 2),
              "sphere": (Shape("s", "sphere", "base", (0.04,)), 0.04, 1)}
    for kind, (shape, height, slots) in shapes.items():
        com = np.array(shape.position)
        base = Body("base", 2.0, np.diag([0.01, 0.02, 0.02]), com=com, position=(-com[0], 0.0, 0.15 + height))
        spec = MechanismSpec([base], shapes=[shape], ground=GroundPlane(offset=0.1, friction=0.5), name=kind)
        lay = tabulated_layout(spec)
        assert not lay.groups and len(lay.base_slots) == slots, kind
        model = pack_tabulated([spec], dt=2e-3)
        model.step(500)
        z = model.position.numpy()[0, 2]
        assert abs(z - (0.1 + height)) < 1e-3, (kind, z)
        normals = model.impulse.numpy()[0][MAX_GROUPS + 3 * np.arange(8)]
        assert abs(normals.sum() / 2e-3 / (2.0 * 9.81) - 1.0) < 0.02, kind
        body_q, _ = model.body_poses()
        assert np.abs(body_q[0, 0, :2] - [0.0, 0.0]).max() < 1e-3, kind
