"""Per-world diagnostics, cheap enough for every step: constraint violation, energy, solver stats."""

from __future__ import annotations

import numpy as np
import warp as wp

from engine.dynamics import spring_potential_of
from engine.joints import compute_joint_residuals
from engine.model import ROW_ANGULAR, ROW_LINEAR, ForceArrays, Model, ModelArrays, State, WorkArrays

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["compute_metrics", "metrics_numpy"]


@wp.kernel
def world_metrics(m: ModelArrays, fa: ForceArrays, w: WorkArrays, body_q: wp.array2d(dtype=wp.transform),
                  body_qd: wp.array2d(dtype=wp.spatial_vector)):
    """Max |phi| over linear [m] and angular [rad] joint rows of w.row_residual; kinetic,
    gravitational and spring energy [J] of body_q, body_qd (engine.forces' springs: their
    potentials); into w.violation_linear, violation_angular, energy."""
    world = wp.tid()
    lin = float(0.0)
    ang = float(0.0)
    for i in range(m.row_count[world]):
        kind = m.row_kind[world, i]
        if kind == ROW_LINEAR:
            lin = wp.max(lin, wp.abs(w.row_residual[world, i]))
        elif kind == ROW_ANGULAR:
            ang = wp.max(ang, wp.abs(w.row_residual[world, i]))
    energy = float(0.0)
    g = m.world_gravity[world]
    for b in range(m.body_count[world]):
        X = body_q[world, b]
        u = body_qd[world, b]
        mass = m.body_mass[world, b]
        v = wp.spatial_top(u)
        w_body = wp.quat_rotate_inv(wp.transform_get_rotation(X), wp.spatial_bottom(u))
        energy += 0.5 * mass * wp.dot(v, v) + 0.5 * wp.dot(w_body, m.body_inertia[world, b] * w_body)
        energy -= mass * wp.dot(g, wp.transform_get_translation(X))
    for k in range(fa.force_count[world]):
        energy += spring_potential_of(world, k, m, fa, body_q, w.no_low)
    w.violation_linear[world] = lin
    w.violation_angular[world] = ang
    w.energy[world] = energy


def compute_metrics(model: Model, state: State) -> None:
    """Fill model.work.violation_linear [m], violation_angular [rad] and energy [J] for state."""
    compute_joint_residuals(model, state.body_q, model.work.row_residual)
    wp.launch(world_metrics, dim=model.num_worlds, device=model.device,
              inputs=[model.arrays, model.force_arrays, model.work.arrays, state.body_q, state.body_qd])


def metrics_numpy(model: Model) -> dict[str, np.ndarray]:
    """The per-world metrics and solver statistics of the last step/compute_metrics, as NumPy (W,)."""
    work = model.work
    names = ("violation_linear", "violation_angular", "energy", "iterations", "converged", "diverged",
             "residual_primal", "residual_dual")
    return {name: getattr(work, name).numpy().copy() for name in names}
