"""Reduced against maximal coordinates on the same walkers: outcomes, walking speeds and time.

    python benchmarks/walker_reduced.py --device cpu --designs 16 --out DIR

Samples designs of the walker family (three legs per side, seeded), evaluates every design with
model="reduced" (engine.legged: torso + crank angles) and model="maximal" (every link a body,
every joint its rows), each batch with the study's settings (studies/walker.toml: duration, dt,
[solver]), and reports per design both walking speeds and failure reasons; in summary the wall
time of each batch, how often both models agree on failing, and the walking-speed differences of
the designs that walk in both. Prints one JSON object; writes walker_reduced_<device>.json and
.csv (one row per design) and a scatter plot of the speeds (PNG).
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
import warp as wp  # noqa: E402

from morphopt.evaluate import evaluate_dynamic  # noqa: E402
from morphopt.families import load_family  # noqa: E402
from morphopt.study_spec import load_study_spec  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--designs", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_study_spec(ROOT / "studies" / "walker.toml")
    family = load_family("walker")
    params = [{**family.space.default(), **spec.fixed}]
    params += [{**p, **spec.fixed} for p in family.space.sample(np.random.default_rng(args.seed), args.designs - 1)]
    runs, seconds = {}, {}
    for model in ("reduced", "maximal"):
        evaluate_dynamic(family, params[:1], duration=4 * spec.dt, dt=spec.dt, device=args.device,
                         config=spec.solver_config(), model=model)  # compile outside the timing
        t0 = time.perf_counter()
        runs[model] = evaluate_dynamic(family, params, duration=spec.duration, dt=spec.dt, device=args.device,
                                       config=spec.solver_config(), model=model)
        seconds[model] = time.perf_counter() - t0
    rows = []
    for i, p in enumerate(params):
        row = {"design": i, "leg_family": p["leg_family"]}
        for model, run in runs.items():
            row[f"{model}_speed"] = run.metrics[i].get("walking_speed", float("nan"))
            row[f"{model}_failure"] = run.failures[i]
        rows.append(row)
    both = [r for r in rows if not r["reduced_failure"] and not r["maximal_failure"]]
    diff = np.array([r["reduced_speed"] - r["maximal_speed"] for r in both])
    ref = np.array([r["maximal_speed"] for r in both])
    report = {
        "device": wp.get_device(args.device).name if args.device != "cpu" else "cpu", "designs": len(params),
        "duration": spec.duration, "dt": spec.dt, "solver": spec.solver,
        "seconds": seconds, "speedup": seconds["maximal"] / seconds["reduced"],
        "fail_agreement": float(np.mean([bool(r["reduced_failure"]) == bool(r["maximal_failure"]) for r in rows])),
        "walking_in_both": len(both),
        "speed_abs_diff_median": float(np.median(np.abs(diff))) if len(both) else None,
        "speed_rel_diff_median": float(np.median(np.abs(diff) / np.maximum(ref, 1e-9))) if len(both) else None,
        "speed_correlation": float(np.corrcoef(ref, ref + diff)[0, 1]) if len(both) > 2 else None,
        "default_speed": {m: rows[0][f"{m}_speed"] for m in runs}, "warp": wp.config.version,
    }
    stem = out / f"walker_reduced_{args.device.split(':')[0]}"
    stem.with_suffix(".json").write_text(json.dumps({**report, "designs_table": rows}, indent=1))
    import pandas as pd

    pd.DataFrame(rows).to_csv(stem.with_suffix(".csv"), index=False)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    if both:
        top = max(max(r["maximal_speed"] for r in both), max(r["reduced_speed"] for r in both)) * 1.1
        ax.plot([0, top], [0, top], color="0.7", lw=1)
        for family_name, marker in (("jansen_leg", "o"), ("klann_leg", "s")):
            pts = [(r["maximal_speed"], r["reduced_speed"]) for r in both if r["leg_family"] == family_name]
            if pts:
                ax.scatter(*zip(*pts), marker=marker, label=family_name, s=18)
        ax.legend()
    ax.set_xlabel("walking speed, maximal coordinates [m/s]")
    ax.set_ylabel("walking speed, reduced coordinates [m/s]")
    ax.set_title(f"{len(both)} walkers, {report['device']}")
    fig.tight_layout()
    fig.savefig(stem.with_suffix(".png"), dpi=120)
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
