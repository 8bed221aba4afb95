"""Theo Jansen's Strandbeest leg: a crank and eleven bars (two rigid triangles), one foot.

Default parameters are Jansen's published link lengths (the "holy numbers", here in metres at
1:100 scale of his millimetre drawing... i.e. 38 -> 0.038 m). Node names follow the usual
drawing: O crank axle, A fixed pivot, M crank pin, B / C upper and lower joints on the crank
links j and k, D the top of the upper triangle (A, B, D), E the knee, F the foot of the lower
triangle (C, E, F).
"""

from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Dyad, Link, Linkage

HOLY_NUMBERS = dict(a=38.0, b=41.5, c=39.3, d=40.1, e=55.8, f=39.4, g=36.7, h=65.7, i=49.0, j=50.0, k=61.9,
                    l=7.8, m=15.0)
SCALE = 1e-3  # the numbers are in millimetres

MEANING = dict(a="crank axle O to fixed pivot A, horizontally", b="fixed pivot A to upper joint B",
               c="fixed pivot A to lower joint C", d="fixed pivot A to top D of the upper triangle",
               e="upper joint B to top D (upper triangle A, B, D)", f="top D to knee E",
               g="lower joint C to knee E", h="knee E to foot F (lower triangle C, E, F)",
               i="lower joint C to foot F", j="crank pin M to upper joint B", k="crank pin M to lower joint C",
               l="crank axle O above fixed pivot A, vertically", m="crank radius: axle O to crank pin M")

space = DesignSpace({name: Float(0.8 * value * SCALE, 1.2 * value * SCALE, default=value * SCALE, unit="m",
                                 help=f"{MEANING[name]} (Jansen's {value:g} mm)")
                     for name, value in HOLY_NUMBERS.items()})


def generate(params: dict, *, crank_speed: float = 2.0, phase: float = 0.0) -> Linkage:
    """The leg for ``params`` (lengths [m]); crank_speed [rad/s]."""
    p = params
    return Linkage(
        name="jansen_leg",
        ground={"O": (0.0, 0.0), "A": (-p["a"], -p["l"])},
        crank=Crank("O", "M", p["m"], phase=phase, speed=crank_speed),
        dyads=[
            Dyad("B", "M", p["j"], "A", p["b"], branch=-1),  # upper joint, above A
            Dyad("C", "M", p["k"], "A", p["c"], branch=1),  # lower joint, below A
            Dyad("D", "B", p["e"], "A", p["d"], branch=-1),  # top of the upper triangle, outward
            Dyad("E", "D", p["f"], "C", p["g"], branch=-1),  # knee
            Dyad("F", "E", p["h"], "C", p["i"], branch=-1),  # foot
        ],
        links=[Link("crank", ("O", "M")), Link("link_j", ("M", "B")), Link("link_k", ("M", "C")),
               Link("upper", ("A", "B", "D")), Link("link_c", ("A", "C")), Link("link_f", ("D", "E")),
               Link("lower", ("C", "E", "F"))],
        points={"foot": "F"},
    )
