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
# # The nominal optimum against the robust one
#
# An optimizer that sees one nominal world finds a design that is best there, and possibly fragile:
# laser-cut links are off by a fraction of a millimetre, floors slope, payloads change. A study with
# a `[robustness]` table judges every design over perturbed worlds of its own instead. Here we run
# two searches each for a path-synthesis four-bar (kinematic, manufacturing tolerances) and for the
# walker (dynamic, slopes, payloads and friction), one nominal and one robust, and then judge both
# optima under the same 128 scenarios: the distribution of the objective and the share of
# scenarios in which the design fails.

# %%
import os
import pathlib
import tempfile

import matplotlib.pyplot as plt
import numpy as np

from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
from morphopt.families import load_family
from morphopt.metrics import path_error
from morphopt.robust import Distribution, Robustness, draw, expand, scenario_hooks
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec

SMALL = os.environ.get("MORPHOPT_SWEEP_SIZE") == "small"
DEVICE = os.environ.get("MORPHOPT_DEVICE", "cpu")
OUT = pathlib.Path(os.environ.get("MORPHOPT_SWEEP_OUT", "figures"))
OUT.mkdir(parents=True, exist_ok=True)
WORK = pathlib.Path(tempfile.mkdtemp(prefix="robust_sweep_"))  # the studies' storage
JUDGE = 32 if SMALL else 128  # common scenarios both optima are judged in


def study(name: str, text: str):
    """Run a study written as TOML text; its spec and best design."""
    path = WORK / f"{name}.toml"
    path.write_text(text)
    spec = load_study_spec(path)
    result = run_study(spec, progress=False)
    return spec, result.best_params


# %% [markdown]
# ## A four-bar tracing a curve, with 1 mm tolerances
#
# The target is `studies/four_bar_path.toml`'s curve. The robust search perturbs the crank, coupler
# and rocker lengths by 1 mm (normal) in 8 scenarios per design and minimizes the mean path error
# of the worst 20 % of them (CVaR at 0.8); a scenario in which the linkage cannot turn counts as
# failed, and more than a quarter failed fails the design.

# %%
base = (pathlib.Path("../four_bar_path.toml").read_text() if pathlib.Path("../four_bar_path.toml").exists()
        else pathlib.Path("studies/four_bar_path.toml").read_text())
gens, worlds = (6, 24) if SMALL else (40, 64)
common = base.replace("generations = 40", f"generations = {gens}").replace("worlds = 64", f"worlds = {worlds}")
tolerances = "\n".join(f"{n} = {{ normal = [0.0, 0.001] }}" for n in ("crank", "coupler", "rocker"))
nominal_spec, nominal = study("path_nominal", common.replace('name = "four_bar_path"', 'name = "path_nominal"'))
robust_spec, robust = study("path_robust", common.replace('name = "four_bar_path"', 'name = "path_robust"')
                            + f"\n[robustness]\nsamples = 8\naggregate = \"cvar\"\nlevel = 0.8\n"
                              f"max_failure_share = 0.25\n[robustness.parameters]\n{tolerances}\n")
print("nominal optimum:", {k: round(v, 4) for k, v in nominal.items()})
print("robust optimum: ", {k: round(v, 4) for k, v in robust.items()})

# %% [markdown]
# Both optima are judged under the same `JUDGE` scenarios of the same tolerances.

# %%
four_bar = load_family("four_bar")
judge = Robustness(samples=JUDGE, parameters={n: Distribution("normal", 0.0, 0.001)
                                              for n in ("crank", "coupler", "rocker")})
scenarios = draw(judge, seed=2024, generation=0)
target = np.asarray(nominal_spec.target)
batch = expand([nominal, robust], scenarios, four_bar.space)
evaluation = evaluate_kinematic(four_bar, batch, samples=120, keep_paths=True)
errors = np.array([path_error(m["paths"]["coupler_point"], target) if not f else np.nan
                   for m, f in zip(evaluation.metrics, evaluation.failures)]).reshape(2, JUDGE + 1)
for label, row in zip(("nominal", "robust"), errors):
    kept = row[1:][np.isfinite(row[1:])]
    print(f"{label:8}: nominal error {1e3 * row[0]:.2f} mm; over {JUDGE} scenarios: failed "
          f"{100 * np.mean(~np.isfinite(row[1:])):.0f} %, mean {1e3 * kept.mean():.2f} mm, "
          f"worst {1e3 * kept.max():.2f} mm")

fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
bins = np.linspace(0.0, np.nanmax(errors[:, 1:]) * 1e3 * 1.05, 25)
for label, row in zip(("nominal optimum", "robust optimum"), errors):
    left.hist(1e3 * row[1:][np.isfinite(row[1:])], bins=bins, alpha=0.6,
              label=f"{label} ({100 * np.mean(~np.isfinite(row[1:])):.0f} % failed)")
