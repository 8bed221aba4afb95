"""engine.spec's faster checks and batch constructors give exactly what the per-item constructors give.

Body.batch, Joint.batch, TrackedPoint.batch and Shape.batch (morphopt's builders make walkers with them)
check whole arrays at once and then hold the numbers without re-checking them: each item must
equal, bit for bit, the one its constructor makes of the same row, and a batch with any row the
constructor refuses must give None (the caller then builds one by one for the constructor's
error). check_inertia's symmetry test is np.allclose's, written for a 3x3 matrix; constant
orientations and axes are normalized once, yet every item keeps its own array. A MechanismSpec
pickles as columns (morphopt.build's workers send specs back pickled) and unpickles into the same
items.
"""

import dataclasses
import math
import pickle

import numpy as np
import pytest

from engine import Body, Joint, JointDrive, MechanismSpec, Shape, ShapeType, TrackedPoint
from engine.spec import check_inertia


def _same(a, b):
    """Every field of two spec items equal, arrays by dtype, shape and bytes (signed zeros too)."""
    assert type(a) is type(b)
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape, field.name
            assert x.tobytes() == y.tobytes(), field.name
        elif dataclasses.is_dataclass(x):
            _same(x, y)
        else:
            assert type(x) is type(y) and (x == y or (x != x and y != y)), (field.name, x, y)
            if isinstance(x, float):
                assert math.copysign(1.0, x) == math.copysign(1.0, y), field.name


def _inertias(rng, n):
    """Plausible inertia tensors: rotated diagonals whose moments satisfy the triangle inequality."""
    out = []
    for _ in range(n):
        a, b = rng.uniform(0.1, 1.0, 2)
        moments = np.array([a, b, rng.uniform(abs(a - b), a + b)]) * 10.0 ** rng.uniform(-6, 1)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        out.append(q @ np.diag(moments) @ q.T)
    return np.array(out)


def _bodies(rng, n=9):
    names = [f"b{i}" for i in range(n)]
    mass = rng.uniform(0.01, 3.0, n)
    inertia = _inertias(rng, n)
    com, position = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    position[0, 1] = -0.0
    orientation = rng.normal(size=(n, 4))
    orientation[1] = (0.0, -math.sin(0.3), 0.0, math.cos(0.3))
    velocity, spin = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    return names, mass, inertia, com, position, orientation, velocity, spin


def test_body_batch_equals_the_constructor_row_by_row():
    rng = np.random.default_rng(0)
    names, mass, inertia, com, position, orientation, velocity, spin = _bodies(rng)
    made = Body.batch(names, mass, inertia, com, position, orientation, velocity, spin)
    at_rest = Body.batch(names, mass, inertia, com, position, orientation)
    for i, name in enumerate(names):
        one = Body(name, mass[i], inertia[i], com=com[i], position=position[i], orientation=orientation[i])
        _same(at_rest[i], one)
        one.velocity, one.angular_velocity = velocity[i], spin[i]
        _same(made[i], one)


@pytest.mark.parametrize("defect", ["name", "mass", "nan", "asymmetric", "triangle", "negative", "quaternion", "shape"])
def test_body_batch_refuses_what_the_constructor_refuses(defect):
    rng = np.random.default_rng(1)
    names, mass, inertia, com, position, orientation, velocity, spin = _bodies(rng)
    k = 4
    if defect == "name":
        names[k] = ""
    elif defect == "mass":
        mass[k] = 0.0
    elif defect == "nan":
        com[k, 2] = math.nan
    elif defect == "asymmetric":
        inertia[k, 0, 1] += 1e-5 * np.abs(inertia[k]).max()
    elif defect == "triangle":
        inertia[k] = np.diag([1.0, 1.0, 2.001])
    elif defect == "negative":
        inertia[k] = np.diag([1.0, -0.1, 1.0])
    elif defect == "quaternion":
        orientation[k] = 0.0
    else:
        inertia = inertia[:, :2]
    assert Body.batch(names, mass, inertia, com, position, orientation, velocity, spin) is None
    if defect != "shape":
        with pytest.raises(ValueError):
            Body(names[k], mass[k], inertia[k], com=com[k], position=position[k], orientation=orientation[k])


def _joints(rng, n=7):
    names = [f"j{i}" for i in range(n)]
    types = ["revolute", "inline", "revolute", "revolute", "inline", "revolute", "revolute"][:n]
    parents = [None, "a", "b", "a", None, "c", "b"][:n]
    children = ["a", "b", "c", "d", "e", "f", "g"][:n]
    drives = [JointDrive(damping=5.0, target_velocity=2.0, effort_limit=20.0) if i in (0, 3) else None
              for i in range(n)]
    return names, types, parents, children, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), drives


