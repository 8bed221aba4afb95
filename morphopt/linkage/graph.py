"""Planar linkages as kinematic graphs: ground pivots, one driving crank, RRR dyads, rigid links.

Coordinates are planar (x, y) [m] with y up; engine.MechanismSpec puts the plane at y = 0 of
the world (planar x -> world x, planar y -> world z) with every pivot turning about world -y, so
that a positive planar angle is counter-clockwise.

Nodes are solved in order: ground pivots are fixed, the crank tip turns about its centre, and each
entry of ``dyads`` places a new node: a Dyad at distance ``ra`` from node ``a`` and ``rb`` from
node ``b``, on the ``branch`` side (+1: left of the direction a -> b, -1: right); an Offset at
fixed coordinates in the frame of two placed nodes. Links name the rigid bodies: each
is a set of nodes whose distances never change (binary bars, ternary plates, the crank).

A batched linkage holds many designs of one topology at once: any number (coordinate, length,
phase, branch) may be a (D,) array instead of a float. Families whose generate function is
written with NumPy operations get batched linkages for free (morphopt.evaluate calls generate once
per topology with arrays of parameters); the per-design checks of the numbers then happen in the
kinematics, which report a design that cannot close as infeasible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

__all__ = ["Crank", "Dyad", "Link", "Linkage", "Offset"]


@dataclass(frozen=True)
class Crank:
    """The driver: node ``tip`` at ``radius`` [m] from ground node ``center``, at angle
    ``phase + speed * t`` [rad] (speed in [rad/s], counter-clockwise positive)."""

    center: str
    tip: str
    radius: float
    phase: float = 0.0
    speed: float = 2.0 * math.pi


@dataclass(frozen=True)
class Dyad:
    """RRR dyad: node ``node`` at distance ``ra`` from node ``a`` and ``rb`` from node ``b``."""

    node: str
    a: str
    ra: float
    b: str
    rb: float
    branch: int = 1


@dataclass(frozen=True)
class Offset:
    """A node fixed in the frame of nodes a -> b: ``along`` [m] in the direction a -> b and
    ``across`` [m] to its left (coupler points, collinear extensions, ternary plates)."""

    node: str
    a: str
    b: str
    along: float
    across: float = 0.0


@dataclass(frozen=True)
class Link:
    """A rigid body through ``nodes`` (at least two)."""

    name: str
    nodes: tuple


@dataclass
class Linkage:
    """One planar linkage design (see the module docstring)."""

    name: str
    ground: dict
    crank: Crank
    dyads: list = field(default_factory=list)
    links: list = field(default_factory=list)
    points: dict = field(default_factory=dict)

    def __post_init__(self):
        where = f"linkage '{self.name}'"
        self.ground = {k: (_number(v[0]), _number(v[1])) for k, v in self.ground.items()}
        self.crank = _plain(self.crank)
        self.dyads = [_plain(d) for d in self.dyads]
        batched = self.batch_size is not None
        known = set(self.ground)
        if self.crank.center not in known:
            raise ValueError(f"{where}: crank centre '{self.crank.center}' is not a ground pivot")
        if batched:
            if any(isinstance(d, Dyad) and not np.all(np.isin(d.branch, (1, -1))) for d in self.dyads):
                raise ValueError(f"{where}: every dyad branch must be +1 or -1")
        elif not self.crank.radius > 0.0:
            raise ValueError(f"{where}: crank radius must be positive, got {self.crank.radius}")
        known.add(self.crank.tip)
        for dyad in self.dyads:
            for end in (dyad.a, dyad.b):
                if end not in known:
                    raise ValueError(f"{where}: node '{dyad.node}' uses node '{end}' before it is placed")
            if dyad.node in known:
                raise ValueError(f"{where}: node '{dyad.node}' is placed twice")
            if isinstance(dyad, Dyad) and not batched and (not (dyad.ra > 0.0 and dyad.rb > 0.0)
                                                           or dyad.branch not in (1, -1)):
                raise ValueError(f"{where}: dyad '{dyad.node}' needs positive lengths and branch +1 or -1")
            known.add(dyad.node)
        for link in self.links:
            if len(link.nodes) < 2:
                raise ValueError(f"{where}: link '{link.name}' needs at least two nodes")
            for node in link.nodes:
                if node not in known:
                    raise ValueError(f"{where}: link '{link.name}' names unknown node '{node}'")
        for point, node in self.points.items():
            if node not in known:
                raise ValueError(f"{where}: tracked point '{point}' names unknown node '{node}'")

    @property
    def batch_size(self) -> int | None:
        """D when some number is a (D,) array (a batched linkage), None for a single design."""
        numbers = [*(c for xy in self.ground.values() for c in xy), self.crank.radius, self.crank.phase]
        for d in self.dyads:
            numbers += [d.along, d.across] if isinstance(d, Offset) else [d.ra, d.rb, d.branch]
        numbers = [x for x in numbers if type(x) not in _SCALARS]  # plain numbers have no length
        sizes = {np.shape(x)[0] for x in numbers if np.ndim(x) == 1}
        if any(np.ndim(x) > 1 for x in numbers) or len(sizes) > 1:
            raise ValueError(f"linkage '{self.name}': numbers must be floats or (D,) arrays of one length, "
                             f"got lengths {sorted(sizes)}")
        return sizes.pop() if sizes else None

    @property
    def nodes(self) -> list[str]:
        """All nodes in solving order."""
        return [*self.ground, self.crank.tip, *(d.node for d in self.dyads)]

    @property
    def topology(self) -> tuple:
        """Everything but the numbers: designs with equal topology solve in one batch."""
        return (tuple(self.ground), (self.crank.center, self.crank.tip),
                tuple((type(d).__name__, d.node, d.a, d.b, getattr(d, "branch", 0)) for d in self.dyads),
                tuple((link.name, tuple(link.nodes)) for link in self.links), tuple(self.points.items()))


_SCALARS = (float, int)


def _number(value):
    """A float, or a float64 array for a batched linkage."""
    if type(value) is float:
        return value
    return float(value) if np.ndim(value) == 0 else np.asarray(value, dtype=np.float64)


def _plain(item):
    """The item with 0-d NumPy numbers turned into Python numbers (NumPy-written families)."""
    if not any(isinstance(value, np.ndarray | np.generic) for value in vars(item).values()):
        return item  # nothing to turn (the fields of these dataclasses are all there is in vars)
    zero_d = {f.name: getattr(item, f.name).item() for f in fields(item)
              if isinstance(getattr(item, f.name), np.ndarray | np.generic) and np.ndim(getattr(item, f.name)) == 0}
    return replace(item, **zero_d) if zero_d else item
