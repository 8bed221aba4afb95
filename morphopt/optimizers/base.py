"""The ask/tell interface shared by the optimizers, with failure penalties and best tracking."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from morphopt.design_space import DesignSpace

__all__ = ["Optimizer"]


class Optimizer:
    """Base class: ``ask(count)`` proposes designs, ``tell(params, values)`` reports their values.

    Values are minimized. A failed design (value inf or NaN) is told as a finite penalty worse than
    every finite value seen so far, so optimizers that cannot take NaN still rank it last.
    Attributes: space, seed, best_params, best_value, evaluations.
    """

    def __init__(self, space: DesignSpace, *, seed: int = 0):
        self.space = space
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.best_params: dict | None = None
        self.best_value = math.inf
        self.evaluations = 0
        self._worst_finite = -math.inf

    def ask(self, count: int) -> list[dict]:
        """``count`` new parameter dicts to evaluate (every one inside the design space)."""
        raise TypeError(f"{type(self).__name__} does not implement ask()")

    def tell(self, params: Sequence[dict], values: Sequence[float]) -> None:
        """Record a batch; subclasses call this first, then use ``penalized(values)``."""
        if len(params) != len(values):
            raise ValueError(f"tell: {len(params)} designs but {len(values)} values")
        for p, v in zip(params, values):
            self.evaluations += 1
            if math.isfinite(v):
                self._worst_finite = max(self._worst_finite, v)
                if v < self.best_value:
                    self.best_value, self.best_params = float(v), dict(p)

    def penalized(self, values: Sequence[float]) -> np.ndarray:
        """Values with failures replaced by a penalty worse than any finite value seen."""
        values = np.asarray(values, dtype=float)
        worst = self._worst_finite if math.isfinite(self._worst_finite) else 0.0
        penalty = worst + max(1.0, abs(worst))
        return np.where(np.isfinite(values), values, penalty)
