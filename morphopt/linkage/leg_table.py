"""A one-DoF leg linkage tabulated over its crank turn by morphopt's planar kinematics.

The engine tabulates a MechanismSpec's one-DoF sub-chains itself (engine.reduced.tabulated_layout);
this table, from the linkage graph and solve_at alone, is the independent reference its tests
compare with.

The cycle kinematics place every node at N crank angles; each link's planar angle (the direction
of its first two nodes, as in link_body) and centre of mass follow, and their derivatives in the
crank angle come from the Fourier series of the samples (exact for the band-limited part of a
smooth periodic function: the error falls faster than any power of N).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from morphopt.linkage.graph import Linkage
from morphopt.linkage.kinematics import solve_at
from morphopt.linkage.to_spec import BarStyle, link_body, world

__all__ = ["TABLE_SAMPLES", "LegTable", "leg_table", "periodic_derivatives"]

TABLE_SAMPLES = 512


@dataclass
class LegTable:
    """A leg's kinematics over a crank turn at psi_n = 2 pi n / N, lengths as the linkage's.

    links (N, K, 3): per link its centre of mass in the plane (x, z) [m] and its angle [rad], with
    links_d1, links_d2 their derivatives in psi; foot, foot_d1, foot_d2 (N, 3): the foot point
    (x, z, 0) and its derivatives; foot_link: the link carrying it; closure_error: the largest
    distance [m] between a pivot as its links place it halfway between samples (linear
    interpolation) and the exact one."""

    name: str
    links: np.ndarray
    links_d1: np.ndarray
    links_d2: np.ndarray
    foot: np.ndarray
    foot_d1: np.ndarray
    foot_d2: np.ndarray
    foot_link: int
    link_names: list = field(default_factory=list)
    closure_error: float = 0.0

    @property
    def samples(self) -> int:
        """Crank angles in the table (N)."""
        return int(np.shape(self.links)[0])


def periodic_derivatives(values: np.ndarray, winding: np.ndarray | float = 0.0) -> tuple:
    """First and second derivatives of samples (N, ...) of f(psi) over psi = 2 pi n / N, where
    f(psi) - winding * psi is periodic (winding: turns of an angle per crank turn)."""
    n = values.shape[0]
    psi = 2.0 * np.pi * np.arange(n) / n
    shape = (n,) + (1,) * (values.ndim - 1)
    periodic = values - np.asarray(winding) * psi.reshape(shape)
    spectrum = np.fft.rfft(periodic, axis=0)
    k = np.fft.rfftfreq(n, 1.0 / n).reshape((-1,) + (1,) * (values.ndim - 1))
    if n % 2 == 0:
        spectrum[-1] = 0.0  # the Nyquist term has no well-defined derivative
    d1 = np.fft.irfft(1j * k * spectrum, n=n, axis=0) + np.asarray(winding)
    d2 = np.fft.irfft(-(k**2) * spectrum, n=n, axis=0)
    return d1, d2


def _unwrapped(angles: np.ndarray) -> tuple:
    """Unwrapped angles (N, K) and their winding over the turn (K,)."""
    unwrapped = np.unwrap(angles, axis=0)
    closing = np.angle(np.exp(1j * (unwrapped[0] - unwrapped[-1])))  # last sample -> first of the next turn
    winding = np.round((unwrapped[-1] + closing - unwrapped[0]) / (2.0 * np.pi))
    return unwrapped, winding


def leg_table(linkage: Linkage, *, foot: str = "foot", samples: int = TABLE_SAMPLES) -> LegTable:
    """The LegTable of ``linkage`` (one crank turn, its crank at angle 2 pi n / samples; lengths as
    given, so the table's scale 1 is the linkage's own size). Raises ValueError when it cannot
    complete a crank turn."""
    geometry = replace(linkage, crank=replace(linkage.crank, phase=0.0, speed=0.0))  # neither moves a table
    key = (repr(geometry), foot, samples)
    if key not in _TABLES:
        if len(_TABLES) >= 64:
            _TABLES.pop(next(iter(_TABLES)))
        _TABLES[key] = _tabulate(linkage.name, foot, samples, geometry)
    return _TABLES[key]


_TABLES: dict = {}  # tables by geometry (a walker's legs share one: its family's at unit scale)


def _tabulate(name: str, foot: str, samples: int, linkage: Linkage) -> LegTable:
    psi = 2.0 * np.pi * np.arange(2 * samples) / (2 * samples)  # samples and the midpoints between them
    solution = solve_at([linkage], psi[None])[0]
    if not solution.feasible:
        raise ValueError(f"leg '{name}' cannot be tabulated: {solution.reason}")
    nodes = {k: v[0::2] for k, v in solution.nodes.items()}
    middle = {k: v[1::2] for k, v in solution.nodes.items()}
    K = len(linkage.links)
    angles = np.zeros((samples, K))
    local = []  # per link: centre of mass and nodes in the link frame (planar)
    for k, link in enumerate(linkage.links):
        a, b = nodes[link.nodes[0]], nodes[link.nodes[1]]
        angles[:, k] = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
        body = link_body(link.name, [world(nodes[n][0]) for n in link.nodes], BarStyle())
        c, s = np.cos(angles[0, k]), np.sin(angles[0, k])
        to_link = np.array([[c, s], [-s, c]])
        local.append((body.com[[0, 2]], [to_link @ (nodes[n][0] - a[0]) for n in link.nodes]))
    angles, winding = _unwrapped(angles)
    com = np.zeros((samples, K, 2))
    for k, link in enumerate(linkage.links):
        c, s = np.cos(angles[:, k]), np.sin(angles[:, k])
        com_local = local[k][0]
        com[:, k] = nodes[link.nodes[0]] + np.stack([c * com_local[0] - s * com_local[1],
                                                     s * com_local[0] + c * com_local[1]], axis=1)
    values = np.concatenate([com, angles[:, :, None]], axis=2)
    d1 = np.zeros_like(values)
    d2 = np.zeros_like(values)
    d1[..., :2], d2[..., :2] = periodic_derivatives(com)
    d1[..., 2], d2[..., 2] = periodic_derivatives(angles, winding)
    foot_node = linkage.points[foot]
    foot_xy = nodes[foot_node]
    f1, f2 = periodic_derivatives(foot_xy)
    pad = np.zeros((samples, 1))
    foot_link = next(k for k, link in enumerate(linkage.links) if foot_node in link.nodes)
    # the pivots placed by the links read from the table halfway between samples
    error = 0.0
    for k, link in enumerate(linkage.links):
        mid_values = 0.5 * (values[:, k] + np.roll(values[:, k], -1, axis=0))
        mid_values[-1, 2] += np.pi * winding[k]  # the angle's last interval wraps by a whole turn
        c, s = np.cos(mid_values[:, 2]), np.sin(mid_values[:, 2])
        com_local = local[k][0]
        origin = mid_values[:, :2] - np.stack([c * com_local[0] - s * com_local[1],
                                               s * com_local[0] + c * com_local[1]], axis=1)
        for node, offset in zip(link.nodes, local[k][1]):
            placed = origin + np.stack([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]], axis=1)
            error = max(error, float(np.abs(placed - middle[node]).max()))
    return LegTable(name, values, d1, d2, np.concatenate([foot_xy, pad], 1), np.concatenate([f1, pad], 1),
                    np.concatenate([f2, pad], 1), foot_link, [link.name for link in linkage.links], error)
