"""MechanismSpec: the host-side description of ONE world, validated on creation.

A spec lists rigid bodies, joints between them (or between a body and the world), drives on
joints and named tracked points. There is no spanning tree: any joint may close a loop.
Everything is in SI units and the world frame is Z up (see engine.model for all conventions).

Frames:
- A body's *frame* has its origin at ``Body.position`` and orientation ``Body.orientation``;
  ``Body.com`` is the centre of mass in that frame and ``Body.inertia`` the inertia tensor about
  the centre of mass, in body-frame axes [kg m^2].
- A joint connects an anchor frame on the parent (``parent_position``/``parent_orientation``,
  in the parent body frame, or in the world frame when ``parent`` is None) to an anchor frame
  on the child (``child_position``/``child_orientation``, in the child body frame). The joint
  holds the two anchor frames together except for its free motions, which are expressed with
  ``axis`` (and ``axis2`` for universal joints) in the anchor frames.
"""

from __future__ import annotations

import enum
import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from engine.forces import FORCE_TYPES, BodyWrench, JointSpring, JointTorque, LinearSpring

__all__ = ["Body", "BodyWrench", "GroundPlane", "Joint", "JointDrive", "JointSpring", "JointTorque", "JointType",
           "LinearSpring", "MechanismSpec", "Relief", "Shape", "ShapeType", "TrackedPoint"]


class JointType(enum.IntEnum):
    """Joint types and the number of bilateral constraint rows each one contributes."""

    REVOLUTE = 0  # rotation about axis: 3 position rows + 2 angular rows
    PRISMATIC = 1  # translation along axis: 2 position rows + 3 angular rows
    SPHERICAL = 2  # free rotation: 3 position rows
    UNIVERSAL = 3  # rotation about axis (parent) and axis2 (child): 3 position rows + 1 angular row
    CYLINDRICAL = 4  # rotation about and translation along axis: 2 position rows + 2 angular rows
    FIXED = 5  # no relative motion: 3 position rows + 3 angular rows
    INLINE = 6  # the child anchor stays on the parent's axis line: 2 position rows normal to the axis


JOINT_ROW_COUNT = {
    JointType.REVOLUTE: 5,
    JointType.PRISMATIC: 5,
    JointType.SPHERICAL: 3,
    JointType.UNIVERSAL: 4,
    JointType.CYLINDRICAL: 4,
    JointType.FIXED: 6,
    JointType.INLINE: 2,
}

DRIVABLE = (JointType.REVOLUTE, JointType.PRISMATIC)


def _array(value, what: str) -> np.ndarray:
    """``value`` as a float64 array, raising ValueError naming ``what`` when it holds no plain numbers."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: expected numbers, got {value!r}") from exc


def _name(value, what: str) -> str:
    """A non-empty string naming a body (for joints, points and shapes), else ValueError naming ``what``."""
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what}: must be a body name (a non-empty string), got {value!r}")
    return value


def _items(value, kind: str, where: str) -> list:
    """The list of ``kind`` items of a mechanism, from any iterable; ValueError naming the list otherwise."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
        raise ValueError(f"{where}: the {kind} list must be a list, got {type(value).__name__}")
    return list(value)


def _vector(value, size: int, what: str) -> np.ndarray:
    """Convert to a float64 vector of ``size`` entries, raising ValueError naming ``what``."""
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: expected {size} numbers, got {value!r}") from exc
    if array.size != size:
        raise ValueError(f"{what}: expected {size} numbers, got {array.size}")
    if not all(map(math.isfinite, array.tolist())):  # np.isfinite's test, without a ufunc call on 3 numbers
        raise ValueError(f"{what}: must be finite, got {array.tolist()}")
    return array


def _scalar(value, what: str, *, minimum: float | None = None, strict: bool = False,
            allow_inf: bool = False) -> float:
    """Convert to a float, checking finiteness and an optional lower bound."""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: expected a number, got {value!r}") from exc
    if math.isnan(number) or (math.isinf(number) and not (allow_inf and number > 0)):
        raise ValueError(f"{what}: must be finite, got {number}")
    if minimum is not None and (number <= minimum if strict else number < minimum):
        relation = ">" if strict else ">="
        raise ValueError(f"{what}: must be {relation} {minimum}, got {number}")
    return number


def _quaternion(value, what: str) -> np.ndarray:
    """A unit quaternion (x, y, z, w) from any non-zero finite 4-vector."""
    return _once(value, "quaternion", what)


def _unit_quaternion(value, what: str) -> np.ndarray:
    quat = _vector(value, 4, what)
    norm = math.sqrt(float(quat @ quat))
    if norm < 1e-9:
        raise ValueError(f"{what}: quaternion must be non-zero, got {quat.tolist()}")
    return quat / norm


def _unit_axis(value, what: str) -> np.ndarray:
    """A joint axis normalized (a non-zero finite 3-vector)."""
    axis = _vector(value, 3, what)
    norm = math.sqrt(float(axis @ axis))
    if norm < 1e-9:
        raise ValueError(f"{what} must be non-zero, got {axis.tolist()}")
    return axis / norm


