"""Design spaces: bounded floats, integers and categorical choices, with unit-cube maps.

A DesignSpace is an ordered set of named parameters. Optimizers see only this module and
parameter dicts: they sample in the unit cube (floats, ints) or pick categories, and the space
maps between that and the design's own values. Optuna distributions come from the same
definitions. Each parameter may carry a ``unit`` ("m", "rad/s", "" for none) and a ``help``
line (what it is), shown by `morphopt families show`; neither changes any computation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Choice", "DesignSpace", "Float", "Int"]


@dataclass(frozen=True)
class Float:
    """A real parameter in [low, high]; ``log`` samples it on a log scale (low > 0); ``unit`` and
    ``help``: its unit and meaning, for people."""

    low: float
    high: float
    default: float | None = None
    log: bool = False
    unit: str = ""
    help: str = ""

    def check(self, name: str) -> None:
        """Raise ValueError naming ``name`` when the bounds or the default are invalid."""
        if not (math.isfinite(self.low) and math.isfinite(self.high)) or self.low >= self.high:
            raise ValueError(f"parameter '{name}': bounds must be finite with low < high, got [{self.low}, {self.high}]")
        if self.log and self.low <= 0.0:
            raise ValueError(f"parameter '{name}': a log-scaled range needs low > 0, got {self.low}")
        if self.default is not None and not self.low <= self.default <= self.high:
            raise ValueError(f"parameter '{name}': default {self.default} outside [{self.low}, {self.high}]")

    def to_unit(self, value: float) -> float:
        """Position of ``value`` in [0, 1] (linear or logarithmic in the range)."""
        if self.log:
            return (math.log(value) - math.log(self.low)) / (math.log(self.high) - math.log(self.low))
        return (value - self.low) / (self.high - self.low)

    def from_unit(self, u: float) -> float:
        """The value at unit coordinate ``u`` (clipped into [0, 1])."""
        u = min(max(float(u), 0.0), 1.0)
        if self.log:
            return math.exp(math.log(self.low) + u * (math.log(self.high) - math.log(self.low)))
        return self.low + u * (self.high - self.low)

    def contains(self, value) -> bool:
        """True for a real number (not a bool) within the bounds."""
        real = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
        return real and self.low <= value <= self.high

    @property
    def center(self) -> float:
        """The default, or the middle of the range (geometric middle on a log scale)."""
        return self.default if self.default is not None else self.from_unit(0.5)


@dataclass(frozen=True)
class Int:
    """An integer parameter in [low, high] (both included); ``unit`` and ``help`` as for Float."""

    low: int
    high: int
    default: int | None = None
    unit: str = ""
    help: str = ""

    def check(self, name: str) -> None:
        """Raise ValueError naming ``name`` when the bounds or the default are invalid."""
        if int(self.low) != self.low or int(self.high) != self.high or self.low >= self.high:
            raise ValueError(f"parameter '{name}': integer bounds with low < high expected, got [{self.low}, {self.high}]")
        if self.default is not None and not self.low <= self.default <= self.high:
            raise ValueError(f"parameter '{name}': default {self.default} outside [{self.low}, {self.high}]")

    def to_unit(self, value: int) -> float:
        """Centre of ``value``'s cell when [0, 1] is cut into one equal cell per integer."""
        return (value - self.low + 0.5) / (self.high - self.low + 1)

    def from_unit(self, u: float) -> int:
        """The integer whose cell holds ``u`` (clipped into [0, 1])."""
        u = min(max(float(u), 0.0), 1.0)
        return min(self.high, self.low + int(math.floor(u * (self.high - self.low + 1))))

    def contains(self, value) -> bool:
        """True for an integer (not a bool) within the bounds."""
        return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and self.low <= value <= self.high

    @property
    def center(self) -> int:
        """The default, or the integer in the middle of the range."""
        return self.default if self.default is not None else self.from_unit(0.5)


@dataclass(frozen=True)
class Choice:
    """A categorical parameter: one of ``options`` (strings, numbers or booleans); ``unit`` and
    ``help`` as for Float."""

    options: tuple
    default: object = None
    unit: str = ""
    help: str = ""

    def __post_init__(self):
        object.__setattr__(self, "options", tuple(self.options))

    def check(self, name: str) -> None:
        """Raise ValueError naming ``name`` when the options are empty or repeated, or the default is not one."""
        if len(self.options) < 1 or len(set(self.options)) != len(self.options):
            raise ValueError(f"parameter '{name}': choices must be distinct and non-empty, got {list(self.options)}")
        if self.default is not None and self.default not in self.options:
            raise ValueError(f"parameter '{name}': default {self.default!r} is not one of {list(self.options)}")

    def to_unit(self, value) -> float:
        """Centre of ``value``'s cell when [0, 1] is cut into one equal cell per option."""
        return (self.options.index(value) + 0.5) / len(self.options)

    def from_unit(self, u: float):
        """The option whose cell holds ``u`` (clipped into [0, 1])."""
        u = min(max(float(u), 0.0), 1.0)
        return self.options[min(len(self.options) - 1, int(math.floor(u * len(self.options))))]

    def contains(self, value) -> bool:
        """True when ``value`` is one of the options."""
        return value in self.options

    @property
    def center(self):
        """The default, or the first option."""
        return self.default if self.default is not None else self.options[0]


