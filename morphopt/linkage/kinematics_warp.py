"""Cycle kinematics as Warp kernels (float64): a thread per (design, crank angle) places every node
of a linkage, a thread per design reduces the cycle to feasibility, transmission angle, stride and
step height. The same kernels run on the CPU (the batch split over the cores) and on a GPU.

The topology is passed as small integer tables and the numbers as (designs, placements) arrays
(``LinkageTables``), so one compiled kernel serves every family. Node positions live in a
per-thread scratch vector; only the nodes asked for are written out, so a batch of many designs
moves little memory.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp

from morphopt.linkage.graph import Linkage, Offset
from morphopt.metrics import BISECTIONS, GROUND_BAND

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["MAX_NODES", "LinkageTables", "solve_tables"]

MAX_NODES = 32
_scratch = wp.types.vector(length=2 * MAX_NODES, dtype=wp.float64)

KIND_DYAD = wp.constant(0)
KIND_OFFSET = wp.constant(1)


CPU_LANES = 8  # crank angles per CPU thread, interleaved: independent chains that one core overlaps
GPU_LANES = 1  # a GPU hides latency with other threads and keeps each thread's scratch small


def _cycle_points_kernel(LANES: int, NODES: int):
    """The placement kernel for LANES crank angles per thread and linkages of up to NODES nodes
    (the per-thread scratch holds exactly that much); both are read as constants in the kernel."""
    _lanes = wp.types.matrix(shape=(2 * NODES, LANES), dtype=wp.float64)
    _lane_ints = wp.types.vector(length=LANES, dtype=wp.int32)
    _lane_floats = wp.types.vector(length=LANES, dtype=wp.float64)

    @wp.kernel(module="unique")
    def cycle_points(
        angles: wp.array2d(dtype=wp.float64),
        phase: wp.array(dtype=wp.float64),
        turn: wp.array(dtype=wp.vec2d),
        samples: int,
        ground_node: wp.array(dtype=wp.int32),
        ground_xy: wp.array2d(dtype=wp.vec2d),
        crank_center: int,
        crank_tip: int,
        crank_radius: wp.array(dtype=wp.float64),
        kind: wp.array(dtype=wp.int32),
        node: wp.array(dtype=wp.int32),
        node_a: wp.array(dtype=wp.int32),
        node_b: wp.array(dtype=wp.int32),
        branch: wp.array2d(dtype=wp.float64),
        first: wp.array2d(dtype=wp.float64),
        second: wp.array2d(dtype=wp.float64),
        coefficients: wp.array3d(dtype=wp.float64),
        out_nodes: wp.array(dtype=wp.int32),
        # out
        points_out: wp.array3d(dtype=wp.vec2d),
        failed_out: wp.array2d(dtype=wp.int32),
        cos_out: wp.array2d(dtype=wp.float64),
    ):
        """Place the nodes of design d at crank angles LANES * c ... LANES * c + LANES - 1 (angles[d, i],
        or phase[d] + 2 pi i / samples when ``angles`` is empty, turn[i] = (cos, sin)(2 pi i / samples)); record per angle the first placement that
        cannot close (-1: none, the number of placements: the crank itself) and the largest |cos| of a
        dyad's transmission angle. coefficients[d, k] = (ra^2 - rb^2, ra^2, ra^2 + rb^2, 1 / (2 ra rb))."""
        d, c = wp.tid()
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        half = wp.float64(0.5)
        s = _lanes()
        radius = crank_radius[d]
        count = kind.shape[0]
        failed = _lane_ints(-1)
        worst = _lane_floats()
        for g in range(ground_node.shape[0]):
            xy = ground_xy[d, g]
            n = ground_node[g]
            for lane in range(wp.static(LANES)):
                s[2 * n, lane] = xy[0]
                s[2 * n + 1, lane] = xy[1]
        start = wp.vec2d(wp.cos(phase[d]), wp.sin(phase[d]))
        for lane in range(wp.static(LANES)):
            i = wp.min(c * LANES + lane, samples - 1)
            cs = turn[i]
            cos_t = start[0] * cs[0] - start[1] * cs[1]
            sin_t = start[1] * cs[0] + start[0] * cs[1]
            if angles.shape[0] > 0:
                cos_t = wp.cos(angles[d, i])
                sin_t = wp.sin(angles[d, i])
            s[2 * crank_tip, lane] = s[2 * crank_center, lane] + radius * cos_t
            s[2 * crank_tip + 1, lane] = s[2 * crank_center + 1, lane] + radius * sin_t
            if not (radius > zero):
                failed[lane] = count
        for k in range(count):
            a = node_a[k]
            b = node_b[k]
            n = node[k]
            is_dyad = kind[k] == KIND_DYAD
            f = first[d, k]
            g2 = second[d, k]
            sign = branch[d, k]
            c0 = coefficients[d, k, 0]
            c1 = coefficients[d, k, 1]
            c2 = coefficients[d, k, 2]
            c3 = coefficients[d, k, 3]
            lengths_ok = f > zero and g2 > zero
            for lane in range(wp.static(LANES)):
                ax = s[2 * a, lane]
                ay = s[2 * a + 1, lane]
                dx = s[2 * b, lane] - ax
                dy = s[2 * b + 1, lane] - ay
                dist2 = dx * dx + dy * dy
                dist = wp.sqrt(dist2)
                inv = one / wp.max(dist, wp.float64(1.0e-300))
                ex = dx * inv
                ey = dy * inv
                along = f
                across = g2
                if is_dyad:
                    along = (c0 + dist2) * half * inv
                    h2 = c1 - along * along
                    if not (h2 >= zero and dist > zero and lengths_ok):
                        if failed[lane] < 0:
                            failed[lane] = k
                    across = wp.sqrt(wp.max(h2, zero))
                    if sign < zero:
                        across = -across
                    worst[lane] = wp.max(worst[lane], wp.min(wp.abs((c2 - dist2) * c3), one))
                s[2 * n, lane] = ax + along * ex - across * ey
                s[2 * n + 1, lane] = ay + along * ey + across * ex
        for lane in range(wp.static(LANES)):
            i = c * LANES + lane
            if i < samples:
                for p in range(out_nodes.shape[0]):
                    m = out_nodes[p]
                    points_out[d, i, p] = wp.vec2d(s[2 * m, lane], s[2 * m + 1, lane])
                failed_out[d, i] = failed[lane]
                cos_out[d, i] = worst[lane]

    return cycle_points


