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
    Failed designs are told as a penalty (pycma would silently replace NaN by the median).
    """

    def __init__(self, space, *, popsize: int, sigma0: float = 0.25, x0: dict | None = None, seed: int = 0):
        super().__init__(space, seed=seed)
        if popsize < 2:
            raise ValueError(f"CMA-ES needs a population of at least 2, got {popsize}")
        start = space.to_unit(x0 or space.default())
        options = {"popsize": popsize, "bounds": [0.0, 1.0], "seed": seed + 1, "verbose": -9}
        self.es = cma.CMAEvolutionStrategy(start, sigma0, options)
        self.popsize = popsize
        self._pending: list[np.ndarray] | None = None

    def ask(self, count: int) -> list[dict]:
        if count != self.popsize:
            raise ValueError(f"CMA-ES was set up for batches of {self.popsize}, asked for {count}")
        self._pending = self.es.ask()
        return [self.space.from_unit(x) for x in self._pending]

    def tell(self, params, values) -> None:
        if self._pending is None or len(params) != len(self._pending):
            raise ValueError("CMA-ES: tell() must follow ask() with the same batch")
        super().tell(params, values)
        self.es.tell(self._pending, self.penalized(values).tolist())
        self._pending = None

    @property
    def mean(self) -> dict:
        """The distribution mean as a design."""
        return self.space.from_unit(self.es.mean)
