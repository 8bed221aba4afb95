"""Property tests of MechanismSpec validation and pack_worlds' input checks.

Valid random mechanisms always pass; a valid mechanism with one random defect (a non-physical
mass or inertia, a wrong vector, an unknown or duplicate name, a wrong type) always raises
ValueError naming the body, joint, point or shape at fault and the field, never another exception.
"""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from engine import Body, GroundPlane, Joint, JointDrive, JointType, MechanismSpec, Shape, TrackedPoint, pack_worlds
from engine.scenes import fourbar

SETTINGS = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])

finite = st.floats(-10.0, 10.0, allow_nan=False)
positive = st.floats(1e-3, 100.0)
non_finite = st.sampled_from([math.nan, math.inf, -math.inf])
not_a_number = st.sampled_from(["heavy", None, [1.0, 2.0], {"kg": 1.0}, 1j, object()])
NAMES = ("ground_link", "crank", "coupler", "rocker")


def rotation(angles) -> np.ndarray:
    """A rotation matrix from three angles [rad] (z, y, x)."""
    a, b, c = angles
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    return rz @ ry @ rx


angles = st.tuples(*[st.floats(-math.pi, math.pi)] * 3)


@st.composite
def inertia_tensors(draw, valid: bool):
    """R diag(moments) R^T: positive moments within the triangle inequality give a valid tensor;
    one moment <= -1e-3 of the largest (or all zero) gives a symmetric tensor that is clearly not
    positive definite."""
    moments = np.array(draw(st.lists(st.floats(1e-4, 10.0), min_size=3, max_size=3)))
    largest = int(np.argmax(moments))
    moments[largest] = min(moments[largest], moments.sum() - moments[largest])  # I_max <= sum of the others
    if not valid:
        k = draw(st.integers(0, 2))
        moments[k] = -draw(st.floats(1e-3, 1.0)) * moments.max()
        if draw(st.booleans()):
            moments[:] = 0.0
    R = rotation(draw(angles))
    tensor = R @ np.diag(moments) @ R.T
    return (tensor + tensor.T) / 2.0


@st.composite
def quaternions(draw):
    q = draw(st.lists(finite, min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 1e-3))
    return tuple(q)


@st.composite
def axes(draw):
    return tuple(draw(st.lists(finite, min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-3)))


@st.composite
def valid_mechanisms(draw):
    """Keyword arguments of a valid random mechanism: 1 to 4 bodies, joints between distinct
    bodies (or the world), drives and ordered limits on drivable joints only, points and shapes."""
    count = draw(st.integers(1, 4))
    names = NAMES[:count]
    bodies = [{"name": n, "mass": draw(positive), "inertia": draw(inertia_tensors(valid=True)),
               "com": tuple(draw(st.lists(finite, min_size=3, max_size=3))), "orientation": draw(quaternions())}
              for n in names]
    joints = []
    for k in range(draw(st.integers(0, 4))):
        child = draw(st.sampled_from(names))
        parent = draw(st.sampled_from([None, *[n for n in names if n != child]]))
        kind = draw(st.sampled_from(list(JointType)))
        joint = {"name": f"j{k}", "type": draw(st.sampled_from([kind, kind.name.lower()])), "parent": parent,
                 "child": child, "axis": draw(axes()),
                 "parent_position": tuple(draw(st.lists(finite, min_size=3, max_size=3)))}
        if kind in (JointType.REVOLUTE, JointType.PRISMATIC):
            low, high = sorted(draw(st.lists(finite, min_size=2, max_size=2)))
            joint.update(limit_lower=low, limit_upper=high, armature=draw(st.floats(0.0, 1.0)),
                         drive={"stiffness": draw(st.floats(0.0, 1e3)), "damping": draw(st.floats(0.0, 10.0)),
                                "effort_limit": draw(st.floats(1e-3, 1e3) | st.just(math.inf))})
        joints.append(joint)
    points = [{"name": "tip", "body": draw(st.sampled_from(names)), "position": (0.1, 0.0, 0.0)}]
    shapes = [{"name": "ball", "type": "sphere", "body": names[0], "size": draw(st.floats(1e-3, 1.0)),
               "restitution": draw(st.floats(0.0, 1.0)), "collision_group": draw(st.integers(0, 3))}]
    return {"bodies": bodies, "joints": joints, "points": points, "shapes": shapes}


def build(kwargs) -> MechanismSpec:
    """The MechanismSpec of keyword dicts (bodies, joints with drives, points, shapes)."""
    joints = [dict(j, drive=JointDrive(**j["drive"])) if isinstance(j.get("drive"), dict) else j
              for j in kwargs["joints"]]
    return MechanismSpec([Body(**b) for b in kwargs["bodies"]], [Joint(**j) for j in joints],
                         [TrackedPoint(**p) for p in kwargs["points"]], shapes=[Shape(**s) for s in kwargs["shapes"]],
                         ground=GroundPlane())