_CYCLE_POINTS = {}


@wp.kernel
def dyad_coefficients(first: wp.array2d(dtype=wp.float64), second: wp.array2d(dtype=wp.float64),
                      coefficients: wp.array3d(dtype=wp.float64)):
    """(ra^2 - rb^2, ra^2, ra^2 + rb^2, 1 / (2 ra rb)) of every dyad, computed once per design."""
    d, k = wp.tid()
    ra = first[d, k]
    rb = second[d, k]
    coefficients[d, k, 0] = ra * ra - rb * rb
    coefficients[d, k, 1] = ra * ra
    coefficients[d, k, 2] = ra * ra + rb * rb
    coefficients[d, k, 3] = wp.float64(0.5) / (ra * rb)


@wp.func
def _hermite(p0: wp.float64, p1: wp.float64, m0: wp.float64, m1: wp.float64, s: wp.float64):
    """The cubic Hermite curve from p0 to p1 with tangents m0, m1 at s (morphopt.metrics.hermite)."""
    s2 = s * s
    s3 = s2 * s
    one, two, three = wp.float64(1.0), wp.float64(2.0), wp.float64(3.0)
    return (two * s3 - three * s2 + one) * p0 + (s3 - two * s2 + s) * m0 + (three * s2 - two * s3) * p1 + (s3 - s2) * m1


@wp.func
def _coordinate(points: wp.array3d(dtype=wp.vec2d), d: int, i: int, p: int, axis: int):
    """Coordinate ``axis`` of output node p at crank step i (taken cyclically) of design d."""
    n = points.shape[1]
    return points[d, (i + n) % n, p][axis]


@wp.func
def _refined_extreme(points: wp.array3d(dtype=wp.vec2d), d: int, p: int, axis: int, sign: wp.float64):
    """The lowest (sign 1) or highest (-1) value of coordinate ``axis`` over the cycle, refined by the
    parabola through the extreme sample and its neighbours: (value, sample, offset); the rule of
    morphopt.metrics.gait_metrics_batch's extreme."""
    n = points.shape[1]
    at = int(0)
    best = sign * _coordinate(points, d, 0, p, axis)
    for i in range(1, n):
        v = sign * _coordinate(points, d, i, p, axis)
        if v < best:
            best = v
            at = i
    f0 = _coordinate(points, d, at, p, axis)
    fm = _coordinate(points, d, at - 1, p, axis)
    fq = _coordinate(points, d, at + 1, p, axis)
    curve = fm - wp.float64(2.0) * f0 + fq
    offset = wp.float64(0.0)
    if sign * curve > wp.float64(0.0):
        offset = wp.float64(0.5) * (fm - fq) / curve
    half = wp.float64(0.5)
    return wp.vec3d(f0 + half * (fq - fm) * offset + half * curve * offset * offset, wp.float64(at), offset)


