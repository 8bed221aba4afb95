"""Time per step of reduced-coordinate walkers (engine.legged) against the number of worlds.

    python benchmarks/legged_steps.py --device cuda --worlds 4096 16384 65536 --steps 1000 --out DIR
    [--kernel auto|tiled|thread]

Random three-leg walkers of the walker family (seeded), with the walker study's time step and
solver settings (studies/walker.toml; --dt and --max-iterations override them): a rollout of
--steps steps (records every 10), then, on CUDA, the replay of a captured graph of 10 steps 20
times. Prints one JSON object and writes legged_steps_<device>[_<kernel>].json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

from engine.legged import legged_rollout, legged_step_batch, pack_legged  # noqa: E402
from engine import SolverConfig  # noqa: E402
from morphopt.families import load_family  # noqa: E402
from morphopt.study_spec import load_study_spec  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, nargs="+", default=[64])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--dt", type=float, default=None, help="time step [s] (default: the walker study's)")
    parser.add_argument("--max-iterations", type=int, default=None, help="PADMM cap (default: the walker study's)")
    parser.add_argument("--kernel", choices=["auto", "tiled", "thread"], default="auto",
                        help="one warp per world (tiled), one thread per world, or the model's choice (auto)")
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    walker = load_family("walker")
    study = load_study_spec(ROOT / "studies" / "walker.toml")
    args.dt = args.dt or study.dt
    config = study.solver_config() or SolverConfig()
    if args.max_iterations:
        config = dataclasses.replace(config, max_iterations=args.max_iterations)
    rng = np.random.default_rng(0)
    runs = []
    for worlds in args.worlds:
        params = [{**p, "legs_per_side": 3} for p in walker.space.sample(rng, worlds)]
        t0 = time.perf_counter()
        specs = [walker.build_legged(p) for p in params]
        t1 = time.perf_counter()
        model = pack_legged(specs, device=args.device, dt=args.dt, config=config,
                            tiled={"auto": None, "tiled": True, "thread": False}[args.kernel])
        t2 = time.perf_counter()
        trace = legged_rollout(model, args.steps, record_every=10)
        wp.synchronize_device(model.device)
        t3 = time.perf_counter()
        run = {"worlds": worlds, "tiled": model.tiled, "build_s": t1 - t0, "pack_s": t2 - t1, "rollout_s": t3 - t2,
               "rollout_ms_per_step": (t3 - t2) / args.steps * 1e3,
               "simulated_s_per_s": worlds * args.steps * args.dt / (t3 - t2),
               "iterations_mean": float(trace.iterations[1:].mean()),
               "iterations_max": int(trace.iterations[1:].max()), "diverged": int(trace.diverged.sum())}
        if model.device.is_cuda:
            with wp.ScopedCapture(device=model.device) as capture:
                legged_step_batch(model, 10)
            wp.synchronize_device(model.device)
            t4 = time.perf_counter()
            for _ in range(20):
                wp.capture_launch(capture.graph)
            wp.synchronize_device(model.device)
            step = (time.perf_counter() - t4) / 200
            run.update(replay_ms_per_step=step * 1e3, replay_simulated_s_per_s=worlds * args.dt / step)
        runs.append(run)
        print(json.dumps(run), flush=True)
    report = {"device": wp.get_device(args.device).name if args.device != "cpu" else "cpu", "dt": args.dt,
              "solver": {k: str(v) if hasattr(v, "value") else v for k, v in dataclasses.asdict(config).items()},
              "steps": args.steps, "runs": runs, "warp": wp.config.version}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    suffix = "" if args.kernel == "auto" else f"_{args.kernel}"
    (out / f"legged_steps_{args.device.split(':')[0]}{suffix}.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
