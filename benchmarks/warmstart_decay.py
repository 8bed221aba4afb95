"""DR Legs standing over a long run with and without the warm-start decay (Tuning.warmstart_decay).

    python -m benchmarks.warmstart_decay --device cuda --worlds 4096 --assets DIR [--free-rho 1e-3]

Over-constrained loops leave impulse components that move nothing; a full warm start lets them
grow step after step, and the PADMM iterations grow with them. The throughput benchmark's 70 steps
see only the start of that. Prints one JSON object per decay: median ms per step and mean PADMM
iterations (of the last step of every 10) over steps 10-100 and 100-400, and the largest impulse.
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import warp as wp


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=400, help="a multiple of 10, at least 110")
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs")
    parser.add_argument("--decays", type=float, nargs="+", default=[0.0, 0.05])
    parser.add_argument("--free-rho", type=float, default=None, help="Tuning.free_rho (default: its default)")
    args = parser.parse_args(argv)
    if args.free_rho is not None and args.free_rho <= 0.0:
        parser.error(f"--free-rho must be > 0, got {args.free_rho}")
    if args.steps < 110 or args.steps % 10:
        parser.error(f"--steps: expected a multiple of 10 of at least 110, got {args.steps}")
    wp.config.quiet = True
    from benchmarks.scenes import dr_legs
    from engine import SolverConfig, pack_worlds
    from engine.rollout import Stepper

    spec = dr_legs(True, args.assets).specs[0]
    extra = {} if args.free_rho is None else {"free_rho": args.free_rho}
    for decay in args.decays:
        model = pack_worlds([spec] * args.worlds, device=args.device, dt=1e-2,
                            config=SolverConfig().tuned(warmstart_decay=decay, **extra))
        stepper = Stepper(model, model.state(), model.control(), chunk=10)
        rows = []
        for _ in range(args.steps // 10):
            wp.synchronize_device(args.device)
            start = time.perf_counter()
            stepper.advance()
            wp.synchronize_device(args.device)
            rows.append(((time.perf_counter() - start) / 10 * 1e3, float(model.work.iterations.numpy().mean()),
                         float(np.abs(stepper.state.row_lambda.numpy()).max())))
        r = np.array(rows[1:])  # the first chunk compiles and captures
        print(json.dumps({
            "scene": "drlegs_standing", "device": wp.get_device(args.device).name, "worlds": args.worlds,
            "warmstart_decay": decay, "free_rho": model.config.tuning.free_rho,
            "ms_per_step_steps_10_100": float(np.median(r[:9, 0])),
            "ms_per_step_steps_100_end": float(np.median(r[9:, 0])), "iterations_steps_10_100": float(r[:9, 1].mean()),
            "iterations_steps_100_end": float(r[9:, 1].mean()), "impulse_max": float(r[:, 2].max()),
            "diverged_worlds": int(model.work.diverged.numpy().sum())}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