def test_joint_batch_equals_the_constructor_row_by_row():
    rng = np.random.default_rng(2)
    axis = (0.0, -1.0, 0.0)
    names, types, parents, children, p, c, drives = _joints(rng)
    made = Joint.batch(names, types, parents, children, p, c, axis, drives)
    for i in range(len(names)):
        drive = None if drives[i] is None else JointDrive(damping=5.0, target_velocity=2.0, effort_limit=20.0)
        _same(made[i], Joint(names[i], types[i], parents[i], children[i], parent_position=p[i], child_position=c[i],
                             axis=axis, drive=drive))
    tilted = Joint.batch(names, types, parents, children, p, c, (0.3, 0.4, 1.2), drives)
    _same(tilted[2], Joint(names[2], types[2], parents[2], children[2], parent_position=p[2], child_position=c[2],
                           axis=(0.3, 0.4, 1.2)))
    made[0].parent_orientation[0] = 7.0  # every joint holds its own arrays
    made[0].axis[1] = 7.0
    assert made[1].parent_orientation[0] == 0.0 and made[1].axis[1] == -1.0
    assert Joint("x", "revolute", None, "a", axis=axis).axis[1] == -1.0


@pytest.mark.parametrize("defect", ["self", "name", "parent", "nan", "type", "drive_inline", "drive_gain", "axis"])
def test_joint_batch_refuses_what_the_constructor_refuses(defect):
    rng = np.random.default_rng(3)
    names, types, parents, children, p, c, drives = _joints(rng)
    axis, k = (0.0, -1.0, 0.0), 3
    if defect == "self":
        children[k] = parents[k]
    elif defect == "name":
        names[k] = ""
    elif defect == "parent":
        parents[k] = ""
    elif defect == "nan":
        c[k, 0] = math.inf
    elif defect == "type":
        types[k] = "hinge"
    elif defect == "drive_inline":
        types[k] = "inline"
    elif defect == "drive_gain":
        drives[k] = JointDrive(damping=-1.0)
    else:
        axis = (0.0, 0.0, 0.0)
    assert Joint.batch(names, types, parents, children, p, c, axis, drives) is None
    drive = drives[k] if defect == "drive_gain" else (JointDrive(damping=5.0) if drives[k] is not None else None)
    with pytest.raises(ValueError):
        Joint(names[k], types[k], parents[k], children[k], parent_position=p[k], child_position=c[k], axis=axis,
              drive=drive)


def test_point_batch_equals_the_constructor_and_refuses_bad_rows():
    rng = np.random.default_rng(4)
    positions = rng.normal(size=(3, 3))
    made = TrackedPoint.batch(["p", "q", "r"], ["a", "b", "a"], positions)
    for point, (name, body, position) in zip(made, zip(["p", "q", "r"], ["a", "b", "a"], positions)):
        _same(point, TrackedPoint(name, body, position))
    positions[1, 1] = math.nan
    assert TrackedPoint.batch(["p", "q", "r"], ["a", "b", "a"], positions) is None
    assert TrackedPoint.batch(["p", "", "r"], ["a", "b", "a"], np.zeros((3, 3))) is None


def test_inertia_symmetry_test_is_np_allclose():
    """check_inertia refuses exactly the tensors np.allclose(I, I.T, rtol=1e-6, atol=1e-12) calls
    asymmetric, at and around its bounds."""
    rng = np.random.default_rng(5)
    for _ in range(4000):
        inertia = _inertias(rng, 1)[0]
        i, j = rng.choice(3, 2, replace=False)
        scale = rng.choice([0.0, 1e-13, 1e-12, 1e-7, 1e-6, 2e-6])
        inertia[i, j] = inertia[j, i] * (1.0 + rng.choice([-1.0, 1.0]) * scale) + rng.choice([0.0, 1e-12, -1e-12])
        symmetric = np.allclose(inertia, inertia.T, rtol=1e-6, atol=1e-12)
        try:
            check_inertia(inertia, "b")
            refused = False
        except ValueError as exc:
            refused = "symmetric" in str(exc)
        assert refused == (not symmetric)


