"""Per-world health of a rollout: the worlds whose motion the engine cannot vouch for, and why.

A world is flagged (Health.flags, a bit each) when
- DIVERGED: its state turned non-finite, or a body moved faster than SolverConfig.max_speed
  (engine.integrate's guard froze it);
- FAR: it was packed with coordinates where float32's spacing exceeds
  SolverConfig.health_joint_tolerance (no joint can be closed to it there);
- JOINTS_OPEN: a record's largest linear joint error exceeds health_joint_tolerance [m], or its
  angular one health_angular_tolerance [rad] (engine.rollout checks every record);
- UNCONVERGED: the PADMM stopped unconverged (iteration cap or stall) with a residual above
  SolverConfig.health_residual (engine.rollout's per-step statistics kernel checks every step);
- EFFORT_LIMIT: a drive's torque passed its effort limit where the plan checks limits but does not
  enforce them (reduced coordinates: the world stops there).
The flags live on the device (engine.rollout.Stepper) and cost no host synchronization.
Limits measured on the CPU (mass ratio, distance from the origin): benchmarks/results/README.md,
"Limits: mass ratio and distance from the origin".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["DIVERGED", "EFFORT_LIMIT", "FAR", "Health", "JOINTS_OPEN", "UNCONVERGED", "far_flags"]

DIVERGED = wp.constant(1)
FAR = wp.constant(2)
JOINTS_OPEN = wp.constant(4)
UNCONVERGED = wp.constant(8)
EFFORT_LIMIT = wp.constant(16)
MASS_RATIO_LIMIT = 1.0e4  # documented (the README section above): a flagged world's reason names a larger ratio


def far_flags(extent: np.ndarray, tolerance: float) -> np.ndarray:
    """FAR for each world whose largest coordinate magnitude ``extent`` [m] has a float32 spacing
    above ``tolerance`` [m] (at 5 mm: from 65536 m on), else 0; int32 (W,)."""
    spacing = np.spacing(np.abs(np.asarray(extent, np.float32)))
    return np.where(spacing > np.float32(tolerance), FAR, 0).astype(np.int32)


@wp.kernel
def check_joints(
    violation_linear: wp.array(dtype=float),
    violation_angular: wp.array(dtype=float),
    diverged: wp.array(dtype=wp.int32),
    tolerance_linear: float,
    tolerance_angular: float,
    # in/out
    flags: wp.array(dtype=wp.int32),
    linear_max: wp.array(dtype=float),
    angular_max: wp.array(dtype=float),
):
    """Per world, after engine.metrics measured a state: the largest joint errors so far, and the
    JOINTS_OPEN and DIVERGED bits."""
    world = wp.tid()
    lin = violation_linear[world]
    ang = violation_angular[world]
    linear_max[world] = wp.max(linear_max[world], lin)
    angular_max[world] = wp.max(angular_max[world], ang)
    bits = flags[world]
    if lin > tolerance_linear or ang > tolerance_angular or not wp.isfinite(lin) or not wp.isfinite(ang):
        bits = bits | JOINTS_OPEN
    if diverged[world] != 0:
        bits = bits | DIVERGED
    flags[world] = bits


@wp.func
def note_residual(world: int, converged: int, iterations: int, residual: float, threshold: float,
                  flags: wp.array(dtype=wp.int32), residual_max: wp.array(dtype=float),
                  residual_iterations: wp.array(dtype=wp.int32)):
    """A solved step's PADMM outcome: an unconverged stop keeps its residual if the largest so far
    (and its iteration count), and sets UNCONVERGED above ``threshold``."""
    if converged != 0:
        return
    if residual > residual_max[world] or not wp.isfinite(residual):
        residual_max[world] = residual
        residual_iterations[world] = iterations
    if residual > threshold or not wp.isfinite(residual):
        flags[world] = flags[world] | UNCONVERGED


def _length(metres: float) -> str:
    """A length in mm below 1 m, else in m."""
    return f"{metres * 1e3:.3g} mm" if abs(metres) < 1.0 else f"{metres:.3g} m"


@dataclass
class Health:
    """The health of every world of a rollout, as NumPy arrays (W,).

    flags: the bits above (0: healthy); linear_max [m] and angular_max [rad]: largest joint errors
    over the records; residual_max: largest residual an unconverged PADMM stopped at (0: every step
    converged) and residual_iterations its iterations; extent: largest coordinate magnitude when
    packed [m]; mass_ratio: largest mass ratio of two jointed bodies; and the tolerances used.
    """

    flags: np.ndarray
    linear_max: np.ndarray
    angular_max: np.ndarray
    residual_max: np.ndarray
    residual_iterations: np.ndarray
    extent: np.ndarray
    mass_ratio: np.ndarray
    joint_tolerance: float
    angular_tolerance: float
    residual_threshold: float
    max_speed: float
    effort_detail: list | None = None  # per world: which drive passed its limit ('' or None: not known)

    @property
    def ok(self) -> np.ndarray:
        """(W,) bool: True where no flag is set."""
        return self.flags == 0

    def reason(self, world: int) -> str:
        """Why ``world`` is flagged, one clause per flag joined by '; ' ("" when healthy); a diverged
        world's open joints and solver residuals are its divergence's, not named again."""
        bits = int(self.flags[world])
        parts = []
        if bits & DIVERGED:
            parts.append(f"diverged: the state turned non-finite or a body moved faster than {self.max_speed:g} m/s")
        if bits & FAR:
            extent = float(self.extent[world])
            spacing = float(np.spacing(np.float32(extent)))
            parts.append(f"too far from the origin: coordinates reach {extent:.3g} m, where float32 resolves only "
                         f"{_length(spacing)} (joint tolerance {_length(self.joint_tolerance)})")
        if bits & DIVERGED:  # the other flags follow from it
            return "; ".join(parts)
        if bits & EFFORT_LIMIT:
            detail = self.effort_detail[world] if self.effort_detail else ""
            parts.append(f"effort limit: {detail or 'a drive'} passed its effort limit, so the world stopped there")
            return "; ".join(parts)
        if bits & JOINTS_OPEN:
            linear, angular = float(self.linear_max[world]), float(self.angular_max[world])
            if not linear <= self.joint_tolerance:
                text = (f"diverged: joints came apart by {linear:.3g} m "
                        f"(more than the {self.joint_tolerance:g} m tolerance)")
            else:
                text = (f"diverged: joints turned apart by {angular:.3g} rad "
                        f"(more than the {self.angular_tolerance:g} rad tolerance)")
            ratio = float(self.mass_ratio[world])
            if ratio > MASS_RATIO_LIMIT:
                text += (f"; its jointed bodies' masses differ by 1:{ratio:.3g}, beyond the documented "
                         f"1:{MASS_RATIO_LIMIT:g}")
            parts.append(text)
        if bits & UNCONVERGED:
            parts.append(f"solver did not converge: residual {float(self.residual_max[world]):.3g} after "
                         f"{int(self.residual_iterations[world])} iterations (threshold {self.residual_threshold:g})")
        return "; ".join(parts)

    def reasons(self) -> list[str]:
        """reason() of every world."""
        return [self.reason(w) for w in range(len(self.flags))]
