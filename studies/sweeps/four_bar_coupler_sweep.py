# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Four-bar coupler curves: how far can two link lengths move the path?
#
# The `four_bar` family is a crank-rocker with a point riding on its coupler. As the crank turns,
# that point traces a closed **coupler curve**, and coupler-curve synthesis asks which link
# lengths make it follow a curve we want.
#
# Here we ask a small version of that question. We fix a **target curve**: the coupler path
# of a reference four-bar from the same family, with the crank and rocker lengths set to values
# that fall between the grid nodes and every other parameter at its default. Then we sweep a grid over
# the two lengths `crank` and `rocker` (the other four parameters stay at their defaults) and
# measure, for every design, how far its coupler curve is from the target. Because the target
# comes from the same family, we know the answer: the error should vanish near the reference
# lengths. The sweep shows what the error does around that point: how narrow the valley is,
# which direction of the plane is forgiving, and where the mechanism stops working altogether.
#
# The whole grid is one batched call of the cycle kinematics: every design is one world of the
# same batch.

# %%
import os
import pathlib
import time

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm

from morphopt.evaluate import evaluate_kinematic
from morphopt.families import load_family
from morphopt.metrics import path_error
from morphopt.sweep import grid

SMALL = os.environ.get("MORPHOPT_SWEEP_SIZE") == "small"
DEVICE = os.environ.get("MORPHOPT_DEVICE", "cpu")
OUT = pathlib.Path(os.environ.get("MORPHOPT_SWEEP_OUT", "figures"))
OUT.mkdir(parents=True, exist_ok=True)

N = 6 if SMALL else 64  # grid points per axis: N x N designs in one batch
POINT = "coupler_point"  # the tracked point of the four_bar family

family = load_family("four_bar")
space = family.space
print(f"device: {DEVICE}, grid: {N} x {N} = {N * N} designs")

# %% [markdown]
# ## The target and the grid
#
# The reference design differs from the defaults only in its crank and rocker lengths. Its
# coupler curve, sampled over one crank turn, is the target. The grid spans each of the two
# lengths over its whole range in the design space, so the reference lies inside the grid.

# %%
REFERENCE = {**space.default(), "crank": 0.083, "rocker": 0.285}

crank_values = np.linspace(space.parameters["crank"].low, space.parameters["crank"].high, N).tolist()
rocker_values = np.linspace(space.parameters["rocker"].low, space.parameters["rocker"].high, N).tolist()
params = grid(space, {"crank": crank_values, "rocker": rocker_values})
print(f"{len(params)} parameter sets; other parameters:",
      {k: v for k, v in space.default().items() if k not in ("crank", "rocker")})

# %% [markdown]
# ## One batched evaluation
#
# The reference design and the whole grid go into the same call: the reference is simply the
# last world of the batch. A design that cannot complete a crank turn (the coupler and rocker
# cannot reach each other at some crank angle) comes back as a failure with its reason; the
# others carry on.

# %%
start = time.perf_counter()
evaluation = evaluate_kinematic(family, params + [REFERENCE], device=DEVICE)
elapsed = time.perf_counter() - start
print(f"evaluated {len(params) + 1} designs in one batch in {elapsed:.2f} s")

if evaluation.failures[-1]:
    raise RuntimeError(f"the reference design is infeasible: {evaluation.failures[-1]}")
target = evaluation.metrics[-1]["paths"][POINT]

feasible = evaluation.feasible[:-1]
reasons = sorted({reason for reason in evaluation.failures[:-1] if reason})
print(f"feasible: {int(feasible.sum())} of {len(params)}, infeasible: {int((~feasible).sum())}")
for reason in reasons[:5]:
    print("  e.g.", reason)

# %% [markdown]
# ## Path error of every feasible design
#
# `path_error` resamples both curves by arc length and takes the smallest RMS distance over
# every starting point and both directions of travel, so it compares the *shape and placement*
# of the curves, not how fast the point moves along them. Infeasible designs get no error (NaN)
# and are drawn grey.

# %%
errors = np.full(len(params), np.nan)
for i, ok in enumerate(feasible):
    if ok:
        errors[i] = path_error(evaluation.metrics[i]["paths"][POINT], target)
error_map = errors.reshape(len(crank_values), len(rocker_values))  # (crank, rocker)

best = int(np.nanargmin(errors))
worst = int(np.nanargmax(errors))
for label, i in (("best", best), ("worst", worst)):
    print(f"{label:5s}: crank {params[i]['crank']:.3f} m, rocker {params[i]['rocker']:.3f} m, "
          f"path error {1e3 * errors[i]:.2f} mm")
print(f"median path error of the feasible designs: {1e3 * np.nanmedian(errors):.2f} mm")