_CHECKS = {"quaternion": _unit_quaternion, "axis": _unit_axis}
_PLAIN = (float, int)
_ONCE: dict = {}  # (id of a tuple of plain numbers, check) -> (the tuple, its checked array)
_ONCE_SIZE = 256


def _once(value, check: str, what: str) -> np.ndarray:
    """_CHECKS[check](value, what), computed once per tuple object of plain numbers (a dataclass's
    default, a module's constant axis: the same object for every joint) and copied out, so that
    every item still gets its own array; anything else (arrays, lists) is checked every time. A
    tuple is immutable and kept alive by the cache, so its id cannot come back for another one."""
    if type(value) is not tuple:
        return _CHECKS[check](value, what)
    key = (id(value), check)
    entry = _ONCE.get(key)
    if entry is None or entry[0] is not value:
        if not all(type(x) in _PLAIN for x in value):
            return _CHECKS[check](value, what)
        result = _CHECKS[check](value, what)  # raises for bad numbers: nothing is kept
        if len(_ONCE) >= _ONCE_SIZE:
            _ONCE.pop(next(iter(_ONCE)))
        _ONCE[key] = entry = (value, result)
    return entry[1].copy()


TRIANGLE_TOLERANCE = 1e-5  # share of the largest principal moment by which it may exceed the other two's sum


def _close(x: float, y: float) -> bool:
    """np.isclose(x, y, rtol=1e-6, atol=1e-12) of two finite numbers (the same operations)."""
    return abs(x - y) <= 1e-12 + 1e-6 * abs(y) or x == y


def check_inertia(inertia, where: str) -> np.ndarray:
    """A symmetric 3x3 inertia tensor [kg m^2] whose principal moments are positive and satisfy the
    triangle inequality (each at most the sum of the other two, as for any real mass distribution:
    I_1 + I_2 - I_3 = 2 sum m z^2 >= 0), else ValueError naming ``where`` and the moments. A
    tensor outside that set is no rigid body; the step would integrate it without complaint."""
    inertia = _array(inertia, f"{where}: inertia [kg m^2]")
    if inertia.shape == (3,):
        inertia = np.diag(inertia)
    if inertia.shape != (3, 3):
        raise ValueError(f"{where}: inertia must be 3x3 or a 3-vector, got shape {inertia.shape}")
    rows = inertia.tolist()
    if not all(math.isfinite(x) for row in rows for x in row):
        raise ValueError(f"{where}: inertia must be finite, got {rows}")
    (_, a01, a02), (a10, _, a12), (a20, a21, _) = rows
    if not (_close(a01, a10) and _close(a10, a01) and _close(a02, a20) and _close(a20, a02) and _close(a12, a21)
            and _close(a21, a12)):  # np.allclose(inertia, inertia.T, rtol=1e-6, atol=1e-12), entry by entry
        raise ValueError(f"{where}: inertia must be symmetric, got {rows}")
    moments = np.linalg.eigvalsh(inertia)  # ascending
    if not moments[0] > 0.0:
        raise ValueError(f"{where}: inertia must be positive definite, got eigenvalues {moments.tolist()}")
    if moments[2] > (moments[0] + moments[1]) + TRIANGLE_TOLERANCE * moments[2]:
        shown = ", ".join(f"{m:.6g}" for m in moments)
        raise ValueError(f"{where}: inertia violates the triangle inequality: principal moments ({shown}) kg m^2, "
                         f"the largest exceeds the sum of the other two ({moments[0] + moments[1]:.6g}); "
                         f"no mass distribution has it")
    return inertia


def _held(cls, **values):
    """An instance of dataclass ``cls`` holding ``values`` (every field, in order) without running its
    __post_init__: for the batch constructors, whose array checks stand for it."""
    item = object.__new__(cls)
    item.__dict__.update(values)
    return item


def _stack(value, shape: tuple) -> np.ndarray | None:
    """``value`` when it is a float64 array of ``shape``, else None."""
    return value if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.shape == shape else None


_F64 = np.dtype(np.float64)


def _finite(*arrays) -> bool:
    return all(np.isfinite(a).all() for a in arrays)


def _names(values) -> bool:
    return all(isinstance(v, str) and v for v in values)


