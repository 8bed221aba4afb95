"""Four-bar crank-rocker with a coupler point: the classic coupler-curve synthesis family.

Ground pivots O (crank) and D (rocker) on the x axis, crank O-M, coupler M-C, rocker D-C; the
tracked point P rides on the coupler at ``point_u`` of the way from M to C and ``point_v`` [m]
to its left.
"""

import math

import numpy as np

from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Dyad, Link, Linkage

space = DesignSpace({
    "ground": Float(0.15, 0.45, default=0.30, unit="m", help="ground link: crank pivot O to rocker pivot D"),
    "crank": Float(0.04, 0.15, default=0.10, unit="m", help="crank: pivot O to crank pin M"),
    "coupler": Float(0.15, 0.45, default=0.30, unit="m", help="coupler: crank pin M to rocker joint C"),
    "rocker": Float(0.10, 0.40, default=0.25, unit="m", help="rocker: pivot D to joint C"),
    "point_u": Float(-0.5, 1.5, default=0.5, unit="", help="coupler point P along M -> C, as a fraction of the coupler"),
    "point_v": Float(-0.2, 0.2, default=0.1, unit="m", help="coupler point P to the left of the line M -> C"),
})


def generate(params: dict, *, crank_speed: float = 2.0 * math.pi, phase: float = 0.0) -> Linkage:
    """The four-bar for ``params`` (lengths [m]; floats, or arrays for a batch of designs)."""
    p = params
    along, side = p["point_u"] * p["coupler"], p["point_v"]
    to_m = np.hypot(along, side)
    to_c = np.hypot(p["coupler"] - along, side)
    return Linkage(
        name="four_bar",
        ground={"O": (0.0, 0.0), "D": (p["ground"], 0.0)},
        crank=Crank("O", "M", p["crank"], phase=phase, speed=crank_speed),
        dyads=[Dyad("C", "M", p["coupler"], "D", p["rocker"], branch=1),
               Dyad("P", "M", np.maximum(to_m, 1e-9), "C", np.maximum(to_c, 1e-9), branch=np.where(side >= 0, 1, -1))],
        links=[Link("crank", ("O", "M")), Link("coupler", ("M", "C", "P")), Link("rocker", ("D", "C"))],
        points={"coupler_point": "P"},
    )