@wp.kernel
def cycle_reduce(
    points: wp.array3d(dtype=wp.vec2d),
    failed: wp.array2d(dtype=wp.int32),
    cos_max: wp.array2d(dtype=wp.float64),
    ground_band: wp.float64,
    bisections: int,
    # out
    fail_step_out: wp.array(dtype=wp.int32),
    fail_placement_out: wp.array(dtype=wp.int32),
    cos_out: wp.array(dtype=wp.float64),
    stride_out: wp.array2d(dtype=wp.float64),
    full_out: wp.array2d(dtype=wp.float64),
    height_out: wp.array2d(dtype=wp.float64),
):
    """Per design: the first failing crank step and placement (-1: feasible), the largest |cos mu|
    and, per output node, the stride, full stride and step height of its closed path by the rule of
    morphopt.metrics.gait_metrics (refined extrema, band edges on the Hermite curve); NaN when
    infeasible."""
    d = wp.tid()
    samples = failed.shape[1]
    fail_step = int(-1)  # noqa: UP018 - int(): a variable, not a constant, for Warp
    fail_placement = int(-1)  # noqa: UP018
    worst = wp.float64(0.0)
    for i in range(samples):
        if failed[d, i] >= 0 and fail_step < 0:
            fail_step = i
            fail_placement = failed[d, i]
        worst = wp.max(worst, cos_max[d, i])
    fail_step_out[d] = fail_step
    fail_placement_out[d] = fail_placement
    cos_out[d] = worst
    nan = wp.float64(wp.nan)
    half = wp.float64(0.5)
    two = wp.float64(2.0)
    for p in range(points.shape[2]):
        if fail_step >= 0:
            stride_out[d, p] = nan
            full_out[d, p] = nan
            height_out[d, p] = nan
            continue
        lowest = _refined_extreme(points, d, p, 1, wp.float64(1.0))
        low = lowest[0]
        high = _refined_extreme(points, d, p, 1, wp.float64(-1.0))[0]
        band = low + ground_band * (high - low)
        at = int(lowest[1])
        offset = lowest[2]
        x0 = _coordinate(points, d, at, p, 0)
        xm = _coordinate(points, d, at - 1, p, 0)
        xq = _coordinate(points, d, at + 1, p, 0)
        bottom = x0 + half * (xq - xm) * offset + half * (xm - two * x0 + xq) * offset * offset
        left = bottom
        right = bottom
        for i in range(samples):
            x = _coordinate(points, d, i, p, 0)
            y = _coordinate(points, d, i, p, 1)
            xp = _coordinate(points, d, i - 1, p, 0)
            xn = _coordinate(points, d, i + 1, p, 0)
            yn = _coordinate(points, d, i + 1, p, 1)
            inside = y <= band
            if inside:
                left = wp.min(left, x)
                right = wp.max(right, x)
                if _coordinate(points, d, i - 1, p, 1) <= band and yn <= band:
                    curve = xp - two * x + xn
                    vertex = x
                    if curve != wp.float64(0.0):
                        vertex = x - (xn - xp) * (xn - xp) / (wp.float64(8.0) * curve)
                    if x >= xp and x >= xn:
                        right = wp.max(right, vertex)
                    if x <= xp and x <= xn:
                        left = wp.min(left, vertex)
            if inside != (yn <= band):  # a band edge between samples i and i + 1
                tx0 = half * (xn - xp)
                tx1 = half * (_coordinate(points, d, i + 2, p, 0) - x)
                ty0 = half * (yn - _coordinate(points, d, i - 1, p, 1))
                ty1 = half * (_coordinate(points, d, i + 2, p, 1) - y)
                lo = wp.float64(0.0)
                hi = wp.float64(1.0)
                for _ in range(bisections):
                    s = half * (lo + hi)
                    if (_hermite(y, yn, ty0, ty1, s) <= band) == inside:
                        lo = s
                    else:
                        hi = s
                edge = _hermite(x, xn, tx0, tx1, half * (lo + hi))
                left = wp.min(left, edge)
                right = wp.max(right, edge)
        stride_out[d, p] = right - left
        full_out[d, p] = (_refined_extreme(points, d, p, 0, wp.float64(-1.0))[0]
                          - _refined_extreme(points, d, p, 0, wp.float64(1.0))[0])
        height_out[d, p] = high - low


