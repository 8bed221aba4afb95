"""Optimizer conformance: every optimizer honours the ask/tell contract; each finds a toy optimum."""

import math

import numpy as np
import pytest

from morphopt.design_space import Choice, DesignSpace, Float, Int
from morphopt.optimizers import OPTIMIZERS


def make(name, space, batch, seed):
    cls = OPTIMIZERS[name]
    return cls(space, popsize=batch, seed=seed) if name == "cma" else cls(space, seed=seed)


def sphere_space():
    return DesignSpace({"x": Float(-2.0, 2.0, default=1.5), "y": Float(-2.0, 2.0, default=-1.5)})


@pytest.mark.parametrize("name", sorted(OPTIMIZERS))
def test_conformance(name):
    """ask returns in-bounds designs of the space; tell accepts failures; same seed, same designs;
    the best design is tracked."""
    space = DesignSpace({"a": Float(0.0, 1.0), "n": Int(1, 4), "c": Choice(("p", "q"))})
    runs = []
    for _ in range(2):
        opt = make(name, space, 8, seed=3)
        asked = []
        for generation in range(3):
            batch = opt.ask(8)
            assert len(batch) == 8
            for params in batch:
                space.validate(params)
            values = [p["a"] + p["n"] if i % 3 else math.inf for i, p in enumerate(batch)]
            opt.tell(batch, values)
            asked.append(batch)
        runs.append((asked, opt.best_value, opt.best_params))
    assert runs[0] == runs[1]
    assert math.isfinite(runs[0][1]) and opt.evaluations == 24


@pytest.mark.parametrize("name, budget, tolerance", [("cma", 30, 1e-3), ("random", 40, 0.2), ("optuna", 12, 0.1)])
def test_finds_the_optimum_of_a_shifted_sphere(name, budget, tolerance):
    """On (x - 0.3)^2 + (y + 0.7)^2 the optimizer gets within ``tolerance`` of (0.3, -0.7)."""
    opt = make(name, sphere_space(), 16, seed=1)
    for _ in range(budget):
        batch = opt.ask(16)
        opt.tell(batch, [(p["x"] - 0.3) ** 2 + (p["y"] + 0.7) ** 2 for p in batch])
    best = opt.best_params
    assert math.hypot(best["x"] - 0.3, best["y"] + 0.7) < tolerance


def test_cma_ranks_failures_last():
    """Failed designs get a penalty worse than every finite value, so the mean moves away from them."""
    opt = OPTIMIZERS["cma"](sphere_space(), popsize=12, seed=0)
    for _ in range(25):
        batch = opt.ask(12)
        # everything with x < 0 "fails"; the optimum of x^2 + y^2 restricted to x >= 0 is at x = 0
        opt.tell(batch, [math.nan if p["x"] < 0 else p["x"] ** 2 + p["y"] ** 2 for p in batch])
    assert opt.best_params["x"] >= 0 and opt.best_value < 1e-3
    assert np.isfinite(opt.penalized([math.inf])).all()


def test_cma_ipop_restarts_double_the_population():
    """With IPOP restarts the strategy restarts once it has converged, doubles its population up
    to the batch size, keeps filling whole batches and keeps the best design found."""
    space = sphere_space()
    opt = OPTIMIZERS["cma"](space, popsize=32, seed=2, restarts=3)
    populations = [opt.es.popsize]
    for _ in range(150):
        batch = opt.ask(32)
        assert len(batch) == 32
        opt.tell(batch, [(p["x"] - 0.3) ** 2 + (p["y"] + 0.7) ** 2 for p in batch])
        if opt.es.popsize != populations[-1]:
            populations.append(opt.es.popsize)
    assert opt.restarts_done >= 2
    assert populations[:3] == [6, 12, 24] and max(populations) <= 32
    assert opt.best_value < 1e-8


def test_cma_bipop_alternates_large_and_small_populations():
    """BIPOP on a multimodal function (a bowl with ripples, global minimum 0 at (0.3, -0.7)):
    after the first run, restarts alternate between the doubling large-population regime and
    small populations between the default and half the current large one, balancing the
    generations spent in each; the global minimum is found."""
    import math

    space = sphere_space()
    opt = OPTIMIZERS["cma"](space, popsize=48, seed=4, restarts=12, restart_strategy="bipop")

    def f(p):
        dx, dy = p["x"] - 0.3, p["y"] + 0.7
        return dx * dx + dy * dy + 0.05 * (2.0 - math.cos(20 * math.pi * dx) - math.cos(20 * math.pi * dy))

    for _ in range(400):
        batch = opt.ask(48)
        opt.tell(batch, [f(p) for p in batch])
    default = opt.default_population
    assert opt.restarts_done >= 4
    assert opt.runs[0] == ("large", default)
    large = [p for regime, p in opt.runs if regime == "large"]
    assert len(large) >= 2 and large == [min(default * 2**k, 48) for k in range(len(large))]
    for k, (regime, p) in enumerate(opt.runs):
        if regime == "small":  # between the default and half the large population reached before it
            reached = max(q for r, q in opt.runs[:k] if r == "large")
            assert default <= p <= max(default, reached // 2)
    spent = opt.generations_in
    assert spent["small"] > 0 and spent["large"] > 0
    assert opt.best_value < 1e-6
    with pytest.raises(ValueError, match="restart_strategy"):
        OPTIMIZERS["cma"](space, popsize=8, restart_strategy="lbfgs")


def test_cma_maps_samples_into_the_unit_cube_like_pycma():
    """The population-wide map into the cube equals pycma's own BoundTransform sample by sample
    (identity inside, quadratic tails, periodic outside), and a CMA-ES run hands out the same
    designs as pycma's ask with its bounds option would, generation after generation."""
    import cma

    from morphopt.optimizers.cma_es import into_cube

    x = np.linspace(-7.0, 8.0, 3001)
    reference = cma.transformations.BoxConstraintsLinQuadTransformation([[0.0, 1.0]])
    assert np.abs(into_cube(x) - np.array([reference.transform([v])[0] for v in x])).max() < 1e-12
    space = DesignSpace({"x": Float(-2.0, 2.0, default=1.9), "y": Float(-2.0, 2.0, default=0.0)})

    def value(p):
        return (p["x"] - 2.0) ** 2 + (p["y"] - 0.5) ** 2

    opt = OPTIMIZERS["cma"](space, popsize=16, seed=0, sigma0=0.4)  # pycma seeds NumPy's global generator:
    ours = []  # run the two strategies one after the other
    for _ in range(30):
        ours.append(opt.ask(16))
        opt.tell(ours[-1], [value(p) for p in ours[-1]])
    plain = cma.CMAEvolutionStrategy(space.to_unit(space.default()), 0.4,
                                     {"popsize": 16, "bounds": [0.0, 1.0], "seed": 1, "verbose": -9})
    for batch in ours:
        asked = plain.ask()
        expected = space.from_unit_many(asked)
        assert all(abs(a[k] - b[k]) < 1e-12 for a, b in zip(batch, expected) for k in ("x", "y"))
        plain.tell(asked, [value(p) for p in expected])
    assert opt.best_params["x"] > 1.99 and abs(opt.best_params["y"] - 0.5) < 1e-2
