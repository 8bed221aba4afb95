"""Optuna samplers (TPE by default, NSGA-II, any other) through ask/tell on whole batches.

The Optuna study lives in memory during a run (its SQL storages are far too slow for thousands
of trials per generation); morphopt's own storage records the designs.
"""

from __future__ import annotations

import math

from morphopt.optimizers.base import Optimizer

__all__ = ["OptunaSampler"]

SAMPLERS = {"tpe": "TPESampler", "nsga2": "NSGAIISampler", "random": "RandomSampler"}


class OptunaSampler(Optimizer):
    """Batch ask/tell over an in-memory Optuna study. Failed designs are told as FAIL trials.

    directions: one "minimize"/"maximize" per objective for a multi-objective (Pareto) study;
    tell() then takes the objective vectors as a third argument (the scalar values still track
    the best design by score).
    """

    def __init__(self, space, *, sampler: str = "tpe", seed: int = 0, directions: list | None = None,
                 **sampler_options):
        import optuna  # only studies that use Optuna need it installed

        super().__init__(space, seed=seed)
        if sampler not in SAMPLERS:
            raise ValueError(f"unknown Optuna sampler '{sampler}', expected one of {sorted(SAMPLERS)}")
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self.directions = list(directions) if directions else None
        self.sampler_name = sampler
        self.study = optuna.create_study(sampler=getattr(optuna.samplers, SAMPLERS[sampler])(seed=seed, **sampler_options),
                                         directions=self.directions)
        self.distributions = space.optuna_distributions()
        self._pending: list = []

    def sampler_states(self) -> list:
        """The NumPy random states inside the sampler, in a fixed order (for checkpoint summaries)."""
        import numpy as np

        found, seen = [], set()

        def walk(obj, depth):
            if id(obj) in seen or depth > 3:
                return
            seen.add(id(obj))
            if isinstance(obj, np.random.RandomState):
                found.append(obj)
                return
            if type(obj).__name__ == "LazyRandomState":
                found.append(obj.rng)
                return
            for key in sorted(getattr(obj, "__dict__", {})):
                walk(obj.__dict__[key], depth + 1)

        walk(self.study.sampler, 0)
        return found

    @property
    def takes_stored_designs(self) -> bool:
        """True when a replay may hand the stored designs to ``ask_stored`` (TPE and random keep no
        state but the trials and their random generators; NSGA-II marks the trials it samples)."""
        return self.sampler_name in ("tpe", "random")

    def ask_stored(self, designs: list[dict]) -> list[dict]:
        """Ask for trials with these parameters (a resume's replay: the sampler is not consulted,
        which would cost what all the run's sampling cost; its random states are restored after)."""
        for design in designs:
            self.study.enqueue_trial(design, skip_if_exists=False)
        return self.ask(len(designs))

    def ask(self, count: int) -> list[dict]:
        self._pending = [self.study.ask(self.distributions) for _ in range(count)]
        return [dict(trial.params) for trial in self._pending]

    def tell(self, params, values, objectives=None) -> None:
        import optuna

        if len(params) != len(self._pending):
            raise ValueError("Optuna: tell() must follow ask() with the same batch")
        if (objectives is None) != (self.directions is None):
            raise ValueError("Optuna: objective vectors go with a multi-objective study (directions), and only there")
        super().tell(params, values)
        for k, (trial, value) in enumerate(zip(self._pending, values)):
            if objectives is not None:
                vector = [float(v) for v in objectives[k]]
                if all(math.isfinite(v) for v in vector):
                    self.study.tell(trial, vector)
                else:
                    self.study.tell(trial, state=optuna.trial.TrialState.FAIL)
            elif math.isfinite(value):
                self.study.tell(trial, float(value))
            else:
                self.study.tell(trial, state=optuna.trial.TrialState.FAIL)
        self._pending = []
