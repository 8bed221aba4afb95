"""The fast build path makes the same specs as the plain one, to the last bit.

``_reference_*`` below is a frozen copy of the build code as it was before the host-side speed-ups
(morphopt.linkage.to_spec's link_body / linkage_parts / to_spec and the walker family's
build_spec, one Body and Joint at a time through the validating constructors): every field of
every body, joint, drive, tracked point, shape and ground of the specs built today must equal its
output bit for bit (signed zeros included), and a design that cannot be built must fail with the
same message. Change the reference only together with a deliberate change of the specs.
"""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np
import pytest

from engine import Body, GroundPlane, Joint, JointDrive, MechanismSpec, Shape, TrackedPoint
from morphopt.build import build_specs
from morphopt.families import load_family
from morphopt.linkage.to_spec import ASSEMBLY_STEP, BarStyle, assemble, linkage_parts, to_spec

# -- the frozen reference ----------------------------------------------------------------------------

_AXIS = (0.0, -1.0, 0.0)
_EYE = np.eye(3)
_ACROSS_THICKNESS = np.diag([1.0, 0.0, 1.0])


def _world(xy):
    return np.array([xy[0], 0.0, xy[1]])


def _planar_rotation(angle):
    return (0.0, -math.sin(0.5 * angle), 0.0, math.cos(0.5 * angle))


def _matrix(q):
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _bar_inertia(start, end, style):
    axis = end - start
    length = math.sqrt(float(axis @ axis))
    mass = style.density * style.width * style.thickness * length
    u = axis / length
    v = np.array([u[2], 0.0, -u[0]])
    inertia = (mass / 12.0) * ((length**2) * (_EYE - np.outer(u, u))
                               + style.width**2 * (_EYE - np.outer(v, v))
                               + style.thickness**2 * _ACROSS_THICKNESS)
    return mass, 0.5 * (start + end), inertia


def _reference_link_body(name, points, style):
    bars = [_bar_inertia(points[i], points[j], style) for i in range(len(points)) for j in range(i + 1, len(points))]
    mass = sum(m for m, _, _ in bars)
    com = sum(m * c for m, c, _ in bars) / mass
    inertia = sum(I + m * ((c - com) @ (c - com) * np.eye(3) - np.outer(c - com, c - com)) for m, c, I in bars)
    direction = points[1] - points[0]
    angle = math.atan2(direction[2], direction[0])
    rotation = _planar_rotation(angle)
    R = _matrix(rotation)
    return Body(name, mass, R.T @ inertia @ R, com=R.T @ (com - points[0]), position=points[0], orientation=rotation)


def _local(body, point):
    return _matrix(body.orientation).T @ (point - body.position)


def _close_loops_in_plane(joints):
    root = {}

    def find(name):
        while root.setdefault(name, name) != name:
            root[name] = root[root[name]]
            name = root[name]
        return name

    out = list(joints)
    for k in sorted(range(len(joints)), key=lambda k: joints[k].drive is None):
        joint = joints[k]
        a, b = find(joint.parent if joint.parent is not None else "\0world"), find(joint.child)
        if a != b:
            root[a] = b
        else:
            out[k] = dataclasses.replace(joint, type="inline")
    return out


