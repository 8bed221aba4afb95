"""Reference scenes of the engine's tests and engine.testspeed: planar linkages of slender bars.

Every bar lies in the x-z plane and turns about +y: a body turned by phi maps its local x axis
to u(phi) = (cos phi, 0, -sin phi). A bar's frame sits at its first pivot, its centre of mass at
(L/2, 0, 0); mass = line density * L; cross-section thickness t gives the inertia
diag(m 2 t^2 / 12, m (L^2 + t^2) / 12, m (L^2 + t^2) / 12).
Each builder returns a Scene: the spec and the lowest potential energy the mechanism can reach
(its static equilibrium), used to normalize energy drift.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from engine.spec import Body, Joint, JointType, MechanismSpec, TrackedPoint

__all__ = ["SCENES", "Scene", "bar", "chain", "fourbar", "fourbar_configuration", "make_scene", "pendulum", "sixbar"]

Y_AXIS = (0.0, 1.0, 0.0)
GRAVITY = 9.81


@dataclass
class Scene:
    """A spec plus the potential energy of its static equilibrium [J]."""

    spec: MechanismSpec
    potential_min: float


def u(phi: float) -> np.ndarray:
    """Direction of a bar turned by phi about +y."""
    return np.array([math.cos(phi), 0.0, -math.sin(phi)])


def quat_y(phi: float) -> tuple:
    """Quaternion (x, y, z, w) of a rotation by phi about +y."""
    return (0.0, math.sin(0.5 * phi), 0.0, math.cos(0.5 * phi))


def bar(name: str, length: float, origin, phi: float, omega: float = 0.0, origin_velocity=(0.0, 0.0, 0.0),
        density: float = 1.0, thickness: float = 0.01) -> Body:
    """A slender bar from ``origin`` along u(phi), turning at omega about +y [rad/s]."""
    m = density * length
    com_offset = 0.5 * length * u(phi)
    v_com = np.asarray(origin_velocity, float) + omega * np.cross(np.array(Y_AXIS), com_offset)
    inertia = np.diag([m * 2.0 * thickness**2 / 12.0, m * (length**2 + thickness**2) / 12.0,
                       m * (length**2 + thickness**2) / 12.0])
    return Body(name, m, inertia, com=(0.5 * length, 0.0, 0.0), position=origin, orientation=quat_y(phi),
                velocity=v_com, angular_velocity=(0.0, omega, 0.0))


def pin(name: str, parent: str | None, child: str, parent_position, child_position=(0.0, 0.0, 0.0)) -> Joint:
    """A revolute joint about +y."""
    return Joint(name, JointType.REVOLUTE, parent, child, parent_position=parent_position,
                 child_position=child_position, axis=Y_AXIS)


def circle_intersection(p0: np.ndarray, r0: float, p1: np.ndarray, r1: float) -> np.ndarray:
    """The lower (smaller z) intersection of two circles in the x-z plane; ValueError if none."""
    delta = p1 - p0
    dist = float(np.linalg.norm(delta))
    if dist > r0 + r1 or dist < abs(r0 - r1) or dist == 0.0:
        raise ValueError("circles do not intersect: the linkage cannot be assembled here")
    ex = delta / dist
    ez = np.cross(ex, np.array(Y_AXIS))
    a = (r0 * r0 - r1 * r1 + dist * dist) / (2.0 * dist)
    h = math.sqrt(max(r0 * r0 - a * a, 0.0))
    c1, c2 = p0 + a * ex + h * ez, p0 + a * ex - h * ez
    return c1 if c1[2] < c2[2] else c2


def angle_of(vec: np.ndarray) -> float:
    """phi with u(phi) parallel to vec."""
    return math.atan2(-vec[2], vec[0])


def _y_cross(r) -> np.ndarray:
    """The x and z components of y x r."""
    return np.array([r[2], -r[0]])


def fourbar_configuration(ground: float, crank: float, coupler: float, rocker: float, phi1: float, omega1: float):
    """Assembled pivots A, B, C, D, bar angles and loop-consistent angular speeds of a four-bar."""
    A, D = np.zeros(3), np.array([ground, 0.0, 0.0])
    B = A + crank * u(phi1)
    C = circle_intersection(B, coupler, D, rocker)
    phi2, phi3 = angle_of(C - B), angle_of(C - D)
    # velocity closure: omega1 y x (B-A) + omega2 y x (C-B) = omega3 y x (C-D) in the x-z plane
    matrix = np.stack([_y_cross(C - B), -_y_cross(C - D)], axis=1)
    omega2, omega3 = np.linalg.solve(matrix, -omega1 * _y_cross(B - A))
    return dict(A=A, B=B, C=C, D=D, phi=(phi1, phi2, phi3), omega=(omega1, omega2, omega3))


def _bar_potential(length: float, start: np.ndarray, end: np.ndarray, density: float = 1.0) -> float:
    return density * length * GRAVITY * 0.5 * (start[2] + end[2])


def _lowest_potential(potential, samples: int = 1440) -> float:
    """The least potential(crank angle) over ``samples`` angles of a turn (angles at which the
    linkage cannot be assembled are skipped)."""
    best = math.inf
    for k in range(samples):
        try:
            best = min(best, potential(2.0 * math.pi * k / samples))
        except (ValueError, np.linalg.LinAlgError):
            continue
    return best


def pendulum(length: float = 0.5, angle: float = math.radians(30.0)) -> Scene:
    """A bar hanging from a world pivot, released at ``angle`` from the downward vertical."""
    phi = 0.5 * math.pi - angle  # u(phi) = (sin angle, 0, -cos angle)
    spec = MechanismSpec([bar("rod", length, (0.0, 0.0, 0.0), phi)],
                         [pin("pivot", None, "rod", (0.0, 0.0, 0.0))],
                         [TrackedPoint("tip", "rod", (length, 0.0, 0.0))], name="pendulum")
    return Scene(spec, -length * GRAVITY * 0.5 * length)


def fourbar(ground: float = 0.30, crank: float = 0.10, coupler: float = 0.30, rocker: float = 0.25,
            crank_angle: float = math.radians(45.0), crank_speed: float = 3.0) -> Scene:
    """Passive four-bar hanging under gravity (lower branch), started assembled at crank_speed."""
    s = fourbar_configuration(ground, crank, coupler, rocker, crank_angle, crank_speed)
    (phi1, phi2, phi3), (w1, w2, w3) = s["phi"], s["omega"]
    v_B = w1 * np.cross(np.array(Y_AXIS), s["B"] - s["A"])
    bodies = [bar("crank", crank, s["A"], phi1, w1), bar("coupler", coupler, s["B"], phi2, w2, v_B),
              bar("rocker", rocker, s["D"], phi3, w3)]
    joints = [pin("ground_crank", None, "crank", s["A"]), pin("crank_coupler", "crank", "coupler", (crank, 0, 0)),
              pin("coupler_rocker", "coupler", "rocker", (coupler, 0, 0), (rocker, 0, 0)),
              pin("ground_rocker", None, "rocker", s["D"])]
    points = [TrackedPoint("coupler_mid", "coupler", (0.5 * coupler, 0.0, 0.0))]

    def potential(phi: float) -> float:
        c = fourbar_configuration(ground, crank, coupler, rocker, phi, 0.0)
        return (_bar_potential(crank, c["A"], c["B"]) + _bar_potential(coupler, c["B"], c["C"])
                + _bar_potential(rocker, c["D"], c["C"]))

    return Scene(MechanismSpec(bodies, joints, points, name="fourbar"), _lowest_potential(potential))


SIXBAR = dict(ground=0.30, crank=0.10, coupler=0.30, rocker=0.25, lever=0.10, pivot2=(0.50, 0.0, 0.15),
              coupler2=0.25, rocker2=0.20)


def _sixbar_configuration(phi1: float, omega1: float, p=SIXBAR):
    """Watt II six-bar: the four-bar drives, through its rocker extended by a lever beyond D, a
    second four-bar (lever, coupler2, rocker2 on the ground pivot F)."""
    s = fourbar_configuration(p["ground"], p["crank"], p["coupler"], p["rocker"], phi1, omega1)
    D, F = s["D"], np.asarray(p["pivot2"], float)
    phi3, w3 = s["phi"][2], s["omega"][2]
    E = D - p["lever"] * u(phi3)  # lever on the far side of D
    H = circle_intersection(E, p["coupler2"], F, p["rocker2"])
    phi4, phi5 = angle_of(H - E), angle_of(H - F)
    v_E = w3 * _y_cross(E - D)
    matrix = np.stack([_y_cross(H - E), -_y_cross(H - F)], axis=1)
    w4, w5 = np.linalg.solve(matrix, -v_E)
    s.update(E=E, F=F, H=H, phi4=phi4, phi5=phi5, omega4=w4, omega5=w5)
    return s


def sixbar(crank_angle: float = math.radians(45.0), crank_speed: float = 3.0) -> Scene:
    """Passive Watt II six-bar hanging under gravity (7 revolute joints, 2 loops)."""
    p = SIXBAR
    s = _sixbar_configuration(crank_angle, crank_speed)
    (phi1, phi2, phi3), (w1, w2, w3) = s["phi"], s["omega"]
    y = np.array(Y_AXIS)
    lever_length = p["rocker"] + p["lever"]
    bodies = [
        bar("crank", p["crank"], s["A"], phi1, w1),
        bar("coupler", p["coupler"], s["B"], phi2, w2, w1 * np.cross(y, s["B"] - s["A"])),
        # rocker + lever as one bar from E through D to C
        bar("rocker", lever_length, s["E"], phi3, w3, w3 * np.cross(y, s["E"] - s["D"])),
        bar("coupler2", p["coupler2"], s["E"], s["phi4"], s["omega4"], w3 * np.cross(y, s["E"] - s["D"])),
        bar("rocker2", p["rocker2"], s["F"], s["phi5"], s["omega5"]),
    ]
    joints = [
        pin("ground_crank", None, "crank", s["A"]),
        pin("crank_coupler", "crank", "coupler", (p["crank"], 0, 0)),
        pin("coupler_rocker", "coupler", "rocker", (p["coupler"], 0, 0), (lever_length, 0, 0)),
        pin("ground_rocker", None, "rocker", s["D"], (p["lever"], 0, 0)),
        pin("lever_coupler2", "rocker", "coupler2", (0, 0, 0)),
        pin("coupler2_rocker2", "coupler2", "rocker2", (p["coupler2"], 0, 0), (p["rocker2"], 0, 0)),
        pin("ground_rocker2", None, "rocker2", s["F"]),
    ]
    points = [TrackedPoint("coupler2_mid", "coupler2", (0.5 * p["coupler2"], 0.0, 0.0))]

    def potential(phi: float) -> float:
        c = _sixbar_configuration(phi, 0.0)
        return (_bar_potential(p["crank"], c["A"], c["B"]) + _bar_potential(p["coupler"], c["B"], c["C"])
                + _bar_potential(lever_length, c["E"], c["C"]) + _bar_potential(p["coupler2"], c["E"], c["H"])
                + _bar_potential(p["rocker2"], c["F"], c["H"]))

    return Scene(MechanismSpec(bodies, joints, points, name="sixbar"), _lowest_potential(potential))


def chain(links: int = 10, length: float = 0.1, angle: float = math.radians(30.0),
          densities: list[float] | None = None) -> Scene:
    """An open chain of bars hanging from a world pivot, released straight at ``angle`` from
    vertical; densities: each link's line density [kg/m] (default 1)."""
    densities = [1.0] * links if densities is None else list(densities)
    if len(densities) != links:
        raise ValueError(f"chain: expected {links} densities, got {len(densities)}")
    phi = 0.5 * math.pi - angle  # u(phi) = (sin angle, 0, -cos angle)
    bodies, joints = [], []
    origin = np.zeros(3)
    for k in range(links):
        bodies.append(bar(f"link{k}", length, origin, phi, density=densities[k]))
        parent = None if k == 0 else f"link{k - 1}"
        joints.append(pin(f"joint{k}", parent, f"link{k}", origin if k == 0 else (length, 0.0, 0.0)))
        origin = origin + length * u(phi)
    points = [TrackedPoint("tip", f"link{links - 1}", (length, 0.0, 0.0))]
    # hanging straight: link k's centre at -(k + 1/2) length
    potential_min = -GRAVITY * sum(d * length * (k + 0.5) * length for k, d in enumerate(densities))
    return Scene(MechanismSpec(bodies, joints, points, name="chain"), potential_min)


SCENES = {"pendulum": pendulum, "fourbar": fourbar, "sixbar": sixbar, "chain": chain}


def shifted(spec: MechanismSpec, distance: float) -> MechanismSpec:
    """A copy of ``spec`` moved by ``distance`` [m] along x (far from the origin, float32 resolves
    less: engine.health's FAR flag)."""
    spec = copy.deepcopy(spec)
    offset = np.array([distance, 0.0, 0.0])
    for body in spec.bodies:
        body.position = body.position + offset
    for joint in spec.joints:
        if joint.parent is None:
            joint.parent_position = joint.parent_position + offset
    return spec


def make_scene(name: str) -> Scene:
    """Build a scene by name (one of SCENES)."""
    if name not in SCENES:
        raise ValueError(f"unknown scene '{name}', expected one of {sorted(SCENES)}")
    return SCENES[name]()
