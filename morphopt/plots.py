"""Figures people look at: study convergence and the best design drawn with its paths."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_study"]


def _plot_pareto(ax, frame, spec) -> None:
    """The first two objectives of every feasible design, the Pareto front highlighted."""
    from morphopt.study import objective_metric_names, pareto_front

    names = objective_metric_names(spec)[:2]
    feasible = frame[frame["failure"] == ""]
    front = pareto_front(frame, spec).sort_values(f"metric_{names[0]}")
    ax.plot(feasible[f"metric_{names[0]}"], feasible[f"metric_{names[1]}"], ".", color="0.6", ms=3, label="designs")
    ax.plot(front[f"metric_{names[0]}"], front[f"metric_{names[1]}"], "o-", color="C3", ms=4, label="Pareto front")
    ax.set_xlabel(f"{names[0]} ({spec.objectives[0].direction})")
    ax.set_ylabel(f"{names[1]} ({spec.objectives[1].direction})")
    ax.set_title(f"Pareto front: {len(front)} designs")
    ax.grid(alpha=0.3)
    ax.legend()


def plot_study(frame, spec, family, path: str) -> str:
    """Convergence (best value per generation) beside the best design and its tracked paths, and
    with several objectives the Pareto front of the first two; PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from morphopt.linkage import solve_cycles

    panels = 3 if spec.multi_objective else 2
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4.5))
    ax_curve, ax_design = axes[0], axes[1]
    feasible = frame[frame["failure"] == ""]
    maximize = spec.direction == "maximize"
    per_generation = feasible.groupby("generation")["value"].agg("max" if maximize else "min")
    best_so_far = per_generation.cummax() if maximize else per_generation.cummin()
    ax_curve.plot(per_generation.index, per_generation.values, "o", alpha=0.5, label="best of the generation")
    ax_curve.plot(best_so_far.index, best_so_far.values, "-", label="best so far")
    ax_curve.set_xlabel("generation")
    ax_curve.set_ylabel(f"{spec.metric} ({'maximize' if maximize else 'minimize'})")
    ax_curve.set_title(f"{spec.name}: {len(frame)} designs, {len(feasible)} feasible")
    ax_curve.grid(alpha=0.3)
    ax_curve.legend()
    if not feasible.empty:
        best = feasible.loc[feasible["value"].idxmax() if maximize else feasible["value"].idxmin()]
        params = {name: best[name] for name in family.space.names}
        linkage = family.generate(params)
        solution = solve_cycles([linkage], samples=180)[0]
        for link in linkage.links:
            nodes = [solution.nodes[n][0] for n in link.nodes]
            closed = np.array(nodes + nodes[:1] if len(nodes) > 2 else nodes)
            ax_design.plot(closed[:, 0], closed[:, 1], "-o", color="0.3", lw=2, ms=3)
        for name in linkage.points:
            trace = solution.point(name, linkage)
            ax_design.plot(trace[:, 0], trace[:, 1], "-", lw=1.5, label=name)
        ax_design.set_aspect("equal")
        ax_design.set_title(f"best design: {spec.metric} = {best['value']:.4g}")
        ax_design.legend()
        ax_design.set_xlabel("x [m]")
        ax_design.set_ylabel("y [m]")
    if spec.multi_objective:
        _plot_pareto(axes[2], frame, spec)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
