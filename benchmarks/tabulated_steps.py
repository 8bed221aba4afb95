"""Time per step of the tabulated path (engine.reduced.tabulated, from MechanismSpecs) against
engine.legged (the walker-specific path it ports) on the same walkers, in one process.

    python benchmarks/tabulated_steps.py --device cuda --worlds 4096 --out DIR

Per scene (random three-leg walkers of the walker family, seeded; the default walker copied),
both paths run a 200-step rollout with the walker study's dt and solver settings, then, on
CUDA, replay a captured graph of 10 steps 20 times (twice, alternating, the faster replay kept).
Prints one JSON object and writes tabulated_steps_<device>.json.
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

from engine import SolverConfig, Tuning  # noqa: E402
from engine.legged import legged_rollout, legged_step_batch, pack_legged  # noqa: E402
from engine.reduced.tabulated import pack_tabulated, rollout_tabulated  # noqa: E402
from morphopt.families import load_family  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def replay_ms(device, step, repeats: int = 20) -> float:
    """Milliseconds per step of a captured graph of 10 steps replayed ``repeats`` times."""
    with wp.ScopedCapture(device=device) as capture:
        step(10)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        wp.capture_launch(capture.graph)
    wp.synchronize_device(device)
    return (time.perf_counter() - t0) / (10 * repeats) * 1e3


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, nargs="+", default=[64])
    parser.add_argument("--dt", type=float, default=2e-3)
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    walker = load_family("walker")
    config = SolverConfig(tuning=Tuning(rho_update_interval=8))
    runs = []
    for worlds in args.worlds:
        rng = np.random.default_rng(0)
        scenes = {"random": [{**p, "legs_per_side": 3} for p in walker.space.sample(rng, worlds)],
                  "default": [walker.space.default()] * worlds}
        for scene, params in scenes.items():
            t0 = time.perf_counter()
            specs = [walker.build_spec(p) for p in params]
            legged_specs = [walker.build_legged(p) for p in params]
            t1 = time.perf_counter()
            tab = pack_tabulated(specs, device=args.device, dt=args.dt, config=config)
            t2 = time.perf_counter()
            leg = pack_legged(legged_specs, device=args.device, dt=args.dt, config=config)
            run = {"worlds": worlds, "scene": scene, "tiled": tab.tiled, "build_s": t1 - t0,
                   "pack_tabulated_s": t2 - t1, "tables": int(tab.links[0].shape[0]),
                   "closure_error_m": tab.closure_error}
            for name, model, rollout, step in (("tabulated", tab, rollout_tabulated, tab.step),
                                               ("legged", leg, legged_rollout,
                                                lambda n, m=leg: legged_step_batch(m, n))):
                t3 = time.perf_counter()
                trace = rollout(model, 200, record_every=10)
                wp.synchronize_device(model.device)
                run[f"{name}_rollout_ms_per_step"] = (time.perf_counter() - t3) / 200 * 1e3
                run[f"{name}_iterations_mean"] = float(trace.iterations[1:].mean())
                run[f"{name}_diverged"] = int(trace.diverged.sum())
                run[f"{name}_torso_x"] = float(np.median(trace.points[-1, :, 0, 0] - trace.points[0, :, 0, 0]))
            if wp.get_device(args.device).is_cuda:
                best = {"tabulated": [], "legged": []}
                for _ in range(2):
                    best["tabulated"].append(replay_ms(tab.device, tab.step))
                    best["legged"].append(replay_ms(leg.device, lambda n: legged_step_batch(leg, n)))
                run.update({f"{k}_replay_ms_per_step": min(v) for k, v in best.items()})
            runs.append(run)
            print(json.dumps(run), flush=True)
    device = wp.get_device(args.device)
    result = {"device": device.name if device.is_cuda else "cpu", "dt": args.dt, "runs": runs}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"tabulated_steps_{'cuda' if device.is_cuda else 'cpu'}.json").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
