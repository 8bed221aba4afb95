"""Random search: the baseline, and the template for a new optimizer."""

from __future__ import annotations

from morphopt.optimizers.base import Optimizer

__all__ = ["RandomSearch"]


class RandomSearch(Optimizer):
    """Independent uniform samples of the design space (seeded)."""

    def ask(self, count: int) -> list[dict]:
        return self.space.sample(self.rng, count)

    def tell(self, params, values) -> None:
        super().tell(params, values)
