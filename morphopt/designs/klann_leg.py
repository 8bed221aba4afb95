"""A Klann-type leg: a Stephenson III six-bar (crank, ternary coupler, two rockers, ternary leg).

Nodes: O crank axle, A upper and B lower frame pivots, M crank pin, C coupler-rocker joint, D end
of the ternary coupler (M, C, D), E leg-rocker joint, F the foot on the ternary leg (D, E, F).
The default dimensions were found by a search of this topology for a long flat stance and a high
foot lift (flat stance about 2.9 crank lengths, foot lift 3.1), scaled to a 15 mm crank like jansen_leg.
"""

from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Dyad, Link, Linkage, Offset

DEFAULTS = dict(ax=-0.268, ay=0.176, bx=-0.059, by=-0.383, mc=0.283, bc=0.481, d_along=0.909, d_across=0.23,
                de=0.681, ae=0.375, f_along=0.599, f_across=-0.868)  # for a 0.1 m crank
SCALE = 0.15  # -> 15 mm crank

MEANING = dict(ax="upper frame pivot A, horizontally from the crank axle O",
               ay="upper frame pivot A, vertically from the crank axle O",
               bx="lower frame pivot B, horizontally from the crank axle O",
               by="lower frame pivot B, vertically from the crank axle O",
               mc="crank pin M to coupler-rocker joint C (along the coupler)", bc="lower rocker: pivot B to joint C",
               d_along="coupler end D, along the coupler line M -> C from M",
               d_across="coupler end D, to the left of the coupler line M -> C",
               de="upper rocker's joint E to coupler end D (along the leg)", ae="upper rocker: pivot A to joint E",
               f_along="foot F, along the leg line D -> E from D", f_across="foot F, to the left of the leg line D -> E")

space = DesignSpace({"m": Float(0.012, 0.018, default=0.015, unit="m", help="crank radius: axle O to crank pin M"),
                     **{name: Float(min(0.8 * v, 1.2 * v) * SCALE, max(0.8 * v, 1.2 * v) * SCALE, default=v * SCALE,
                                    unit="m", help=MEANING[name])
                        for name, v in DEFAULTS.items()}})


def generate(params: dict, *, crank_speed: float = 2.0, phase: float = 0.0) -> Linkage:
    """The leg for ``params`` (lengths [m]); crank_speed [rad/s]."""
    p = params
    return Linkage(
        name="klann_leg",
        ground={"O": (0.0, 0.0), "A": (p["ax"], p["ay"]), "B": (p["bx"], p["by"])},
        crank=Crank("O", "M", p["m"], phase=phase, speed=crank_speed),
        dyads=[Dyad("C", "M", p["mc"], "B", p["bc"], branch=-1),
               Offset("D", "M", "C", p["d_along"], p["d_across"]),
               Dyad("E", "D", p["de"], "A", p["ae"], branch=-1),
               Offset("F", "D", "E", p["f_along"], p["f_across"])],
        links=[Link("crank", ("O", "M")), Link("coupler", ("M", "C", "D")), Link("lower_rocker", ("B", "C")),
               Link("upper_rocker", ("A", "E")), Link("leg", ("D", "E", "F"))],
        points={"foot": "F"},
    )