@dataclass
class Body:
    """A rigid body.

    Attributes:
        name: unique name in the mechanism.
        mass: [kg], > 0.
        inertia: 3x3 inertia tensor about the centre of mass in body-frame axes [kg m^2],
            symmetric positive definite, its principal moments satisfying the triangle inequality
            (check_inertia; a 3-vector is taken as the diagonal).
        com: centre of mass in the body frame [m].
        position: body frame origin in the world frame [m].
        orientation: body frame orientation, quaternion (x, y, z, w).
        velocity: initial linear velocity of the centre of mass, world frame [m/s].
        angular_velocity: initial angular velocity, world frame [rad/s].
    """

    name: str
    mass: float
    inertia: object
    com: object = (0.0, 0.0, 0.0)
    position: object = (0.0, 0.0, 0.0)
    orientation: object = (0.0, 0.0, 0.0, 1.0)
    velocity: object = (0.0, 0.0, 0.0)
    angular_velocity: object = (0.0, 0.0, 0.0)

    def __post_init__(self):
        where = f"body '{self.name}'"
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"body name must be a non-empty string, got {self.name!r}")
        self.mass = _scalar(self.mass, f"{where}: mass [kg]", minimum=0.0, strict=True)
        self.inertia = check_inertia(self.inertia, where)
        self.com = _vector(self.com, 3, f"{where}: com [m]")
        self.position = _vector(self.position, 3, f"{where}: position [m]")
        self.orientation = _quaternion(self.orientation, f"{where}: orientation")
        self.velocity = _vector(self.velocity, 3, f"{where}: velocity [m/s]")
        self.angular_velocity = _vector(self.angular_velocity, 3, f"{where}: angular_velocity [rad/s]")

    @classmethod
    def batch(cls, names, mass, inertia, com, position, orientation, velocity=None, angular_velocity=None):
        """Bodies from stacked numbers: names (N strings), mass (N,), inertia (N, 3, 3), com and
        position (N, 3), orientation (N, 4), velocity and angular_velocity (N, 3) or None (zero),
        float64 arrays. The same bodies as ``Body(name, mass, inertia, com=..., ...)`` row by row
        (the constructor's checks run on the arrays at once; each body holds the numbers the
        constructor would: views of the rows, the orientation normalized as it normalizes), or
        None when any row fails a check: build those one by one for the constructor's error."""
        n = len(names)
        mass, inertia = _stack(mass, (n,)), _stack(inertia, (n, 3, 3))
        com, position, orientation = _stack(com, (n, 3)), _stack(position, (n, 3)), _stack(orientation, (n, 4))
        velocity = np.zeros((n, 3)) if velocity is None else _stack(velocity, (n, 3))
        angular_velocity = np.zeros((n, 3)) if angular_velocity is None else _stack(angular_velocity, (n, 3))
        arrays = (mass, inertia, com, position, orientation, velocity, angular_velocity)
        if any(a is None for a in arrays) or not _names(names) or not _finite(*arrays) or not (mass > 0.0).all():
            return None
        if n == 0:
            return []
        if not (np.abs(inertia - inertia.swapaxes(1, 2)) <= 1e-12 + 1e-6 * np.abs(inertia.swapaxes(1, 2))).all():
            return None  # check_inertia's symmetry (np.isclose's test)
        moments = np.linalg.eigvalsh(inertia)  # LAPACK on each matrix, as for one
        if not ((moments[:, 0] > 0.0) & ~(moments[:, 2] > (moments[:, 0] + moments[:, 1])
                                          + TRIANGLE_TOLERANCE * moments[:, 2])).all():
            return None
        norm = np.sqrt((orientation[:, None, :] @ orientation[:, :, None])[:, 0, 0])  # quat @ quat of each
        if not (norm >= 1e-9).all():
            return None
        unit = orientation / norm[:, None]
        new, out = object.__new__, []
        for name, m, I, c, p, q, v, w in zip(names, mass.tolist(), inertia, com, position, unit, velocity,
                                             angular_velocity):  # _held of each row, written out
            item = new(cls)
            item.__dict__.update(name=name, mass=m, inertia=I, com=c, position=p, orientation=q, velocity=v,
                                 angular_velocity=w)
            out.append(item)
        return out


@dataclass
class JointDrive:
    """An implicit PD drive on a revolute or prismatic joint.

    Joint torque (force) = stiffness (target_position - q) + damping (target_velocity - dq),
    clamped to +/- effort_limit [N m] or [N]; integrated implicitly, so stiff drives are stable.
    stiffness in [N m/rad] or [N/m], damping in [N m s/rad] or [N s/m].
    """

    stiffness: float = 0.0
    damping: float = 0.0
    target_position: float = 0.0
    target_velocity: float = 0.0
    effort_limit: float = math.inf

    def validate(self, where: str):
        """Check the gains and limits (finite, non-negative; ``where`` names the joint in errors)."""
        self.stiffness = _scalar(self.stiffness, f"{where}: drive stiffness", minimum=0.0)
        self.damping = _scalar(self.damping, f"{where}: drive damping", minimum=0.0)
        self.target_position = _scalar(self.target_position, f"{where}: drive target_position")
        self.target_velocity = _scalar(self.target_velocity, f"{where}: drive target_velocity")
        self.effort_limit = _scalar(self.effort_limit, f"{where}: drive effort_limit", minimum=0.0,
                                    strict=True, allow_inf=True)


