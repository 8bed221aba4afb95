"""The source of a toy design family the study tests write next to their study files."""

TOY_FAMILY = '''
"""A crank alone: its tip's path is a circle of radius r (step height 2 r)."""
from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Link, Linkage

space = DesignSpace({"r": Float(0.01, 0.05, default=0.02), "x": Float(-1.0, 1.0, default=0.0)})


def generate(params, *, crank_speed=6.283185307179586, phase=0.0):
    return Linkage(name="toy", ground={"O": (params["x"], 0.0)},
                   crank=Crank("O", "T", params["r"], phase=phase, speed=crank_speed),
                   links=[Link("crank", ("O", "T"))], points={"tip": "T"})
'''
