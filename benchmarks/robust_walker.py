"""Nominal against robust walker search, judged under the same scenarios (issue: robust design).

    python -m benchmarks.robust_walker --device cuda [--worlds 512] [--generations 10] [--samples 8]
    python -m benchmarks.robust_walker --device cpu --worlds 16 --generations 1 --samples 2 --judge 8

Runs two walker studies with the same seed, population and simulation: one on flat ground with the
nominal torso (nominal optimum), one with a ``[robustness]`` table of ``--samples`` scenarios per
design (slopes uniform in +-5 degrees, payloads uniform in 0-30 % of the torso's mass; with
--roughness R also rough ground, bumps of amplitude uniform in [0, R] m) maximizing the worst
speed among them; with --rejudge K the robust optimum is the best of the search's K best stored
designs under 32 fresh scenarios instead of the search's own pick (its scenarios are redrawn every
generation, so the best value seen is partly the luck of its draw). Then simulates both optima in one batch under ``--judge`` common
scenarios drawn from the same distributions with another seed, and reports per optimum the nominal
speed, the share of scenarios it falls in, and the mean and worst speed. Writes
robust_walker_<device>.json and .csv (one row per design and scenario), and a histogram PNG when
matplotlib is installed.
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

from benchmarks.run import RESULTS, device_tag
from morphopt.evaluate import evaluate_dynamic
from morphopt.families import load_family
from morphopt.robust import Distribution, Robustness, draw, expand, scenario_hooks
from morphopt.storage import read_designs
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec

SLOPE = Distribution("uniform", low=-5.0, high=5.0)  # degrees
PAYLOAD = Distribution("uniform", low=0.0, high=0.3)  # share of the torso's mass


def study_text(name: str, args, robust: bool) -> str:
    """The study file of one search."""
    text = f"""[study]