@dataclass
class Joint:
    """A joint between ``parent`` (a body name, or None for the world) and ``child``.

    Attributes:
        name: unique joint name.
        type: JointType (or its name, e.g. "revolute").
        parent, child: body names; parent None means the world.
        parent_position, parent_orientation: anchor frame in the parent body frame (world frame
            when parent is None) [m], quaternion (x, y, z, w).
        child_position, child_orientation: anchor frame in the child body frame.
        axis: joint axis in the anchor frame (revolute, prismatic, cylindrical, inline; universal:
            the parent-side axis); normalized on creation. An inline joint keeps the child anchor
            on the parent's axis line and leaves every rotation free: it closes a loop of a planar
            linkage whose other joints already hold it in the plane, without the redundant
            out-of-plane rows a revolute closure would add.
        axis2: universal joints only: the child-side axis, in the child anchor frame.
        armature: added joint-space inertia [kg m^2] or [kg] (revolute, prismatic).
        damping: viscous joint damping [N m s/rad] or [N s/m] (revolute, prismatic).
        drive: optional JointDrive (revolute, prismatic).
        limit_lower, limit_upper: joint position limits [rad] or [m] (revolute, prismatic);
            -inf / inf for none. Enforced as unilateral rows in the same solve.
    """

    name: str
    type: JointType
    parent: str | None
    child: str
    parent_position: object = (0.0, 0.0, 0.0)
    parent_orientation: object = (0.0, 0.0, 0.0, 1.0)
    child_position: object = (0.0, 0.0, 0.0)
    child_orientation: object = (0.0, 0.0, 0.0, 1.0)
    axis: object = (0.0, 0.0, 1.0)
    axis2: object = (0.0, 1.0, 0.0)
    armature: float = 0.0
    damping: float = 0.0
    drive: JointDrive | None = None
    limit_lower: float = -math.inf
    limit_upper: float = math.inf

    def __post_init__(self):
        where = f"joint '{self.name}'"
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"joint name must be a non-empty string, got {self.name!r}")
        try:
            self.type = JointType[self.type.upper()] if isinstance(self.type, str) else JointType(self.type)
        except (KeyError, ValueError) as exc:
            names = ", ".join(t.name.lower() for t in JointType)
            raise ValueError(f"{where}: type must be one of {names}, got {self.type!r}") from exc
        if not isinstance(self.child, str) or not self.child:
            raise ValueError(f"{where}: child must be a body name, got {self.child!r}")
        if self.parent is not None and (not isinstance(self.parent, str) or not self.parent):
            raise ValueError(f"{where}: parent must be a body name or None (world), got {self.parent!r}")
        if self.parent == self.child:
            raise ValueError(f"{where}: parent and child are the same body '{self.child}'")
        self.parent_position = _vector(self.parent_position, 3, f"{where}: parent_position [m]")
        self.child_position = _vector(self.child_position, 3, f"{where}: child_position [m]")
        self.parent_orientation = _quaternion(self.parent_orientation, f"{where}: parent_orientation")
        self.child_orientation = _quaternion(self.child_orientation, f"{where}: child_orientation")
        self.axis = _once(self.axis, "axis", f"{where}: axis")
        self.axis2 = _once(self.axis2, "axis", f"{where}: axis2")
        self.armature = _scalar(self.armature, f"{where}: armature", minimum=0.0)
        self.damping = _scalar(self.damping, f"{where}: damping", minimum=0.0)
        drivable = self.type in DRIVABLE
        if not drivable and (self.drive is not None or self.armature > 0.0 or self.damping > 0.0):
            raise ValueError(f"{where}: drives, armature and damping need a revolute or prismatic "
                             f"joint, this one is {self.type.name.lower()}")
        for attr in ("limit_lower", "limit_upper"):
            value = getattr(self, attr)
            try:
                value = float(value)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{where}: {attr}: expected a number, got {value!r}") from exc
            if math.isnan(value):
                raise ValueError(f"{where}: {attr} must not be NaN")
            setattr(self, attr, value)
        if self.has_limits and not drivable:
            raise ValueError(f"{where}: limits need a revolute or prismatic joint, this one is {self.type.name.lower()}")
        if self.limit_lower > self.limit_upper:
            raise ValueError(f"{where}: limit_lower {self.limit_lower} is above limit_upper {self.limit_upper}")
        if self.drive is not None:
            if not isinstance(self.drive, JointDrive):
                raise ValueError(f"{where}: drive must be a JointDrive, got {type(self.drive).__name__}")
            self.drive.validate(where)

    @classmethod
    def batch(cls, names, types, parents, children, parent_position, child_position, axis, drives):
        """Joints from stacked numbers: names, types (JointType or name), parents (name or None),
        children, parent_position and child_position (N, 3) float64 arrays, one ``axis`` for all,
        drives (JointDrive or None each, validated here), the other fields at their defaults. The
        same joints as the constructor makes row by row (its checks on the arrays at once; each
        joint holds the numbers it would), or None when any row fails a check: build those one by
        one for the constructor's error."""
        n = len(names)
        parent_position, child_position = _stack(parent_position, (n, 3)), _stack(child_position, (n, 3))
        if parent_position is None or child_position is None or not _finite(parent_position, child_position):
            return None
        if not (_names(names) and _names(children) and all(p is None or (isinstance(p, str) and p) for p in parents)):
            return None
        if any(p == c for p, c in zip(parents, children)):
            return None
        try:
            types = [_JOINT_TYPES.get(t) or (JointType[t.upper()] if isinstance(t, str) else JointType(t)) for t in types]
            defaults = cls.__dataclass_fields__
            default_q, default_axis2 = defaults["parent_orientation"].default, defaults["axis2"].default
            unit = _once(axis, "axis", "axis")
            for kind, drive in zip(types, drives):
                if drive is not None:
                    if kind not in DRIVABLE or not isinstance(drive, JointDrive):
                        return None
                    drive.validate("joint")
        except (AttributeError, KeyError, TypeError, ValueError):
            return None
        unit_q, unit_axis2 = _once(default_q, "quaternion", ""), _once(default_axis2, "axis", "")
        # every joint its own arrays (rows of one array per field, as Body.batch's rows)
        parent_q, child_q = np.tile(unit_q, (n, 1)), np.tile(unit_q, (n, 1))
        axes, axes2 = np.tile(unit, (n, 1)), np.tile(unit_axis2, (n, 1))
        new, out, same = object.__new__, [], itertools.repeat
        for row in zip(names, types, parents, children, parent_position, parent_q, child_position, child_q, axes, axes2,
                       same(0.0), same(0.0), drives, same(-math.inf), same(math.inf)):  # _held of each row
            item = new(cls)
            item.__dict__.update(zip(_JOINT_FIELDS, row))
            out.append(item)
        return out


    @property
    def has_limits(self) -> bool:
        """True when either position limit is finite."""
        return math.isfinite(self.limit_lower) or math.isfinite(self.limit_upper)

    @property
    def limit_sides(self) -> list[int]:
        """+1 for a finite lower limit, -1 for a finite upper limit (one unilateral row each)."""
        return [side for side, value in ((1, self.limit_lower), (-1, self.limit_upper)) if math.isfinite(value)]


