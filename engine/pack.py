"""pack_worlds: turn a list of MechanismSpec (all different, if you like) into one padded Model."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import warp as wp

from engine.model import Model, SolverConfig, Workspace
from engine.spec import JOINT_ROW_COUNT, JointType, MechanismSpec, joint_dynamics_rows

__all__ = ["pack_worlds"]

ROW_KINDS = {  # bilateral row kinds per joint type: 0 linear [m], 1 angular [rad]
    JointType.REVOLUTE: (0, 0, 0, 1, 1),
    JointType.PRISMATIC: (0, 0, 1, 1, 1),
    JointType.SPHERICAL: (0, 0, 0),
    JointType.UNIVERSAL: (0, 0, 0, 1),
    JointType.CYLINDRICAL: (0, 0, 1, 1),
    JointType.FIXED: (0, 0, 0, 1, 1, 1),
}
ROW_TILE = 8  # the padded row count is a multiple of this (tile size of the Delassus matrix)


def _rotate(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Rotate vec by the unit quaternion (x, y, z, w)."""
    u, s = quat[:3], quat[3]
    return vec + 2.0 * np.cross(u, np.cross(u, vec) + s * vec)


def pack_worlds(specs: Sequence[MechanismSpec], device=None, *, config: SolverConfig | None = None,
                dt: float = 1.0e-3) -> Model:
    """Pack one world per spec into a padded batch on ``device``.

    Args:
        specs: the worlds; they may differ in bodies, joints and constraint rows.
        device: Warp device ("cpu", "cuda", "cuda:0", ...); None = Warp's default.
        config: SolverConfig (default settings when None).
        dt: initial time step of every world [s] (change it with Model.set_dt or step()).

    Returns:
        Model with arrays of shape (num_worlds, max_X) and per-world counts.
    """
    specs = list(specs)
    if not specs:
        raise ValueError("pack_worlds: needs at least one MechanismSpec")
    for index, spec in enumerate(specs):
        if not isinstance(spec, MechanismSpec):
            raise ValueError(f"pack_worlds: world {index} is a {type(spec).__name__}, expected MechanismSpec")
    config = config or SolverConfig()
    if not isinstance(config, SolverConfig):
        raise ValueError(f"pack_worlds: config must be a SolverConfig, got {type(config).__name__}")
    device = wp.get_device(device)

    num_worlds = len(specs)
    max_bodies = max(len(s.bodies) for s in specs)
    max_joints = max(1, max(len(s.joints) for s in specs))
    max_points = max(1, max(len(s.points) for s in specs))
    max_rows = max(1, max(s.row_count for s in specs))
    max_rows = ROW_TILE * ((max_rows + ROW_TILE - 1) // ROW_TILE)

    W, B, J, R, P = num_worlds, max_bodies, max_joints, max_rows, max_points
    f32 = np.float32
    h = {
        "body_count": np.zeros(W, np.int32), "joint_count": np.zeros(W, np.int32),
        "row_count": np.zeros(W, np.int32), "point_count": np.zeros(W, np.int32),
        "body_mass": np.zeros((W, B), f32), "body_inv_mass": np.zeros((W, B), f32),
        "body_inertia": np.tile(np.eye(3, dtype=f32), (W, B, 1, 1)),
        "body_inv_inertia": np.tile(np.eye(3, dtype=f32), (W, B, 1, 1)),
        "body_q_init": np.tile(np.array([0, 0, 0, 0, 0, 0, 1], f32), (W, B, 1)),
        "body_qd_init": np.zeros((W, B, 6), f32),
        "joint_type": np.zeros((W, J), np.int32), "joint_parent": np.full((W, J), -1, np.int32),
        "joint_child": np.zeros((W, J), np.int32),
        "joint_X_p": np.tile(np.array([0, 0, 0, 0, 0, 0, 1], f32), (W, J, 1)),
        "joint_X_c": np.tile(np.array([0, 0, 0, 0, 0, 0, 1], f32), (W, J, 1)),
        "joint_axis": np.zeros((W, J, 3), f32), "joint_axis2": np.zeros((W, J, 3), f32),
        "joint_row_start": np.zeros((W, J), np.int32), "joint_inertia_row": np.full((W, J), -1, np.int32),
        "joint_drive_row": np.full((W, J), -1, np.int32),
        "joint_armature": np.zeros((W, J), f32), "joint_damping": np.zeros((W, J), f32),
        "joint_stiffness": np.zeros((W, J), f32), "joint_drive_damping": np.zeros((W, J), f32),
        "joint_effort_limit": np.full((W, J), 1.0e30, f32),
        "joint_target_position_init": np.zeros((W, J), f32),
        "joint_target_velocity_init": np.zeros((W, J), f32),
        "row_kind": np.zeros((W, R), np.int32), "row_body_p": np.full((W, R), -1, np.int32),
        "row_body_c": np.full((W, R), -1, np.int32),
        "world_gravity": np.zeros((W, 3), f32), "world_dt": np.full(W, dt, f32),
        "point_body": np.zeros((W, P), np.int32), "point_local": np.zeros((W, P, 3), f32),
        "padmm_eta": np.full(W, config.eta, f32), "padmm_rho_init": np.full(W, config.rho, f32),
        "padmm_tolerance": np.full(W, config.tolerance, f32),
    }
    for w, spec in enumerate(specs):
        index = spec.body_index
        coms = [body.com for body in spec.bodies]
        h["body_count"][w] = len(spec.bodies)
        h["joint_count"][w] = len(spec.joints)
        h["point_count"][w] = len(spec.points)
        h["world_gravity"][w] = spec.gravity
        for b, body in enumerate(spec.bodies):
            h["body_mass"][w, b] = body.mass
            h["body_inv_mass"][w, b] = 1.0 / body.mass
            h["body_inertia"][w, b] = body.inertia
            h["body_inv_inertia"][w, b] = np.linalg.inv(body.inertia)
            com_world = body.position + _rotate(body.orientation, body.com)
            h["body_q_init"][w, b] = np.concatenate([com_world, body.orientation])
            h["body_qd_init"][w, b] = np.concatenate([body.velocity, body.angular_velocity])
        row = 0
        for j, joint in enumerate(spec.joints):
            parent = -1 if joint.parent is None else index[joint.parent]
            child = index[joint.child]
            parent_com = np.zeros(3) if parent < 0 else coms[parent]
            h["joint_type"][w, j] = int(joint.type)
            h["joint_parent"][w, j] = parent
            h["joint_child"][w, j] = child
            h["joint_X_p"][w, j] = np.concatenate([joint.parent_position - parent_com, joint.parent_orientation])
            h["joint_X_c"][w, j] = np.concatenate([joint.child_position - coms[child], joint.child_orientation])
            h["joint_axis"][w, j] = joint.axis
            h["joint_axis2"][w, j] = joint.axis2
            h["joint_row_start"][w, j] = row
            kinds = ROW_KINDS[joint.type]
            assert len(kinds) == JOINT_ROW_COUNT[joint.type]
            for kind in kinds:
                h["row_kind"][w, row], h["row_body_p"][w, row], h["row_body_c"][w, row] = kind, parent, child
                row += 1
            h["joint_armature"][w, j] = joint.armature
            h["joint_damping"][w, j] = joint.damping
            if joint.drive is not None:
                h["joint_stiffness"][w, j] = joint.drive.stiffness
                h["joint_drive_damping"][w, j] = joint.drive.damping
                h["joint_effort_limit"][w, j] = min(joint.drive.effort_limit, 1.0e30)
                h["joint_target_position_init"][w, j] = joint.drive.target_position
                h["joint_target_velocity_init"][w, j] = joint.drive.target_velocity
            for name, present in zip(("joint_inertia_row", "joint_drive_row"), joint_dynamics_rows(joint)):
                if present:
                    h[name][w, j] = row
                    h["row_kind"][w, row], h["row_body_p"][w, row], h["row_body_c"][w, row] = 2, parent, child
                    row += 1
        h["row_count"][w] = row
        for p, point in enumerate(spec.points):
            b = index[point.body]
            h["point_body"][w, p] = b
            h["point_local"][w, p] = point.position - coms[b]

    model = Model()
    model.device = device
    model.config = config
    model.specs = specs
    model.num_worlds, model.max_bodies, model.max_joints = W, B, J
    model.max_rows, model.max_points = R, P
    model.body_names = [[b.name for b in s.bodies] for s in specs]
    model.joint_names = [[j.name for j in s.joints] for s in specs]
    model.point_names = [[p.name for p in s.points] for s in specs]
    dtypes = {
        "body_inertia": wp.mat33, "body_inv_inertia": wp.mat33, "body_q_init": wp.transform,
        "body_qd_init": wp.spatial_vector, "joint_X_p": wp.transform, "joint_X_c": wp.transform,
        "joint_axis": wp.vec3, "joint_axis2": wp.vec3, "world_gravity": wp.vec3, "point_local": wp.vec3,
    }
    for name, value in h.items():
        dtype = dtypes.get(name, wp.int32 if value.dtype == np.int32 else float)
        setattr(model, name, wp.array(value, dtype=dtype, device=device))
    model._dt_host = h["world_dt"].copy()
    model.work = Workspace(W, B, R, device)
    return model