def base() -> dict:
    """A valid four-bar-like mechanism as keyword dicts: the one every defect is applied to."""
    bodies = [{"name": n, "mass": 1.0, "inertia": (0.01, 0.02, 0.03)} for n in ("crank", "coupler", "rocker")]
    joints = [{"name": "motor", "type": "revolute", "parent": None, "child": "crank", "axis": (0, 1, 0),
               "drive": {"damping": 1.0, "target_velocity": 6.0, "effort_limit": 5.0}},
              {"name": "elbow", "type": "revolute", "parent": "crank", "child": "coupler", "axis": (0, 1, 0)},
              {"name": "knee", "type": "revolute", "parent": "coupler", "child": "rocker", "axis": (0, 1, 0),
               "limit_lower": -1.0, "limit_upper": 1.0},
              {"name": "pivot", "type": "inline", "parent": None, "child": "rocker", "axis": (0, 1, 0)}]
    points = [{"name": "tip", "body": "coupler", "position": (0.1, 0.0, 0.0)}]
    shapes = [{"name": "foot", "type": "capsule", "body": "rocker", "size": (0.01, 0.05)}]
    return {"bodies": bodies, "joints": joints, "points": points, "shapes": shapes}


VECTOR_FIELDS = {"bodies": ("com", "position", "velocity", "angular_velocity", "orientation"),
                 "joints": ("parent_position", "child_position", "parent_orientation", "child_orientation", "axis",
                            "axis2"),
                 "points": ("position",), "shapes": ("position", "orientation")}


@st.composite
def wrong_vectors(draw, size: int):
    """A vector of the wrong length, with a non-finite entry, or not numbers at all."""
    return draw(st.one_of(
        st.lists(finite, min_size=0, max_size=6).filter(lambda v: len(v) != size).map(tuple),
        st.tuples(*[finite] * (size - 1), non_finite).map(lambda v: v[-1:] + v[:-1]),
        not_a_number, st.text(max_size=5)))


@st.composite
def defects(draw):
    """(kind, index, field, bad value, fragments the message must contain) for one defect of base()."""
    spec = base()
    kind = draw(st.sampled_from(["bodies", "joints", "points", "shapes"]))
    index = draw(st.integers(0, len(spec[kind]) - 1))
    item = spec[kind][index]["name"]
    choice = draw(st.sampled_from(["vector", "scalar", "name", "reference"]))
    if choice == "vector":
        field = draw(st.sampled_from(VECTOR_FIELDS[kind]))
        return kind, index, field, draw(wrong_vectors(4 if "orientation" in field else 3)), (item, field)
    if choice == "name":  # an empty or non-string name, or the name of another item of the list
        others = [x["name"] for k, x in enumerate(spec[kind]) if k != index]
        bad = draw(st.sampled_from(["", None, 7, *others]))
        return kind, index, "name", bad, (("duplicate", bad) if bad in others else ("name",))
    if choice == "reference":  # an unknown body name, or not a name at all
        field = {"bodies": "name", "joints": draw(st.sampled_from(["parent", "child"])), "points": "body",
                 "shapes": "body"}[kind]
        if kind == "bodies":  # a joint naming a body that is not there
            kind, index, item, field = "joints", 1, "elbow", "child"
        bad = draw(st.text(min_size=1, max_size=8).filter(lambda t: t not in ("crank", "coupler", "rocker"))
                   | st.sampled_from([["crank"], 3.5]))
        return kind, index, field, bad, (item, field if not isinstance(bad, str) else bad)
    scalars = {"bodies": ["mass", "inertia"], "joints": ["armature", "damping", "limit_lower", "type"],
               "points": ["position"], "shapes": ["size", "friction", "restitution", "collision_group"]}
    field = draw(st.sampled_from(scalars[kind]))
    bad = draw({  # a non-physical or non-numeric value for a scalar field
        "position": not_a_number,
        "mass": st.floats(max_value=0.0) | non_finite | not_a_number,
        "inertia": (inertia_tensors(valid=False) | st.just([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0, 0, 1.0]])
                    | wrong_vectors(3) | st.just([[1.0, 0.0], [0.0, 1.0]])),
        "armature": st.floats(max_value=-1e-9) | non_finite | not_a_number,
        "damping": st.floats(max_value=-1e-9) | non_finite | not_a_number,
        "limit_lower": st.floats(1.5, 1e6) if index == 2 else st.just(math.nan) | not_a_number,
        "type": (st.text(max_size=8).filter(lambda t: t.upper() not in JointType.__members__)
                 | st.sampled_from([None, 1.5, 99, ["revolute"]])),
        "size": (st.tuples(st.floats(max_value=0.0), positive) | st.tuples(positive, non_finite)
                 | st.just((0.1, 0.2, 0.3)) | positive | st.sampled_from(["heavy", None, {"m": 0.1}, 1j])),
        "friction": st.floats(max_value=-1e-9) | non_finite | not_a_number,
        "restitution": st.floats(1.0 + 1e-9, 1e6) | st.floats(max_value=-1e-9) | non_finite,
        "collision_group": st.integers(max_value=-1) | st.floats(0.1, 0.9) | non_finite | not_a_number,
    }[field])
    return kind, index, field, bad, (item, field if field != "limit_lower" or index != 2 else "limit")