_JOINT_TYPES = {**{t: t for t in JointType}, **{t.name.lower(): t for t in JointType}}  # Joint.batch's fast path
_JOINT_FIELDS = tuple(Joint.__dataclass_fields__)  # Joint.batch's columns, in field order


class ShapeType(enum.IntEnum):
    """Collision primitives. Capsules and cylinders run along their local z axis."""

    SPHERE = 0  # size[0] = radius
    CAPSULE = 1  # size[0] = radius, size[1] = half length of the segment
    BOX = 2  # size = half extents (x, y, z)
    CYLINDER = 3  # size[0] = radius, size[1] = half height


@dataclass
class Shape:
    """A collision primitive fixed on a body.

    Attributes:
        name: unique shape name.
        type: ShapeType or its name ("sphere", "capsule", "box", "cylinder").
        body: the body it is attached to.
        size: sphere (radius,), capsule (radius, half_length), box (hx, hy, hz), cylinder
            (radius, half_height) [m].
        position, orientation: shape frame in the body frame [m], quaternion (x, y, z, w).
        friction: Coulomb friction coefficient (combined per pair by the geometric mean).
        restitution: Newton restitution coefficient in [0, 1] (combined per pair by the maximum).
        collision_group: shapes sharing a non-zero group never collide with each other.
    """

    name: str
    type: ShapeType
    body: str
    size: object
    position: object = (0.0, 0.0, 0.0)
    orientation: object = (0.0, 0.0, 0.0, 1.0)
    friction: float = 0.8
    restitution: float = 0.0
    collision_group: int = 0

    def __post_init__(self):
        where = f"shape '{self.name}'"
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"shape name must be a non-empty string, got {self.name!r}")
        try:
            self.type = ShapeType[self.type.upper()] if isinstance(self.type, str) else ShapeType(self.type)
        except (KeyError, ValueError) as exc:
            names = ", ".join(t.name.lower() for t in ShapeType)
            raise ValueError(f"{where}: type must be one of {names}, got {self.type!r}") from exc
        self.body = _name(self.body, f"{where}: body")
        count = {ShapeType.SPHERE: 1, ShapeType.CAPSULE: 2, ShapeType.BOX: 3, ShapeType.CYLINDER: 2}[self.type]
        size = _array(self.size, f"{where}: size [m]").reshape(-1)
        if size.size != count:
            raise ValueError(f"{where}: a {self.type.name.lower()} needs {count} size value(s), got {size.tolist()}")
        if not np.all(np.isfinite(size)) or np.any(size <= 0.0):
            raise ValueError(f"{where}: size values must be positive and finite, got {size.tolist()}")
        self.size = np.concatenate([size, np.zeros(3 - count)])
        self.position = _vector(self.position, 3, f"{where}: position [m]")
        self.orientation = _quaternion(self.orientation, f"{where}: orientation")
        self.friction = _scalar(self.friction, f"{where}: friction", minimum=0.0)
        self.restitution = _scalar(self.restitution, f"{where}: restitution", minimum=0.0)
        if self.restitution > 1.0:
            raise ValueError(f"{where}: restitution must be <= 1, got {self.restitution}")
        group = self.collision_group
        try:  # an int, or a float holding one
            integral = not isinstance(group, bool) and float(group).is_integer() and int(group) == group
        except (TypeError, ValueError, OverflowError):
            integral = False
        if not integral or group < 0:
            raise ValueError(f"{where}: collision_group must be a non-negative integer, got {group!r}")
        self.collision_group = int(group)

    @classmethod
    def batch(cls, names, types, bodies, size, position, orientation, *, friction=0.8, restitution=0.0,
              collision_group=0):
        """Shapes from stacked numbers: names, types (ShapeType each) and body names (N each), size
        (N, 3) float64 (a shape's sizes, then zeros: a capsule (radius, half length, 0)), position
        (N, 3), orientation (N, 4), friction and restitution (N,) or one number, one non-negative
        integer collision_group. The constructor's shapes row by row (its checks on the arrays at
        once; each shape holds the numbers it would: views of the rows, the orientation normalized
        as it normalizes), or None when any row fails a check: build those one by one for the
        constructor's error."""
        n = len(names)
        size, position, orientation = _stack(size, (n, 3)), _stack(position, (n, 3)), _stack(orientation, (n, 4))
        if size is None or position is None or orientation is None or not _finite(size, position, orientation):
            return None
        if not (_names(names) and _names(bodies)) or not all(type(t) is ShapeType for t in types):
            return None
        friction = np.broadcast_to(np.asarray(friction, dtype=np.float64), (n,))
        restitution = np.broadcast_to(np.asarray(restitution, dtype=np.float64), (n,))
        integral = type(collision_group) is int and collision_group >= 0
        if not (integral and _finite(friction, restitution) and (friction >= 0.0).all() and (restitution >= 0.0).all()
                and (restitution <= 1.0).all()):
            return None
        count = np.array([_SIZES[t] for t in types], dtype=int).reshape(n)
        used = np.arange(3) < count[:, None]
        if not ((size > 0.0) | ~used).all() or (size[~used] != 0.0).any():
            return None
        norm = np.sqrt((orientation[:, None, :] @ orientation[:, :, None])[:, 0, 0])  # quat @ quat of each
        if not (norm >= 1e-9).all():
            return None
        unit = orientation / norm[:, None]
        size = size + 0.0  # the constructor's zeros are positive
        return [_held(cls, name=names[i], type=types[i], body=bodies[i], size=size[i], position=position[i],
                      orientation=unit[i], friction=f, restitution=r, collision_group=collision_group)
                for i, (f, r) in enumerate(zip(friction.tolist(), restitution.tolist()))]