Parameter = Float | Int | Choice


class DesignSpace:
    """Named parameters in a fixed order.

    Args:
        parameters: mapping name -> Float | Int | Choice.
    """

    def __init__(self, parameters: Mapping[str, Parameter]):
        if not parameters:
            raise ValueError("a design space needs at least one parameter")
        for name, parameter in parameters.items():
            if not isinstance(parameter, (Float, Int, Choice)):
                raise ValueError(f"parameter '{name}': expected Float, Int or Choice, got {type(parameter).__name__}")
            parameter.check(name)
            if not (isinstance(parameter.unit, str) and isinstance(parameter.help, str)):
                raise ValueError(f"parameter '{name}': unit and help must be text, got {parameter.unit!r} and "
                                 f"{parameter.help!r}")
        self.parameters: dict[str, Parameter] = dict(parameters)

    @property
    def names(self) -> list[str]:
        """Parameter names in order."""
        return list(self.parameters)

    @property
    def dimension(self) -> int:
        """Number of parameters."""
        return len(self.parameters)

    def default(self) -> dict:
        """Each parameter's default (or the middle of its range, or its first choice)."""
        return {name: p.center for name, p in self.parameters.items()}

    def validate(self, params: Mapping) -> dict:
        """Return a copy of ``params`` after checking that every parameter is present and in range."""
        unknown = sorted(set(params) - set(self.parameters))
        if unknown:
            raise ValueError(f"unknown design parameter(s) {unknown}; expected {self.names}")
        out = {}
        for name, parameter in self.parameters.items():
            if name not in params:
                raise ValueError(f"design parameter '{name}' is missing")
            value = params[name]
            if not parameter.contains(value):
                raise ValueError(f"design parameter '{name}' = {value!r} is outside {_describe(parameter)}")
            out[name] = value
        return out

    def to_unit(self, params: Mapping) -> np.ndarray:
        """Unit-cube coordinates (dimension,) of a parameter dict."""
        return np.array([p.to_unit(params[name]) for name, p in self.parameters.items()])

    def from_unit(self, u: Sequence[float]) -> dict:
        """Parameter dict of unit-cube coordinates (clipped into the cube)."""
        u = np.asarray(u, dtype=float).reshape(-1)
        if u.size != self.dimension:
            raise ValueError(f"expected {self.dimension} unit coordinates, got {u.size}")
        return {name: p.from_unit(x) for (name, p), x in zip(self.parameters.items(), u)}

    def from_unit_many(self, units) -> list[dict]:
        """Parameter dicts of the rows of ``units`` (count, dimension), clipped into the cube: the
        same values as from_unit row by row, computed a column at a time."""
        units = np.clip(np.asarray(units, dtype=float).reshape(-1, self.dimension), 0.0, 1.0)
        columns = []
        for k, p in enumerate(self.parameters.values()):
            u = units[:, k]
            if isinstance(p, Float):
                if p.log:
                    low = math.log(p.low)
                    columns.append(np.exp(low + u * (math.log(p.high) - low)).tolist())
                else:
                    columns.append((p.low + u * (p.high - p.low)).tolist())
            elif isinstance(p, Int):
                steps = np.minimum(np.floor(u * (p.high - p.low + 1)).astype(np.int64), p.high - p.low)
                columns.append((int(p.low) + steps).tolist())
            else:
                picks = np.minimum(np.floor(u * len(p.options)).astype(np.int64), len(p.options) - 1)
                columns.append([p.options[i] for i in picks.tolist()])
        names = self.names
        return [dict(zip(names, row)) for row in zip(*columns)]

    def sample(self, rng: np.random.Generator, count: int) -> list[dict]:
        """``count`` independent uniform samples."""
        return self.from_unit_many(rng.random((count, self.dimension)))

    def optuna_distributions(self) -> dict:
        """The same space as Optuna distributions."""
        import optuna

        out = {}
        for name, p in self.parameters.items():
            if isinstance(p, Float):
                out[name] = optuna.distributions.FloatDistribution(p.low, p.high, log=p.log)
            elif isinstance(p, Int):
                out[name] = optuna.distributions.IntDistribution(int(p.low), int(p.high))
            else:
                out[name] = optuna.distributions.CategoricalDistribution(p.options)
        return out


def _describe(parameter) -> str:
    if isinstance(parameter, Choice):
        return f"the choices {list(parameter.options)}"
    kind = "integers" if isinstance(parameter, Int) else "reals"
    return f"{kind} in [{parameter.low}, {parameter.high}]"