@SETTINGS
@given(valid_mechanisms())
def test_valid_random_mechanisms_pass(kwargs):
    """Positive masses, positive definite inertias, joints between existing bodies with non-zero
    axes and ordered limits: the spec is created and keeps every body and joint."""
    spec = build(kwargs)
    assert [b.name for b in spec.bodies] == [b["name"] for b in kwargs["bodies"]]
    assert len(spec.joints) == len(kwargs["joints"])
    for body in spec.bodies:
        assert np.linalg.eigvalsh(body.inertia).min() > 0.0 and abs(np.linalg.norm(body.orientation) - 1.0) < 1e-12


@SETTINGS
@given(defects())
def test_one_defect_raises_value_error_naming_item_and_field(defect):
    """One defect anywhere in a valid mechanism raises ValueError (never another exception type)
    whose message names the item (body, joint, point or shape) and the field or unknown name."""
    kind, index, field, bad, fragments = defect
    kwargs = base()
    kwargs[kind][index][field] = bad
    with pytest.raises(ValueError) as error:
        build(kwargs)
    message = str(error.value)
    for fragment in fragments:
        assert str(fragment) in message, (fragment, message)


@SETTINGS
@given(st.sampled_from(["bodies", "joints", "points", "shapes"]),
       st.sampled_from([None, 3, "crank", {"name": "crank"}, [None], [{"name": "crank"}]]))
def test_wrong_item_types_are_named(kind, bad):
    """A list of the wrong things (or no list) raises ValueError naming the list and the expected type."""
    spec = base()
    items = {"bodies": [Body(**b) for b in spec["bodies"]], "joints": [], "points": [], "shapes": []}
    items[kind] = bad
    with pytest.raises(ValueError, match=r"mechanism 'mechanism'") as error:
        MechanismSpec(items["bodies"], items["joints"], items["points"], shapes=items["shapes"])
    expected = {"bodies": "body", "joints": "joint", "points": "tracked point", "shapes": "shape"}[kind]
    assert f"{expected} list" in str(error.value)


@pytest.mark.parametrize("case, message", [
    ("empty list", "needs at least one MechanismSpec"),
    ("a string", "specs must be a list of MechanismSpec, got str"),
    ("None", "specs must be a list of MechanismSpec, got NoneType"),
    ("one spec", "specs must be a list of MechanismSpec, got MechanismSpec"),
    ("spec then dict", "world 1 is a dict, expected MechanismSpec"),
])
def test_pack_worlds_names_the_bad_world(case, message):
    """pack_worlds refuses anything but a non-empty list of MechanismSpec, naming the world's index."""
    spec = fourbar().spec
    specs = {"empty list": [], "a string": "fourbar", "None": None, "one spec": spec, "spec then dict": [spec, {}]}
    with pytest.raises(ValueError, match="pack_worlds: " + message):
        pack_worlds(specs[case], device="cpu")


@pytest.mark.parametrize("kwargs, message", [
    ({"dt": 0.0}, r"dt must be a positive finite time step \[s\], got 0.0"),
    ({"dt": -1e-3}, r"dt must be a positive finite time step"),
    ({"dt": math.nan}, r"dt must be a positive finite time step"),
    ({"dt": math.inf}, r"dt must be a positive finite time step"),
    ({"dt": "fast"}, r"dt must be a positive finite time step \[s\], got 'fast'"),
    ({"dt": None}, r"dt must be a positive finite time step"),
    ({"device": "gpu"}, r"device 'gpu' is not available \('cpu', 'cuda' or 'cuda:N'\)"),
    ({"device": "cuda:99"}, r"device 'cuda:99' is not available"),
    ({"contact_capacity": -1}, r"contact_capacity must be a non-negative integer, got -1"),
    ({"contact_capacity": 2.5}, r"contact_capacity must be a non-negative integer, got 2.5"),
    ({"contact_capacity": "4"}, r"contact_capacity must be a non-negative integer, got '4'"),
    ({"config": {"tolerance": 1e-6}}, r"config must be a SolverConfig, got dict"),
])
def test_pack_worlds_names_the_bad_parameter(kwargs, message):
    """A bad time step, device, contact capacity or config raises ValueError naming the parameter and the value."""
    kwargs = {"device": "cpu", **kwargs}
    with pytest.raises(ValueError, match=r"pack_worlds: " + message):
        pack_worlds([fourbar().spec], **kwargs)
