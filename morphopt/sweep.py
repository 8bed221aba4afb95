"""Parameter sets for design sweeps: full grids and one-at-a-time variations around a base design.

Both return plain lists of parameter dicts, ready for one batched call of
``morphopt.evaluate.evaluate_kinematic`` or ``evaluate_dynamic`` (one world per design).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence

__all__ = ["grid", "one_at_a_time"]


def _check_names(space, names) -> None:
    unknown = [name for name in names if name not in space.names]
    if unknown:
        raise ValueError(f"sweep: unknown parameter(s) {unknown}, expected some of {space.names}")


def grid(space, axes: Mapping[str, Sequence], base: Mapping | None = None) -> list[dict]:
    """Every combination of the values in ``axes`` (name -> values), the other parameters from
    ``base`` (the space's defaults when None). The last axis varies fastest, so the results
    reshape to (len(axes[first]), ..., len(axes[last]))."""
    _check_names(space, axes)
    start = dict(space.default() if base is None else base)
    names = list(axes)
    return [{**start, **dict(zip(names, values))} for values in itertools.product(*(axes[n] for n in names))]


def one_at_a_time(space, relative: Sequence[float], base: Mapping | None = None,
                  names: Sequence[str] | None = None) -> tuple[list[dict], list[tuple[str, float]]]:
    """Each parameter in ``names`` (default: every float parameter) scaled by (1 + r) for r in
    ``relative``, the others at ``base``. Returns the parameter sets and, for each, the
    (parameter, r) it varies."""
    start = dict(space.default() if base is None else base)
    names = [n for n in space.names if isinstance(start[n], float)] if names is None else list(names)
    _check_names(space, names)
    params, labels = [], []
    for name in names:
        for r in relative:
            params.append({**start, name: start[name] * (1.0 + r)})
            labels.append((name, float(r)))
    return params, labels
