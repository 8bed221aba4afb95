"""Per-world diagnostics, cheap enough for every step: constraint violation, energy, solver stats."""

from __future__ import annotations

import numpy as np
import warp as wp

from engine.joints import compute_joint_residuals
from engine.model import ROW_ANGULAR, ROW_LINEAR, Model, State

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["compute_metrics", "metrics_numpy"]


@wp.kernel
def world_metrics(
    # model
    body_count: wp.array(dtype=wp.int32),
    row_count: wp.array(dtype=wp.int32),
    row_kind: wp.array2d(dtype=wp.int32),
    body_mass: wp.array2d(dtype=float),
    body_inertia: wp.array2d(dtype=wp.mat33),
    world_gravity: wp.array(dtype=wp.vec3),
    # in
    body_q: wp.array2d(dtype=wp.transform),
    body_qd: wp.array2d(dtype=wp.spatial_vector),
    row_residual: wp.array2d(dtype=float),
    # out
    violation_linear_out: wp.array(dtype=float),
    violation_angular_out: wp.array(dtype=float),
    energy_out: wp.array(dtype=float),
):
    """Max |phi| over linear [m] and angular [rad] joint rows; kinetic + gravitational energy [J]."""
    world = wp.tid()
    lin = float(0.0)
    ang = float(0.0)
    for i in range(row_count[world]):
        kind = row_kind[world, i]
        if kind == ROW_LINEAR:
            lin = wp.max(lin, wp.abs(row_residual[world, i]))
        elif kind == ROW_ANGULAR:
            ang = wp.max(ang, wp.abs(row_residual[world, i]))
    energy = float(0.0)
    g = world_gravity[world]
    for b in range(body_count[world]):
        X = body_q[world, b]
        u = body_qd[world, b]
        m = body_mass[world, b]
        v = wp.spatial_top(u)
        w_body = wp.quat_rotate_inv(wp.transform_get_rotation(X), wp.spatial_bottom(u))
        energy += 0.5 * m * wp.dot(v, v) + 0.5 * wp.dot(w_body, body_inertia[world, b] * w_body)
        energy -= m * wp.dot(g, wp.transform_get_translation(X))
    violation_linear_out[world] = lin
    violation_angular_out[world] = ang
    energy_out[world] = energy


def compute_metrics(model: Model, state: State) -> None:
    """Fill model.work.violation_linear [m], violation_angular [rad] and energy [J] for state."""
    work = model.work
    compute_joint_residuals(model, state.body_q, work.row_residual)
    wp.launch(world_metrics, dim=model.num_worlds, device=model.device,
              inputs=[model.body_count, model.row_count, model.row_kind, model.body_mass, model.body_inertia,
                      model.world_gravity, state.body_q, state.body_qd, work.row_residual],
              outputs=[work.violation_linear, work.violation_angular, work.energy])


def metrics_numpy(model: Model) -> dict[str, np.ndarray]:
    """The per-world metrics and solver statistics of the last step/compute_metrics, as NumPy (W,)."""
    work = model.work
    names = ("violation_linear", "violation_angular", "energy", "iterations", "converged", "diverged",
             "residual_primal", "residual_dual")
    return {name: getattr(work, name).numpy().copy() for name in names}
