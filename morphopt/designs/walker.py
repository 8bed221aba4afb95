"""A walker: a box torso carrying legs of one family (Jansen or Klann) on both sides, every crank
turning at one speed with phase offsets, standing on the ground plane. ``leg_family`` and
``legs_per_side`` change the topology, so one batch holds structurally different worlds.

Feet are capsule shoes along the walking direction. Each leg's crank has its own velocity-driven
motor on the torso, all with the same target speed
and phases spread evenly along a side (the right side ``side_phase`` behind the left): stiff motors keep the
phase offsets of a common crankshaft while the effort limit is not reached.
"""

import importlib.util
import math
import pathlib

import numpy as np

from engine import GroundPlane, MechanismSpec, Shape, TrackedPoint
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


def _quat_mul(a, b):
    av, aw, bv, bw = np.asarray(a[:3]), a[3], np.asarray(b[:3]), b[3]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), [aw * bw - av @ bv]])


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


def _layout(params: dict, crank_speed: float | None) -> dict:
    """_sizes plus the legs' linkages, assembled in one batched solve, and the start height."""
    lay = _sizes(params, crank_speed)
    scale, speed = lay["scale"], lay["speed"]
    leg_family = LEG_FAMILIES[lay["p"]["leg_family"]]
    leg = {k: v * scale for k, v in leg_family.space.default().items()}
    placements = [(f"{name}_", x, y, leg_family.generate(leg, crank_speed=speed, phase=phase))
                  for name, x, y, phase in lay["places"]]
    solutions = assemble([linkage for _, _, _, linkage in placements])  # every leg in one batched solve
    for (prefix, _, _, _), solution in zip(placements, solutions):
        if not solution.feasible:
            raise ValueError(f"leg '{prefix.rstrip('_')}' cannot be assembled: {solution.reason}")
    lowest = min(solution.nodes["F"][0, 1] for solution in solutions)
    return dict(lay, style=_style(scale), placements=placements, solutions=solutions,
                height=-lowest + lay["foot_radius"] + 0.001)


def build_spec(params: dict, *, crank_speed: float | None = None, effort_limit: float = 20.0) -> MechanismSpec:
    """The walker's MechanismSpec (crank_speed overrides the parameter when given) [rad/s]."""
    lay = _layout(params, crank_speed)
    half, height, reach, foot_radius = lay["half"], lay["height"], lay["reach"], lay["foot_radius"]
    torso = link_body("torso", [np.array([-half[0], 0.0, height]), np.array([half[0], 0.0, height])],
                      BarStyle(width=2 * half[1], thickness=2 * half[2], density=1.0))
    torso.mass = lay["p"]["torso_mass"]
    torso.inertia = lay["torso_inertia"]
    torso.com = np.array([half[0], 0.0, 0.0])
    bodies, joints = [torso], []
    shapes = [Shape("torso", "box", "torso", half, position=(half[0], 0.0, 0.0), collision_group=1)]
    # torso_up: one torso half-length above the centre, for the torso's tilt (falls are failures)
    points = [TrackedPoint("torso", "torso", (half[0], 0.0, 0.0)),
              TrackedPoint("torso_up", "torso", (half[0], 0.0, half[0]))]
    placements = lay["placements"]  # every leg's numbers computed at once, its objects leg by leg
    legs = linkages_parts([linkage for _, _, _, linkage in placements], style=lay["style"], crank_damping=CRANK_DAMPING,
                          effort_limit=effort_limit, start_at_speed=False, base=torso, solutions=lay["solutions"],
                          origins=[(x, y, height) for _, x, y, _ in placements],
                          prefixes=[prefix for prefix, _, _, _ in placements])
    for (prefix, _, _, _), (leg_bodies, leg_joints, leg_points) in zip(placements, legs):
        bodies += leg_bodies
        joints += leg_joints
        points += leg_points
        foot = next(pt for pt in leg_points if pt.name == prefix + "foot")
        body = next(b for b in leg_bodies if b.name == foot.body)
        # a shoe: a capsule along the walking direction (world x at the start), so that two rows of
        # feet stand without tipping sideways
        shoe = _quat_mul(_quat_conj(body.orientation), SHOE_ALONG_X)
        shapes.append(Shape(prefix + "foot", "capsule", foot.body, (foot_radius, 0.25 * reach), position=foot.position,
                            orientation=shoe, friction=1.0, collision_group=1))
    return MechanismSpec(bodies, joints, points, shapes=shapes, ground=GroundPlane(friction=1.0), name="walker")
