"""Metrics of mechanism paths and rollouts: pure NumPy functions, no engine, no optimizer.

Paths are arrays (N, 2) of planar points [m] sampled over one crank cycle at equal crank-angle
steps (closed curves: sample N+1 would equal sample 0).

Gait metrics (gait_metrics) describe the curve through the samples, not the samples: extrema
are refined by a parabola through the extreme sample and its neighbours, and the ground band's
edges are found on the cubic Hermite (Catmull-Rom) curve through the samples, so that they
converge with the sampling (benchmarks/results/README.md, "Stride against sampling").
morphopt.linkage.kinematics_warp's cycle_reduce computes the same numbers on the device.
"""

from __future__ import annotations

import numpy as np

__all__ = ["GROUND_BAND", "gait_metrics", "gait_metrics_batch", "path_error", "resample_closed",
           "stride_and_step_height", "torque_stats"]

GROUND_BAND = 0.02  # the stance: points within 2 % of the step height above the lowest point
BISECTIONS = 40  # halvings of a sample interval to find a band edge (2^-40 of it)


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


def stride_and_step_height(foot: np.ndarray, *, ground_band: float = GROUND_BAND,
                           closed: bool = True) -> tuple[float, float]:
    """Stride and step height [m] of a foot path (N, 2), y up: gait_metrics without the full stride."""
    stride, _, height = gait_metrics(foot, ground_band=ground_band, closed=closed)
    return stride, height


def gait_metrics(path: np.ndarray, *, ground_band: float = GROUND_BAND, closed: bool = True) -> tuple:
    """(stride, full stride, step height) [m] of one path (N, 2), y up; NaN for a non-finite path.

    step height: the vertical extent of the curve. stride (flat stance): the horizontal extent of
    the part of the curve within ``ground_band`` times the step height above its lowest point (a
    foot that rocks up and down while it pushes gets a short stride). full stride: the curve's
    whole horizontal extent (the "stride" quoted in the literature for Jansen's leg). closed: the
    samples are one whole cycle (the last joins the first); False: an open run of records (a
    dynamic rollout's last turn), whose ends are not joined.
    """
    path = np.asarray(path, float)
    stride, full, height = gait_metrics_batch(path[:, 0:1], path[:, 1:2], ground_band=ground_band, closed=closed)
    return float(stride[0]), float(full[0]), float(height[0])


