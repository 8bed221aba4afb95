"""A walker: a box torso carrying Jansen legs on both sides, every crank turning at one speed
with phase offsets, standing on the ground plane. ``legs_per_side`` changes the topology, so a
batch holds structurally different worlds.

Each leg's crank has its own velocity-driven motor on the torso, all with the same target speed
and phases spread evenly (the right side half a turn behind the left): stiff motors keep the
phase offsets of a common crankshaft while the effort limit is not reached.
"""

import importlib.util
import math
import pathlib

import numpy as np

from engine import GroundPlane, MechanismSpec, Shape, TrackedPoint
from morphopt.design_space import DesignSpace, Float, Int
from morphopt.linkage import BarStyle, linkage_parts, solve_at
from morphopt.linkage.to_spec import link_body

_spec = importlib.util.spec_from_file_location("walker_leg", pathlib.Path(__file__).with_name("jansen_leg.py"))
leg_family = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(leg_family)

space = DesignSpace({
    "legs_per_side": Int(1, 2, default=1),  # 2 per side needs more rows than the dense solver takes
    "scale": Float(2.0, 5.0, default=3.0),  # leg size relative to Jansen's 15 mm-crank drawing
    "crank_speed": Float(2.0, 10.0, default=5.0),  # [rad/s]
    "stance": Float(0.5, 1.5, default=1.0),  # leg spacing along the torso, in crank-to-pivot lengths
    "torso_mass": Float(0.5, 4.0, default=1.5),  # [kg]
})


def build_spec(params: dict, *, crank_speed: float | None = None, effort_limit: float = 20.0) -> MechanismSpec:
    """The walker's MechanismSpec (crank_speed overrides the parameter when given) [rad/s]."""
    p = space.validate(params)
    scale, count = p["scale"], int(p["legs_per_side"])
    speed = p["crank_speed"] if crank_speed is None else crank_speed
    leg = {k: v * scale for k, v in leg_family.space.default().items()}
    spacing = p["stance"] * 2.0 * leg["a"]
    width = 0.6 * leg["a"]
    half = (0.5 * max(count, 1) * spacing + leg["a"], width, 0.1 * leg["a"])
    foot_radius = 0.004 * scale
    style = BarStyle(width=0.004 * scale, thickness=0.002 * scale, density=1200.0)
    placements = []
    for side, y in ((0, width + 0.01 * scale), (1, -(width + 0.01 * scale))):
        for k in range(count):
            phase = 2.0 * math.pi * k / count + math.pi * side
            placements.append((f"{'left' if side == 0 else 'right'}{k}_", (k - 0.5 * (count - 1)) * spacing, y,
                               leg_family.generate(leg_family.space.default() | {n: v for n, v in leg.items()},
                                                   crank_speed=speed, phase=phase)))
    lowest = min(solve_at([linkage], np.array([[linkage.crank.phase]]))[0].nodes["F"][0, 1]
                 for _, _, _, linkage in placements)
    height = -lowest + foot_radius + 0.001
    torso = link_body("torso", [np.array([-half[0], 0.0, height]), np.array([half[0], 0.0, height])],
                      BarStyle(width=2 * half[1], thickness=2 * half[2], density=1.0))
    torso.mass = p["torso_mass"]
    hx, hy, hz = half
    torso.inertia = p["torso_mass"] / 3.0 * np.diag([hy * hy + hz * hz, hx * hx + hz * hz, hx * hx + hy * hy])
    torso.com = np.array([half[0], 0.0, 0.0])
    bodies, joints = [torso], []
    shapes = [Shape("torso", "box", "torso", half, position=(half[0], 0.0, 0.0), collision_group=1)]
    points = [TrackedPoint("torso", "torso", (half[0], 0.0, 0.0))]
    for prefix, x, y, linkage in placements:
        leg_bodies, leg_joints, leg_points = linkage_parts(
            linkage, style=style, crank_damping=5.0, effort_limit=effort_limit, start_at_speed=False,
            origin=(x, y, height), prefix=prefix, base=torso)
        bodies += leg_bodies
        joints += leg_joints
        points += leg_points
        foot = next(pt for pt in leg_points if pt.name == prefix + "foot")
        shapes.append(Shape(prefix + "foot", "sphere", foot.body, (foot_radius,), position=foot.position,
                            friction=1.0, collision_group=1))
    return MechanismSpec(bodies, joints, points, shapes=shapes, ground=GroundPlane(friction=1.0), name="walker")