@dataclass
class LinkageTables:
    """A group of same-topology linkages as arrays: node names, ground nodes and their (D, G, 2)
    positions, crank centre/tip, radius and phase (D,), placement kinds and nodes (K,), branch,
    first and second numbers (D, K) (ra, rb of a dyad; along, across of an offset)."""

    names: list
    placements: list
    ground_node: np.ndarray
    ground_xy: np.ndarray
    crank_center: int
    crank_tip: int
    radius: np.ndarray
    phase: np.ndarray
    kind: np.ndarray
    node: np.ndarray
    node_a: np.ndarray
    node_b: np.ndarray
    branch: np.ndarray
    first: np.ndarray
    second: np.ndarray

    @property
    def count(self) -> int:
        """Number of designs in the tables."""
        return len(self.radius)

    @classmethod
    def from_linkages(cls, linkages) -> LinkageTables:
        """Tables of a list of same-topology linkages, or of one linkage whose numbers are (D,)
        arrays (a batched linkage, see Linkage.batch_size)."""
        if isinstance(linkages, Linkage):
            template, count = linkages, linkages.batch_size or 1
            column = lambda get: np.broadcast_to(np.asarray(get(template), np.float64), (count,))
        else:
            template, count = linkages[0], len(linkages)
            column = lambda get: np.array([get(g) for g in linkages], np.float64)
        names = template.nodes
        if len(names) > MAX_NODES:
            raise ValueError(f"linkage '{template.name}' has {len(names)} nodes; the compiled kinematics "
                             f"take at most {MAX_NODES}")
        index = {name: k for k, name in enumerate(names)}
        placements = list(template.dyads)
        ground = list(template.ground)
        ground_xy = np.stack([np.stack([column(lambda g, n=n: g.ground[n][0]), column(lambda g, n=n: g.ground[n][1])],
                                       axis=-1) for n in ground], axis=1)
        width = max(len(placements), 1)  # keep the tables 2-D when a linkage is a bare crank
        branch, first, second = (np.zeros((count, width)) for _ in range(3))
        for k, p in enumerate(placements):
            if isinstance(p, Offset):
                first[:, k] = column(lambda g, k=k: g.dyads[k].along)
                second[:, k] = column(lambda g, k=k: g.dyads[k].across)
            else:
                first[:, k] = column(lambda g, k=k: g.dyads[k].ra)
                second[:, k] = column(lambda g, k=k: g.dyads[k].rb)
                branch[:, k] = column(lambda g, k=k: g.dyads[k].branch)
        ints = lambda values: np.array(values, np.int32)
        return cls(names, placements, ints([index[n] for n in ground]), np.ascontiguousarray(ground_xy),
                   index[template.crank.center], index[template.crank.tip],
                   np.ascontiguousarray(column(lambda g: g.crank.radius)),
                   np.ascontiguousarray(column(lambda g: g.crank.phase)),
                   ints([1 if isinstance(p, Offset) else 0 for p in placements]),
                   ints([index[p.node] for p in placements]), ints([index[p.a] for p in placements]),
                   ints([index[p.b] for p in placements]), branch, first, second)


