"""The spanning tree the tree formats share: every body once, loops closed by the rest."""

import numpy as np
import pytest

from engine import Body, Joint, JointDrive, MechanismSpec
from morphopt.families import load_family
from morphopt.formats.tree import initial_coordinate, matrix_to_quat, quat_to_matrix, spanning_tree
from morphopt.linkage.to_spec import to_spec


@pytest.mark.parametrize("family", ["four_bar", "jansen_leg", "klann_leg", "watt_sixbar"])
def test_linkage_trees_span_every_body_and_keep_the_drive(family):
    module = load_family(family)
    spec = to_spec(module.generate(module.space.default()))
    tree = spanning_tree(spec)
    assert sorted(tree.order) == sorted(b.name for b in spec.bodies) and not tree.roots
    assert len(tree.tree) + len(tree.loops) == len(spec.joints)
    # a loop per independent cycle: joints - bodies (each body has one tree joint)
    assert len(tree.loops) == len(spec.joints) - len(spec.bodies)
    driven = [j for j in spec.joints if j.drive is not None]
    assert driven and all(any(t.joint is j for t in tree.tree.values()) for j in driven)
    assert all(j.type.name == "INLINE" for j in tree.loops)  # the linkage's loop closures stay closures
    placed = {None}
    for body in tree.order:  # every body comes after its tree parent
        assert tree.tree[body].parent in placed
        placed.add(body)


def test_floating_component_is_rooted_at_its_heaviest_body_and_reversed_joints_are_marked():
    bodies = [Body("leg", 1.0, [0.1, 0.1, 0.1]), Body("pelvis", 5.0, [1, 1, 1]), Body("foot", 0.5, [0.1] * 3)]
    joints = [Joint("hip", "revolute", "leg", "pelvis"), Joint("ankle", "revolute", "leg", "foot")]
    tree = spanning_tree(MechanismSpec(bodies, joints))
    assert tree.roots == ["pelvis"] and tree.order[0] == "pelvis"
    assert tree.tree["leg"].reversed and tree.tree["leg"].parent == "pelvis"
    assert not tree.tree["foot"].reversed and not tree.loops


def test_a_spherical_tree_joint_is_refused_by_name():
    bodies = [Body("a", 1.0, [1, 1, 1]), Body("b", 1.0, [1, 1, 1])]
    with pytest.raises(ValueError, match="joint 'ball'"):
        spanning_tree(MechanismSpec(bodies, [Joint("ball", "spherical", "a", "b")]))


def test_quaternion_helpers_and_the_initial_coordinate():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quat_to_matrix(q)
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R)
    angle = 0.7
    child = (0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2))
    spec = MechanismSpec([Body("a", 1.0, [1, 1, 1]), Body("b", 1.0, [1, 1, 1], orientation=child)],
                         [Joint("j", "revolute", "a", "b", drive=JointDrive(stiffness=1.0))])
    assert np.isclose(initial_coordinate(spec, spec.joints[0]), angle)
