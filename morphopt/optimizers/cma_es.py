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
        restarts: IPOP restarts. With restarts the strategy starts from pycma's default population
            (4 + 3 ln n) and doubles it at every restart from a random point, up to the batch
            size; every generation still fills the whole batch (pycma ranks all the samples told).
    Failed designs are told as a penalty (pycma would silently replace NaN by the median).
    """

    def __init__(self, space, *, popsize: int, sigma0: float = 0.25, x0: dict | None = None, seed: int = 0,
                 restarts: int = 0):
        super().__init__(space, seed=seed)
        if popsize < 2:
            raise ValueError(f"CMA-ES needs a population of at least 2, got {popsize}")
        if restarts < 0:
            raise ValueError(f"CMA-ES restarts must be >= 0, got {restarts}")
        self.batch, self.sigma0, self.restarts_left, self.restarts_done = popsize, sigma0, restarts, 0
        population = popsize if restarts == 0 else min(popsize, 4 + int(3 * np.log(space.dimension)))
        self.es = self._strategy(space.to_unit(x0 or space.default()), population)
        self.popsize = popsize
        self._pending: list[np.ndarray] | None = None

    def _strategy(self, start, population: int):
        options = {"popsize": max(population, 2), "bounds": [0.0, 1.0], "seed": self.seed + 1 + self.restarts_done,
                   "verbose": -9}
        return cma.CMAEvolutionStrategy(start, self.sigma0, options)

    def ask(self, count: int) -> list[dict]:
        if count != self.batch:
            raise ValueError(f"CMA-ES was set up for batches of {self.batch}, asked for {count}")
        self._pending = self.es.ask(number=count)
        return [self.space.from_unit(x) for x in self._pending]

    def tell(self, params, values) -> None:
        if self._pending is None or len(params) != len(self._pending):
            raise ValueError("CMA-ES: tell() must follow ask() with the same batch")
        super().tell(params, values)
        self.es.tell(self._pending, self.penalized(values).tolist())
        self._pending = None
        if self.restarts_left > 0 and self.es.stop():
            self.restarts_left -= 1
            self.restarts_done += 1
            population = min(2 * self.es.popsize, self.batch)
            self.es = self._strategy(self.rng.random(self.space.dimension), population)

    @property
    def mean(self) -> dict:
        """The distribution mean as a design."""
        return self.space.from_unit(self.es.mean)