def _reference_linkage_parts(linkage, *, style=BarStyle(), crank_damping=50.0, effort_limit=50.0,
                             start_at_speed=True, origin=(0.0, 0.0, 0.0), prefix="", base=None, solution=None):
    crank = linkage.crank
    h = ASSEMBLY_STEP
    if solution is None:
        solution = assemble([linkage])[0]
    if not solution.feasible:
        raise ValueError(f"linkage '{linkage.name}' cannot be assembled: {solution.reason}")
    origin = np.asarray(origin, dtype=float)

    def place(xy):
        return _world(xy) + origin

    node_xy = {name: path[0] for name, path in solution.nodes.items()}
    node_rate = {name: (path[1] - path[0]) / h * (crank.speed if start_at_speed else 0.0)
                 for name, path in solution.nodes.items()}
    bodies, joints, link_of = [], [], {}
    for link in linkage.links:
        points = [place(node_xy[n]) for n in link.nodes]
        body = _reference_link_body(prefix + link.name, points, style)
        v0, v1 = _world(node_rate[link.nodes[0]]), _world(node_rate[link.nodes[1]])
        r = points[1] - points[0]
        dv = v1 - v0
        omega_y = (r[2] * dv[0] - r[0] * dv[2]) / max(float(r @ r), 1e-300)
        arm = _matrix(body.orientation) @ body.com
        body.velocity = v0 + np.array([omega_y * arm[2], 0.0, -omega_y * arm[0]])
        body.angular_velocity = np.array([0.0, omega_y, 0.0])
        bodies.append(body)
        for node in link.nodes:
            link_of.setdefault(node, []).append((link, body))
    for node, members in link_of.items():
        anchor = place(node_xy[node])
        if node in linkage.ground:
            for link, body in members:
                drive = None
                if node == crank.center and crank.tip in link.nodes:
                    drive = JointDrive(damping=crank_damping, target_velocity=crank.speed, effort_limit=effort_limit)
                parent_position = anchor if base is None else _local(base, anchor)
                joints.append(Joint(f"{prefix}{node}_{link.name}", "revolute", None if base is None else base.name,
                                    body.name, parent_position=parent_position, child_position=_local(body, anchor),
                                    axis=_AXIS, drive=drive))
            continue
        (parent_link, parent_body), *children = members
        for link, body in children:
            joints.append(Joint(f"{prefix}{node}_{parent_link.name}_{link.name}", "revolute", parent_body.name,
                                body.name, parent_position=_local(parent_body, anchor),
                                child_position=_local(body, anchor), axis=_AXIS))
    points = []
    for point, node in linkage.points.items():
        _, body = link_of[node][0]
        points.append(TrackedPoint(prefix + point, body.name, _local(body, place(node_xy[node]))))
    return bodies, _close_loops_in_plane(joints), points


def _reference_to_spec(linkage, *, style=BarStyle(), crank_damping=50.0, effort_limit=50.0,
                       gravity=(0.0, 0.0, -9.81), start_at_speed=True):
    bodies, joints, points = _reference_linkage_parts(linkage, style=style, crank_damping=crank_damping,
                                                      effort_limit=effort_limit, start_at_speed=start_at_speed)
    return MechanismSpec(bodies, joints, points, gravity=gravity, name=linkage.name)


def _quat_mul(a, b):
    av, aw, bv, bw = np.asarray(a[:3]), a[3], np.asarray(b[:3]), b[3]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), [aw * bw - av @ bv]])


