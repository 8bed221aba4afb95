"""A walker: a box torso carrying legs of one family (Jansen or Klann) on both sides, every crank
turning at one speed with phase offsets, standing on the ground plane. ``leg_family`` and
``legs_per_side`` change the topology, so one batch holds structurally different worlds.

Feet are capsule shoes along the walking direction. Each leg's crank has its own velocity-driven
motor on the torso, all with the same target speed
and phases spread evenly along a side (the right side ``side_phase`` behind the left): stiff motors keep the
phase offsets of a common crankshaft while the effort limit is not reached.
"""

import copy
import dataclasses
import importlib.util
import math
import pathlib

import numpy as np

from engine import Body, GroundPlane, MechanismSpec, Shape, ShapeType, TrackedPoint
from engine.spatial import cross
from morphopt.design_space import Choice, DesignSpace, Float, Int
from morphopt.linkage import BarStyle
from morphopt.linkage.to_spec import assemble, link_body, linkages_parts



def _load_leg(name):
    spec = importlib.util.spec_from_file_location(f"walker_{name}", pathlib.Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


LEG_FAMILIES = {name: _load_leg(name) for name in ("jansen_leg", "klann_leg")}

space = DesignSpace({
    "leg_family": Choice(tuple(LEG_FAMILIES), default="jansen_leg", help="family of every leg (its default leg, scaled)"),
    "legs_per_side": Int(1, 4, default=3, help="legs on each side of the torso, cranks spread evenly in phase"),
    "scale": Float(2.0, 5.0, default=3.0, unit="",
                   help="leg size relative to the families' 15 mm-crank legs (3: a 45 mm crank)"),
    "crank_speed": Float(2.0, 10.0, default=5.0, unit="rad/s", help="target speed of every crank motor"),
    "stance": Float(0.5, 1.5, default=1.0, unit="",
                    help="leg spacing along the torso, in units of 2 x 38 mm x scale (Jansen's axle-to-pivot a)"),
    "torso_mass": Float(0.5, 4.0, default=1.5, unit="kg", help="mass of the box torso"),
    "side_phase": Float(0.0, 3.141592653589793, default=0.0, unit="rad",
                        help="crank phase of the right legs behind the left ones"),
})


CRANK_DAMPING = 5.0  # [N m s/rad]: the crank motors' velocity gain
SHOE_ALONG_X = np.array([0.0, math.sin(math.pi / 4), 0.0, math.cos(math.pi / 4)])  # capsule z -> world x


def _quat_muls(a, b):
    """Quaternion products (x, y, z, w) of every row of a (N, 4) with b (4,), row by row as for one
    (vector parts: aw bv + bw av + av x bv; w: aw bw - av . bv, the dot product as matmul takes it,
    the same as the 1-D ``@``)."""
    av, aw, bv, bw = a[:, :3], a[:, 3:], np.broadcast_to(b[:3], (len(a), 3)), b[3]
    dot = (av[:, None, :] @ bv[:, :, None])[:, 0]
    return np.concatenate([aw * bv + bw * av + cross(av, bv), aw * bw - dot], axis=1)


def _quat_conj(q):
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _style(scale: float) -> BarStyle:
    """The legs' bars at a walker's scale."""
    return BarStyle(width=0.004 * scale, thickness=0.002 * scale, density=1200.0)


def _sizes(params: dict, crank_speed: float | None) -> dict:
    """The walker's sizes before any kinematics: the validated parameters, scale, crank
    speed, body sizes, the torso's inertia about its centre and every leg's place (name, x and y
    of its plane's origin relative to the torso centre, crank phase)."""
    p = space.validate(params)
    scale, count = p["scale"], int(p["legs_per_side"])
    reach = 38.0e-3 * scale  # crank axle to frame pivot of Jansen's drawing, sets the body size
    spacing = p["stance"] * 2.0 * reach
    width = 0.6 * reach
    half = (0.5 * max(count, 1) * spacing + reach, width, 0.1 * reach)
    places = [(f"{'left' if side == 0 else 'right'}{k}", (k - 0.5 * (count - 1)) * spacing, y,
               2.0 * math.pi * k / count + p["side_phase"] * side)
              for side, y in ((0, width + 0.01 * scale), (1, -(width + 0.01 * scale))) for k in range(count)]
    hx, hy, hz = half
    inertia = p["torso_mass"] / 3.0 * np.diag([hy * hy + hz * hz, hx * hx + hz * hz, hx * hx + hy * hy])
    return dict(p=p, scale=scale, speed=p["crank_speed"] if crank_speed is None else crank_speed, reach=reach,
                half=half, foot_radius=0.004 * scale, places=places, torso_inertia=inertia)


def _placements(lay: dict) -> list:
    """Every leg of a walker's _sizes as (name prefix, x, y, its linkage at its crank phase). The
    legs differ in their crank phase only (a leg family's generate puts the phase into the crank
    alone): the first is generated, the others are copies with their phase (_at_phase)."""
    scale, speed = lay["scale"], lay["speed"]
    leg_family = LEG_FAMILIES[lay["p"]["leg_family"]]
    leg = {k: v * scale for k, v in leg_family.space.default().items()}
    out, first = [], None
    for name, x, y, phase in lay["places"]:
        if first is None:
            first = leg_family.generate(leg, crank_speed=speed, phase=phase)
            out.append((f"{name}_", x, y, first))
        else:
            out.append((f"{name}_", x, y, _at_phase(first, phase)))
    return out


def _at_phase(linkage, phase: float):
    """A copy of a leg with its crank at ``phase`` (the plain float Linkage would keep): what
    generate makes for that phase, without checking the same graph again. The copies share the
    leg's graph containers, which nothing changes after a Linkage is made."""
    leg = copy.copy(linkage)
    leg.crank = dataclasses.replace(linkage.crank, phase=float(phase))
    return leg


def _placed(lay: dict, placements: list, solutions: list) -> dict:
    """_sizes plus the legs and their assembly (assemble's solutions), the bars' style and the start
    height; ValueError naming the first leg that cannot be assembled."""
    for (prefix, _, _, _), solution in zip(placements, solutions):
        if not solution.feasible:
            raise ValueError(f"leg '{prefix.rstrip('_')}' cannot be assembled: {solution.reason}")
    lowest = min(solution.nodes["F"][0, 1] for solution in solutions)
    return dict(lay, style=_style(lay["scale"]), placements=placements, solutions=solutions,
                height=-lowest + lay["foot_radius"] + 0.001)


def _layout(params: dict, crank_speed: float | None) -> dict:
    """_sizes plus the legs' linkages, assembled in one batched solve, and the start height."""
    lay = _sizes(params, crank_speed)
    placements = _placements(lay)
    return _placed(lay, placements, assemble([linkage for _, _, _, linkage in placements]))


def build_spec(params: dict, *, crank_speed: float | None = None, effort_limit: float = 20.0) -> MechanismSpec:
    """The walker's MechanismSpec (crank_speed overrides the parameter when given) [rad/s]."""
    made = _specs([_layout(params, crank_speed)], effort_limit)[0]
    if isinstance(made, ValueError):
        raise made
    return made


def build_specs(designs: list, *, crank_speed: float | None = None, effort_limit: float = 20.0) -> list:
    """build_spec of every design, with the work shared across designs (morphopt.build calls it for
    a generation): every leg of every walker assembled in one batched solve, the torsos and shapes
    made from arrays. Per design its MechanismSpec, the same to the last bit as build_spec's, or
    the ValueError build_spec raises for it (returned, not raised)."""
    out, lays, legs = [None] * len(designs), {}, []
    for i, params in enumerate(designs):
        try:
            lay = _sizes(params, crank_speed)
            placements = _placements(lay)
        except ValueError as exc:
            out[i] = exc
            continue
        lays[i] = (lay, placements, len(legs))
        legs += [linkage for _, _, _, linkage in placements]
    solutions = assemble(legs) if legs else []
    placed = {}
    for i, (lay, placements, first) in lays.items():
        try:
            placed[i] = _placed(lay, placements, solutions[first:first + len(placements)])
        except ValueError as exc:
            out[i] = exc
    for i, spec in zip(placed, _specs(list(placed.values()), effort_limit)):
        out[i] = spec
    return out


_TORSO_ORIENTATION = (0.0, -0.0, 0.0, 1.0)  # link_body's frame of a bar along +x: planar_rotation(0.0)


def _torsos(lays: list) -> list:
    """The torso bodies of placed walkers: link_body's bar along x at the start height, then the
    box's mass, inertia about its centre and centre (what build_spec sets); made from arrays."""
    half = np.array([lay["half"][0] for lay in lays])
    zero = np.zeros(len(lays))
    position = np.stack([-half, zero, np.array([lay["height"] for lay in lays])], axis=1)
    bodies = Body.batch(["torso"] * len(lays), np.array([float(lay["p"]["torso_mass"]) for lay in lays]),
                        np.array([lay["torso_inertia"] for lay in lays]).reshape(-1, 3, 3),
                        np.stack([half, zero, zero], axis=1), position,
                        np.array([_TORSO_ORIENTATION] * len(lays)))
    if bodies is None:  # a check fails: the constructor names it
        return [Body("torso", lay["p"]["torso_mass"], lay["torso_inertia"], com=(lay["half"][0], 0.0, 0.0),
                     position=(-lay["half"][0], 0.0, lay["height"]), orientation=_TORSO_ORIENTATION) for lay in lays]
    return bodies


def _legs(lays: list, torsos: list, effort_limit: float, together: bool):
    """Per placed walker an iterator of its legs' (bodies, joints, points) on its torso. together:
    every leg of every walker in one linkages_parts call (one style and base per leg), or None when
    any leg raises (then call again walker by walker, which raises it for its own walker only)."""
    args = []  # per walker: linkages_parts's per-leg arguments
    for lay, torso in zip(lays, torsos):
        placements = lay["placements"]
        args.append(dict(linkages=[linkage for _, _, _, linkage in placements], solutions=list(lay["solutions"]),
                         origins=[(x, y, lay["height"]) for _, x, y, _ in placements],
                         prefixes=[prefix for prefix, _, _, _ in placements],
                         styles=[lay["style"]] * len(placements), bases=[torso] * len(placements)))
    common = dict(crank_damping=CRANK_DAMPING, effort_limit=effort_limit, start_at_speed=False)
    if not together:
        return [linkages_parts(**mine, **common) for mine in args]
    every = {k: [v for mine in args for v in mine[k]] for k in args[0]} if args else {}
    try:
        made = list(linkages_parts(**every, **common)) if args else []
    except ValueError:
        return None
    out, start = [], 0
    for mine in args:
        out.append(iter(made[start:start + len(mine["linkages"])]))
        start += len(mine["linkages"])
    return out


def _specs(lays: list, effort_limit: float) -> list:
    """The MechanismSpecs of placed walkers (_placed): per walker the spec or the ValueError its
    parts raise. Legs are made for every walker at once (_legs; walker by walker when a leg
    raises), torsos and shapes for every walker at once."""
    parts, feet = [], []
    torsos = _torsos(lays)
    legs_of = _legs(lays, torsos, effort_limit, together=True) or _legs(lays, torsos, effort_limit, together=False)
    for lay, torso, legs in zip(lays, torsos, legs_of):
        placements = lay["placements"]
        points = [TrackedPoint("torso", "torso", (lay["half"][0], 0.0, 0.0)),
                  TrackedPoint("torso_up", "torso", (lay["half"][0], 0.0, lay["half"][0]))]
        bodies, joints, mine = [torso], [], []
        try:
            for (prefix, _, _, _), (leg_bodies, leg_joints, leg_points) in zip(placements, legs):
                bodies += leg_bodies
                joints += leg_joints
                points += leg_points
                foot = next(pt for pt in leg_points if pt.name == prefix + "foot")
                mine.append((prefix + "foot", foot, next(b for b in leg_bodies if b.name == foot.body)))
        except ValueError as exc:
            parts.append(exc)
            continue
        parts.append((bodies, joints, points))
        feet.append((lay, mine))
    shapes = iter(_shapes(feet))
    out = []
    for made in parts:
        if isinstance(made, ValueError):
            out.append(made)
            continue
        try:
            out.append(MechanismSpec(*made, shapes=next(shapes), ground=GroundPlane(friction=1.0), name="walker"))
        except ValueError as exc:
            out.append(exc)
    return out


def _shapes(feet: list) -> list:
    """Per walker its shapes: the torso's box, then per leg a shoe, a capsule along the walking
    direction (world x at the start) so that two rows of feet stand without tipping sideways.
    feet: per walker (its placed layout, per leg (shape name, foot point, foot body))."""
    names, types, bodies, size, position, orientation, friction, counts = [], [], [], [], [], [], [], []
    for lay, mine in feet:
        half, reach, radius = lay["half"], lay["reach"], lay["foot_radius"]
        names.append("torso")
        types.append(ShapeType.BOX)
        bodies.append("torso")
        size.append(half)
        position.append((half[0], 0.0, 0.0))
        orientation.append((0.0, 0.0, 0.0, 1.0))
        friction.append(0.8)
        for name, foot, body in mine:
            names.append(name)
            types.append(ShapeType.CAPSULE)
            bodies.append(foot.body)
            size.append((radius, 0.25 * reach, 0.0))
            position.append(foot.position)
            orientation.append(body.orientation)  # the foot body's, turned into its shoe's below
            friction.append(1.0)
        counts.append(1 + len(mine))
    orientation = np.array(orientation, dtype=float).reshape(-1, 4)
    shoe = np.array([t == ShapeType.CAPSULE for t in types], bool)
    orientation[shoe] = _quat_muls(_quat_conj(orientation[shoe].T).T, SHOE_ALONG_X)
    made = Shape.batch(names, types, bodies, np.array(size, dtype=float).reshape(-1, 3),
                       np.array(position, dtype=float).reshape(-1, 3), orientation, friction=np.array(friction),
                       collision_group=1) if names else []
    if made is None:  # a check fails: the constructor names it
        made = [Shape(n, t, b, s[:2] if t == ShapeType.CAPSULE else s, position=p, orientation=q, friction=f,
                      collision_group=1)
                for n, t, b, s, p, q, f in zip(names, types, bodies, size, position, orientation, friction)]
    out, start = [], 0
    for count in counts:
        out.append(made[start:start + count])
        start += count
    return out
