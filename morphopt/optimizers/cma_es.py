"""CMA-ES (pycma) on the unit cube of a design space, one population member per world."""

from __future__ import annotations

import cma
import numpy as np

from morphopt.optimizers.base import Optimizer

__all__ = ["CMAES"]


class CMAES(Optimizer):
    """pycma's CMAEvolutionStrategy with bounds [0, 1] on the unit-cube coordinates.

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
        options = {"popsize": max(population, 2), "bounds": [0.0, 1.0], "seed": self.seed + 1 + self.restarts_done,
                   "verbose": -9}
        return cma.CMAEvolutionStrategy(start, sigma or self.sigma0, options)

    def ask(self, count: int) -> list[dict]:
        if count != self.batch:
            raise ValueError(f"CMA-ES was set up for batches of {self.batch}, asked for {count}")
        self._pending = self.es.ask(number=count)
        return self.space.from_unit_many(self._pending)

    def tell(self, params, values) -> None:
        if self._pending is None or len(params) != len(self._pending):
            raise ValueError("CMA-ES: tell() must follow ask() with the same batch")
        super().tell(params, values)
        self.es.tell(self._pending, self.penalized(values).tolist())
        self._pending = None
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
        return self.space.from_unit(self.es.mean)
