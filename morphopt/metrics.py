"""Metrics of mechanism paths and rollouts: pure NumPy functions, no engine, no optimizer.

Paths are arrays (N, 2) of planar points [m] sampled over one crank cycle at equal crank-angle
steps (closed curves: sample N+1 would equal sample 0).
"""

from __future__ import annotations

import numpy as np

__all__ = ["path_error", "resample_closed", "stride_and_step_height", "torque_stats"]


def resample_closed(path: np.ndarray, count: int) -> np.ndarray:
    """``count`` points equally spaced by arc length along the closed polyline ``path`` (N, 2)."""
    closed = np.vstack([path, path[:1]])
    segment = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(segment)])
    if s[-1] <= 0.0:
        return np.repeat(path[:1], count, axis=0)
    targets = np.linspace(0.0, s[-1], count, endpoint=False)
    return np.stack([np.interp(targets, s, closed[:, k]) for k in range(2)], axis=1)


def path_error(path: np.ndarray, target: np.ndarray, *, samples: int = 128) -> float:
    """RMS distance [m] between a closed path and a closed target curve.

    Rule for phase and sampling: both curves are resampled to ``samples`` points equally spaced
    by arc length (so the crank's speed profile along the path does not matter), then the error is
    the smallest RMS distance over every cyclic shift of the path's starting point and both
    directions of travel. Returns inf for a path containing NaN (infeasible design).
    """
    if not np.all(np.isfinite(path)):
        return float("inf")
    p = resample_closed(np.asarray(path, float), samples)
    t = resample_closed(np.asarray(target, float), samples)
    shifts = (np.arange(samples)[:, None] + np.arange(samples)[None, :]) % samples  # (shift, sample)
    best = np.inf
    for candidate in (p, p[::-1]):
        squared = np.sum((candidate[shifts] - t[None]) ** 2, axis=-1).mean(axis=1)
        best = min(best, float(np.sqrt(squared.min())))
    return best


def stride_and_step_height(foot: np.ndarray, *, ground_band: float = 0.02) -> tuple[float, float]:
    """Stride length and step height [m] of a closed foot path (N, 2), y up.

    The stance phase is the flat bottom of the path: the points within ``ground_band`` times the
    step height above the lowest point (2 %: a foot that rocks up and down while it pushes gets a
    short stride); stride = horizontal extent of the stance phase; step height = the path's
    vertical extent (how high the foot lifts above its lowest point).
    """
    if not np.all(np.isfinite(foot)):
        return float("nan"), float("nan")
    low, high = foot[:, 1].min(), foot[:, 1].max()
    stance = foot[foot[:, 1] <= low + ground_band * (high - low)]
    return float(np.ptp(stance[:, 0])), float(high - low)


def torque_stats(torque: np.ndarray) -> tuple[float, float]:
    """Peak |torque| and RMS torque [N m] of a torque history (T,)."""
    torque = np.asarray(torque, float)
    return float(np.abs(torque).max()), float(np.sqrt(np.mean(torque**2)))
