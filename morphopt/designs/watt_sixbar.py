"""Watt II six-bar: a crank-rocker four-bar whose rocker, extended past its pivot as a lever,
drives a second four-bar; the tracked point rides on the second coupler.

Nodes: O crank pivot, D rocker pivot, F second rocker pivot (ground); M crank pin; C first coupler
joint; E lever end (on the rocker line beyond D); H second coupler joint; P coupler point.
"""

import math

from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Dyad, Link, Linkage, Offset

space = DesignSpace({
    "ground": Float(0.2, 0.4, default=0.30, unit="m", help="crank pivot O to rocker pivot D (on the x axis)"),
    "crank": Float(0.05, 0.14, default=0.10, unit="m", help="crank: pivot O to crank pin M"),
    "coupler": Float(0.2, 0.4, default=0.30, unit="m", help="first coupler: crank pin M to joint C"),
    "rocker": Float(0.15, 0.35, default=0.25, unit="m", help="rocker: pivot D to joint C"),
    "lever": Float(0.05, 0.2, default=0.10, unit="m", help="rocker's lever past its pivot: D to lever end E"),
    "pivot2_x": Float(0.3, 0.7, default=0.50, unit="m", help="second rocker pivot F, horizontally from O"),
    "pivot2_y": Float(-0.3, 0.1, default=-0.15, unit="m", help="second rocker pivot F, vertically from O"),
    "coupler2": Float(0.15, 0.4, default=0.25, unit="m", help="second coupler: lever end E to joint H"),
    "rocker2": Float(0.1, 0.35, default=0.20, unit="m", help="second rocker: pivot F to joint H"),
    "point_u": Float(-0.5, 1.5, default=0.5, unit="",
                     help="coupler point P along E -> H, as a fraction of the second coupler"),
    "point_v": Float(-0.15, 0.15, default=0.05, unit="m", help="coupler point P to the left of the line E -> H"),
})


def generate(params: dict, *, crank_speed: float = 2.0 * math.pi, phase: float = 0.0) -> Linkage:
    """The six-bar for ``params`` (lengths [m])."""
    p = params
    return Linkage(
        name="watt_sixbar",
        ground={"O": (0.0, 0.0), "D": (p["ground"], 0.0), "F": (p["pivot2_x"], p["pivot2_y"])},
        crank=Crank("O", "M", p["crank"], phase=phase, speed=crank_speed),
        dyads=[Dyad("C", "M", p["coupler"], "D", p["rocker"], branch=1),
               Offset("E", "D", "C", -p["lever"]),
               Dyad("H", "E", p["coupler2"], "F", p["rocker2"], branch=-1),
               Offset("P", "E", "H", p["point_u"] * p["coupler2"], p["point_v"])],
        links=[Link("crank", ("O", "M")), Link("coupler", ("M", "C")), Link("rocker", ("D", "C", "E")),
               Link("coupler2", ("E", "H", "P")), Link("rocker2", ("F", "H"))],
        points={"coupler_point": "P"},
    )
