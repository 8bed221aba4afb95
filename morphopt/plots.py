"""Figures people look at: study convergence and the best design drawn with its paths.

The best design is drawn as the family builds it: a linkage family (``generate``) as its links in
the plane with the tracked points' paths over a crank turn, and a path-synthesis study's target
curves dashed; a family of whole worlds (``build_spec``, a walker) as a side view (x, z) of its
initial pose: every body as the polygon of its joints' anchors, the tracked points, the ground.
Every axis is labelled with its unit; generations are integers.
"""

from __future__ import annotations

import numpy as np

__all__ = ["draw_design", "plot_study", "study_figure"]


def _metric_label(name: str, frame) -> str:
    from morphopt.report import _points, metric_label

    return metric_label(name, _points([c[len("metric_"):] for c in frame.columns if c.startswith("metric_")]))


def _plot_pareto(ax, frame, spec) -> None:
    """The first two objectives of every feasible design, the Pareto front highlighted."""
    from morphopt.study import objective_metric_names, pareto_front

    names = objective_metric_names(spec)[:2]
    feasible = frame[frame["failure"] == ""]
    front = pareto_front(frame, spec).sort_values(f"metric_{names[0]}")
    ax.plot(feasible[f"metric_{names[0]}"], feasible[f"metric_{names[1]}"], ".", color="0.6", ms=3, label="designs")
    ax.plot(front[f"metric_{names[0]}"], front[f"metric_{names[1]}"], "o-", color="C3", ms=4, label="Pareto front")
    ax.set_xlabel(f"{_metric_label(names[0], frame)} ({spec.objectives[0].direction})")
    ax.set_ylabel(f"{_metric_label(names[1], frame)} ({spec.objectives[1].direction})")
    ax.set_title(f"Pareto front: {len(front)} designs")
    ax.grid(alpha=0.3)
    ax.legend()


def _plot_convergence(ax, frame, spec) -> None:
    from matplotlib.ticker import MaxNLocator

    feasible = frame[frame["failure"] == ""]
    maximize = spec.direction == "maximize"
    label = "score" if spec.multi_objective else _metric_label(spec.metric, frame)
    if not feasible.empty:
        per_generation = feasible.groupby("generation")["value"].agg("max" if maximize else "min")
        best_so_far = per_generation.cummax() if maximize else per_generation.cummin()
        ax.plot(per_generation.index, per_generation.values, "o", alpha=0.5, label="best of the generation")
        ax.plot(best_so_far.index, best_so_far.values, "-", label="best so far")
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no feasible design yet", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlim(-0.5, max(int(frame["generation"].max()), 1) + 0.5)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("generation")
    ax.set_ylabel(f"{label} ({'maximize' if maximize else 'minimize'})")
    ax.set_title(f"{spec.name}: {len(frame)} designs, {len(feasible)} feasible")
    ax.grid(alpha=0.3)