def _quat_conj(q):
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _reference_walker_spec(walker, params, *, crank_speed=None, effort_limit=20.0):
    """The walker family's build_spec as it was (its _sizes and _layout inlined)."""
    p = walker.space.validate(params)
    scale, count = p["scale"], int(p["legs_per_side"])
    reach = 38.0e-3 * scale
    spacing = p["stance"] * 2.0 * reach
    width = 0.6 * reach
    half = (0.5 * max(count, 1) * spacing + reach, width, 0.1 * reach)
    places = [(f"{'left' if side == 0 else 'right'}{k}", (k - 0.5 * (count - 1)) * spacing, y,
               2.0 * math.pi * k / count + p["side_phase"] * side)
              for side, y in ((0, width + 0.01 * scale), (1, -(width + 0.01 * scale))) for k in range(count)]
    hx, hy, hz = half
    torso_inertia = p["torso_mass"] / 3.0 * np.diag([hy * hy + hz * hz, hx * hx + hz * hz, hx * hx + hy * hy])
    speed = p["crank_speed"] if crank_speed is None else crank_speed
    foot_radius = 0.004 * scale
    leg_family = walker.LEG_FAMILIES[p["leg_family"]]
    leg = {k: v * scale for k, v in leg_family.space.default().items()}
    placements = [(f"{name}_", x, y, leg_family.generate(leg, crank_speed=speed, phase=phase))
                  for name, x, y, phase in places]
    solutions = assemble([linkage for _, _, _, linkage in placements])
    for (prefix, _, _, _), solution in zip(placements, solutions):
        if not solution.feasible:
            raise ValueError(f"leg '{prefix.rstrip('_')}' cannot be assembled: {solution.reason}")
    lowest = min(solution.nodes["F"][0, 1] for solution in solutions)
    height = -lowest + foot_radius + 0.001
    style = BarStyle(width=0.004 * scale, thickness=0.002 * scale, density=1200.0)

    torso = _reference_link_body("torso", [np.array([-half[0], 0.0, height]), np.array([half[0], 0.0, height])],
                                 BarStyle(width=2 * half[1], thickness=2 * half[2], density=1.0))
    torso.mass = p["torso_mass"]
    torso.inertia = torso_inertia
    torso.com = np.array([half[0], 0.0, 0.0])
    bodies, joints = [torso], []
    shapes = [Shape("torso", "box", "torso", half, position=(half[0], 0.0, 0.0), collision_group=1)]
    points = [TrackedPoint("torso", "torso", (half[0], 0.0, 0.0)),
              TrackedPoint("torso_up", "torso", (half[0], 0.0, half[0]))]
    along_x = np.array([0.0, math.sin(math.pi / 4), 0.0, math.cos(math.pi / 4)])
    for (prefix, x, y, linkage), solution in zip(placements, solutions):
        leg_bodies, leg_joints, leg_points = _reference_linkage_parts(
            linkage, style=style, crank_damping=walker.CRANK_DAMPING, effort_limit=effort_limit,
            start_at_speed=False, origin=(x, y, height), prefix=prefix, base=torso, solution=solution)
        bodies += leg_bodies
        joints += leg_joints
        points += leg_points
        foot = next(pt for pt in leg_points if pt.name == prefix + "foot")
        body = next(b for b in leg_bodies if b.name == foot.body)
        shoe = _quat_mul(_quat_conj(body.orientation), along_x)
        shapes.append(Shape(prefix + "foot", "capsule", foot.body, (foot_radius, 0.25 * reach), position=foot.position,
                            orientation=shoe, friction=1.0, collision_group=1))
    return MechanismSpec(bodies, joints, points, shapes=shapes, ground=GroundPlane(friction=1.0), name="walker")


# -- comparison ----------------------------------------------------------------------------------------


def _fields(obj, path="spec") -> list:
    """Every leaf of a spec as (path, kind, exact value): arrays by dtype, shape and bytes."""
    if isinstance(obj, np.ndarray):
        return [(path, "array", obj.dtype.str, obj.shape, np.ascontiguousarray(obj).tobytes())]
    if isinstance(obj, float):
        return [(path, "float", np.float64(obj).tobytes())]
    if isinstance(obj, enum.Enum):
        return [(path, type(obj).__name__, obj.name)]
    if obj is None or isinstance(obj, (bool, int, str)):
        return [(path, type(obj).__name__, obj)]
    if dataclasses.is_dataclass(obj):
        out = [(path, "class", type(obj).__name__)]
        for f in dataclasses.fields(obj):
            out += _fields(getattr(obj, f.name), f"{path}.{f.name}")
        return out
    if isinstance(obj, (list, tuple)):
        out = [(path, type(obj).__name__, len(obj))]
        for i, item in enumerate(obj):
            out += _fields(item, f"{path}[{i}]")
        return out
    raise AssertionError(f"{path}: unexpected {type(obj).__name__}")


def _assert_identical(new, old):
    a, b = _fields(new), _fields(old)
    assert len(a) == len(b), (len(a), len(b))
    for x, y in zip(a, b):
        assert x == y, f"{x[0]} differs: {x[2:]} != {y[2:]}"


def _outcome(build):
    try:
        return build()
    except ValueError as exc:
        return f"cannot be built: {exc}"


