"""Earlier benchmark suites (core, stabilization, contact, scaling), declared as data; print one JSON
line per case, write CSV (and PNG). `python -m benchmarks.run` is the main benchmark now.

    python benchmarks/suites.py --suite core --device cuda --out benchmarks/results/h100
    python benchmarks/suites.py --suite stabilization --device cpu --worlds 64

Every case is engine.testspeed.run with the arguments below; repeats give medians.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import warp as wp  # noqa: E402

from engine.model import SolverConfig  # noqa: E402
from engine.testspeed import STABILIZATION, run  # noqa: E402

SUITES = {
    # testspeed JSON of the acceptance: fourbar and the heterogeneous mix
    "core": [
        dict(scene="fourbar", steps=1000, dt=1e-3),
        dict(scene="mixed", steps=1000, dt=1e-3),
    ],
    # position projection (SHAKE or plain) against velocity-level Baumgarte feedback, both integrators
    "stabilization": [
        dict(scene=scene, steps=5000, dt=1e-3, integrator=integrator, stabilization=stab)
        for scene in ("fourbar", "sixbar")
        for integrator in ("euler", "moreau")
        for stab in ("shake", "projection", "baumgarte")
    ],
    # contacts and limits (issue acceptance: walker and box_stack), fourbar for the skipped stages
    "contact": [dict(scene=scene, steps=1000, dt=1e-3) for scene in
                ("walker", "box_stack", "fourbar_limits", "ball_bounce", "box_slide", "box_on_plane", "fourbar")],
    # throughput against batch size
    "scaling": [dict(scene="fourbar", steps=200, dt=1e-3, worlds=n) for n in (1, 16, 256, 1024, 4096, 16384)],
}

FIELDS = ["scene", "num_worlds", "steps", "dt", "integrator", "stabilization", "step_ms_median", "world_steps_per_s",
          "max_constraint_violation_m", "max_constraint_violation_rad", "energy_drift_rel", "padmm_iterations_mean",
          "padmm_iterations_max", "diverged_worlds", "contacts_mean", "contacts_max", "contact_overflow_worlds",
          "max_penetration_m", "complementarity_max", "stage_ms", "fused_stage_cycles", "fused_inverse", "compile_s",
          "device", "device_name", "repeats"]


def run_case(case: dict, device: str, worlds: int, repeats: int) -> dict:
    stabilization = case.get("stabilization", "shake")
    config = SolverConfig(integrator=case.get("integrator", SolverConfig.integrator), **STABILIZATION[stabilization])
    results = [run(case["scene"], case.get("worlds", worlds), case["steps"], case["dt"], device, config=config)
               for _ in range(repeats)]
    best = dict(results[-1])
    best["step_ms_median"] = statistics.median(r["step_ms_median"] for r in results)
    best["world_steps_per_s"] = best["num_worlds"] / (best["step_ms_median"] * 1e-3)
    best["stabilization"] = stabilization
    best["repeats"] = repeats
    return best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suite", choices=sorted(SUITES), default="core")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=64, help="worlds per case unless the case sets them")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="folder for <suite>.csv (and .png)")
    parser.add_argument("--plot-csv", default=None, help="only redraw the PNG of a scaling CSV written earlier")
    args = parser.parse_args(argv)
    if args.plot_csv:
        with open(args.plot_csv) as handle:
            rows = [{k: (float(v) if k in ("num_worlds", "world_steps_per_s") else v) for k, v in row.items()}
                    for row in csv.DictReader(handle)]
        _plot_scaling(rows, args.plot_csv.replace(".csv", ".png"))
        return 0
    wp.config.log_level = wp.LOG_WARNING
    rows = []
    for case in SUITES[args.suite]:
        result = run_case(case, args.device, args.worlds, args.repeats)
        print(json.dumps(result), flush=True)
        rows.append(result)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        path = os.path.join(args.out, f"{args.suite}_{args.device.replace(':', '')}.csv")
        with open(path, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=FIELDS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        if args.suite == "scaling":
            _plot_scaling(rows, path.replace(".csv", ".png"))
    return 0


def _plot_scaling(rows, path):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.loglog([r["num_worlds"] for r in rows], [r["world_steps_per_s"] for r in rows], "o-")
    ax.set_xlabel("worlds")
    ax.set_ylabel("world-steps / s")
    ax.set_title(f"{rows[0]['scene']} on {rows[0]['device_name']}")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
