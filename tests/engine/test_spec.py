"""Validation of MechanismSpec, pack_worlds and SolverConfig: bad input names the offending item."""

import math

import numpy as np
import pytest

from engine import Body, Joint, JointDrive, MechanismSpec, SolverConfig, Tuning, pack_worlds
from engine.scenes import fourbar


def body(name="b", **kw):
    return Body(name, kw.pop("mass", 1.0), kw.pop("inertia", (0.1, 0.1, 0.1)), **kw)


def test_negative_mass_names_body_and_field():
    """A body with negative mass is rejected, naming the body and the field."""
    with pytest.raises(ValueError, match=r"body 'crank'.*mass"):
        body("crank", mass=-1.0)


def test_zero_mass_rejected():
    """A dynamic body needs positive mass."""
    with pytest.raises(ValueError, match=r"body 'link'.*mass.*> 0"):
        body("link", mass=0.0)


def test_non_positive_definite_inertia_rejected():
    """An inertia tensor with a negative eigenvalue is rejected."""
    with pytest.raises(ValueError, match=r"body 'rocker'.*positive definite"):
        body("rocker", inertia=np.diag([1.0, -0.1, 1.0]))


def test_asymmetric_inertia_rejected():
    """An inertia tensor must be symmetric."""
    with pytest.raises(ValueError, match=r"body 'b'.*symmetric"):
        body(inertia=[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]])


@pytest.mark.parametrize("field,value", [("mass", math.nan), ("position", (0, math.inf, 0)),
                                         ("velocity", (math.nan, 0, 0)), ("com", (0, 0, math.nan))])
def test_non_finite_body_values_rejected(field, value):
    """NaN or infinite body values are rejected, naming the body and the field."""
    kwargs = {field: value}
    with pytest.raises(ValueError, match=rf"body 'b'.*{field}"):
        body(**kwargs)


def test_joint_naming_missing_body():
    """A joint whose child does not exist names the joint and the missing body."""
    with pytest.raises(ValueError, match=r"joint 'hinge'.*child body 'ghost' does not exist"):
        MechanismSpec([body("a")], [Joint("hinge", "revolute", None, "ghost")])


def test_zero_axis_rejected():
    """A joint axis of zero length is rejected."""
    with pytest.raises(ValueError, match=r"joint 'hinge'.*axis must be non-zero"):
        Joint("hinge", "revolute", None, "a", axis=(0, 0, 0))


def test_non_finite_joint_anchor_rejected():
    """A NaN anchor position names the joint and the field."""
    with pytest.raises(ValueError, match=r"joint 'hinge'.*parent_position"):
        Joint("hinge", "revolute", None, "a", parent_position=(0, math.nan, 0))


def test_unknown_joint_type_rejected():
    """An unknown joint type lists the valid ones."""
    with pytest.raises(ValueError, match=r"joint 'j'.*revolute"):
        Joint("j", "hinge", None, "a")


def test_drive_on_spherical_joint_rejected():
    """Drives need a revolute or prismatic joint."""
    with pytest.raises(ValueError, match=r"joint 'ball'.*revolute or prismatic"):
        Joint("ball", "spherical", None, "a", drive=JointDrive(stiffness=1.0))


def test_negative_drive_gain_rejected():
    """A negative drive stiffness is rejected, naming the joint."""
    with pytest.raises(ValueError, match=r"joint 'motor'.*stiffness"):
        Joint("motor", "revolute", None, "a", drive=JointDrive(stiffness=-5.0))


def test_duplicate_body_names_rejected():
    """Body names are unique within a mechanism."""
    with pytest.raises(ValueError, match=r"duplicate body name 'a'"):
        MechanismSpec([body("a"), body("a")])


def test_duplicate_joint_names_rejected():
    """Joint names are unique within a mechanism."""
    with pytest.raises(ValueError, match=r"duplicate joint name 'j'"):
        MechanismSpec([body("a"), body("b")], [Joint("j", "revolute", None, "a"), Joint("j", "revolute", "a", "b")])


def test_self_joint_rejected():
    """A joint cannot connect a body to itself."""
    with pytest.raises(ValueError, match=r"joint 'j'.*same body"):
        Joint("j", "fixed", "a", "a")


def test_pack_rejects_empty_and_foreign_input():
    """pack_worlds needs MechanismSpecs and says which world is wrong."""
    with pytest.raises(ValueError, match="at least one"):
        pack_worlds([], device="cpu")
    with pytest.raises(ValueError, match="world 1 is a dict"):
        pack_worlds([fourbar().spec, {}], device="cpu")


def test_solver_config_rejects_bad_values():
    """SolverConfig names the invalid field."""
    with pytest.raises(ValueError, match="max_iterations"):
        SolverConfig(max_iterations=0)
    with pytest.raises(ValueError, match="integrator"):
        SolverConfig(integrator="rk4")
    with pytest.raises(ValueError, match="sparse_ordering"):
        SolverConfig(tuning=Tuning(sparse_ordering="nested_dissection"))


def test_row_layout_of_fourbar():
    """Four revolute joints give 4 x 5 bilateral rows; the padded count is a multiple of 8."""
    spec = fourbar().spec
    assert spec.row_count == 20
    model = pack_worlds([spec], device="cpu")
    assert model.row_count.numpy()[0] == 20 and model.max_rows == 24


def test_shape_with_wrong_size_count_rejected():
    """A box needs three half extents; the error names the shape."""
    from engine import Shape

    with pytest.raises(ValueError, match=r"shape 'foot'.*box needs 3"):
        Shape("foot", "box", "b", (0.1, 0.1))


def test_shape_with_non_positive_radius_rejected():
    """A sphere's radius must be positive."""
    from engine import Shape

    with pytest.raises(ValueError, match=r"shape 'ball'.*positive"):
        Shape("ball", "sphere", "b", (-0.1,))


def test_restitution_above_one_rejected():
    """Restitution is a coefficient in [0, 1]."""
    from engine import GroundPlane, Shape

    with pytest.raises(ValueError, match=r"shape 'ball'.*restitution"):
        Shape("ball", "sphere", "b", (0.1,), restitution=1.5)
    with pytest.raises(ValueError, match=r"ground plane.*restitution"):
        GroundPlane(restitution=2.0)


def test_shape_on_missing_body_rejected():
    """A shape must sit on a body of the mechanism."""
    from engine import Shape

    with pytest.raises(ValueError, match=r"shape 'ball'.*body 'ghost' does not exist"):
        MechanismSpec([body("a")], shapes=[Shape("ball", "sphere", "ghost", (0.1,))])


def test_inverted_or_misplaced_limits_rejected():
    """limit_lower above limit_upper, or limits on a spherical joint, are rejected."""
    with pytest.raises(ValueError, match=r"joint 'knee'.*limit_lower"):
        Joint("knee", "revolute", None, "a", limit_lower=1.0, limit_upper=0.5)
    with pytest.raises(ValueError, match=r"joint 'ball'.*limits need a revolute or prismatic"):
        Joint("ball", "spherical", None, "a", limit_lower=-1.0)


def test_negative_contact_capacity_rejected():
    """pack_worlds refuses a negative contact capacity."""
    with pytest.raises(ValueError, match="contact_capacity"):
        pack_worlds([fourbar().spec], device="cpu", contact_capacity=-1)
