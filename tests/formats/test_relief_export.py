"""A spec whose ground has relief (engine.Relief) is refused by every exporter, by name: none of the
formats holds the bumps, and a ground written flat would silently simulate another world."""

import pytest

from engine import Body, GroundPlane, MechanismSpec, Relief, Shape
from morphopt.formats.mjcf import mjcf_string, write_mjcf
from morphopt.formats.urdf import write_urdf


def _spec():
    return MechanismSpec(bodies=[Body("ball", 1.0, [[1e-3, 0, 0], [0, 1e-3, 0], [0, 0, 1e-3]], position=(0, 0, 0.1))],
                         shapes=[Shape("s", "sphere", "ball", (0.05,))],
                         ground=GroundPlane(relief=Relief(0.01)), name="bumpy")


@pytest.mark.parametrize("write", [lambda s, d: write_mjcf(s, d / "m.xml"), lambda s, d: mjcf_string(s),
                                   lambda s, d: write_urdf(s, d / "m.urdf")])
def test_relief_is_refused_by_name(write, tmp_path):
    with pytest.raises(ValueError, match="mechanism 'bumpy': its ground has relief"):
        write(_spec(), tmp_path)
    assert not any(tmp_path.iterdir())  # nothing written


def test_usd_refuses_relief(tmp_path):
    pytest.importorskip("pxr")
    from morphopt.formats.usd import write_usd
    with pytest.raises(ValueError, match="its ground has relief.*USD"):
        write_usd(_spec(), tmp_path / "m.usda")
    assert not any(tmp_path.iterdir())
