"""A toy design family the study tests write next to their study files, and a kinematic study of it."""

import textwrap

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


def toy_study(tmp_path, generations: int = 3, worlds: int = 4, extra: str = ""):
    """toy.py and toy.toml in ``tmp_path``: maximize the tip's step height, 32 samples a turn."""
    (tmp_path / "toy.py").write_text(TOY_FAMILY)
    path = tmp_path / "toy.toml"
    path.write_text(textwrap.dedent(f"""
        [study]
        name = "toy"
        family = "{(tmp_path / 'toy.py').as_posix()}"
        generations = {generations}
        worlds = {worlds}
        [objective]
        metric = "tip_step_height"
        direction = "maximize"
        [simulation]
        samples = 32
    """) + textwrap.dedent(extra))
    return path
