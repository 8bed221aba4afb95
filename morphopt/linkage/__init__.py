"""Planar linkage generator: kinematic graphs, batched cycle kinematics, the one conversion to
engine.MechanismSpec."""

from morphopt.linkage.graph import Crank, Dyad, Link, Linkage
from morphopt.linkage.kinematics import CycleSolution, solve_at, solve_cycles
from morphopt.linkage.to_spec import BarStyle, to_spec

__all__ = ["BarStyle", "Crank", "CycleSolution", "Dyad", "Link", "Linkage", "solve_at", "solve_cycles", "to_spec"]