def _chunks(count: int, device: str) -> list[tuple[int, int]]:
    """Design ranges launched side by side: one per core on the CPU (Warp runs a CPU launch on one
    thread and releases the interpreter lock while it runs), one range on a GPU."""
    workers = (os.cpu_count() or 1) if wp.get_device(device).is_cpu else 1
    workers = max(1, min(workers, count // 64 or 1))
    edges = np.linspace(0, count, workers + 1).astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def solve_tables(tables: LinkageTables, *, samples: int | None = None, angles: np.ndarray | None = None,
                 nodes: list[str] | None = None, device: str = "cpu", ground_band: float = GROUND_BAND,
                 keep_points: bool = True) -> dict:
    """Solve every design of ``tables`` over ``samples`` crank angles phase + 2 pi k / samples (or
    at its own ``angles`` (D, N)) and reduce each cycle.

    Returns a dict of NumPy arrays: "points" (D, N, len(nodes), 2) [m] of the nodes asked for (all
    by default; omitted when keep_points is False, which saves the copy from a GPU), "fail_step"
    and "fail_placement" (D,) first crank step and placement that cannot close (-1: feasible; the
    number of placements: the crank itself), "transmission_angle_min" (D,) [rad], "stride",
    "stride_full" and "step_height" (D, len(nodes)) [m] (the rule of morphopt.metrics.gait_metrics
    on the closed path).
    """
    count = tables.count
    nodes = list(tables.names) if nodes is None else list(nodes)
    out_nodes = np.array([tables.names.index(n) for n in nodes], np.int32)
    if angles is not None:
        angles = np.ascontiguousarray(angles, np.float64)
        samples = angles.shape[1]
    elif samples is None:
        raise ValueError("solve_tables needs samples or angles")
    turn_angles = 2.0 * math.pi * np.arange(samples) / samples
    turn = wp.array(np.stack([np.cos(turn_angles), np.sin(turn_angles)], axis=-1), dtype=wp.vec2d, device=device)
    per_design = {"phase": tables.phase, "ground_xy": tables.ground_xy, "radius": tables.radius,
                  "branch": tables.branch, "first": tables.first, "second": tables.second}
    host = {"points": np.empty((count, samples, len(nodes), 2)), "failed": np.empty((count, samples), np.int32),
            "cos": np.empty((count, samples)), "fail_step": np.empty(count, np.int32),
            "fail_placement": np.empty(count, np.int32), "cos_max": np.empty(count),
            "stride": np.empty((count, len(nodes))), "stride_full": np.empty((count, len(nodes))),
            "step_height": np.empty((count, len(nodes)))}
    shared = {name: wp.array(getattr(tables, name), dtype=wp.int32, device=device)
              for name in ("ground_node", "kind", "node", "node_a", "node_b")}
    shared["out_nodes"] = wp.array(out_nodes, dtype=wp.int32, device=device)
    is_cpu = wp.get_device(device).is_cpu
    lanes = CPU_LANES if is_cpu else GPU_LANES
    scratch = min(MAX_NODES, 8 * ((len(tables.names) + 7) // 8))
    if (lanes, scratch) not in _CYCLE_POINTS:
        _CYCLE_POINTS[lanes, scratch] = _cycle_points_kernel(lanes, scratch)
    kernel = _CYCLE_POINTS[lanes, scratch]

    def run(lo: int, hi: int):
        def put(array, dtype):
            return wp.array(array[lo:hi], dtype=dtype, device=device, copy=not is_cpu)

        def out(name, dtype):  # on the CPU the kernels write straight into the host arrays
            if is_cpu:
                return put(host[name], dtype)
            shape = host[name][lo:hi].shape
            return wp.empty(shape[:-1] if dtype is wp.vec2d else shape, dtype=dtype, device=device)

        arrays = {k: put(v, wp.vec2d if k == "ground_xy" else wp.float64) for k, v in per_design.items()}
        chunk_angles = (put(angles, wp.float64) if angles is not None
                        else wp.empty((0, 0), dtype=wp.float64, device=device))
        points, failed, cos = out("points", wp.vec2d), out("failed", wp.int32), out("cos", wp.float64)
        coefficients = wp.empty((hi - lo, tables.first.shape[1], 4), dtype=wp.float64, device=device)
        wp.launch(dyad_coefficients, dim=tables.first[lo:hi].shape, device=device,
                  inputs=[arrays["first"], arrays["second"]], outputs=[coefficients])
        wp.launch(kernel, dim=(hi - lo, (samples + lanes - 1) // lanes), device=device,
                  inputs=[chunk_angles, arrays["phase"], turn, samples, shared["ground_node"], arrays["ground_xy"],
                          tables.crank_center, tables.crank_tip, arrays["radius"], shared["kind"], shared["node"],
                          shared["node_a"], shared["node_b"], arrays["branch"], arrays["first"], arrays["second"],
                          coefficients, shared["out_nodes"]],
                  outputs=[points, failed, cos])
        reduced = {name: out(name, dtype) for name, dtype in (
            ("fail_step", wp.int32), ("fail_placement", wp.int32), ("cos_max", wp.float64),
            ("stride", wp.float64), ("stride_full", wp.float64), ("step_height", wp.float64))}
        wp.launch(cycle_reduce, dim=hi - lo, device=device, inputs=[points, failed, cos, ground_band, BISECTIONS],
                  outputs=list(reduced.values()))
        if not is_cpu:
            for name, array in reduced.items():
                host[name][lo:hi] = array.numpy()
            if keep_points:
                host["points"][lo:hi] = points.numpy()

    ranges = _chunks(count, device)
    if len(ranges) == 1:
        run(*ranges[0])
    else:
        with ThreadPoolExecutor(len(ranges)) as pool:
            list(pool.map(lambda r: run(*r), ranges))
    result = {"fail_step": host["fail_step"], "fail_placement": host["fail_placement"],
              "transmission_angle_min": np.arccos(host["cos_max"]), "stride": host["stride"],
              "stride_full": host["stride_full"], "step_height": host["step_height"]}
    if keep_points:
        result["points"] = host["points"]
    return result
