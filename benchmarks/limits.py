"""Where float32 PADMM stops resolving a mechanism, and whether engine.health flags it there.

    python benchmarks/limits.py --device cpu --out benchmarks/results/cpu

Two sweeps, 1 s at dt 1 ms each, every case a world of one batch (each world's PADMM stops on its
own, so the batch changes no world's motion):
- mass ratio: engine.scenes' 10-link chain hanging from a pivot, its links alternating between line
  densities 1 and the ratio (1 to 1e8), under the default SolverConfig and under tight tolerances
  (1e-8 absolute and relative, cap 200, one penalty for all rows: benchmarks.stress S5's settings);
- distance from the origin: engine.scenes' passive four-bar moved along x (0, then 1 m to 1e6 m),
  default SolverConfig; the float32 spacing at that distance beside it.
Per case: the largest joint error over the records (every 10 steps) [m], the PADMM iterations per
step (mean, max), the largest residual an unconverged step stopped at, and engine.health's flags and
reason. Prints one JSON object per case; writes limits_<device>.csv and .png.
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

RATIOS = (1.0, 10.0, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8)
DISTANCES = (0.0, 1.0, 10.0, 1e2, 1e3, 1e4, 3e4, 6e4, 7e4, 1e5, 1e6)


def sweep(specs, labels: list[dict], config, device: str, duration: float, dt: float) -> list[dict]:
    """Roll the worlds out together; one row per world."""
    from engine import pack_worlds, rollout

    model = pack_worlds(specs, device=device, dt=dt, config=config)
    start = time.perf_counter()
    trace, _ = rollout(model, model.state(), model.control(), round(duration / dt), record_every=10)
    wall = time.perf_counter() - start
    health = trace.health
    rows = []
    for w, label in enumerate(labels):
        rows.append({**label, "joint_error_max_m": float(np.nanmax(trace.violation_linear[:, w])),
                     "iterations_mean": float(trace.iterations[1:, w].mean()),
                     "iterations_max": int(trace.iterations[1:, w].max()),
                     "unconverged_residual_max": float(health.residual_max[w]),
                     "flags": int(health.flags[w]), "flagged": bool(health.flags[w] != 0),
                     "reason": health.reason(w), "batch_wall_s": wall})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--duration", type=float, default=1.0)
    parser.add_argument("--dt", type=float, default=1e-3)
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.quiet = True
    from engine import SolverConfig, Tuning
    from engine.scenes import chain, fourbar, shifted

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    configs = {"default": SolverConfig(),
               "tight": SolverConfig(tolerance=1e-8, relative_tolerance=1e-8, max_iterations=200,
                                     tuning=Tuning(cap_joint_penalty=False))}
    rows = []
    for name, config in configs.items():
        specs = [chain(10, densities=[r if k % 2 else 1.0 for k in range(10)]).spec for r in RATIOS]
        labels = [{"sweep": "mass_ratio", "config": name, "mass_ratio": r, "distance_m": 0.0} for r in RATIOS]
        rows += sweep(specs, labels, config, args.device, args.duration, args.dt)
    base = fourbar().spec
    labels = [{"sweep": "distance", "config": "default", "mass_ratio": 1.0, "distance_m": d,
               "float32_spacing_m": float(np.spacing(np.float32(d + 0.3)))} for d in DISTANCES]
    rows += sweep([shifted(base, d) for d in DISTANCES], labels, configs["default"], args.device, args.duration,
                  args.dt)
    for row in rows:
        print(json.dumps({"device": wp.get_device(args.device).name, **row}), flush=True)

    import pandas as pd

    stem = out / f"limits_{args.device.split(':')[0]}"
    pd.DataFrame(rows).to_csv(stem.with_suffix(".csv"), index=False)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tolerance = configs["default"].health_joint_tolerance
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, marker in (("default", "o"), ("tight", "s")):
        part = [r for r in rows if r["sweep"] == "mass_ratio" and r["config"] == name]
        x = [r["mass_ratio"] for r in part]
        y = [max(r["joint_error_max_m"], 1e-9) for r in part]
        left.loglog(x, y, marker=marker, label=f"{name} tolerances")
        left.scatter([a for a, r in zip(x, part) if r["flagged"]], [b for b, r in zip(y, part) if r["flagged"]],
                     s=120, facecolors="none", edgecolors="red")
    left.axhline(tolerance, color="grey", ls="--", label="health_joint_tolerance")
    left.set(xlabel="mass ratio of neighbouring links", ylabel="largest joint error in 1 s [m]",
             title="10-link chain (red rings: flagged)")
    left.legend(fontsize=8)
    part = [r for r in rows if r["sweep"] == "distance" and r["distance_m"] > 0.0]
    x = [r["distance_m"] for r in part]
    right.loglog(x, [max(r["joint_error_max_m"], 1e-9) for r in part], marker="o", label="largest joint error")
    right.loglog(x, [r["float32_spacing_m"] for r in part], ls=":", label="float32 spacing")
    right.scatter([a for a, r in zip(x, part) if r["flagged"]],
                  [max(r["joint_error_max_m"], 1e-9) for r in part if r["flagged"]], s=120, facecolors="none",
                  edgecolors="red")
    right.axhline(tolerance, color="grey", ls="--", label="health_joint_tolerance")
    right.set(xlabel="distance from the origin [m]", ylabel="[m]", title="four-bar (red rings: flagged)")
    right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(stem.with_suffix(".png"), dpi=110)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