# A rough width of the valley along each axis: how far each length can move from the best cell,
# the other length held, while the error stays below a tenth of the median error.
TOLERANCE = 0.1 * np.nanmedian(errors)
row, column = np.unravel_index(best, error_map.shape)
padded = np.pad(np.nan_to_num(error_map, nan=np.inf), 1, constant_values=np.inf)
neighbours = np.stack([padded[1 + di:padded.shape[0] - 1 + di, 1 + dj:padded.shape[1] - 1 + dj]
                       for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj])
local_minima = int((np.isfinite(error_map) & (error_map < neighbours.min(axis=0))).sum())
print(f"local minima of the path error on the grid (8 neighbours): {local_minima}")
for name, values, line in (("crank", crank_values, error_map[:, column]), ("rocker", rocker_values, error_map[row, :])):
    inside = np.asarray(values)[np.nan_to_num(line, nan=np.inf) <= TOLERANCE]
    print(f"{name:6s}: error <= {1e3 * TOLERANCE:.1f} mm for {name} in "
          f"[{inside.min():.3f}, {inside.max():.3f}] m (width {inside.max() - inside.min():.3f} m)")

# %% [markdown]
# ## The picture: path error over the crank-rocker plane

# %%
def cell_edges(values):
    """Cell boundaries around equally spaced grid values, for pcolormesh."""
    values = np.asarray(values)
    step = values[1] - values[0]
    return np.concatenate([values - step / 2, values[-1:] + step / 2])


cmap = plt.get_cmap("viridis").copy()
cmap.set_bad("lightgrey")
shown = np.ma.masked_invalid(1e3 * error_map)  # mm
low = max(float(shown.min()), 1e-2)
fig, ax = plt.subplots(figsize=(6.4, 5.2))
mesh = ax.pcolormesh(cell_edges(rocker_values), cell_edges(crank_values), shown, cmap=cmap,
                     norm=LogNorm(vmin=low, vmax=max(float(shown.max()), 1.01 * low)))
fig.colorbar(mesh, ax=ax, label="path error to the target [mm] (log scale)")
ax.plot(REFERENCE["rocker"], REFERENCE["crank"], marker="*", color="white", markeredgecolor="black",
        markersize=14, linestyle="none", label="reference (target) design")
ax.plot(params[best]["rocker"], params[best]["crank"], marker="o", color="tab:green", markeredgecolor="black",
        linestyle="none", label="best feasible")
ax.plot(params[worst]["rocker"], params[worst]["crank"], marker="s", color="tab:red", markeredgecolor="black",
        linestyle="none", label="worst feasible")
ax.set_xlabel("rocker length [m]")
ax.set_ylabel("crank length [m]")
ax.set_title(f"Four-bar coupler path error, {N} x {N} designs\n"
             f"grey: {int((~feasible).sum())} infeasible (no full crank turn)")
ax.legend(loc="lower right", fontsize=8, framealpha=0.85)
fig.tight_layout()
fig.savefig(OUT / "four_bar_path_error_map.png", dpi=120)
plt.show()

# %% [markdown]
# ## The best and the worst feasible coupler curves over the target
#
# The dot on each curve marks where the coupler point is at crank angle zero.

# %%
fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
closed_target = np.vstack([target, target[:1]])
for ax, i, label, color in ((axes[0], best, "best", "tab:green"), (axes[1], worst, "worst", "tab:red")):
    path = evaluation.metrics[i]["paths"][POINT]
    closed = np.vstack([path, path[:1]])
    ax.plot(closed_target[:, 0], closed_target[:, 1], color="black", linestyle="--", linewidth=2, label="target")
    ax.plot(closed[:, 0], closed[:, 1], color=color, linewidth=1.5,
            label=f"{label}: crank {params[i]['crank']:.3f} m, rocker {params[i]['rocker']:.3f} m")
    ax.plot(path[0, 0], path[0, 1], marker="o", color=color)
    ax.set_title(f"{label} feasible design: path error {1e3 * errors[i]:.2f} mm")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
fig.tight_layout()
fig.savefig(OUT / "four_bar_best_worst_curves.png", dpi=120)
plt.show()

# %% [markdown]
# ## What the picture shows
#
# - **The reference is found.** The smallest path error sits next to the reference lengths, and
#   the best feasible coupler curve lies almost on top of the target. It does not match exactly
#   because the reference lies between grid nodes; a finer grid gets closer.
# - **One smooth valley.** The error grows steadily in every direction away from the reference:
#   within the two lengths swept here the map shows a single basin and no second design that draws
#   nearly the same curve (the count of local minima printed above checks this on the grid).
#   The printed valley widths say how precisely each length has to be held for a close match.
# - **Feasibility ends at a hard edge.** The grey cells are designs with a long crank and a short
#   rocker: coupler and rocker cannot meet for part of the crank turn, so the mechanism does not
#   complete a cycle. The error does not fade out toward that edge; the designs next to it are
#   among the worst feasible ones, and their coupler curves differ from the target in size, shape
#   and position, not just by an offset.
#
# The numbers printed above (best, worst and median error, the valley widths, the count of
# infeasible designs) come from this run and change with the grid size.