def gait_metrics_batch(x: np.ndarray, y: np.ndarray, first=None, *, ground_band: float = GROUND_BAND,
                       closed: bool = True) -> tuple:
    """gait_metrics of B paths at once: x, y (N, B), path b being samples first[b]..N-1 (first:
    (B,) ints, None: all from 0; a closed path must use all N). Returns (stride, full stride,
    step height), each (B,). A few passes over the arrays; the refinements touch only the samples
    next to extremes and band edges."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    count = x.shape[1]
    first = np.zeros(count, int) if first is None else np.asarray(first, int).reshape(count)
    if closed and first.any():
        raise ValueError("gait_metrics_batch: a closed path uses all its samples (first = 0)")
    if count == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    start = int(first.min())
    x, y, first = x[start:], y[start:], first - start
    n = x.shape[0]
    cols = np.arange(count)
    if first.any():  # rows before a path's first sample repeat it: they change no extreme, band or edge
        before = np.arange(n)[:, None] < first[None, :]
        x, y = np.where(before, x[first, cols], x), np.where(before, y[first, cols], y)
    finite = np.isfinite(x.sum(axis=0)) & np.isfinite(y.sum(axis=0))
    if not finite.all():
        x, y = np.where(finite, x, 0.0), np.where(finite, y, 0.0)

    def neighbour(k, b, step):
        """Index of sample k + step of path b (clamped to an open path's ends) and whether it exists."""
        j = k + step
        if closed:
            return j % n, np.ones(j.shape, bool)
        return np.clip(j, first[b], n - 1), (j >= first[b]) & (j <= n - 1)

    def shifted(a, step):
        """a[k + step] for every row k (cyclic when closed, else the last row repeated)."""
        if closed:
            return np.roll(a, -step, axis=0)
        return np.concatenate([a[step:], np.repeat(a[-1:], step, axis=0)]) if step > 0 else a

    def extreme(f, sign):
        """Sample, parabola offset and refined value of each path's lowest (sign 1) or highest (-1) f."""
        at = np.maximum(f.argmin(axis=0) if sign > 0 else f.argmax(axis=0), first)
        (kp, okp), (kq, okq) = neighbour(at, cols, -1), neighbour(at, cols, 1)
        f0, fm, fq = f[at, cols], f[kp, cols], f[kq, cols]
        curve = fm - 2.0 * f0 + fq
        ok = okp & okq & (sign * curve > 0.0)
        offset = np.where(ok, 0.5 * (fm - fq) / np.where(ok, curve, 1.0), 0.0)
        return at, offset, f0 + 0.5 * (fq - fm) * offset + 0.5 * curve * offset * offset

    at, offset, low = extreme(y, 1.0)
    high = extreme(y, -1.0)[2]
    band = low + ground_band * (high - low)
    inb = y <= band[None, :]
    # the lowest point of the curve is in the stance (its x on the parabola through the same samples)
    kp, kq = neighbour(at, cols, -1)[0], neighbour(at, cols, 1)[0]
    x0, xm, xq = x[at, cols], x[kp, cols], x[kq, cols]
    bottom = x0 + 0.5 * (xq - xm) * offset + 0.5 * (xm - 2.0 * x0 + xq) * offset * offset
    right = np.maximum(np.max(x, axis=0, where=inb, initial=-np.inf), bottom)
    left = np.minimum(np.min(x, axis=0, where=inb, initial=np.inf), bottom)
    # a turn of x inside the stance: the vertex of the parabola through the sample and its neighbours
    ks, bs = np.nonzero(inb & shifted(inb, 1) & np.roll(inb, 1, axis=0))
    (kp, okp), (kq, okq) = neighbour(ks, bs, -1), neighbour(ks, bs, 1)
    keep = okp & okq & inb[kp, bs]
    ks, bs, kp, kq = ks[keep], bs[keep], kp[keep], kq[keep]
    xk, xm, xq = x[ks, bs], x[kp, bs], x[kq, bs]
    curve = xm - 2.0 * xk + xq
    vertex = xk - np.where(curve != 0.0, (xq - xm) ** 2 / (8.0 * np.where(curve != 0.0, curve, 1.0)), 0.0)
    top, bottom_turn = (xk >= xm) & (xk >= xq), (xk <= xm) & (xk <= xq)
    np.maximum.at(right, bs[top], vertex[top])
    np.minimum.at(left, bs[bottom_turn], vertex[bottom_turn])
    # the band's edges: where the Hermite curve between two samples crosses it
    ks, bs = np.nonzero(inb != shifted(inb, 1))
    if ks.size:
        (kp, okp), (kq, okq) = neighbour(ks, bs, -1), neighbour(ks, bs, 1)
        kr, okr = neighbour(kq, bs, 1)
        near = np.maximum(okp.astype(float) + okq, 1.0)  # tangents: central differences, one-sided at ends
        far = np.maximum(okq.astype(float) + okr, 1.0)
        tangent = lambda f: ((f[kq, bs] - f[kp, bs]) / near, (f[kr, bs] - f[ks, bs]) / far)  # noqa: E731
        (mx0, mx1), (my0, my1) = tangent(x), tangent(y)
        edges = hermite_crossings(x[ks, bs], x[kq, bs], mx0, mx1, y[ks, bs], y[kq, bs], my0, my1, band[bs])
        np.maximum.at(right, bs, edges)
        np.minimum.at(left, bs, edges)
    full = extreme(x, -1.0)[2] - extreme(x, 1.0)[2]
    nan = np.full(count, np.nan)
    return np.where(finite, right - left, nan), np.where(finite, full, nan), np.where(finite, high - low, nan)


def hermite(p0, p1, m0, m1, s):
    """The cubic Hermite curve from p0 to p1 with tangents m0, m1 (per sample step) at s in [0, 1]."""
    s2 = s * s
    s3 = s2 * s
    return (2.0 * s3 - 3.0 * s2 + 1.0) * p0 + (s3 - 2.0 * s2 + s) * m0 + (3.0 * s2 - 2.0 * s3) * p1 + (s3 - s2) * m1


def hermite_crossings(x0, x1, mx0, mx1, y0, y1, my0, my1, band):
    """x where the Hermite segments (x0..x1, y0..y1 and their tangents) cross y = band, found by
    BISECTIONS halvings (y0 and y1 lie on opposite sides of the band)."""
    lo, hi = np.zeros_like(x0), np.ones_like(x0)
    start = y0 <= band
    for _ in range(BISECTIONS):
        s = 0.5 * (lo + hi)
        same = (hermite(y0, y1, my0, my1, s) <= band) == start
        lo, hi = np.where(same, s, lo), np.where(same, hi, s)
    return hermite(x0, x1, mx0, mx1, 0.5 * (lo + hi))


def torque_stats(torque: np.ndarray) -> tuple[float, float]:
    """Peak |torque| and RMS torque [N m] of a torque history (T,)."""
    torque = np.asarray(torque, float)
    return float(np.abs(torque).max()), float(np.sqrt(np.mean(torque**2)))
