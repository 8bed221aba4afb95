"""CMA-ES (pycma) on the unit cube of a design space, one population member per world."""

from __future__ import annotations

import math

import cma
import numpy as np

from morphopt.optimizers.base import Optimizer

__all__ = ["CMAES", "into_cube"]


# Widths of the quadratic tails at the lower and upper bound of [0, 1] (5 % of the interval).
_TAIL_LOW, _TAIL_HIGH = 0.05, 0.05


def into_cube(genotypes) -> np.ndarray:
    """Map unbounded CMA-ES coordinates into the unit cube, for a whole population at once (the
    same map as pycma's BoundTransform with bounds [0, 1], which applies it sample by sample).

    The map is the identity on [a, 1 - b] (a = b = 0.05), quadratic in the tails [-3 a, a]
    and [1 - b, 1 + 3 b] (continuous with slope 1 where it meets the identity, flat on the bound
    at -a and 1 + b), and continues periodically by reflection with period 2 (1 + a + b). So an
    optimum on a bound is reachable and a sample never leaves the cube.
    """
    a, b = _TAIL_LOW, _TAIL_HIGH
    half = 1.0 + a + b
    t = np.mod(np.asarray(genotypes, dtype=float) + a, 2.0 * half)
    x = np.where(t > half, 2.0 * half - t, t) - a  # in [-a, 1 + b]
    low = (x + a) ** 2 / (4.0 * a)
    high = 1.0 - (x - 1.0 - b) ** 2 / (4.0 * b)
    return np.clip(np.where(x < a, low, np.where(x > 1.0 - b, high, x)), 0.0, 1.0)


def _identity(x, copy_if_changed=True):
    return x


class CMAES(Optimizer):
    """pycma's CMAEvolutionStrategy on the unit-cube coordinates of a design space.

    pycma runs with bounds [0, 1] (its BoundTransform), but the transformation of the samples into
    the cube is done here for the whole population in one NumPy expression (into_cube, the same
    map) instead of sample by sample inside pycma (~70 ms of an ask of 4096): during ask pycma's
    repair is the identity, so it hands out and archives the samples themselves, and tell gives
    them back; the search is the same as with pycma's own transformation.

    Args:
        space: the DesignSpace; integers and choices are decoded from their unit coordinate.
        popsize: designs per generation (the batch size: worlds per batch).
        sigma0: initial step size in the unit cube.
        x0: starting design (default: the space's defaults).
        seed: pycma's seed (reproducible runs).
        restarts: number of restarts, each from a random point once pycma's stop criteria fire.
            With restarts the strategy starts from pycma's default population (4 + 3 ln n).
        restart_strategy: "ipop" doubles the population at every restart (up to the batch size);
            "bipop" alternates that large-population regime with a small-population regime
            (population default * (large / 2 default)^(U^2), step size sigma0 * 10^(-2 U), U uniform
            in [0, 1]), choosing at each restart the regime that has used fewer generations.
        Every generation fills the whole batch whatever the population (pycma ranks all the samples
        told), so a small population costs as much as a large one per generation.
    Failed designs are told as a penalty (pycma would silently replace NaN by the median).
    """

    def __init__(self, space, *, popsize: int, sigma0: float = 0.25, x0: dict | None = None, seed: int = 0,
                 restarts: int = 0, restart_strategy: str = "ipop"):
        super().__init__(space, seed=seed)
        if restart_strategy not in ("ipop", "bipop"):
            raise ValueError(f"CMA-ES restart_strategy must be 'ipop' or 'bipop', got {restart_strategy!r}")
        self.restart_strategy = restart_strategy
        if popsize < 2:
            raise ValueError(f"CMA-ES needs a population of at least 2, got {popsize}")
        if restarts < 0:
            raise ValueError(f"CMA-ES restarts must be >= 0, got {restarts}")
        self.batch, self.sigma0, self.restarts_left, self.restarts_done = popsize, sigma0, restarts, 0
        self.default_population = max(2, min(popsize, 4 + int(3 * np.log(space.dimension))))
        population = popsize if restarts == 0 else self.default_population
        self.large_population = population
        self.regime = "large"  # BIPOP: the first run counts as the large regime
        self.generations_in = {"large": 0, "small": 0}
        self.runs = [("large", population)]  # (regime, population) of every run, in order
        self.es = self._strategy(space.to_unit(x0 or space.default()), population)
        self.popsize = popsize
        self._pending: list[np.ndarray] | None = None

    def _strategy(self, start, population: int, sigma: float | None = None):
        # pycma samples from NumPy's global generator unless given its own; a private one (seeded as pycma
        # would seed the global one: the same samples) keeps the search independent of other code's draws
        self.randn_state = np.random.RandomState(self.seed + 1 + self.restarts_done)
        options = {"popsize": max(population, 2), "bounds": [0.0, 1.0], "seed": math.nan,
                   "randn": self.randn_state.randn, "verbose": -9}
        return cma.CMAEvolutionStrategy(start, sigma or self.sigma0, options)

    def ask(self, count: int) -> list[dict]:
        if count != self.batch:
            raise ValueError(f"CMA-ES was set up for batches of {self.batch}, asked for {count}")
        handler = self.es.boundary_handler
        handler.repair = _identity  # an instance attribute over the class's method, for this ask only
        try:
            self._pending = self.es.ask(number=count)
        finally:
            del handler.repair
        return self.space.from_unit_many(into_cube(self._pending))

    def tell(self, params, values) -> None:
        if self._pending is None or len(params) != len(self._pending):
            raise ValueError("CMA-ES: tell() must follow ask() with the same batch")
        super().tell(params, values)
        self.es.tell(self._pending, self.penalized(values).tolist())
        self.es._tell2_args = None  # pycma's copy of tell's arguments, for inspection only: kept, every
        self._pending = None        # checkpoint would pickle its population array by array (10 ms at 4096)
        self.generations_in[self.regime] += 1
        if self.restarts_left > 0 and self.es.stop():
            self.restarts_left -= 1
            self.restarts_done += 1
            sigma = self.sigma0
            if self.restart_strategy == "bipop" and self.generations_in["small"] < self.generations_in["large"]:
                self.regime = "small"
                u = self.rng.random()
                ratio = max(1.0, 0.5 * self.large_population / self.default_population)
                population = max(2, int(self.default_population * ratio ** (u * u)))
                sigma = self.sigma0 * 10.0 ** (-2.0 * self.rng.random())
            else:
                self.regime = "large"
                self.large_population = min(2 * self.large_population, self.batch)
                population = self.large_population
            self.runs.append((self.regime, population))
            self.es = self._strategy(self.rng.random(self.space.dimension), population, sigma)

    @property
    def mean(self) -> dict:
        """The distribution mean as a design."""
        return self.space.from_unit(into_cube(self.es.mean))  # pycma's mean is a genotype
