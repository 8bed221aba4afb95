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
print(pd.Series({name: 1e3 * base[name] for name in LINKS}, name="published length [mm]").to_frame().T.to_string())

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
# The stride is measured on the flat bottom of the foot path (the part of the path within 2 % of
# the step height above its lowest point; `foot_stride_full` would be the whole horizontal extent,
# see `morphopt families show jansen_leg`), so it need not change linearly with a length, or even
# monotonically. A straight-line fit would hide that, so each length is scored by its mean
# sensitivity instead: the average of |change of stride in %| / |change of length in %| over the
# feasible designs of its sweep (a value of 1 means the stride changes, on average, as much as the
# length). The same score for the step height, the stride's range over the sweep, the published
# leg's stride as a fraction of the best one of the sweep and the number of infeasible designs
# complete the picture: a length can matter because it changes the gait, or because the leg stops
# working.


# %%
def sensitivity(r, values, ref):
    """Mean |relative change of values| / |r| over the finite values with r != 0 (NaN if none)."""
    ok = np.isfinite(values) & (r != 0.0)
    return float(np.mean(np.abs(values[ok] / ref - 1.0) / np.abs(r[ok]))) if ok.any() else np.nan


ranking = pd.DataFrame([{
    "link": name,
    "stride_sensitivity": sensitivity(group.r.to_numpy(), group.stride.to_numpy(), ref_stride),
    "height_sensitivity": sensitivity(group.r.to_numpy(), group.step_height.to_numpy(), ref_height),
    "stride_min_mm": 1e3 * group.stride.min(),
    "stride_max_mm": 1e3 * group.stride.max(),
    "infeasible": int((~group.feasible).sum()),
    "published_of_best": ref_stride / group.stride.max(),
} for name, group in rows.groupby("link", sort=False)]).set_index("link")
ranking = ranking.sort_values(["stride_sensitivity", "infeasible"], ascending=False, na_position="last")
print(ranking.round(2).to_string())
near = int((ranking.published_of_best >= 0.95).sum())
print(f"the published leg's stride is within 5 % of the best of the sweep for {near} of {len(ranking)} lengths")

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
# - Jansen's lengths are a finely tuned point. The stride counts only the flat part of the foot
#   path, and for most lengths a change of a percent or two in either direction shortens it
#   sharply: the published leg sits at or close to the top of a narrow peak, so most sensitivity
#   scores are far above 1. The step height changes more smoothly and, for most lengths, keeps
#   changing in one direction across the sweep.
# - The lengths are far from equally important. A handful (the ranking table's top rows) move the
#   stride most; a few others, among them lengths that mainly shift the frame rather than shape
#   the path, barely change it over the whole sweep.
# - Feasibility is often one-sided: lengthening or shortening some lengths past a limit leaves one
#   of the dyads unable to close during the turn, and the leg locks. The gaps in the
#   one-at-a-time curves and the grey region of the maps mark that limit; on some lengths the
#   published value lies only a few percent inside it, and the step height grows quickly as the
#   limit is approached.
# - On the 2-D maps the long strides do not fill a round region around the published design: they
#   follow a narrow band across the plane, so the two lengths interact. Changing one of them can be
#   partly made up for by changing the other, which a one-at-a-time view cannot show.
