"""Planar linkage generator: kinematic graphs, batched cycle kinematics, the one conversion to
engine.MechanismSpec."""

from morphopt.linkage.graph import Crank, Dyad, Link, Linkage, Offset
from morphopt.linkage.kinematics import CycleSolution, solve_at, solve_cycles
from morphopt.linkage.to_spec import BarStyle, linkage_parts, to_spec

__all__ = ["BarStyle", "Crank", "CycleSolution", "Dyad", "Link", "Linkage", "Offset", "linkage_parts", "solve_at", "solve_cycles", "to_spec"]