_SIZES = {ShapeType.SPHERE: 1, ShapeType.CAPSULE: 2, ShapeType.BOX: 3, ShapeType.CYLINDER: 2}  # sizes of a shape


@dataclass
class Relief:
    """Bumps on a ground plane z = offset: height offset + amplitude sin(2 pi x / wavelength + phase[0])
    sin(2 pi y / wavelength + phase[1]) [m] (rough ground for walkers). A contact sees the ground as
    the surface's tangent plane where the normal through its shape's centre meets it, so keep the
    bumps gentle against the shapes: amplitude (2 pi / wavelength)^2 times a radius well below 1,
    and a box's or capsule's faces touch only at their corners and end spheres. Simulated by the
    tabulated plan (floating-base walkers); engine.pack refuses it on the other plans."""

    amplitude: float
    wavelength: float = 0.5
    phase: object = (0.0, 0.0)

    def __post_init__(self):
        self.amplitude = _scalar(self.amplitude, "ground relief: amplitude [m]", minimum=0.0)
        self.wavelength = _scalar(self.wavelength, "ground relief: wavelength [m]", minimum=0.0)
        if self.wavelength <= 0.0:
            raise ValueError(f"ground relief: wavelength must be positive, got {self.wavelength}")
        phase = _array(self.phase, "ground relief: phase [rad]").reshape(-1)
        if phase.size != 2 or not np.all(np.isfinite(phase)):
            raise ValueError(f"ground relief: phase needs two finite angles [rad], got {phase.tolist()}")
        self.phase = phase

    def height(self, x, y):
        """The bumps' height above the plane at (x, y) [m] (NumPy)."""
        k = 2.0 * np.pi / self.wavelength
        return self.amplitude * np.sin(k * np.asarray(x) + self.phase[0]) * np.sin(k * np.asarray(y) + self.phase[1])


@dataclass
class GroundPlane:
    """A static plane {x : normal . x = offset}; bodies stay on the side the normal points to.
    relief: bumps on it (Relief; a horizontal plane only), None: flat."""

    normal: object = (0.0, 0.0, 1.0)
    offset: float = 0.0
    friction: float = 0.8
    restitution: float = 0.0
    relief: Relief | None = None

    def __post_init__(self):
        normal = _vector(self.normal, 3, "ground plane: normal")
        if np.linalg.norm(normal) < 1e-9:
            raise ValueError("ground plane: normal must be non-zero")
        self.normal = normal / np.linalg.norm(normal)
        self.offset = _scalar(self.offset, "ground plane: offset [m]")
        self.friction = _scalar(self.friction, "ground plane: friction", minimum=0.0)
        self.restitution = _scalar(self.restitution, "ground plane: restitution", minimum=0.0)
        if self.restitution > 1.0:
            raise ValueError(f"ground plane: restitution must be <= 1, got {self.restitution}")
        if self.relief is not None:
            if not isinstance(self.relief, Relief):
                raise ValueError(f"ground plane: relief must be an engine.spec.Relief, got {self.relief!r}")
            if np.abs(self.normal - np.array([0.0, 0.0, 1.0])).max() > 1e-9:
                raise ValueError("ground plane: relief needs a horizontal plane (normal (0, 0, 1)); tilt gravity "
                                 "for a slope")


