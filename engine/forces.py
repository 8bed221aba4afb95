"""Force elements of a MechanismSpec (``MechanismSpec.forces``): springs, dampers and constant loads.

Unlike joints, force elements add no constraint rows: the maximal step evaluates them as body
wrenches in its free-velocity stage, where Control.body_f enters (engine.dynamics.force_wrench_of),
at the integrator's evaluation point (Moreau-Jean: the midpoint poses and the step's starting
twists; semi-implicit Euler: the poses and twists at the start of the step). They are explicit, so
a stiff spring needs a time step well below its period. Each element checks its own fields on
creation; MechanismSpec checks the names it refers to. Host-side only (no Warp here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BodyWrench", "FORCE_TYPES", "JointSpring", "JointTorque", "LinearSpring"]


def _name(value, what: str, *, optional: bool = False):
    if optional and value is None:
        return None
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what}: must be a name (a non-empty string){' or None' if optional else ''}, "
                         f"got {value!r}")
    return value


def _scalar(value, what: str, *, minimum: float | None = None) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: expected a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise ValueError(f"{what}: must be finite, got {number}")
    if minimum is not None and number < minimum:
        raise ValueError(f"{what}: must be >= {minimum}, got {number}")
    return number


def _vector(value, what: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: expected 3 numbers, got {value!r}") from exc
    if array.size != 3 or not np.all(np.isfinite(array)):
        raise ValueError(f"{what}: expected 3 finite numbers, got {value!r}")
    return array


def _element_name(self, kind: str) -> str:
    if not isinstance(self.name, str) or not self.name:
        raise ValueError(f"{kind} name must be a non-empty string, got {self.name!r}")
    return f"{kind} '{self.name}'"


@dataclass
class LinearSpring:
    """A spring-damper between a point of body_a and a point of body_b (None: a point fixed in the world).

    Tension T = stiffness (L - rest_length) + damping dL/dt, with L the points' distance and dL/dt
    their relative velocity along the spring; body_a is pulled towards body_b by T (a positive T
    pulls the points together). tension_only: a cable, T = max(T, 0) and no force at all while
    L < rest_length (it never pushes). point_a in body_a's frame, point_b in body_b's frame (the
    world frame when body_b is None) [m]; stiffness [N/m], damping [N s/m], rest_length [m].
    """

    name: str
    body_a: str
    point_a: object = (0.0, 0.0, 0.0)
    body_b: str | None = None
    point_b: object = (0.0, 0.0, 0.0)
    stiffness: float = 0.0
    damping: float = 0.0
    rest_length: float = 0.0
    tension_only: bool = False

    def __post_init__(self):
        where = _element_name(self, "linear spring")
        self.body_a = _name(self.body_a, f"{where}: body_a")
        self.body_b = _name(self.body_b, f"{where}: body_b", optional=True)
        if self.body_a == self.body_b:
            raise ValueError(f"{where}: body_b: must differ from body_a '{self.body_a}'")
        self.point_a = _vector(self.point_a, f"{where}: point_a [m]")
        self.point_b = _vector(self.point_b, f"{where}: point_b [m]")
        self.stiffness = _scalar(self.stiffness, f"{where}: stiffness [N/m]", minimum=0.0)
        self.damping = _scalar(self.damping, f"{where}: damping [N s/m]", minimum=0.0)
        self.rest_length = _scalar(self.rest_length, f"{where}: rest_length [m]", minimum=0.0)
        if not isinstance(self.tension_only, (bool, np.bool_)):
            raise ValueError(f"{where}: tension_only: must be True or False, got {self.tension_only!r}")
        self.tension_only = bool(self.tension_only)


@dataclass
class JointSpring:
    """A spring-damper on the coordinate q of a revolute or prismatic joint: generalized force
    -stiffness (q - rest_position) - damping dq/dt (an angle difference wrapped to (-pi, pi]),
    applied as equal and opposite torques about (forces along) the joint axis on child and parent.
    stiffness [N m/rad] or [N/m], damping [N m s/rad] or [N s/m], rest_position [rad] or [m]."""

    name: str
    joint: str
    stiffness: float = 0.0
    damping: float = 0.0
    rest_position: float = 0.0

    def __post_init__(self):
        where = _element_name(self, "joint spring")
        self.joint = _name(self.joint, f"{where}: joint")
        self.stiffness = _scalar(self.stiffness, f"{where}: stiffness", minimum=0.0)
        self.damping = _scalar(self.damping, f"{where}: damping", minimum=0.0)
        self.rest_position = _scalar(self.rest_position, f"{where}: rest_position")


@dataclass
class BodyWrench:
    """A constant wrench on a body at its centre of mass, world frame: force [N], torque [N m]."""

    name: str
    body: str
    force: object = (0.0, 0.0, 0.0)
    torque: object = (0.0, 0.0, 0.0)

    def __post_init__(self):
        where = _element_name(self, "body wrench")
        self.body = _name(self.body, f"{where}: body")
        self.force = _vector(self.force, f"{where}: force [N]")
        self.torque = _vector(self.torque, f"{where}: torque [N m]")


@dataclass
class JointTorque:
    """A constant effort on a revolute (torque [N m]) or prismatic (force [N]) joint's coordinate,
    equal and opposite on child and parent, whether or not the joint has a drive (a drive's own
    effort limit does not clamp it)."""

    name: str
    joint: str
    effort: float = 0.0

    def __post_init__(self):
        where = _element_name(self, "joint torque")
        self.joint = _name(self.joint, f"{where}: joint")
        self.effort = _scalar(self.effort, f"{where}: effort")


FORCE_TYPES = (LinearSpring, JointSpring, BodyWrench, JointTorque)
