"""Ask/tell optimizers over a DesignSpace: they see parameter dicts and values, never the engine.

Every optimizer implements ``ask(count) -> list[dict]`` and ``tell(params, values)`` where
values are floats to minimize (inf or NaN for failed designs, which each optimizer maps to a
finite penalty worse than anything feasible seen so far).
"""

from morphopt.optimizers.base import Optimizer
from morphopt.optimizers.cma_es import CMAES
from morphopt.optimizers.optuna_sampler import OptunaSampler
from morphopt.optimizers.random_search import RandomSearch

OPTIMIZERS = {"random": RandomSearch, "cma": CMAES, "optuna": OptunaSampler}

__all__ = ["CMAES", "OPTIMIZERS", "Optimizer", "OptunaSampler", "RandomSearch"]