left.set_xlabel("path error under 1 mm tolerances [mm]")
left.set_ylabel("scenarios")
left.legend()
right.plot(*np.vstack([target, target[:1]]).T, "k--", label="target")
for label, k in (("nominal optimum", 0), ("robust optimum", JUDGE + 1)):
    path = evaluation.metrics[k]["paths"]["coupler_point"]
    right.plot(path[:, 0], path[:, 1], label=label)
right.set_aspect("equal")
right.set_title("coupler curves of the two optima (nominal lengths)")
right.legend()
fig.tight_layout()
fig.savefig(OUT / "robust_four_bar.png", dpi=110)

# %% [markdown]
# ## A walker on slopes with payloads
#
# The robust search judges each walker over 4 scenarios (slopes of +-5 degrees, payloads of 0-30 %
# of the torso's mass, ground friction 0.7-1.2 times) and maximizes its worst speed among them.

# %%
w_gens, w_worlds, seconds = (2, 8, 1.3) if SMALL else (10, 64, 2.0)
walker_text = f"""[study]
name = "NAME"
family = "walker"
mode = "dynamic"
seed = 0
generations = {w_gens}
worlds = {w_worlds}
device = "{DEVICE}"
[objective]
metric = "walking_speed"
direction = "maximize"
[simulation]
duration = {seconds}
dt = 0.005
[fixed]
legs_per_side = 3
"""
world = ("slope = { uniform = [-5.0, 5.0] }\npayload = { uniform = [0.0, 0.3] }\n"
         "friction = { uniform = [0.7, 1.2] }\n")
walker_spec, walker_nominal = study("walker_nominal", walker_text.replace("NAME", "walker_nominal"))
_, walker_robust = study("walker_robust", walker_text.replace("NAME", "walker_robust")
                         + "[robustness]\nsamples = 4\naggregate = \"worst\"\nmax_failure_share = 0.5\n" + world)

walker = load_family("walker")
judge = Robustness(samples=JUDGE, slope=Distribution("uniform", low=-5.0, high=5.0),
                   payload=Distribution("uniform", low=0.0, high=0.3),
                   friction=Distribution("uniform", low=0.7, high=1.2))
scenarios = draw(judge, seed=2024, generation=0)
batch = expand([walker_nominal, walker_robust], scenarios, walker.space)
evaluation = evaluate_dynamic(walker, batch, duration=seconds, dt=0.005, device=DEVICE,
                              spec_hook=scenario_hooks(batch, [None, *scenarios] * 2))
speeds = np.array([m.get("walking_speed", np.nan) if not f else np.nan
                   for m, f in zip(evaluation.metrics, evaluation.failures)]).reshape(2, JUDGE + 1)
fig, ax = plt.subplots(figsize=(6, 4))
for label, row in zip(("nominal optimum", "robust optimum"), speeds):
    kept = row[1:][np.isfinite(row[1:])]
    print(f"{label:16}: nominal {row[0]:.3f} m/s; over {JUDGE} scenarios: failed "
          f"{100 * np.mean(~np.isfinite(row[1:])):.0f} %, mean {kept.mean() if len(kept) else np.nan:.3f}, "
          f"worst {kept.min() if len(kept) else np.nan:.3f} m/s")
    ax.hist(kept, bins=12, alpha=0.6, label=f"{label} ({100 * np.mean(~np.isfinite(row[1:])):.0f} % fell)")
ax.set_xlabel("walking speed on slopes with payloads [m/s]")
ax.set_ylabel("scenarios")
ax.legend()
fig.tight_layout()
fig.savefig(OUT / "robust_walker.png", dpi=110)

# %% [markdown]
# ## The four optima
#
# The four-bars in their plane with their coupler curves and the target; the walkers from the side
# at their initial pose.

# %%
from morphopt.plots import draw_design  # noqa: E402

fig, axes = plt.subplots(2, 2, figsize=(11, 9))
for ax, (label, family, params, spec) in zip(axes.flat, (
        ("four-bar, nominal optimum", four_bar, nominal, nominal_spec),
        ("four-bar, robust optimum", four_bar, robust, robust_spec),
        ("walker, nominal optimum", walker, walker_nominal, walker_spec),
        ("walker, robust optimum", walker, walker_robust, walker_spec))):
    view = draw_design(ax, family, params, spec)
    ax.set_title(label + view, fontsize=10)
    ax.grid(alpha=0.3)
axes[0, 0].legend(fontsize=8)
fig.tight_layout()
fig.savefig(OUT / "robust_designs.png", dpi=110)