def _shapes(rng, n=8):
    types = [ShapeType.BOX, ShapeType.CAPSULE, ShapeType.SPHERE, ShapeType.CYLINDER] * (n // 4)
    size = np.zeros((n, 3))
    for i, kind in enumerate(types):
        count = {ShapeType.BOX: 3, ShapeType.CAPSULE: 2, ShapeType.SPHERE: 1, ShapeType.CYLINDER: 2}[kind]
        size[i, :count] = rng.uniform(0.01, 0.2, count)
    orientation = rng.normal(size=(n, 4))
    orientation[0] = (0.0, -0.0, 0.0, 1.0)
    return ([f"s{i}" for i in range(n)], types, [f"b{i % 3}" for i in range(n)], size, rng.normal(size=(n, 3)),
            orientation)


def test_shape_batch_equals_the_constructor_row_by_row():
    rng = np.random.default_rng(6)
    names, types, bodies, size, position, orientation = _shapes(rng)
    friction = rng.uniform(0.0, 2.0, len(names))
    made = Shape.batch(names, types, bodies, size, position, orientation, friction=friction, restitution=0.25,
                       collision_group=2)
    for i, shape in enumerate(made):
        count = {ShapeType.BOX: 3, ShapeType.CAPSULE: 2, ShapeType.SPHERE: 1, ShapeType.CYLINDER: 2}[types[i]]
        _same(shape, Shape(names[i], types[i], bodies[i], size[i, :count], position=position[i],
                           orientation=orientation[i], friction=friction[i], restitution=0.25, collision_group=2))


@pytest.mark.parametrize("defect", ["size", "padding", "nan", "friction", "restitution", "group", "name", "quat"])
def test_shape_batch_refuses_what_the_constructor_refuses(defect):
    rng = np.random.default_rng(7)
    names, types, bodies, size, position, orientation = _shapes(rng)
    kwargs = dict(friction=0.5, restitution=0.0, collision_group=0)
    if defect == "size":
        size[2, 0] = -0.1
    elif defect == "padding":
        size[1, 2] = 0.3  # a capsule has two sizes
    elif defect == "nan":
        position[3, 1] = math.nan
    elif defect == "friction":
        kwargs["friction"] = -1.0
    elif defect == "restitution":
        kwargs["restitution"] = 1.5
    elif defect == "group":
        kwargs["collision_group"] = -2
    elif defect == "name":
        names[4] = ""
    else:
        orientation[5] = 0.0
    assert Shape.batch(names, types, bodies, size, position, orientation, **kwargs) is None


def _walker_spec(seed):
    from morphopt.families import load_family

    walker = load_family("walker")
    return walker.build_spec(walker.space.sample(np.random.default_rng(seed), 1)[0])


def _same_spec(a, b):
    assert type(a) is type(b) and list(vars(a)) == list(vars(b))
    for name in ("bodies", "joints", "points", "shapes"):
        x, y = getattr(a, name), getattr(b, name)
        assert len(x) == len(y)
        for u, v in zip(x, y):
            assert list(vars(u)) == list(vars(v))
            _same(u, v)
    assert a.name == b.name and a.gravity.tobytes() == b.gravity.tobytes()
    assert (a.ground is None) == (b.ground is None)
    if a.ground is not None:
        _same(a.ground, b.ground)


def test_a_spec_pickles_as_columns_and_comes_back_the_same():
    """A walker's spec (and one with odd items) pickles to less than half its item-by-item size and
    unpickles into the same items, every field bit for bit and of the same type; a subclass or an
    item with an attribute of its own pickles item by item."""
    spec = _walker_spec(1)
    blob = pickle.dumps(spec, protocol=pickle.HIGHEST_PROTOCOL)
    _same_spec(pickle.loads(blob), spec)
    plain = pickle.dumps(object.__reduce_ex__(spec, pickle.HIGHEST_PROTOCOL), protocol=pickle.HIGHEST_PROTOCOL)
    assert len(blob) < 0.6 * len(plain)
    odd = _walker_spec(2)
    odd.bodies[1].mass = np.float64(odd.bodies[1].mass)  # a NumPy scalar among floats
    odd.bodies[2].com = odd.bodies[2].com.astype(np.float32)
    odd.joints[3].limit_upper = 1.5
    odd.joints[0].drive = JointDrive(damping=2.0, target_velocity=-0.0)
    odd.points = []
    back = pickle.loads(pickle.dumps(odd))
    _same_spec(back, odd)
    assert type(back.bodies[1].mass) is np.float64 and back.bodies[2].com.dtype == np.float32
    own = _walker_spec(3)
    own.joints[4].note = "mine"
    assert pickle.loads(pickle.dumps(own)).joints[4].note == "mine"
    sub = _MySpec(own.bodies, own.joints, own.points, shapes=own.shapes, ground=own.ground)
    assert type(pickle.loads(pickle.dumps(sub))) is _MySpec


class _MySpec(MechanismSpec):
    """A subclass: pickled item by item."""
