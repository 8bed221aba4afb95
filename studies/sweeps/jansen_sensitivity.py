# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # How sensitive is Jansen's leg to its link lengths?
#
# Theo Jansen tuned the thirteen lengths of his Strandbeest leg (the "holy numbers") so that the
# foot sweeps a long, flat stride and lifts clear of the ground on the way back. The `jansen_leg`
# family uses those published numbers as its defaults. Here we ask two questions:
#
# 1. If one length is changed by a few percent while the others stay put, how much do the stride
#    length and the step height of the foot change, and does the leg still complete a crank turn?
#    Which lengths matter most?
# 2. For the two lengths that matter most, what does the design landscape look like when both are
#    varied together?
#
# Everything is kinematic: the foot's path over one crank turn, no dynamics. Each question is one
# batched call of `evaluate_kinematic`.

# %%
import os
import pathlib

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from morphopt.evaluate import evaluate_kinematic
from morphopt.families import load_family
from morphopt.sweep import grid, one_at_a_time

SMALL = os.environ.get("MORPHOPT_SWEEP_SIZE") == "small"
DEVICE = os.environ.get("MORPHOPT_DEVICE", "cpu")
OUT = pathlib.Path(os.environ.get("MORPHOPT_SWEEP_OUT", "figures"))
OUT.mkdir(parents=True, exist_ok=True)

STEPS = 5 if SMALL else 21  # relative changes per link, one-at-a-time
GRID = 6 if SMALL else 64  # points per axis of the 2-D maps
SPAN = 0.10  # +-10 % around the published lengths

family = load_family("jansen_leg")
space = family.space
base = space.default()
POINT = "foot"  # the tracked point of the family

# Every parameter of this family is a length (the frame offsets a and l, the crank m and the
# bars); keep only floats with a positive default so that a scaled value is still a length.
LINKS = [name for name in space.names if isinstance(base[name], float) and base[name] > 0.0]
print(f"{len(LINKS)} lengths swept: {', '.join(LINKS)}")
print(pd.Series({name: 1e3 * base[name] for name in LINKS}, name="published length [mm]").to_frame().T)

# %% [markdown]
# ## One length at a time
#
# Each length is scaled by $(1 + r)$ for $r$ from $-10\,\%$ to $+10\,\%$, the others stay at the
# published values. All these designs go into a single batched evaluation. A design that fails
# (typically: one of the dyads cannot close somewhere in the crank turn) has no stride; it is left
# out of the plot as a gap and counted.

# %%
relative = np.linspace(-SPAN, SPAN, STEPS)
params, labels = one_at_a_time(space, relative.tolist(), names=LINKS)
evaluation = evaluate_kinematic(family, params, device=DEVICE, keep_paths=False)


def metric(evaluation, key):
    """The metric ``key`` of every design as a float array, NaN where the design is infeasible."""
    return np.array([m[key] if ok else np.nan for m, ok in zip(evaluation.metrics, evaluation.feasible)])


rows = pd.DataFrame(labels, columns=["link", "r"])
rows["stride"] = metric(evaluation, f"{POINT}_stride")
rows["step_height"] = metric(evaluation, f"{POINT}_step_height")
rows["feasible"] = evaluation.feasible
rows["failure"] = evaluation.failures
print(f"{len(params)} designs, {int((~rows.feasible).sum())} infeasible")
reasons = rows.loc[~rows.feasible, "failure"].str.replace(r" at crank angle .*", "", regex=True)
if len(reasons):
    print(reasons.value_counts().to_string())

# The published leg itself, for reference (r = 0 of any link is the base design).
reference = evaluate_kinematic(family, [base], device=DEVICE, keep_paths=True)
ref_stride = reference.metrics[0][f"{POINT}_stride"]
ref_height = reference.metrics[0][f"{POINT}_step_height"]
print(f"published leg: stride {1e3 * ref_stride:.1f} mm, step height {1e3 * ref_height:.1f} mm")

# %%
colors = plt.get_cmap("tab20")(np.linspace(0.0, 1.0, len(LINKS)))
fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharex=True)
for (name, group), color in zip(rows.groupby("link", sort=False), colors):
    bad = int((~group.feasible).sum())
    label = f"{name} ({bad} infeasible)" if bad else name
    for ax, key, ref in ((axes[0], "stride", ref_stride), (axes[1], "step_height", ref_height)):
        ax.plot(100 * group.r, 100 * (group[key] / ref - 1.0), "-o", ms=3, color=color, label=label)
for ax, title in zip(axes, ("stride length", "step height")):
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.axvline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel("change of one length [%]")
    ax.set_ylabel(f"change of {title} [%]")
    ax.set_title(f"foot {title}")
    ax.grid(alpha=0.3)
axes[1].legend(fontsize=8, ncol=2, title="varied length")
fig.suptitle(f"Jansen leg, one length at a time ({int((~rows.feasible).sum())} of {len(rows)} designs infeasible)")
fig.tight_layout()
fig.savefig(OUT / "jansen_one_at_a_time.png", dpi=120)