@dataclass
class TrackedPoint:
    """A named point fixed on a body whose world trajectory is recorded.

    position: in the body frame [m].
    """

    name: str
    body: str
    position: object = (0.0, 0.0, 0.0)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"tracked point name must be a non-empty string, got {self.name!r}")
        self.body = _name(self.body, f"tracked point '{self.name}': body")
        self.position = _vector(self.position, 3, f"tracked point '{self.name}': position [m]")

    @classmethod
    def batch(cls, names, bodies, position):
        """Tracked points from names, body names and positions (N, 3) float64: the constructor's
        points row by row (its checks at once), or None when any row fails one."""
        position = _stack(position, (len(names), 3))
        if position is None or not (_names(names) and _names(bodies) and _finite(position)):
            return None
        return [_held(cls, name=name, body=body, position=position[i]) for i, (name, body) in enumerate(zip(names, bodies))]


@dataclass
class MechanismSpec:
    """One world: bodies, joints, tracked points, gravity and force elements, validated on creation.

    forces: force elements (engine.forces: LinearSpring, JointSpring, BodyWrench, JointTorque),
    names unique; the maximal plan alone takes them for now (engine.plan).
    Raises ValueError naming the body, joint, point or force element and the field when anything is off.
    """

    bodies: list[Body]
    joints: list[Joint] = field(default_factory=list)
    points: list[TrackedPoint] = field(default_factory=list)
    gravity: object = (0.0, 0.0, -9.81)
    name: str = "mechanism"
    shapes: list[Shape] = field(default_factory=list)
    ground: GroundPlane | None = None
    forces: list = field(default_factory=list)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"mechanism name must be a non-empty string, got {self.name!r}")
        where = f"mechanism '{self.name}'"
        self.bodies = _items(self.bodies, "body", where)
        self.joints = _items(self.joints, "joint", where)
        self.points = _items(self.points, "tracked point", where)
        self.shapes = _items(self.shapes, "shape", where)
        if self.ground is not None and not isinstance(self.ground, GroundPlane):
            raise ValueError(f"mechanism '{self.name}': ground must be a GroundPlane or None")
        if not self.bodies:
            raise ValueError(f"mechanism '{self.name}': needs at least one body")
        self.gravity = _vector(self.gravity, 3, f"mechanism '{self.name}': gravity [m/s^2]")
        for kind, items, cls in (("body", self.bodies, Body), ("joint", self.joints, Joint),
                                 ("tracked point", self.points, TrackedPoint), ("shape", self.shapes, Shape)):
            seen = set()
            for item in items:
                if not isinstance(item, cls):
                    raise ValueError(f"mechanism '{self.name}': expected a {cls.__name__} in the "
                                     f"{kind} list, got {type(item).__name__}")
                if item.name in seen:
                    raise ValueError(f"mechanism '{self.name}': duplicate {kind} name '{item.name}'")
                seen.add(item.name)
        index = self.body_index
        for joint in self.joints:
            for role in ("parent", "child"):
                name = getattr(joint, role)
                if name is not None and name not in index:
                    raise ValueError(f"joint '{joint.name}': {role} body '{name}' does not exist")
        for point in self.points:
            if point.body not in index:
                raise ValueError(f"tracked point '{point.name}': body '{point.body}' does not exist")
        for shape in self.shapes:
            if shape.body not in index:
                raise ValueError(f"shape '{shape.name}': body '{shape.body}' does not exist")
        self.forces = _items(self.forces, "force", where)
        if self.forces:
            self._check_forces(index)

    def _check_forces(self, index: dict) -> None:
        """Force elements: of a known type, names unique, the bodies and joints they name present
        (a joint element on a revolute or prismatic joint)."""
        joints = {joint.name: joint for joint in self.joints}
        seen = set()
        for item in self.forces:
            if not isinstance(item, FORCE_TYPES):
                raise ValueError(f"mechanism '{self.name}': expected a LinearSpring, JointSpring, BodyWrench or "
                                 f"JointTorque in the force list, got {type(item).__name__}")
            what = f"{type(item).__name__} '{item.name}'"
            if item.name in seen:
                raise ValueError(f"mechanism '{self.name}': duplicate force element name '{item.name}'")
            seen.add(item.name)
            if isinstance(item, LinearSpring):
                for role in ("body_a", "body_b"):
                    name = getattr(item, role)
                    if name is not None and name not in index:
                        raise ValueError(f"{what}: {role}: body '{name}' does not exist")
            elif isinstance(item, BodyWrench):
                if item.body not in index:
                    raise ValueError(f"{what}: body: body '{item.body}' does not exist")
            else:
                joint = joints.get(item.joint)
                if joint is None:
                    raise ValueError(f"{what}: joint: joint '{item.joint}' does not exist")
                if joint.type not in (JointType.REVOLUTE, JointType.PRISMATIC):
                    raise ValueError(f"{what}: joint: joint '{item.joint}' is {joint.type.name.lower()}; "
                                     f"joint force elements take revolute and prismatic joints")

    def __reduce_ex__(self, protocol):
        """Pickled as columns: every field of the bodies, joints, tracked points and shapes as one
        array (numbers) or list (the rest), unpickled into the same items (their arrays rows of one
        array per field, floats and types as they were): a worker's specs cost a fraction of the
        item-by-item pickle to send and to receive (morphopt.build). A spec holding anything else
        (a subclass, an attribute of its own) pickles item by item."""
        packed = _packed_spec(self) if type(self) is MechanismSpec else None
        if packed is None:
            return object.__reduce_ex__(self, protocol)
        return _unpacked_spec, packed

    @property
    def body_index(self) -> dict[str, int]:
        """Body name -> index in ``bodies``."""
        return {body.name: i for i, body in enumerate(self.bodies)}

    @property
    def row_count(self) -> int:
        """Number of joint, drive and limit rows of this world (contact rows come on top)."""
        return sum(JOINT_ROW_COUNT[j.type] + sum(joint_dynamics_rows(j)) + len(j.limit_sides) for j in self.joints)


