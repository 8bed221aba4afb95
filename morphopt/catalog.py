"""What the design families offer, as text for people: `morphopt families` lists them (name,
modes, one line of description, where the file is) and `morphopt families show NAME` prints
every parameter (bounds, default, unit, meaning) and the metrics of each mode the family supports,
derived by morphopt.contract as a study would and defined by its DEFINITIONS.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

from morphopt.contract import Mode, definition, family_metrics
from morphopt.design_space import Choice, Int
from morphopt.families import BUILTIN_DIR, available_families, load_family

__all__ = ["FamilyEntry", "family_entry", "family_sheet", "family_table", "modes_of"]


@dataclass(frozen=True)
class FamilyEntry:
    """One family as listed: its name, file, whether it is built in, the first sentence of its
    docstring and the modes it supports."""

    name: str
    path: pathlib.Path
    builtin: bool
    summary: str
    modes: tuple

    @property
    def mode_text(self) -> str:
        """The modes as shown: "kinematic, dynamic"."""
        return ", ".join(self.modes)


def modes_of(family) -> tuple:
    """The modes a family module supports: kinematic with generate; dynamic with generate or build_spec."""
    return ((Mode.KINEMATIC,) if hasattr(family, "generate") else ()) + (Mode.DYNAMIC,)


def _summary(doc: str | None) -> str:
    """The first sentence of a docstring's first paragraph, on one line."""
    paragraph = " ".join((doc or "").strip().split("\n\n")[0].split())
    end = paragraph.find(". ")
    return paragraph if end < 0 else paragraph[:end + 1]


def family_entry(name: str, family=None) -> FamilyEntry:
    """Describe family ``name`` (its loaded module ``family``, else loaded here: ValueError if it
    is unknown or broken)."""
    family = load_family(name) if family is None else family
    path = pathlib.Path(family.__file__).resolve()
    return FamilyEntry(pathlib.Path(name).stem, path, path.parent == BUILTIN_DIR, _summary(family.__doc__),
                       modes_of(family))


def family_table() -> str:
    """One line per family found (./designs/ first, then the built-in ones): name, modes,
    description; a family that cannot be loaded says why instead."""
    rows = []
    for name in available_families():
        try:
            entry = family_entry(name)
        except ValueError as exc:
            rows.append((name, "-", f"cannot be loaded: {exc}"))
            continue
        where = "" if entry.builtin else f" [{entry.path}]"
        rows.append((name, entry.mode_text, entry.summary + where))
    width = [max(len(row[k]) for row in rows) for k in range(2)]
    lines = [f"{name:<{width[0]}}  {modes:<{width[1]}}  {text}" for name, modes, text in rows]
    return "\n".join([*lines, "", f"built-in families: {BUILTIN_DIR}; a ./designs/ folder is searched first. "
                      "'morphopt families show NAME' prints a family's parameters and metrics."])


def _range(parameter) -> str:
    if isinstance(parameter, Choice):
        return "one of " + ", ".join(str(option) for option in parameter.options)
    kind = " (integers)" if isinstance(parameter, Int) else ""
    return f"[{parameter.low:.6g}, {parameter.high:.6g}]{kind}"


def _table(rows: list, indent: str = "  ") -> list[str]:
    """Rows of cells as aligned columns (the last column is not padded)."""
    width = [max(len(row[k]) for row in rows) for k in range(len(rows[0]) - 1)]
    return [indent + "  ".join([*(f"{cell:<{w}}" for cell, w in zip(row, width)), row[-1]]).rstrip() for row in rows]


def _metric_lines(family, mode: Mode) -> list[str]:
    """The metrics of ``mode`` that every design of the family gives (morphopt.contract.family_metrics
    on its own space, every topology probed), a per-point metric once when there are several
    points, with unit and meaning; then the points and metrics of some topologies only."""
    given = family_metrics(family, family.space, {}, mode)
    points = list(given.points)
    some_points = [name for name in given.lacking if f"{name}_stride" in given.lacking]
    some = [name for name in given.lacking
            if name not in some_points and not any(name.startswith(p + "_") for p in some_points)]
    rows, seen = [("name", "unit", "meaning")], set()
    for name in given.metrics:
        meaning = definition(name, points)
        label = meaning.label if meaning and meaning.per_point and len(points) > 1 else name
        if label not in seen:
            seen.add(label)
            rows.append((label, meaning.unit if meaning else "?", meaning.meaning if meaning else "(no definition)"))
    plural = "s" if len(points) != 1 else ""
    lines = [f"metrics, {mode} mode (tracked point{plural}: {', '.join(points) or 'none'}):", *_table(rows)]
    if some_points:
        lines.append(f"  points of some designs only (their topology): {', '.join(some_points)}")
    if some:
        lines.append(f"  metrics of some designs only (their topology): {', '.join(some)}")
    return lines


def family_sheet(name: str) -> str:
    """Everything about family ``name``: description, file, modes, every parameter (range,
    default, unit, meaning) and the metrics of each mode with their units and meaning."""
    family = load_family(name)
    entry = family_entry(name, family)
    doc = " ".join((family.__doc__ or "").strip().split("\n\n")[0].replace("``", "").split())
    lines = [f"{entry.name}: {doc}", f"  file: {entry.path}{' (built in)' if entry.builtin else ''}",
             f"  modes: {entry.mode_text}", "", f"parameters ({family.space.dimension}):"]
    rows = [("name", "range", "default", "unit", "meaning")]
    for pname, parameter in family.space.parameters.items():
        default = parameter.center
        shown = f"{default:.6g}" if isinstance(default, float) else str(default)
        rows.append((pname, _range(parameter), shown, parameter.unit or "-", parameter.help or "(not described)"))
    lines += _table(rows)
    for mode in entry.modes:
        lines += ["", *_metric_lines(family, mode)]
    lines += ["", "unit '-' or '1': a ratio, no unit. A study's [space] may narrow a range, [fixed] hold a value."]
    return "\n".join(lines)

