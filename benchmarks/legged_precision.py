"""Work against precision of the walker study's simulation (the reduced coordinates engine.pack plans
for walkers: TABULATED, the torso and one crank angle per leg; once engine.legged's).

    python benchmarks/legged_precision.py --device cuda --designs 4096 --out DIR

Samples designs of the walker family (three legs per side, seeded, the default design first) and
evaluates them (morphopt.evaluate_dynamic in the engine's own plan, the study's duration) under a grid
of time steps and PADMM settings (SolverConfig with a penalty update every 8 iterations; "loose": rho 1,
tolerance 1e-4, relative tolerance 1e-3), and with the study's own settings, against a reference at
dt 0.5 ms with rho 1 and the iteration cap raised to 400.
Per setting: the wall time of the simulation (simulated seconds per wall second over the batch),
how many designs get the reference's outcome (walks, or fails for the same kind of reason), and
the walking-speed error [m/s] of the designs that walk in both (median, 90th percentile, largest,
and relative to the reference's median speed) and the rank correlation of their speeds with the
reference's (what an optimizer sees), and the plan's coordinates. Prints one JSON object; writes
legged_precision_<device>.json, .csv.gz (one row per design and setting) and a plot of error against
run time (PNG).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import warp as wp  # noqa: E402

from engine import SolverConfig  # noqa: E402
from morphopt.evaluate import evaluate_dynamic  # noqa: E402
from morphopt.families import load_family  # noqa: E402
from morphopt.study_spec import load_study_spec  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]

# (label, dt [s], SolverConfig keywords, its knobs under "tuning": engine.Tuning's, over BASE's); the
# study's own settings run as well. rho: the tabulated plan's starting penalty (Tuning.rho; its default,
# None, is engine.config.TABULATED_RHO = 1)
BASE = {"tuning": {"rho_update_interval": 8}}
LOOSE = {"tolerance": 1e-4, "relative_tolerance": 1e-3, "tuning": {"rho": 1.0}}
SETTINGS = [
    ("dt 2 ms, rho 1e-3", 2e-3, {"tuning": {"rho": 1e-3}}),
    ("dt 2 ms, rho 1", 2e-3, {"tuning": {"rho": 1.0}}),
    ("dt 1 ms, rho 1", 1e-3, {"tuning": {"rho": 1.0}}),
    ("dt 1 ms, loose", 1e-3, LOOSE),
    ("dt 2 ms, loose", 2e-3, LOOSE),
    ("dt 4 ms, loose", 4e-3, LOOSE),
    ("dt 5 ms, loose", 5e-3, LOOSE),
    ("dt 5 ms, loose, cap 30", 5e-3, {**LOOSE, "max_iterations": 30}),
    ("dt 5 ms, loose, cap 20", 5e-3, {**LOOSE, "max_iterations": 20}),
    ("dt 8 ms, loose", 8e-3, LOOSE),
    ("dt 10 ms, loose", 1e-2, LOOSE),
    ("dt 10 ms, loose, cap 30", 1e-2, {**LOOSE, "max_iterations": 30}),
    ("dt 16 ms, loose, cap 30", 1.6e-2, {**LOOSE, "max_iterations": 30}),
    ("dt 20 ms, loose, cap 30", 2e-2, {**LOOSE, "max_iterations": 30}),
]
REFERENCE = ("reference: dt 0.5 ms, rho 1, cap 400", 5e-4, {"max_iterations": 400, "tuning": {"rho": 1.0}})


def config_of(overrides: dict) -> SolverConfig:
    """BASE with ``overrides`` (their tuning over BASE's)."""
    return SolverConfig(**{**BASE, **overrides, "tuning": {**BASE["tuning"], **overrides.get("tuning", {})}})


def outcome(reason: str) -> str:
    """The kind of a failure reason ("" for a design that walks): its first word."""
    return reason.split(" ")[0].split(":")[0] if reason else ""


def plot(report: dict, path) -> None:
    """Walking-speed error against simulated seconds per wall second, one point per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5.5))
    for r in report["results"]:
        if r["speed_error_median"] is None:
            continue
        point = (r["simulated_s_per_s"], max(r["speed_error_median"], 1e-6))
        ax.loglog(*point, "o")
        ax.annotate(f"{r['setting']} ({100 * r['same_outcome']:.0f}% same outcome)", point, fontsize=7,
                    xytext=(4, 2), textcoords="offset points")
    ax.set_xlabel("simulated seconds per wall second (the batch)")
    ax.set_ylabel("walking-speed error against the reference, median [m/s]")
    ax.set_title(f"walkers in reduced coordinates, {report['designs']} designs, {report['device']}")
    ax.grid(True, which="both", alpha=0.3)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--designs", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="three settings only (dt 2, 5, 10 ms)")
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the study's)")
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_study_spec(ROOT / "studies" / "walker.toml")
    family = load_family("walker")
    duration = args.duration or spec.duration
    params = [{**family.space.default(), **spec.fixed}]
    params += [{**p, **spec.fixed} for p in family.space.sample(np.random.default_rng(args.seed), args.designs - 1)]
    settings = [s for s in SETTINGS if s[0] in ("dt 2 ms, rho 1", "dt 5 ms, loose, cap 30", "dt 10 ms, loose")] \
        if args.quick else SETTINGS

    def run(dt, overrides, config=None):
        config = config or config_of(overrides)
        t0 = time.perf_counter()
        evaluation = evaluate_dynamic(family, params, duration=duration, dt=dt, device=args.device, config=config)
        return evaluation, time.perf_counter() - t0

    evaluate_dynamic(family, params[:1], duration=0.02, dt=2e-3, device=args.device,
                     config=SolverConfig())  # compile outside the timing
    reference, _ = run(REFERENCE[1], REFERENCE[2])
    ref_speed = np.array([m.get("walking_speed", np.nan) for m in reference.metrics])
    ref_kind = [outcome(r) for r in reference.failures]
    walks = np.array([k == "" for k in ref_kind])
    ref_median = float(np.median(np.abs(ref_speed[walks]))) if walks.any() else float("nan")
    results, rows = [], []
    study = (f"study (dt {spec.dt * 1e3:g} ms, its [solver])", spec.dt, None)
    for label, dt, overrides in [study, *settings]:
        evaluation, seconds = run(dt, overrides or {},
                                  None if overrides is not None else spec.solver_config() or SolverConfig())
        simulate = evaluation.timings.get("simulate", seconds)
        speed = np.array([m.get("walking_speed", np.nan) for m in evaluation.metrics])
        kind = [outcome(r) for r in evaluation.failures]
        same = np.array([a == b for a, b in zip(kind, ref_kind)])
        both = walks & np.array([k == "" for k in kind])
        err = np.abs(speed[both] - ref_speed[both])
        rank = float(pd.Series(speed[both]).corr(pd.Series(ref_speed[both]), method="spearman")) \
            if both.sum() > 2 else None
        settings_used = (spec.solver or {}) if overrides is None else overrides
        result = {"setting": label, "dt": dt, **settings_used, "designs": len(params),
                  "coordinates": evaluation.plan.coordinates.value,
                  "simulate_s": simulate, "evaluate_s": seconds,
                  "simulated_s_per_s": len(params) * duration / simulate,
                  "same_outcome": float(same.mean()), "walk_in_both": int(both.sum()),
                  "speed_error_median": float(np.median(err)) if err.size else None,
                  "speed_error_p90": float(np.percentile(err, 90)) if err.size else None,
                  "speed_error_max": float(err.max()) if err.size else None,
                  "speed_error_median_relative": float(np.median(err) / ref_median) if err.size else None,
                  "speed_rank_correlation": rank}
        results.append(result)
        print(json.dumps(result), flush=True)
        for i in range(len(params)):
            rows.append({"setting": label, "design": i, "leg_family": params[i]["leg_family"],
                         "reference_outcome": ref_kind[i], "outcome": kind[i],
                         "reference_speed": ref_speed[i], "speed": speed[i]})
    device = wp.get_device(args.device)
    report = {"device": device.name if device.is_cuda else "cpu", "warp": wp.config.version, "base": BASE,
              "designs": len(params), "duration": duration, "seed": args.seed,
              "reference": {"setting": REFERENCE[0], "walk": int(walks.sum()), "median_speed": ref_median},
              "results": results}
    tag = args.device.split(":")[0]
    (out / f"legged_precision_{tag}.json").write_text(json.dumps(report, indent=1))
    pd.DataFrame(rows).to_csv(out / f"legged_precision_{tag}.csv.gz", index=False)
    plot(report, out / f"legged_precision_{tag}.png")
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