def _walker_designs(walker) -> list:
    base = walker.space.default()
    designs = [base, {**base, "legs_per_side": 1}, {**base, "leg_family": "klann_leg", "legs_per_side": 2},
               {**base, "legs_per_side": 4, "side_phase": 1.3, "scale": 4.7, "stance": 0.6}]
    designs += walker.space.sample(np.random.default_rng(11), 4)
    return designs


def test_walker_specs_equal_the_reference_bit_for_bit():
    """Walkers of both leg families, one to four legs per side and random designs (and a crank
    speed override) build exactly the reference's specs, one by one and through build_specs."""
    walker = load_family("walker")
    designs = _walker_designs(walker)
    built = build_specs(walker, designs, workers=1)
    for params, spec in zip(designs, built):
        reference = _outcome(lambda: _reference_walker_spec(walker, params))
        assert not isinstance(reference, str), reference
        _assert_identical(spec, reference)
    fast = walker.build_spec(designs[2], crank_speed=7.5, effort_limit=11.0)
    _assert_identical(fast, _reference_walker_spec(walker, designs[2], crank_speed=7.5, effort_limit=11.0))


def test_walker_that_cannot_be_built_fails_with_the_reference_message():
    """A walker whose legs cannot be assembled fails with the reference's reason."""
    walker = load_family("walker")
    params = {**walker.space.default(), "scale": 1.0e9}
    assert build_specs(walker, [params], workers=1)[0] == _outcome(lambda: _reference_walker_spec(walker, params))


@pytest.mark.parametrize("name", ["jansen_leg", "klann_leg", "four_bar", "watt_sixbar"])
def test_linkage_specs_equal_the_reference_bit_for_bit(name):
    """Linkage families (started at speed and at rest; failures keep their reasons) build the
    reference's specs, and linkage_parts on a base body gives the reference's parts."""
    family = load_family(name)
    designs = [family.space.default()] + family.space.sample(np.random.default_rng(4), 5)
    built = build_specs(family, designs, workers=1)
    for params, spec in zip(designs, built):
        linkage = family.generate(family.space.validate(params), crank_speed=2.0 * math.pi)
        reference = _outcome(lambda: _reference_to_spec(linkage))
        if isinstance(reference, str):
            assert spec == reference
            continue
        _assert_identical(spec, reference)
        style = BarStyle(width=0.02, thickness=0.004, density=900.0)
        _assert_identical(to_spec(linkage, style=style, start_at_speed=False, crank_damping=3.0),
                          _reference_to_spec(linkage, style=style, start_at_speed=False, crank_damping=3.0))
        base = Body("base", 2.0, np.diag([0.1, 0.2, 0.3]), position=(0.1, 0.2, 0.3),
                    orientation=(0.0, -math.sin(0.2), 0.0, math.cos(0.2)))
        kwargs = dict(style=style, origin=(0.3, -0.1, 1.0), prefix="leg_", base=base, effort_limit=7.0)
        _assert_identical(list(linkage_parts(linkage, **kwargs)), list(_reference_linkage_parts(linkage, **kwargs)))


