"""The tables of the tabulated path (host side, NumPy): one sub-chain's kinematics over a turn of
its driving coordinate q, and their cache.

A sub-chain (engine.reduced.tabulated_layout) is a planar linkage of mobility one, so every link
is a function of q: tabulate_sub_chain solves the loop-closure equations over a turn (continuation
and Newton from the spec's pose) and tabulates every link's planar centre of mass and angle with
their exact first and second derivatives in q (implicit function theorem).

Tables are at unit scale: plane coordinates (x, z) relative to the sub-chain's origin (its driving
pivot on the base) divided by the sub-chain's scale, so that sub-chains of one geometry up to a
uniform scale share a table. cached_table keeps them across calls by a key of that geometry
(tabulated_layout builds it); under one key, one table per assembly branch (a sub-chain whose start
is not on a cached table gets a table of its own).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["SubChainTable", "TABLE_SAMPLES", "cached", "cached_branches", "cached_table", "tabulate_sub_chain", "wrap"]

TABLE_SAMPLES = 512  # samples of a turn of the driving coordinate
START_TOLERANCE = 1e-3  # relative to the scale: how far the spec's start may be from a closed pose
NEWTON_TOLERANCE = 1e-12  # residual of the loop-closure equations at unit scale
MIN_STEP = 2.0 * math.pi / 2**16  # the smallest continuation step before a linkage counts as jammed
TABLE_CACHE = 256  # tables kept across packs (by key, oldest dropped first)

_TWO_PI = 2.0 * math.pi


def wrap(angle):
    """Angle(s) wrapped to (-pi, pi]."""
    return np.angle(np.exp(1j * np.asarray(angle)))


@dataclass
class SubChainTable:
    """One sub-chain's kinematics over a turn of its driving coordinate q, at unit scale.

    Sample n is at q = 2 pi n / N. links (N, K, 3): per link its centre of mass in the plane
    (x, z) relative to the sub-chain's origin [scale] and its planar angle phi [rad] (about the
    state frame's -y); links_d1, links_d2 their derivatives in q. contact (N, 3): the centre of
    the sub-chain's contact shape (x, z, and its constant offset along the normal), contact_d1,
    contact_d2; contact_link: the link that carries it (0 and zeros without a shape).
    closure_error: the largest distance [scale] between a joint's anchor (or the contact centre)
    placed by a link read from the table between samples (linearly, as the kernels read it) and
    the exact one, at the midpoints: the loop-closure error the table stands for. key: the cache
    key (engine.reduced.tabulated_layout's docstring)."""

    links: np.ndarray
    links_d1: np.ndarray
    links_d2: np.ndarray
    contact: np.ndarray
    contact_d1: np.ndarray
    contact_d2: np.ndarray
    contact_link: int
    closure_error: float
    key: tuple = ()

    @property
    def samples(self) -> int:
        """Samples of the turn (N)."""
        return int(self.links.shape[0])

    def between(self, q: float) -> tuple:
        """The samples around coordinate q [rad] and the weight of the second (i0, i1, f), as the
        kernels' table_index."""
        n = self.samples
        u = (q / _TWO_PI * n) % n
        i0 = min(int(u), n - 1)
        return i0, (i0 + 1) % n, u - i0

    def at(self, q: float) -> tuple:
        """Links (K, 3) and contact centre (3,) at q [rad], interpolated as the kernels do."""
        i0, i1, f = self.between(q)
        a, b = self.links[i0], self.links[i1]
        step = b - a
        step[:, 2] = wrap(step[:, 2])
        return a + f * step, (1.0 - f) * self.contact[i0] + f * self.contact[i1]


@dataclass
class _Planar:
    """A sub-chain's loop-closure problem at unit scale. Unknowns x (..., 3 K): per link its
    centre of mass (x, z) and angle phi. Joint j holds link ja[j]'s anchor ra[j] (table frame,
    relative to its centre) on link jb[j]'s anchor rb[j]; index K is the base, whose 'anchor' is
    a fixed point of the plane. The driving link d turns with q: phi_d = sign q + offset."""

    K: int
    ja: np.ndarray
    jb: np.ndarray
    ra: np.ndarray
    rb: np.ndarray
    drive: int
    sign: float
    offset: float

    def _extended(self, x):
        x = np.asarray(x, float)
        shape = x.shape[:-1]
        return np.concatenate([x.reshape(*shape, self.K, 3), np.zeros((*shape, 1, 3))], axis=-2)

    @staticmethod
    def _rot(phi, r):
        c, s = np.cos(phi), np.sin(phi)
        return np.stack([c * r[..., 0] - s * r[..., 1], s * r[..., 0] + c * r[..., 1]], axis=-1)

    def anchors(self, x) -> tuple:
        """Every joint's anchor as placed by its two sides (..., J, 2) each."""
        xe = self._extended(x)
        a, b = xe[..., self.ja, :], xe[..., self.jb, :]
        return a[..., :2] + self._rot(a[..., 2], self.ra), b[..., :2] + self._rot(b[..., 2], self.rb)

    def residual(self, x, q) -> np.ndarray:
        pa, pb = self.anchors(x)
        xe = self._extended(x)
        drive = xe[..., self.drive, 2] - (self.sign * np.asarray(q) + self.offset)
        return np.concatenate([(pa - pb).reshape(*pa.shape[:-2], -1), drive[..., None]], axis=-1)

    def jacobian(self, x) -> np.ndarray:
        xe = self._extended(x)
        shape = xe.shape[:-2]
        J = len(self.ja)
        out = np.zeros((*shape, 2 * J + 1, 3 * self.K + 3))
        rows = np.arange(J)
        for side, index, r in ((1.0, self.ja, self.ra), (-1.0, self.jb, self.rb)):
            d = self._rot(xe[..., index, 2], np.stack([-r[:, 1], r[:, 0]], axis=-1))
            out[..., 2 * rows, 3 * index] = side
            out[..., 2 * rows + 1, 3 * index + 1] = side
            out[..., 2 * rows, 3 * index + 2] = side * d[..., 0]
            out[..., 2 * rows + 1, 3 * index + 2] = side * d[..., 1]
        out[..., 2 * J, 3 * self.drive + 2] = 1.0
        return out[..., :3 * self.K]

    def newton(self, x, q, iterations: int = 12) -> tuple:
        """Newton on the closure equations at q from x: (x, converged (...,) bool)."""
        x = np.array(x, float)
        for _ in range(iterations):
            F = self.residual(x, q)
            done = np.abs(F).max(axis=-1) < NEWTON_TOLERANCE
            if done.all():
                return x, done
            try:
                dx = np.linalg.solve(self.jacobian(x), -F[..., None])[..., 0]
            except np.linalg.LinAlgError:
                return x, np.zeros(x.shape[:-1], bool)
            x = x + np.where(done[..., None], 0.0, dx)
        return x, np.abs(self.residual(x, q)).max(axis=-1) < NEWTON_TOLERANCE

    def derivatives(self, x) -> tuple:
        """dx/dq and d2x/dq2 at closed poses x (..., 3 K), from the implicit function theorem."""
        Jm = self.jacobian(x)
        rhs = np.zeros(Jm.shape[:-1])
        rhs[..., -1] = self.sign
        d1 = np.linalg.solve(Jm, rhs[..., None])[..., 0]
        xe, de = self._extended(x), self._extended(d1)
        g = []
        for index, r, side in ((self.ja, self.ra, 1.0), (self.jb, self.rb, -1.0)):
            g.append(side * self._rot(xe[..., index, 2], r) * (de[..., index, 2] ** 2)[..., None])
        rhs2 = np.concatenate([(g[0] + g[1]).reshape(*Jm.shape[:-2], -1), np.zeros((*Jm.shape[:-2], 1))], axis=-1)
        d2 = np.linalg.solve(Jm, rhs2[..., None])[..., 0]
        return d1, d2


def _continue_turn(planar: _Planar, x0: np.ndarray, q0: float, what: str) -> tuple:
    """Poses over one turn q0 .. q0 + 2 pi by continuation (tangent predictor, Newton corrector,
    step halved on a failed or large correction or a sign change of det J): returns the steps'
    offsets t (S,) from q0 and poses (S, 3 K). ValueError when the linkage jams or changes branch."""
    ts, xs = [0.0], [x0]
    t, x = 0.0, x0
    h = _TWO_PI / 64
    sign0 = np.linalg.slogdet(planar.jacobian(x0))[0]
    while t < _TWO_PI - 1e-12:
        step = min(h, _TWO_PI - t)
        d1, d2 = planar.derivatives(x)
        guess = x + step * d1 + 0.5 * step * step * d2
        y, ok = planar.newton(guess, q0 + t + step, iterations=8)
        good = bool(ok) and np.abs(y - guess).max() < 0.02 and np.linalg.slogdet(planar.jacobian(y))[0] == sign0
        if not good:
            h = 0.5 * step
            if h < MIN_STEP:
                raise ValueError(f"{what}: cannot make a full turn of its driving joint: it jams (the loop-closure "
                                 f"equations turn singular) at {wrap(q0 + t):.4f} rad")
            continue
        t, x = t + step, y
        ts.append(t)
        xs.append(x)
        h = min(2.0 * step, _TWO_PI / 64)
    back = y - x0
    back[2::3] = wrap(back[2::3])
    if np.abs(back).max() > 1e-6:
        raise ValueError(f"{what}: does not come back to its start after a full turn of its driving joint "
                         f"(it changes assembly branch; off by {np.abs(back).max():.3g} at unit scale)")
    return np.array(ts), np.array(xs)


def tabulate_sub_chain(planar: _Planar, x0: np.ndarray, q0: float, samples: int, contact: tuple | None,
                       what: str, key: tuple = ()) -> SubChainTable:
    """The SubChainTable of a sub-chain closed at pose x0 (unit scale) at its coordinate q0 [rad].
    contact: (link, local centre (x, y, z) in its table frame relative to its centre of mass [scale])
    or None. ValueError naming ``what`` when the linkage cannot make a full turn."""
    ts, xs = _continue_turn(planar, x0, q0, what)
    fine = 2 * samples  # the samples and the midpoints between them (closure error)
    angles = _TWO_PI * np.arange(fine) / fine
    offsets = (angles - q0) % _TWO_PI
    coarse = np.clip(np.searchsorted(ts, offsets), 1, len(ts) - 1)
    nearer = np.where(offsets - ts[coarse - 1] < ts[coarse] - offsets, coarse - 1, coarse)
    d1, d2 = planar.derivatives(xs)
    delta = offsets - ts[nearer]
    guess = xs[nearer] + delta[:, None] * d1[nearer] + 0.5 * (delta**2)[:, None] * d2[nearer]
    x, ok = planar.newton(guess, q0 + offsets)
    if not ok.all() or np.abs(x - guess).max() > 0.02:
        bad = int(np.argmin(ok)) if not ok.all() else int(np.abs(x - guess).max(axis=1).argmax())
        raise ValueError(f"{what}: the loop-closure equations do not converge near {wrap(angles[bad]):.4f} rad")
    x[:, 2::3] = wrap(x[:, 2::3])
    d1, d2 = planar.derivatives(x)
    K = planar.K
    values, v1, v2 = (a.reshape(fine, K, 3) for a in (x, d1, d2))
    # closure error: every joint's anchor placed by the links interpolated halfway between samples
    exact_a, _ = planar.anchors(x[1::2])
    before, after = values[0::2], np.roll(values[0::2], -1, axis=0)
    middle = 0.5 * (before + after)
    middle[..., 2] = before[..., 2] + 0.5 * wrap(after[..., 2] - before[..., 2])
    placed_a, placed_b = planar.anchors(middle.reshape(samples, -1))
    error = float(max(np.abs(placed_a - exact_a).max(), np.abs(placed_b - exact_a).max()))
    links, links_d1, links_d2 = values[0::2], v1[0::2], v2[0::2]
    centre = np.zeros((samples, 3))
    centre_d1 = np.zeros((samples, 3))
    centre_d2 = np.zeros((samples, 3))
    link = 0
    if contact is not None:
        link, local = contact
        phi, w1, w2 = links[:, link, 2], links_d1[:, link, 2], links_d2[:, link, 2]
        lxz = np.broadcast_to(np.array([local[0], local[2]]), (samples, 2))
        turned = _Planar._rot(phi, lxz)
        normal = np.stack([-turned[:, 1], turned[:, 0]], axis=1)
        centre[:, :2] = links[:, link, :2] + turned
        centre[:, 2] = local[1]
        centre_d1[:, :2] = links_d1[:, link, :2] + normal * w1[:, None]
        centre_d2[:, :2] = links_d2[:, link, :2] + normal * w2[:, None] - turned * (w1**2)[:, None]
        # the contact centre placed by its link halfway between samples, against the exact one
        exact = values[1::2, link]
        lxz = lxz[0]
        error = max(error, float(np.abs(middle[:, link, :2] + _Planar._rot(middle[:, link, 2], lxz)
                                        - exact[:, :2] - _Planar._rot(exact[:, 2], lxz)).max()))
    return SubChainTable(links, links_d1, links_d2, centre, centre_d1, centre_d2, int(link), error, key)


_TABLES: dict = {}  # cache key -> list of tables (one per assembly branch met)


def cached(key: tuple, table) -> bool:
    """Whether ``table`` is one of the tables cached under ``key`` now."""
    return table is not None and any(t is table for t in _TABLES.get(key, ()))


def cached_branches(key: tuple, x0: np.ndarray, q0: np.ndarray) -> list:
    """For sub-chains of one cache key at poses x0 (N, 3 K) and coordinates q0 (N,): the table
    cached_table would return from the tables cached now (the first branch whose pose at q0 is
    x0's), or None where none is (cached_table then makes one, or finds one made since). The
    branches are compared for all sub-chains at once; a sub-chain within 1e-9 of the tolerance
    is compared as cached_table compares it."""
    found = [None] * len(x0)
    open_ = np.arange(len(x0))
    for table in _TABLES.get(key, []):
        if not len(open_):
            break
        n = table.samples
        u = (q0[open_] / _TWO_PI * n) % n
        usable = np.isfinite(u)  # else cached_table decides (and raises)
        u = np.where(usable, u, 0.0)
        i0 = np.minimum(u.astype(int), n - 1)
        f = u - i0
        a, b = table.links[i0], table.links[(i0 + 1) % n]  # (M, K, 3)
        step = b - a
        step[..., 2] = wrap(step[..., 2])
        diff = (a + f[:, None, None] * step).reshape(len(open_), -1) - x0[open_]
        diff[:, 2::3] = wrap(diff[:, 2::3])
        worst = np.where(usable, np.abs(diff).max(axis=1), np.inf)
        near = np.abs(worst - START_TOLERANCE) < 1e-9
        for m in np.nonzero(near)[0]:  # at the tolerance: the scalar comparison decides
            links, _ = table.at(float(q0[open_[m]]))
            d = links.reshape(-1) - x0[open_[m]]
            d[2::3] = wrap(d[2::3])
            worst[m] = 0.0 if np.abs(d).max() < START_TOLERANCE else np.inf
        hit = worst < START_TOLERANCE
        for m in np.nonzero(hit)[0]:
            found[open_[m]] = table
        open_ = open_[~hit]
    return found


def canonical(key: tuple, x0: np.ndarray, q0: float, what: str) -> tuple:
    """The problem a new table of ``key`` is made from, whichever sub-chain asks first: the geometry
    the key holds (anchors, the driving angle's offset and the contact centre, rounded), and the
    pose of x0's assembly branch at q = 0 with angles in (-pi, pi], rounded to 1e-9 (Newton's
    solutions from different starts differ in their last bits, which a chaotic walk would
    amplify). So a table depends on its key alone: a study's results do not depend on which design
    made a table, on the order of a batch or on what a process packed before (morphopt.cluster).
    Returns (planar, x0 at q = 0, contact)."""
    _, K, pairs, ra, rb, drive, sign, turn, contact = key
    ja, jb = (np.array([p[i] for p in pairs], dtype=int) for i in (0, 1))
    planar = _Planar(K, ja, jb, np.array(ra).reshape(-1, 2), np.array(rb).reshape(-1, 2), drive, sign,
                     math.atan2(turn[1], turn[0]))
    x, ok = planar.newton(np.asarray(x0, float)[None], np.array([q0]))
    if not ok.all():
        raise ValueError(f"{what}: its start does not close the loop at its table's geometry")
    ts, xs = _continue_turn(planar, x[0], q0, what)
    i = int(np.argmin(np.abs(ts - (-q0) % _TWO_PI)))
    guess = xs[i].copy()
    guess[2::3] = wrap(guess[2::3])
    guess[3 * drive + 2] = planar.offset
    x, ok = planar.newton(guess[None], np.array([0.0]))
    if not ok.all():
        raise ValueError(f"{what}: the loop-closure equations do not converge at its coordinate's zero")
    for _ in range(2):  # to the last bits: starts on one branch then round alike
        x = x + np.linalg.solve(planar.jacobian(x), -planar.residual(x, np.array([0.0]))[..., None])[..., 0]
    start = np.round(x[0], 9)
    start[2::3] = wrap(start[2::3])
    start[3 * drive + 2] = planar.offset
    return planar, start, None if contact is None else (contact[0], np.array(contact[1], float))


def cached_table(key: tuple, planar: _Planar, x0: np.ndarray, q0: float, samples: int, contact, what: str):
    """The table of ``key`` whose pose at q0 is x0 (another assembly branch gets its own table), made
    from the key's canonical problem (canonical) when none is cached."""
    branches = _TABLES.get(key, [])
    for table in branches:
        links, _ = table.at(q0)
        diff = links.reshape(-1) - x0
        diff[2::3] = wrap(diff[2::3])
        if np.abs(diff).max() < START_TOLERANCE:
            return table
    planar, start, contact = canonical(key, x0, q0, what)
    table = tabulate_sub_chain(planar, start, 0.0, samples, contact, what, key)
    links, _ = table.at(q0)
    diff = links.reshape(-1) - x0
    diff[2::3] = wrap(diff[2::3])
    if np.abs(diff).max() >= START_TOLERANCE:  # (never seen: the canonical start is x0's branch)
        raise ValueError(f"{what}: its table's pose at its start is {np.abs(diff).max():.3g} (unit scale) from the "
                         f"spec's")
    if key not in _TABLES and len(_TABLES) >= TABLE_CACHE:
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES.setdefault(key, []).append(table)
    return table
