"""Free rows' own penalty on (at each --free-rhos value) and off, same run: DR Legs standing and hanging.

    python benchmarks/joint_penalty.py --device cuda --worlds 4096 --assets DIR --out benchmarks/results/h100
    python benchmarks/joint_penalty.py --device cpu --worlds 4 --free-rhos 2e-4 1e-3 --out benchmarks/results/cpu

Tuning.cap_joint_penalty gives the free rows (bilateral joint rows, drive rows inside their
limits) the fixed ADMM penalty Tuning.free_rho (engine.padmm.row_penalty); off, every row
takes the world's rho. For each scene and
setting: median time per step (steps 10 to --steps, CUDA graphs of 10 on a GPU), PADMM iterations
per step, the share of steps that stop at the iteration cap, and the largest joint separation.
Prints one JSON object per row and writes joint_penalty_<device>.json and .csv. Random walkers:
benchmarks/walker_steps.py with --config '{"tuning": {"cap_joint_penalty": false}}'.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import warp as wp  # noqa: E402

from benchmarks.run import clean, engine_run  # noqa: E402
from benchmarks.scenes import dr_legs  # noqa: E402
from engine import SolverConfig, Tuning  # noqa: E402

KEYS = ("step_ms_median", "loop_error_m", "padmm_iterations_mean", "unconverged_step_fraction", "diverged_worlds")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=4)
    parser.add_argument("--steps", type=int, default=70)
    parser.add_argument("--dt", type=float, default=1e-2)
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs")
    parser.add_argument("--free-rhos", type=float, nargs="+", default=[Tuning.free_rho],
                        help="Tuning.free_rho values to run with the penalty on")
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    if args.worlds < 1 or args.steps < 20:
        parser.error("--worlds must be >= 1 and --steps >= 20")
    if min(args.free_rhos) <= 0.0:
        parser.error("--free-rhos must be > 0")
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    device_name = wp.get_device(args.device).name if args.device != "cpu" else "cpu"
    rows = []
    for standing in (True, False):
        scene = dr_legs(standing, args.assets)
        for cap, free_rho in [(True, value) for value in args.free_rhos] + [(False, None)]:
            config = SolverConfig().tuned(cap_joint_penalty=cap, **({} if free_rho is None else {"free_rho": free_rho}))
            result = clean(engine_run(scene.specs, args.worlds, args.dt, args.steps, 10,
                                      config, args.device, np.arange(1), None))
            row = {"scene": "drlegs_standing" if standing else "drlegs_hanging", "cap_joint_penalty": cap,
                   "free_rho": free_rho, "device": device_name, "warp": wp.config.version, "worlds": args.worlds,
                   "steps": args.steps, "dt": args.dt, **{k: result.get(k) for k in KEYS}}
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "joint_penalty_" + ("cuda" if args.device.startswith("cuda") else "cpu")
    (out / f"{name}.json").write_text(json.dumps(rows, indent=1))
    pd.DataFrame(rows).to_csv(out / f"{name}.csv", index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