def test_walker_batch_build_equals_building_each_alone():
    """The walker family's build_specs (a generation's legs assembled in one solve, torsos and shapes
    from arrays) gives every design build_spec's spec to the last bit, both leg families and one to
    four legs per side mixed, with a crank speed override; designs that cannot be built keep their
    reasons in the batch (build_specs here, as evaluate_dynamic builds)."""
    walker = load_family("walker")
    designs = _walker_designs(walker) + [{**p, "legs_per_side": 3} for p in
                                          walker.space.sample(np.random.default_rng(12), 20)]
    designs.insert(5, {**walker.space.default(), "scale": 1.0e9})  # outside the space
    designs.insert(9, {**walker.space.default(), "stance": "wide"})  # not a number
    for crank_speed in (None, 6.5):
        made = walker.build_specs([walker.space.validate(p) for p in designs if p["scale"] < 10.0 and
                                   not isinstance(p["stance"], str)], crank_speed=crank_speed, effort_limit=12.0)
        alone = [walker.build_spec(walker.space.validate(p), crank_speed=crank_speed, effort_limit=12.0)
                 for p in designs if p["scale"] < 10.0 and not isinstance(p["stance"], str)]
        assert len(made) == len(alone)
        for spec, reference in zip(made, alone):
            _assert_identical(spec, reference)
        built = build_specs(walker, designs, crank_speed=crank_speed, workers=1)
        for params, spec in zip(designs, built):
            expected = _outcome(lambda: walker.build_spec(walker.space.validate(params), crank_speed=crank_speed))
            if isinstance(expected, str):
                assert spec == expected
            else:
                _assert_identical(spec, expected)
    assert "'scale'" in built[5] and "'stance'" in built[9]
    feasible = walker.build_specs([{**walker.space.default(), "scale": 2.0}, {**walker.space.default(), "scale": 0.001}])
    assert isinstance(feasible[0], MechanismSpec) and isinstance(feasible[1], ValueError)


def test_linkages_parts_with_a_style_and_base_per_linkage_equals_each_alone():
    """linkages_parts over linkages of two topologies, each with its own style, base (or none),
    origin and prefix, gives every linkage linkage_parts's parts alone to the last bit (the walker
    converts a generation's legs in this one call)."""
    from morphopt.linkage.to_spec import linkages_parts

    linkages, styles, bases, origins, prefixes = [], [], [], [], []
    for k, (name, seed) in enumerate([("jansen_leg", 5), ("klann_leg", 6), ("jansen_leg", 7)]):
        family = load_family(name)
        for j, params in enumerate([family.space.default()] + family.space.sample(np.random.default_rng(seed), 3)):
            linkages.append(family.generate(family.space.validate(params), crank_speed=1.5 + j))
            styles.append(BarStyle(width=0.01 + 0.003 * j, thickness=0.002 + 0.001 * k, density=800.0 + 100 * j))
            angle = 0.1 * (j + 3 * k)
            bases.append(None if j == 2 else Body(f"base{k}", 1.0 + j, np.diag([0.1, 0.2, 0.3]),
                                                  position=(0.1 * j, -0.2, 0.3 * k),
                                                  orientation=(0.0, -math.sin(angle), 0.0, math.cos(angle))))
            origins.append((0.2 * j, 0.1 * k, 1.0))
            prefixes.append(f"leg{k}{j}_")
    solutions = assemble(linkages)
    keep = [i for i, s in enumerate(solutions) if s.feasible]
    assert len(keep) > 6
    pick = lambda items: [items[i] for i in keep]  # noqa: E731
    together = list(linkages_parts(pick(linkages), styles=pick(styles), bases=pick(bases), origins=pick(origins),
                                   prefixes=pick(prefixes), effort_limit=9.0, start_at_speed=True))
    for n, i in enumerate(keep):
        alone = linkage_parts(linkages[i], style=styles[i], base=bases[i], origin=origins[i], prefix=prefixes[i],
                              effort_limit=9.0, start_at_speed=True)
        _assert_identical(list(together[n]), list(alone))


def test_walker_legs_fall_back_walker_by_walker_when_the_generation_call_raises(monkeypatch):
    """When the one call over a generation's legs raises, the walker makes its legs walker by walker:
    the same specs as each alone."""
    walker = load_family("walker")
    designs = [walker.space.validate(p) for p in _walker_designs(walker)]
    alone = [walker.build_spec(p) for p in designs]
    real, refused = walker.linkages_parts, []

    def refuse_generations(linkages, **kwargs):
        if len(set(kwargs["prefixes"])) < len(kwargs["prefixes"]):  # legs of several walkers
            refused.append(len(linkages))
            raise ValueError("refused")
        return real(linkages, **kwargs)

    monkeypatch.setattr(walker, "linkages_parts", refuse_generations)
    for spec, reference in zip(walker.build_specs(designs), alone):
        _assert_identical(spec, reference)
    assert refused