name = "{name}"
family = "walker"
mode = "dynamic"
seed = {args.seed}
generations = {args.generations}
worlds = {args.worlds}
device = "{args.device}"
[objective]
metric = "walking_speed"
direction = "maximize"
[simulation]
duration = {args.duration}
dt = 0.005
[fixed]
legs_per_side = 3
"""
    if robust:
        text += (f"[robustness]\nsamples = {args.samples}\naggregate = \"worst\"\nmax_failure_share = 0.5\n"
                 f"slope = {{ uniform = [{SLOPE.low}, {SLOPE.high}] }}\n"
                 f"payload = {{ uniform = [{PAYLOAD.low}, {PAYLOAD.high}] }}\n")
        if args.roughness > 0.0:
            text += f"roughness = {{ uniform = [0.0, {args.roughness}] }}\n"
    return text


def plot(speeds: np.ndarray, out: dict, path: pathlib.Path) -> None:
    """Histograms of both optima's speeds over the judging scenarios (speeds: (2, 1 + judge), NaN: fell)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, row in zip(("nominal optimum", "robust optimum"), speeds):
        kept = row[1:][np.isfinite(row[1:])]
        ax.hist(kept, bins=16, alpha=0.6, label=f"{label} ({100 * np.mean(~np.isfinite(row[1:])):.0f} % fell)")
    ax.set_xlabel(f"walking speed over {out['judge']} scenarios [m/s]")
    ax.set_ylabel("scenarios")
    world = "slope +-5 deg, payload 0-30 %" + (f", bumps up to {100 * out['roughness']:g} cm" if out["roughness"] else "")
    rejudged = f"; robust pick re-judged among its {out['rejudge']['candidates']} best" if out.get("rejudge") else ""
    ax.set_title(f"{out['device']}: {out['generations']} generations of {out['worlds']}, {out['samples']} scenarios "
                 f"a design{rejudged}\n({world})", fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rejudge(spec, args) -> tuple[dict, dict]:
    """The robust search's ``args.rejudge`` best stored designs judged under 32 fresh scenarios (seed
    7): the one that falls least, then has the best worst speed, and what each scored."""
    walker = load_family("walker")
    frame = read_designs(spec.storage_url, spec.name)
    frame = frame[frame["failure"] == ""].sort_values("value", ascending=False)
    names = walker.space.names
    candidates = []
    for _, row in frame.iterrows():
        params = {n: (row[n].item() if hasattr(row[n], "item") else row[n]) for n in names}
        if params not in candidates:
            candidates.append(params)
        if len(candidates) == args.rejudge:
            break
    rough = Distribution("uniform", low=0.0, high=args.roughness) if args.roughness > 0.0 else None
    fresh = draw(Robustness(samples=32, slope=SLOPE, payload=PAYLOAD, roughness=rough), seed=7, generation=0)
    batch = expand(candidates, fresh, walker.space)
    evaluation = evaluate_dynamic(walker, batch, duration=args.duration, dt=0.005, device=args.device,
                                  spec_hook=scenario_hooks(batch, [None, *fresh] * len(candidates)))
    speeds = np.array([m.get("walking_speed", np.nan) if not f else np.nan
                       for m, f in zip(evaluation.metrics, evaluation.failures)]).reshape(len(candidates), 33)[:, 1:]
    fell = np.mean(~np.isfinite(speeds), axis=1)
    worst = np.array([row[np.isfinite(row)].min() if np.isfinite(row).any() else -np.inf for row in speeds])
    pick = int(np.lexsort((-worst, fell))[0])
    return candidates[pick], {"candidates": len(candidates), "fell_share": fell.tolist(), "worst_speed": worst.tolist(),
                              "picked": pick}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=512, help="designs per generation")
    parser.add_argument("--generations", type=int, default=10)
    parser.add_argument("--samples", type=int, default=8, help="scenarios per design in the robust search")
    parser.add_argument("--judge", type=int, default=128, help="common scenarios both optima are judged in")
    parser.add_argument("--duration", type=float, default=2.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--roughness", type=float, default=0.0, help="bumps' largest amplitude [m] (0: flat ground)")
    parser.add_argument("--rejudge", type=int, default=0, metavar="K",
                        help="re-judge the robust search's K best stored designs under 32 fresh scenarios and keep "
                             "the best of them (against the best-of-generations pick's luck)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    work = pathlib.Path(tempfile.mkdtemp(prefix="robust_walker_"))  # the two studies' storage
    out = {"device": device_tag(args.device), "command": "python -m benchmarks.robust_walker " + " ".join(sys.argv[1:]),
           **{k: getattr(args, k) for k in ("worlds", "generations", "samples", "judge", "duration", "seed",
                                            "roughness")}}
    optima = {}
    for label, robust in (("nominal", False), ("robust", True)):
        path = work / f"walker_{label}.toml"
        path.write_text(study_text(f"walker_{label}", args, robust))
        t = time.perf_counter()
        result = run_study(load_study_spec(path), progress=False)
        optima[label] = result.best_params
        out[f"{label}_search"] = {"seconds": time.perf_counter() - t, "best_value": result.best_value,
                                  "best_params": result.best_params}
        print(json.dumps({label: out[f"{label}_search"]}), file=sys.stderr, flush=True)
        if robust and args.rejudge > 0:
            spec = load_study_spec(path)
            optima[label], out["rejudge"] = rejudge(spec, args)
    walker = load_family("walker")
    rough = Distribution("uniform", low=0.0, high=args.roughness) if args.roughness > 0.0 else None
    scenarios = draw(Robustness(samples=args.judge, slope=SLOPE, payload=PAYLOAD, roughness=rough), seed=2024,
                     generation=0)
    batch = expand([optima["nominal"], optima["robust"]], scenarios, walker.space)
    evaluation = evaluate_dynamic(walker, batch, duration=args.duration, dt=0.005, device=args.device,
                                  spec_hook=scenario_hooks(batch, [None, *scenarios] * 2))
    speeds = np.array([m.get("walking_speed", np.nan) if not f else np.nan
                       for m, f in zip(evaluation.metrics, evaluation.failures)]).reshape(2, args.judge + 1)
    for label, row in zip(("nominal", "robust"), speeds):
        kept = row[1:][np.isfinite(row[1:])]
        out[label] = {"nominal_speed": float(row[0]), "fell_share": float(np.mean(~np.isfinite(row[1:]))),
                      "mean_speed": float(kept.mean()) if len(kept) else None,
                      "worst_speed": float(kept.min()) if len(kept) else None}
    worst = [out[k]["worst_speed"] for k in ("nominal", "robust")]
    out["robust_worst_beats_nominal_worst"] = bool(worst[1] is not None and (worst[0] is None or worst[1] > worst[0]))
    print(json.dumps(out), flush=True)
    folder = pathlib.Path(args.out) if args.out else RESULTS / out["device"]
    folder.mkdir(parents=True, exist_ok=True)
    stem = (f"robust_walker_{out['device']}" + ("_rough" if args.roughness > 0.0 else "")
            + ("_rejudged" if args.rejudge > 0 else ""))
    (folder / f"{stem}.json").write_text(json.dumps(out, indent=1))
    with open(folder / f"{stem}.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["optimum", "scenario", "slope_deg", "payload", "roughness_m", "walking_speed", "failure"])
        for d, label in enumerate(("nominal", "robust")):
            for s in range(args.judge + 1):
                scenario = None if s == 0 else scenarios[s - 1]
                k = d * (args.judge + 1) + s
                writer.writerow([label, s, scenario["slope"] if scenario else 0.0,
                                 scenario["payload"] if scenario else 0.0, scenario["roughness"] if scenario else 0.0,
                                 speeds[d, s], evaluation.failures[k] or ""])
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return
    plot(speeds, out, folder / f"{stem}.png")


if __name__ == "__main__":
    main()
