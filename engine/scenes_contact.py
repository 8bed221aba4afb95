"""Reference scenes with contacts and joint limits (engine tests and engine.testspeed).

box_on_plane, ball_bounce, box_slide, box_stack, walker and fourbar_limits; every builder
returns an engine.scenes.Scene (potential_min is the resting potential energy [J]).
"""

from __future__ import annotations

import math

import numpy as np

from engine.scenes import GRAVITY, Scene, fourbar
from engine.spec import Body, GroundPlane, Joint, JointDrive, MechanismSpec, Shape, TrackedPoint

__all__ = ["CONTACT_SCENES", "ball_bounce", "box_on_plane", "box_slide", "box_stack", "fourbar_limits", "solid_box",
           "walker"]


def solid_box(name: str, half, mass: float, **kwargs) -> Body:
    """A body with the inertia of a solid box of half extents ``half`` [m]."""
    hx, hy, hz = half
    inertia = mass / 3.0 * np.array([hy * hy + hz * hz, hx * hx + hz * hz, hx * hx + hy * hy])
    return Body(name, mass, inertia, **kwargs)


def _cube(name: str, half: float, mass: float, friction: float, **kwargs) -> Scene:
    """A scene of one cube ``box`` above the ground plane (kwargs: its Body's pose and velocity)."""
    body = solid_box("box", (half,) * 3, mass, **kwargs)
    spec = MechanismSpec([body], shapes=[Shape("box", "box", "box", (half,) * 3, friction=friction)],
                         ground=GroundPlane(friction=friction), points=[TrackedPoint("center", "box")], name=name)
    return Scene(spec, mass * GRAVITY * half)


def box_on_plane(half: float = 0.05, mass: float = 1.0, friction: float = 0.8, gap: float = 0.001) -> Scene:
    """A cube released ``gap`` above the ground plane."""
    return _cube("box_on_plane", half, mass, friction, position=(0.0, 0.0, half + gap))


def ball_bounce(radius: float = 0.05, height: float = 1.0, restitution: float = 0.5, mass: float = 1.0) -> Scene:
    """A ball whose bottom starts ``height`` above the ground."""
    inertia = 0.4 * mass * radius**2
    body = Body("ball", mass, (inertia,) * 3, position=(0.0, 0.0, height + radius))
    spec = MechanismSpec([body], shapes=[Shape("ball", "sphere", "ball", (radius,), restitution=restitution)],
                         ground=GroundPlane(restitution=0.0), points=[TrackedPoint("center", "ball")], name="ball_bounce")
    return Scene(spec, mass * GRAVITY * radius)


def box_slide(speed: float = 2.0, friction: float = 0.5, half: float = 0.05, mass: float = 1.0) -> Scene:
    """A cube resting on the plane, launched along +x at ``speed`` [m/s]."""
    return _cube("box_slide", half, mass, friction, position=(0.0, 0.0, half), velocity=(speed, 0.0, 0.0))


def box_stack(count: int = 5, half: float = 0.05, mass: float = 1.0, gap: float = 0.0005) -> Scene:
    """``count`` cubes stacked on the plane, each released ``gap`` above the one below."""
    bodies, shapes = [], []
    for k in range(count):
        z = half + k * (2.0 * half + gap) + gap
        bodies.append(solid_box(f"box{k}", (half,) * 3, mass, position=(0.0, 0.0, z)))
        shapes.append(Shape(f"box{k}", "box", f"box{k}", (half,) * 3, friction=0.8))
    spec = MechanismSpec(bodies, shapes=shapes, ground=GroundPlane(friction=0.8),
                         points=[TrackedPoint(f"box{k}", f"box{k}") for k in range(count)], name="box_stack")
    return Scene(spec, sum(mass * GRAVITY * (half + 2 * half * k) for k in range(count)))


WALKER_PIVOTS = ((0.15, 0.12), (0.15, -0.12), (-0.15, 0.12), (-0.15, -0.12))


def walker(strut_length: float = 0.2, strut_radius: float = 0.02, stiffness: float = 40.0, damping: float = 1.0,
           effort_limit: float = 8.0) -> Scene:
    """A 2 kg box body on four capsule struts, each on a PD-driven revolute pivot about +y.

    Diagonal strut pairs swing in opposite phase when the drive targets follow walker_gait.
    """
    half = (0.2, 0.1, 0.05)
    pivot_z = strut_length + strut_radius + 0.002
    bodies = [solid_box("body", half, 2.0, position=(0.0, 0.0, pivot_z))]
    joints, shapes = [], [Shape("body", "box", "body", half)]
    strut_mass = 0.2
    for k, (x, y) in enumerate(WALKER_PIVOTS):
        name = f"strut{k}"
        inertia = (strut_mass * strut_length**2 / 12, strut_mass * strut_length**2 / 12,
                   0.5 * strut_mass * strut_radius**2)
        bodies.append(Body(name, strut_mass, inertia, com=(0.0, 0.0, -0.5 * strut_length), position=(x, y, pivot_z)))
        joints.append(Joint(f"pivot{k}", "revolute", "body", name, parent_position=(x, y, 0.0), axis=(0, 1, 0),
                            drive=JointDrive(stiffness=stiffness, damping=damping, effort_limit=effort_limit)))
        shapes.append(Shape(name, "capsule", name, (strut_radius, 0.5 * strut_length),
                            position=(0, 0, -0.5 * strut_length), collision_group=1))
    spec = MechanismSpec(bodies, joints, [TrackedPoint("body", "body")], shapes=shapes,
                         ground=GroundPlane(friction=1.0), name="walker")
    return Scene(spec, 0.0)


def walker_gait(time: float, amplitude: float = 0.3, frequency: float = 1.5) -> np.ndarray:
    """Hip targets [rad] of the walker at ``time`` [s]: diagonal pairs in opposite phase."""
    phase = amplitude * math.sin(2.0 * math.pi * frequency * time)
    return np.array([phase, -phase, -phase, phase])


def fourbar_limits(limit: float = 1.85) -> Scene:
    """The passive fourbar of engine.scenes with an upper limit [rad] on its rocker's ground pivot.

    Free, the rocker swings between 1.52 and 1.92 rad about its equilibrium at 1.68 rad; the
    default limit cuts the upper swing, so the rocker comes back to it every cycle."""
    scene = fourbar()
    spec = scene.spec
    joints = []
    for joint in spec.joints:
        if joint.name == "ground_rocker":
            joint = Joint(joint.name, joint.type, joint.parent, joint.child, parent_position=joint.parent_position,
                          child_position=joint.child_position, axis=joint.axis, limit_upper=limit)
        joints.append(joint)
    return Scene(MechanismSpec(spec.bodies, joints, spec.points, name="fourbar_limits"), scene.potential_min)


CONTACT_SCENES = {"box_on_plane": box_on_plane, "ball_bounce": ball_bounce, "box_slide": box_slide,
                  "box_stack": box_stack, "walker": walker, "fourbar_limits": fourbar_limits}
