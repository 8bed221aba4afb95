"""Cycle kinematics as one Warp kernel: a thread per (design, crank angle), the same results as
the NumPy path (morphopt.linkage.kinematics) compiled for the CPU or a GPU.

The topology is passed as small integer tables, the numbers as (designs, placements) arrays, so
one compiled kernel serves every family.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from morphopt.linkage.graph import Linkage, Offset

__all__ = ["solve_group_warp"]

KIND_DYAD = wp.constant(0)
KIND_OFFSET = wp.constant(1)


@wp.kernel
def cycle_positions(
    angles: wp.array2d(dtype=float),
    crank_center: int,
    crank_tip: int,
    crank_radius: wp.array(dtype=float),
    kind: wp.array(dtype=wp.int32),
    node: wp.array(dtype=wp.int32),
    node_a: wp.array(dtype=wp.int32),
    node_b: wp.array(dtype=wp.int32),
    branch: wp.array(dtype=float),
    first: wp.array2d(dtype=float),
    second: wp.array2d(dtype=float),
    # in/out: ground nodes filled in, the rest computed
    positions: wp.array3d(dtype=wp.vec2),
    # out
    failed_at_out: wp.array2d(dtype=wp.int32),
    transmission_out: wp.array2d(dtype=float),
):
    """Place every node of design d at its crank angle i; record the first dyad that cannot close."""
    d, i = wp.tid()
    theta = angles[d, i]
    center = positions[d, i, crank_center]
    positions[d, i, crank_tip] = center + crank_radius[d] * wp.vec2(wp.cos(theta), wp.sin(theta))
    failed = int(-1)
    transmission = float(1.5707963267948966)
    for k in range(kind.shape[0]):
        a = positions[d, i, node_a[k]]
        b = positions[d, i, node_b[k]]
        delta = b - a
        dist = wp.length(delta)
        ex = delta / wp.max(dist, 1.0e-30)
        ey = wp.vec2(-ex[1], ex[0])
        if kind[k] == KIND_OFFSET:
            positions[d, i, node[k]] = a + first[d, k] * ex + second[d, k] * ey
        else:
            ra = first[d, k]
            rb = second[d, k]
            along = (ra * ra - rb * rb + dist * dist) / (2.0 * wp.max(dist, 1.0e-30))
            h2 = ra * ra - along * along
            if (h2 < 0.0 or dist <= 0.0) and failed < 0:
                failed = k
            h = wp.sqrt(wp.max(h2, 0.0))
            positions[d, i, node[k]] = a + along * ex + branch[k] * h * ey
            cos_mu = wp.clamp((ra * ra + rb * rb - dist * dist) / (2.0 * ra * rb), -1.0, 1.0)
            mu = wp.acos(cos_mu)
            transmission = wp.min(transmission, wp.min(mu, 3.141592653589793 - mu))
    failed_at_out[d, i] = failed
    transmission_out[d, i] = transmission


def solve_group_warp(group: list[Linkage], angles: np.ndarray, device: str = "cpu"):
    """Node positions (name -> (D, N, 2)), first failing placement per (D, N) (-1: none) and the
    transmission angle per (D, N) for linkages of one topology."""
    first_linkage = group[0]
    names = first_linkage.nodes
    index = {name: k for k, name in enumerate(names)}
    count, samples = angles.shape
    placements = first_linkage.dyads
    positions = np.zeros((count, samples, len(names), 2), np.float32)
    for name in first_linkage.ground:
        positions[:, :, index[name]] = np.array([g.ground[name] for g in group], np.float32)[:, None, :]
    tables = {
        "kind": [1 if isinstance(p, Offset) else 0 for p in placements],
        "node": [index[p.node] for p in placements], "node_a": [index[p.a] for p in placements],
        "node_b": [index[p.b] for p in placements],
    }
    branch = np.array([getattr(p, "branch", 0) for p in placements], np.float32)
    width = max(len(placements), 1)  # keep the tables 2-D when a linkage is a bare crank
    first = np.zeros((count, width), np.float32)
    second = np.zeros((count, width), np.float32)
    for d, g in enumerate(group):
        for k, p in enumerate(g.dyads):
            first[d, k], second[d, k] = (p.along, p.across) if isinstance(p, Offset) else (p.ra, p.rb)
    arr = lambda x, dtype: wp.array(np.asarray(x), dtype=dtype, device=device)  # noqa: E731
    pos = wp.array(positions, dtype=wp.vec2, device=device)
    failed = wp.zeros((count, samples), dtype=wp.int32, device=device)
    transmission = wp.zeros((count, samples), dtype=float, device=device)
    wp.launch(cycle_positions, dim=(count, samples), device=device,
              inputs=[arr(angles.astype(np.float32), float), index[first_linkage.crank.center],
                      index[first_linkage.crank.tip], arr([g.crank.radius for g in group], float),
                      arr(tables["kind"], wp.int32), arr(tables["node"], wp.int32), arr(tables["node_a"], wp.int32),
                      arr(tables["node_b"], wp.int32), arr(branch, float), arr(first, float), arr(second, float), pos],
              outputs=[failed, transmission])
    out = pos.numpy().astype(np.float64)
    return {name: out[:, :, k] for name, k in index.items()}, failed.numpy(), transmission.numpy()