# %% [markdown]
# ### Ranking the lengths
#
# To compare the lengths we fit a straight line through the feasible points of each curve: its
# slope is an elasticity, percent change of stride per percent change of the length. The range
# (largest minus smallest stride over the sweep) and the number of infeasible designs complete the
# picture: a length can matter because it changes the gait, or because the leg stops working.


# %%
def elasticity(r, values, ref):
    """Slope of the relative change of ``values`` against r, over the finite values (NaN if < 2)."""
    ok = np.isfinite(values)
    if ok.sum() < 2:
        return np.nan
    return float(np.polyfit(r[ok], values[ok] / ref - 1.0, 1)[0])


ranking = pd.DataFrame([{
    "link": name,
    "stride_per_pct": elasticity(group.r.to_numpy(), group.stride.to_numpy(), ref_stride),
    "height_per_pct": elasticity(group.r.to_numpy(), group.step_height.to_numpy(), ref_height),
    "stride_range_mm": 1e3 * (group.stride.max() - group.stride.min()),
    "height_range_mm": 1e3 * (group.step_height.max() - group.step_height.min()),
    "infeasible": int((~group.feasible).sum()),
} for name, group in rows.groupby("link", sort=False)]).set_index("link")
ranking["influence"] = ranking.stride_per_pct.abs()
ranking = ranking.sort_values(["influence", "stride_range_mm"], ascending=False, na_position="last")
print(ranking.round(3).to_string())

TOP = list(ranking.index[:2])
print(f"most influential on the stride: {TOP[0]} and {TOP[1]}")

# %% [markdown]
# ## Two lengths together
#
# The two lengths at the top of the ranking are now varied jointly over the same $\pm 10\,\%$, on
# a grid, again in one batched call. Infeasible designs are masked (grey), and the published
# design is marked with a cross.

# %%
first, second = TOP
scales = 1.0 + np.linspace(-SPAN, SPAN, GRID)
axes_values = {first: (base[first] * scales).tolist(), second: (base[second] * scales).tolist()}
grid_params = grid(space, axes_values)
grid_eval = evaluate_kinematic(family, grid_params, device=DEVICE, keep_paths=False)
stride_map = metric(grid_eval, f"{POINT}_stride").reshape(GRID, GRID)
height_map = metric(grid_eval, f"{POINT}_step_height").reshape(GRID, GRID)
feasible_map = grid_eval.feasible.reshape(GRID, GRID)
print(f"{feasible_map.size} designs, {int((~feasible_map).sum())} infeasible "
      f"({100 * (~feasible_map).mean():.0f} %)")

# %%
extent = [100 * (scales[0] - 1), 100 * (scales[-1] - 1), 100 * (scales[0] - 1), 100 * (scales[-1] - 1)]
fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
for ax, values, title in ((axes[0], stride_map, "stride length"), (axes[1], height_map, "step height")):
    cmap = plt.get_cmap("viridis").copy()
    cmap.set_bad("0.8")
    image = ax.imshow(np.ma.masked_invalid(1e3 * values), origin="lower", extent=extent, aspect="auto",
                      cmap=cmap, interpolation="nearest")
    fig.colorbar(image, ax=ax, label=f"{title} [mm]")
    ax.plot(0.0, 0.0, "x", color="red", ms=9, mew=2, label="published")
    # rows of the maps follow the first axis (y), columns the second (x)
    ax.set_xlabel(f"change of {second} [%]")
    ax.set_ylabel(f"change of {first} [%]")
    ax.set_title(f"foot {title}")
    ax.legend(loc="upper right", fontsize=8)
fig.suptitle(f"Jansen leg, {first} against {second} (grey: cannot complete a crank turn, "
             f"{int((~feasible_map).sum())} of {feasible_map.size})")
fig.tight_layout()
fig.savefig(OUT / "jansen_2d_maps.png", dpi=120)

# %% [markdown]
# ## What the pictures show
#
# - The leg is not equally sensitive to all of its lengths. A few of them move the stride and the
#   step height by more than their own relative change, while others barely matter over
#   $\pm 10\,\%$; the ranking table orders them by the slope of the stride curve.
# - Stride and step height do not always move together: some lengths trade one against the
#   other, so a change that lengthens the stride can flatten the lift of the foot, or the other way
#   round.
# - Feasibility is one-sided for several lengths: shortening or lengthening them past some point
#   makes one of the dyads unable to close during the turn, and the leg locks. The gaps in the
#   one-at-a-time curves and the grey region of the maps mark that boundary; near it the metrics
#   change fastest.
# - On the 2-D maps the published design lies in the feasible region but not necessarily far from
#   its edge, and the contours of stride and step height are not aligned with the axes: the two
#   most influential lengths interact, so tuning them one at a time would miss part of the picture.
