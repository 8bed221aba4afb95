"""DesignSpace: bounds, unit-cube maps, sampling, validation and Optuna distributions."""

import numpy as np
import pytest

from morphopt.design_space import Choice, DesignSpace, Float, Int


def space():
    return DesignSpace({"length": Float(0.1, 0.5, default=0.2), "stiffness": Float(1.0, 1000.0, log=True),
                        "legs": Int(2, 6, default=4), "family": Choice(("jansen", "klann"))})


def test_unit_cube_round_trip():
    """to_unit then from_unit returns the same parameters (floats to 1e-12, ints and choices exactly)."""
    s = space()
    rng = np.random.default_rng(0)
    for params in s.sample(rng, 50):
        back = s.from_unit(s.to_unit(params))
        assert back["legs"] == params["legs"] and back["family"] == params["family"]
        assert abs(back["length"] - params["length"]) < 1e-12
        assert abs(back["stiffness"] - params["stiffness"]) < 1e-9 * params["stiffness"]


def test_samples_stay_in_bounds_and_cover_choices():
    """Uniform samples respect every bound and reach every integer and choice."""
    s = space()
    samples = s.sample(np.random.default_rng(1), 400)
    assert all(0.1 <= p["length"] <= 0.5 and 1.0 <= p["stiffness"] <= 1000.0 for p in samples)
    assert {p["legs"] for p in samples} == {2, 3, 4, 5, 6}
    assert {p["family"] for p in samples} == {"jansen", "klann"}
    # log scale: about half the samples below the geometric mean
    below = np.mean([p["stiffness"] < np.sqrt(1000.0) for p in samples])
    assert 0.4 < below < 0.6


def test_out_of_range_and_unknown_parameters_are_named():
    """validate names the offending parameter."""
    s = space()
    good = s.default()
    with pytest.raises(ValueError, match="'length' = 0.9 is outside reals in"):
        s.validate({**good, "length": 0.9})
    with pytest.raises(ValueError, match="'legs' = 3.5"):
        s.validate({**good, "legs": 3.5})
    with pytest.raises(ValueError, match="unknown design parameter"):
        s.validate({**good, "wings": 2})
    with pytest.raises(ValueError, match="'family' is missing"):
        s.validate({k: v for k, v in good.items() if k != "family"})


def test_bad_definitions_are_rejected():
    """Inverted bounds, log ranges through zero and bad defaults are errors at definition."""
    with pytest.raises(ValueError, match="'x'.*low < high"):
        DesignSpace({"x": Float(1.0, 0.5)})
    with pytest.raises(ValueError, match="'x'.*log"):
        DesignSpace({"x": Float(0.0, 1.0, log=True)})
    with pytest.raises(ValueError, match="'c'.*default"):
        DesignSpace({"c": Choice(("a", "b"), default="z")})


def test_optuna_distributions_match():
    """The Optuna distributions have the same bounds, log flags and choices."""
    import optuna

    dists = space().optuna_distributions()
    assert isinstance(dists["length"], optuna.distributions.FloatDistribution) and dists["length"].high == 0.5
    assert dists["stiffness"].log and dists["legs"].low == 2 and dists["family"].choices == ("jansen", "klann")


def test_from_unit_many_equals_from_unit_row_by_row():
    """The column-at-a-time decoding used for whole batches gives from_unit's values for every row
    (floats to 1e-15 relative, integers and choices exactly), clipping rows outside the cube."""
    s = DesignSpace({"x": Float(-1.0, 2.0), "y": Float(1e-3, 10.0, log=True), "n": Int(1, 4),
                     "kind": Choice(("jansen", "klann", 3))})
    units = np.random.default_rng(4).uniform(-0.2, 1.2, size=(500, 4))
    units[:4] = [[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], [0.25, 0.5, 0.75, 1 / 3], [0.5, 0.5, 0.5, 2 / 3]]
    for row, many in zip(units, s.from_unit_many(units)):
        one = s.from_unit(row)
        assert many["n"] == one["n"] and isinstance(many["n"], int)
        assert many["kind"] == one["kind"]
        for name in ("x", "y"):
            assert abs(many[name] - one[name]) <= 1e-15 * max(1.0, abs(one[name]))