_SPEC_FIELDS = tuple(MechanismSpec.__dataclass_fields__)
_ITEM_KINDS = {"bodies": Body, "joints": Joint, "points": TrackedPoint, "shapes": Shape}
_FIELDS_OF = {cls: tuple(cls.__dataclass_fields__) for cls in _ITEM_KINDS.values()}


def _column(values: list):
    """One field of a list of items, packed: ("f", float64 array) for Python floats, ("a", array
    stacked along a new first axis) for C-ordered float64 arrays of one shape, ("e", enum class,
    int array) for members of one IntEnum, else ("v", the list)."""
    kinds = set(map(type, values))
    if kinds == {float}:
        return "f", np.array(values)
    if kinds == {np.ndarray}:
        layouts = {(a.dtype.str, a.shape, a.strides, a.flags.c_contiguous) for a in values}
        if len(layouts) == 1:
            dtype, shape, strides, contiguous = layouts.pop()
            if dtype == "<f8" and contiguous and shape and all(a.dtype == _F64 for a in values):
                return "a", np.array(values).reshape((len(values),) + shape)
    if len(kinds) == 1:
        kind = next(iter(kinds))
        if isinstance(kind, type) and issubclass(kind, enum.IntEnum):
            return "e", kind, np.array([int(v) for v in values])
    return "v", values


def _unpacked_column(column, numbers: np.ndarray) -> list:
    if column[0] == "f":  # ("f", start, stop) in the spec's numbers
        return numbers[column[1]:column[2]].tolist()
    if column[0] == "a":  # ("a", start, shape of the stacked rows) in the spec's numbers
        shape = column[2]
        return list(numbers[column[1]:column[1] + math.prod(shape)].reshape(shape))  # rows: views of one array
    if column[0] == "e":  # members by value, looked up (a call of the enum class per item costs ten times as much)
        return list(map(column[1]._value2member_map_.__getitem__, column[2].tolist()))
    return column[1]


def _packed_spec(spec: MechanismSpec):
    """(arguments of _unpacked_spec) for a spec whose items are plain Body, Joint, TrackedPoint
    and Shape instances holding their fields only, in field order; else None. Every float and
    float-array column goes into one float64 array of the spec (one array to rebuild, not one a
    column: unpickling cost half as much)."""
    if tuple(spec.__dict__) != _SPEC_FIELDS:
        return None
    lists, parts, size = [], [], 0
    for attr, cls in _ITEM_KINDS.items():
        items = getattr(spec, attr)
        fields = _FIELDS_OF[cls]
        if type(items) is not list or set(map(type, items)) - {cls} or \
                any(tuple(item.__dict__) != fields for item in items):
            return None
        rows = [tuple(item.__dict__.values()) for item in items]
        columns = []
        for values in zip(*rows) if items else ():
            column = _column(list(values))
            if column[0] in ("f", "a"):
                array = column[1]
                parts.append(array.reshape(-1))
                column = ("f", size, size + array.size) if column[0] == "f" else ("a", size, array.shape)
                size += array.size
            columns.append(column)
        lists.append((len(items), columns))
    rest = tuple(getattr(spec, f) for f in _SPEC_FIELDS if f not in _ITEM_KINDS)
    return (rest, np.concatenate(parts) if parts else np.zeros(0), *lists)


_GRAVITY_AND_REST = tuple(f for f in _SPEC_FIELDS if f not in _ITEM_KINDS)


def _unpacked_spec(rest, numbers, *lists) -> MechanismSpec:
    """The MechanismSpec _packed_spec packed (its items rebuilt without their checks: they held
    these values)."""
    new = object.__new__
    made = {}
    for (attr, cls), (count, columns) in zip(_ITEM_KINDS.items(), lists):
        fields = _FIELDS_OF[cls]
        items = []
        for row in zip(*(_unpacked_column(column, numbers) for column in columns)) if count else ():
            item = new(cls)
            item.__dict__.update(zip(fields, row))
            items.append(item)
        made[attr] = items
    spec = new(MechanismSpec)
    values = dict(zip(_GRAVITY_AND_REST, rest), **made)
    spec.__dict__.update((f, values[f]) for f in _SPEC_FIELDS)
    return spec


def joint_dynamics_rows(joint: Joint) -> tuple[bool, bool]:
    """Which joint-space rows a joint adds: (inertia row for armature/damping, drive row)."""
    return joint.armature > 0.0 or joint.damping > 0.0, joint.drive is not None
