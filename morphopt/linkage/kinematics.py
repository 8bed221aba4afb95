"""Batched planar kinematics: node paths of many linkages over a crank cycle, with feasibility.

solve_cycles(linkages, samples) groups the linkages by topology and solves each group with NumPy
over (designs, crank angles) at once - no dynamics. A design is infeasible when some dyad cannot
close at some crank angle (the crank cannot complete a turn: it locks or the linkage never
assembles); the reason names the dyad and the first crank angle where it fails.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from morphopt.linkage.graph import Linkage, Offset

__all__ = ["CycleSolution", "solve_at", "solve_cycles"]


@dataclass
class CycleSolution:
    """Kinematics of one linkage over one crank turn.

    angles (N,) [rad]; nodes: name -> (N, 2) [m] (NaN where infeasible); feasible; reason (empty
    when feasible); transmission_angle_min [rad] over the dyads and the cycle (pi/2 is ideal).
    """

    angles: np.ndarray
    nodes: dict
    feasible: bool
    reason: str
    transmission_angle_min: float

    def point(self, name: str, linkage: Linkage) -> np.ndarray:
        """Path (N, 2) of a tracked point."""
        return self.nodes[linkage.points[name]]


def solve_cycles(linkages: list[Linkage], samples: int = 360, *, device: str | None = None) -> list[CycleSolution]:
    """Solve every linkage over ``samples`` crank angles phase + 2 pi k / samples.

    device None solves in NumPy (the reference); "cpu" or "cuda" runs the compiled Warp kernels
    (float64 as well, much faster for large batches).
    """
    steps = 2.0 * np.pi * np.arange(samples) / samples
    phases = np.array([[linkage.crank.phase] for linkage in linkages])
    return solve_at(linkages, phases + steps[None, :], device=device) if linkages else []


def solve_at(linkages: list[Linkage], angles: np.ndarray, *, device: str | None = None) -> list[CycleSolution]:
    """Solve every linkage at its own crank angles: ``angles`` (len(linkages), N) [rad]."""
    angles = np.asarray(angles, dtype=float)
    groups = defaultdict(list)
    for index, linkage in enumerate(linkages):
        groups[linkage.topology].append(index)
    out: list[CycleSolution | None] = [None] * len(linkages)
    for indices in groups.values():
        group = [linkages[i] for i in indices]
        if device is None:
            solutions = _solve_group(group, angles[indices])
        else:
            solutions = _solve_group_compiled(group, angles[indices], device)
        for index, solution in zip(indices, solutions):
            out[index] = solution
    return out


def _solve_group_compiled(group: list[Linkage], angles: np.ndarray, device: str) -> list[CycleSolution]:
    from morphopt.linkage.kinematics_warp import LinkageTables, solve_tables

    tables = LinkageTables.from_linkages(group)
    result = solve_tables(tables, angles=angles, device=device)
    solutions = []
    for d in range(len(group)):
        feasible = result["fail_step"][d] < 0
        reason = "" if feasible else crank_turn_failure(
            placement_name(tables, result["fail_placement"][d]), angles[d, result["fail_step"][d]])
        nodes = {name: (result["points"][d, :, k] if feasible else np.full((angles.shape[1], 2), np.nan))
                 for k, name in enumerate(tables.names)}
        solutions.append(CycleSolution(angles[d].copy(), nodes, bool(feasible), reason,
                                       float(result["transmission_angle_min"][d])))
    return solutions


def placement_name(tables, placement: int) -> str:
    """How a failure reason names placement ``placement`` of the tables (the crank past the last)."""
    return "the crank" if placement == len(tables.placements) else f"dyad '{tables.placements[placement].node}'"


def crank_turn_failure(what: str, angle: float) -> str:
    """The reason of a design that cannot complete a crank turn: ``what`` (a dyad, the crank) does
    not close at crank angle ``angle`` [rad]."""
    return f"cannot complete a crank turn: {what} does not close at crank angle {np.degrees(angle) % 360.0:.1f} deg"


def _solve_group(group: list[Linkage], angles: np.ndarray) -> list[CycleSolution]:
    first = group[0]
    count, samples = angles.shape
    pos = {}
    for name in first.ground:
        xy = np.array([g.ground[name] for g in group])  # (D, 2)
        pos[name] = np.broadcast_to(xy[:, None, :], (count, samples, 2)).copy()
    radius = np.array([g.crank.radius for g in group])[:, None]
    center = pos[first.crank.center]
    pos[first.crank.tip] = center + radius[..., None] * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    fail_step = np.full(count, samples, dtype=int)
    fail_dyad = [""] * count
    transmission = np.full(count, np.pi / 2)
    for k, dyad in enumerate(first.dyads):
        if isinstance(dyad, Offset):
            along = np.array([g.dyads[k].along for g in group])[:, None, None]
            across = np.array([g.dyads[k].across for g in group])[:, None, None]
            delta = pos[dyad.b] - pos[dyad.a]
            ex = delta / np.maximum(np.linalg.norm(delta, axis=-1), 1e-300)[..., None]
            ey = np.stack([-ex[..., 1], ex[..., 0]], axis=-1)
            pos[dyad.node] = pos[dyad.a] + along * ex + across * ey
            continue
        ra = np.array([g.dyads[k].ra for g in group])[:, None]
        rb = np.array([g.dyads[k].rb for g in group])[:, None]
        a, b = pos[dyad.a], pos[dyad.b]
        delta = b - a
        dist = np.linalg.norm(delta, axis=-1)
        along = (ra**2 - rb**2 + dist**2) / (2.0 * np.maximum(dist, 1e-300))
        h2 = ra**2 - along**2
        bad = (h2 < 0.0) | (dist <= 0.0)
        h = np.sqrt(np.maximum(h2, 0.0))
        ex = delta / np.maximum(dist, 1e-300)[..., None]
        ey = np.stack([-ex[..., 1], ex[..., 0]], axis=-1)
        pos[dyad.node] = a + along[..., None] * ex + (dyad.branch * h)[..., None] * ey
        # transmission angle at the new node: angle between its two links, folded to [0, pi/2]
        cos_mu = np.clip((ra**2 + rb**2 - dist**2) / (2.0 * ra * rb), -1.0, 1.0)
        mu = np.arccos(cos_mu)
        folded = np.where(bad, 0.0, np.minimum(mu, np.pi - mu))
        transmission = np.minimum(transmission, folded.min(axis=1))
        for d in np.nonzero(bad.any(axis=1))[0]:
            first_bad = int(np.argmax(bad[d]))
            if first_bad < fail_step[d]:
                fail_step[d] = first_bad
                fail_dyad[d] = dyad.node
    solutions = []
    for d, linkage in enumerate(group):
        feasible = fail_step[d] == samples
        reason = ""
        if not feasible:
            reason = crank_turn_failure(f"dyad '{fail_dyad[d]}'", angles[d, fail_step[d]])
        nodes = {name: (p[d] if feasible else np.full((samples, 2), np.nan)) for name, p in pos.items()}
        solutions.append(CycleSolution(angles[d].copy(), nodes, bool(feasible), reason, float(transmission[d])))
    return solutions
