"""A stored study as text for people (`morphopt study show`): progress, the best designs with their
member index, objective (named, with its unit), parameters and metrics, and the failures counted
by kind. Units come from morphopt.contract's metric definitions and the design space.
"""

from __future__ import annotations

import re

__all__ = ["failure_kind", "failure_kinds", "metric_label", "study_report"]

_NUMBER = re.compile(r"(?<![\w.'])[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?![\w'])")
_BRACKETS = re.compile(r"(\[[^\]]*\])")


def failure_kind(reason: str) -> str:
    """The reason with the numbers that vary from design to design (a crank angle, a time, a value)
    written as '#', so that designs failing the same way count together; numbers inside [...]
    (a constraint's bounds) and inside names stay."""
    parts = _BRACKETS.split(reason)
    return "".join(part if part.startswith("[") else _NUMBER.sub("#", part) for part in parts)


def failure_kinds(failures) -> list[tuple[int, str]]:
    """(count, kind) of the failure reasons ("" is no failure), most frequent first."""
    counts = {}
    for reason in failures:
        if reason:
            kind = failure_kind(str(reason))
            counts[kind] = counts.get(kind, 0) + 1
    return sorted(((n, kind) for kind, n in counts.items()), key=lambda item: (-item[0], item[1]))


def _points(metrics) -> set:
    """Tracked points named by per-point metric names ("foot" of "foot_stride")."""
    from morphopt.contract import DEFINITIONS

    suffixes = [d.name for d in DEFINITIONS.values() if d.per_point]
    return {m[:-len(s) - 1] for m in metrics for s in suffixes if m.endswith("_" + s) and len(m) > len(s) + 1}


def metric_label(name: str, points=()) -> str:
    """'name [unit]' for a metric with a known unit ('1': no unit, shown bare), else the name."""
    from morphopt.contract import definition

    found = definition(name, points)
    return f"{name} [{found.unit}]" if found is not None and found.unit not in ("", "1") else name


def study_report(frame, spec, space=None, top: int = 10) -> str:
    """`study show`'s text: progress, the ``top`` best feasible designs (rank, generation, member,
    objective, parameters; then their metrics), a multi-objective study's Pareto front, and the
    failures by kind. ``space``: the family's DesignSpace, for the parameters' units."""
    import pandas as pd

    metrics = [c[len("metric_"):] for c in frame.columns if c.startswith("metric_")]
    points = _points(metrics)
    done = int(frame["generation"].max()) + 1
    feasible = frame[frame["failure"] == ""]
    objective = ("score" if spec.multi_objective else metric_label(spec.metric, points))
    lines = [f"study '{spec.name}': {done}/{spec.generations} generations, {len(frame)} designs, "
             f"{len(feasible)} feasible ({100 * len(feasible) / len(frame):.0f} %)"]
    if spec.multi_objective:
        lines.append("objective: score = " + " + ".join(
            f"{o.weight:g} x {'-' if o.direction == 'maximize' else ''}{metric_label(o.metric, points)}"
            for o in spec.objectives) + " (minimize)")
    else:
        lines.append(f"objective: {objective} ({spec.direction})")
    best = feasible.sort_values("value", ascending=spec.direction == "minimize").head(top)
    params = [c for c in frame.columns if c not in ("generation", "member", "value", "failure")
              and not c.startswith("metric_")]
    units = {n: getattr(p, "unit", "") for n, p in (space.parameters.items() if space is not None else ())}
    table = pd.DataFrame({"rank": range(1, len(best) + 1), "generation": best["generation"].to_numpy(),
                          "member": best["member"].to_numpy(), objective: best["value"].to_numpy()})
    for name in params:
        table[f"{name} [{units[name]}]" if units.get(name) else name] = best[name].to_numpy()
    with pd.option_context("display.width", 200, "display.max_columns", 40):
        if best.empty:
            lines.append("no feasible design")
        else:
            lines += [f"best {len(best)} designs:", table.to_string(index=False)]
            shown = pd.DataFrame({"rank": table["rank"]})
            for name in metrics:
                shown[metric_label(name, points)] = best[f"metric_{name}"].to_numpy()
            lines += ["their metrics:", shown.to_string(index=False)]
        if spec.multi_objective:
            from morphopt.study import objective_metric_names, pareto_front

            front = pareto_front(frame, spec)
            names = objective_metric_names(spec)
            lines.append(f"Pareto front: {len(front)} designs ("
                         + ", ".join(f"{o.metric} {o.direction}" for o in spec.objectives) + ")")
            columns = {"generation": front["generation"], "member": front["member"], "score": front["value"]}
            columns.update({metric_label(n, points): front[f"metric_{n}"] for n in names})
            lines.append(pd.DataFrame(columns).head(top).to_string(index=False))
    kinds = failure_kinds(frame["failure"])
    if kinds:
        failed = sum(n for n, _ in kinds)
        lines.append(f"failures: {failed} designs, {len(kinds)} kinds ('#': a number that varies)")
        width = len(str(kinds[0][0]))
        shown = max(top, 10)
        lines += [f"  {n:>{width}}  {kind}" for n, kind in kinds[:shown]]
        if len(kinds) > shown:
            lines.append(f"  ... and {len(kinds) - shown} more kinds ({sum(n for n, _ in kinds[shown:])} designs)")
    return "\n".join(lines)