def _draw_linkage(ax, family, params: dict, spec) -> None:
    """The linkage in the plane at its crank phase, its tracked paths, and path_error targets dashed."""
    from morphopt.linkage import solve_cycles

    linkage = family.generate(params)
    solution = solve_cycles([linkage], samples=180)[0]
    for link in linkage.links:
        nodes = [solution.nodes[n][0] for n in link.nodes]
        closed = np.array(nodes + nodes[:1] if len(nodes) > 2 else nodes)
        ax.plot(closed[:, 0], closed[:, 1], "-o", color="0.3", lw=2, ms=3)
    for name in linkage.points:
        trace = solution.point(name, linkage)
        ax.plot(trace[:, 0], trace[:, 1], "-", lw=1.5, label=f"path of {name}")
    for objective in spec.objectives:
        if objective.metric == "path_error" and objective.target:
            target = np.asarray(objective.target, dtype=float)
            closed = np.vstack([target, target[:1]])
            ax.plot(closed[:, 0], closed[:, 1], "--", color="k", lw=1.2, label=f"target of {objective.point}")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def _rotate(quaternion, vector) -> np.ndarray:
    """vector turned by a unit quaternion (x, y, z, w)."""
    q, v = np.asarray(quaternion, float), np.asarray(vector, float)
    u, w = q[:3], q[3]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _draw_world(ax, family, params: dict, spec) -> None:
    """Side view (x, z) of the world build_spec makes, at its initial pose."""
    world = family.build_spec(params, crank_speed=spec.crank_speed)
    bodies = {b.name: b for b in world.bodies}

    def at(body, local):
        b = bodies[body]
        return _rotate(b.orientation, local) + np.asarray(b.position, float)

    anchors = {name: [] for name in bodies}
    for joint in world.joints:
        anchors[joint.child].append(at(joint.child, joint.child_position))
        if joint.parent is not None:
            anchors[joint.parent].append(at(joint.parent, joint.parent_position))
    for name, points in anchors.items():
        if not points:
            points = [np.asarray(bodies[name].position, float)]
        points = np.array(points)
        if len(points) > 2:  # the polygon of the anchors, in order around their centre
            centre = points.mean(axis=0)
            points = points[np.argsort(np.arctan2(points[:, 2] - centre[2], points[:, 0] - centre[0]))]
            points = np.vstack([points, points[:1]])
        ax.plot(points[:, 0], points[:, 2], "-o", color="0.3", lw=1.5, ms=2)
    for point in world.points:
        where = at(point.body, point.position)
        ax.plot(where[0], where[2], "o", ms=5, label=point.name)
    if world.ground is not None:
        normal = np.asarray(world.ground.normal, float)
        if abs(normal[2]) > 0.99:
            ax.axhline(world.ground.offset / normal[2], color="0.5", lw=1, ls=":", label="ground")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")


def draw_design(ax, family, params: dict, spec) -> str:
    """One design on a matplotlib Axes as the module docstring says (a kinematic study's or a
    linkage family's linkage in its plane, a dynamic study's world from the side), equal axes;
    returns the view's words for a title ("" or " (initial pose, side view)")."""
    if spec.mode == "kinematic" or not hasattr(family, "build_spec"):
        _draw_linkage(ax, family, params, spec)
        view = ""
    else:
        _draw_world(ax, family, params, spec)
        view = " (initial pose, side view)"
    ax.set_aspect("equal", adjustable="datalim")
    return view


def study_figure(frame, spec, family):
    """The matplotlib Figure of plot_study: convergence beside the best design (see the module
    docstring), and with several objectives the Pareto front of the first two."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 3 if spec.multi_objective else 2
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4.5))
    ax_design = axes[1]
    _plot_convergence(axes[0], frame, spec)
    feasible = frame[frame["failure"] == ""]
    if not feasible.empty:
        maximize = spec.direction == "maximize"
        best = feasible.loc[feasible["value"].idxmax() if maximize else feasible["value"].idxmin()]
        params = {name: _plain(best[name]) for name in family.space.names}
        view = draw_design(ax_design, family, params, spec)
        label = "score" if spec.multi_objective else _metric_label(spec.metric, frame)
        ax_design.set_title(f"best design{view}: {label} = {best['value']:.4g}", fontsize=10)
        ax_design.legend(fontsize=8)
        ax_design.grid(alpha=0.3)
    else:
        ax_design.text(0.5, 0.5, "no feasible design to draw", ha="center", va="center", transform=ax_design.transAxes)
        ax_design.set_axis_off()
    if spec.multi_objective:
        _plot_pareto(axes[2], frame, spec)
    fig.tight_layout()
    return fig


def plot_study(frame, spec, family, path: str) -> str:
    """study_figure as a PNG at ``path``; returns the path."""
    import matplotlib.pyplot as plt

    fig = study_figure(frame, spec, family)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _plain(value):
    """A pandas/NumPy scalar as a plain Python value (what a family's functions expect)."""
    return value.item() if hasattr(value, "item") else value
