"""Design-evaluation throughput: kinematic Jansen legs and dynamic walkers, designs per second.

    python benchmarks/designs.py --device cuda --designs 65536 --worlds 4096 --duration 1.0 --out DIR

Prints one JSON object (and writes designs_<device>.json under --out).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

from morphopt.evaluate import evaluate_dynamic  # noqa: E402
from morphopt.families import load_family  # noqa: E402
from morphopt.linkage import kinematics_warp, solve_cycles  # noqa: E402


def kinematic(device: str, designs: int, samples: int = 360) -> dict:
    """Jansen legs perturbed by up to 5 %: kernel-only and end-to-end designs/s."""
    family = load_family("jansen_leg")
    rng = np.random.default_rng(0)
    base = family.space.default()
    linkages = [family.generate({k: v * (1 + 0.05 * rng.uniform(-1, 1)) for k, v in base.items()})
                for _ in range(designs)]
    angles = np.tile(2 * np.pi * np.arange(samples) / samples, (designs, 1))
    kinematics_warp.solve_group_warp(linkages[:8], angles[:8], device=device)  # compile
    launch = wp.launch
    kernel_s = []

    def timed(*args, **kwargs):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        launch(*args, **kwargs)
        wp.synchronize_device(device)
        kernel_s.append(time.perf_counter() - t0)

    kinematics_warp.wp.launch = timed
    try:
        t0 = time.perf_counter()
        solutions = solve_cycles(linkages, samples=samples, device=device)
        total = time.perf_counter() - t0
    finally:
        kinematics_warp.wp.launch = launch
    return {"designs": designs, "samples": samples, "kernel_designs_per_s": designs / kernel_s[0],
            "end_to_end_designs_per_s": designs / total,
            "infeasible_fraction": float(np.mean([not s.feasible for s in solutions]))}


def walkers(device: str, worlds: int, duration: float) -> dict:
    """One generation of random walkers (1 to 4 legs per side, both leg families): designs/s and walking speeds."""
    family = load_family("walker")
    rng = np.random.default_rng(1)
    params = family.space.sample(rng, worlds)
    evaluate_dynamic(family, params[:2], duration=0.02, device=device)  # compile
    t0 = time.perf_counter()
    evaluation = evaluate_dynamic(family, params, duration=duration, device=device)
    seconds = time.perf_counter() - t0
    speeds = [m["walking_speed"] for m, f in zip(evaluation.metrics, evaluation.failures) if not f]
    default = evaluate_dynamic(family, [family.space.default()], duration=duration, device=device).metrics[0]
    return {"worlds": worlds, "duration_s": duration, "seconds": seconds, "designs_per_s": worlds / seconds,
            "feasible": len(speeds), "walking_speed_max": max(speeds, default=float("nan")),
            "walking_speed_median": float(np.median(speeds)) if speeds else float("nan"),
            "default_walking_speed": default["walking_speed"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--designs", type=int, default=4096)
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--duration", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    result = {"device": args.device, "device_name": wp.get_device(args.device).name,
              "kinematic_jansen": kinematic(args.device, args.designs),
              "walker": walkers(args.device, args.worlds, args.duration)}
    print(json.dumps(result))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, f"designs_{args.device.replace(':', '')}.json"), "w") as handle:
            json.dump(result, handle, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
