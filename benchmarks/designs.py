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

import numpy as np
import warp as wp

from morphopt.evaluate import evaluate_dynamic
from morphopt.families import load_family


def _tile(tables, size: int):
    """The batch's tables repeated to ``size`` designs (kernel timings at large batch sizes)."""
    import dataclasses

    take = np.arange(size) % tables.count
    per_design = ("ground_xy", "radius", "phase", "branch", "first", "second")
    return dataclasses.replace(tables, **{k: np.ascontiguousarray(getattr(tables, k)[take]) for k in per_design})


def kinematic(device: str, designs: int, samples: int = 360, repeats: int = 15,
              kernel_sizes: list[int] | None = None) -> dict:
    """Jansen legs perturbed by up to 5 %: end-to-end designs/s of evaluate_kinematic (parameter
    dicts in, metrics and failure reasons out; median of ``repeats``), with and without the paths
    in the metrics, and of the kernels alone (solve_tables on a generated batch)."""
    from morphopt.evaluate import _generate_batched, evaluate_kinematic
    from morphopt.linkage.kinematics_warp import solve_tables

    family = load_family("jansen_leg")
    rng = np.random.default_rng(0)
    base = family.space.default()
    params = [{k: v * (1 + 0.05 * rng.uniform(-1, 1)) for k, v in base.items()} for _ in range(designs)]
    evaluate_kinematic(family, params[:64], samples=samples, device=device)  # compile
    out = {"designs": designs, "samples": samples, "repeats": repeats, "threads": os.cpu_count()}
    for name, keep in (("end_to_end", False), ("end_to_end_with_paths", True)):
        seconds = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            evaluation = evaluate_kinematic(family, params, samples=samples, device=device, keep_paths=keep)
            seconds.append(time.perf_counter() - t0)
        out[f"{name}_designs_per_s"] = designs / float(np.median(seconds))
    out["infeasible_fraction"] = float(1.0 - evaluation.feasible.mean())
    (_, tables, points), = _generate_batched(family, params)[0]
    nodes = list(points.values())
    for size in kernel_sizes or [designs]:
        tiled = _tile(tables, size)
        solve_tables(tiled, samples=samples, nodes=nodes, device=device, keep_points=False)  # allocate once
        seconds = []
        for _ in range(repeats):
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            solve_tables(tiled, samples=samples, nodes=nodes, device=device, keep_points=False)
            seconds.append(time.perf_counter() - t0)
        out.setdefault("kernels_designs_per_s", {})[str(size)] = size / float(np.median(seconds))
    return out


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
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--kernel-designs", type=int, nargs="*", default=None,
                        help="batch sizes for the kernel-only timing (default: --designs)")
    parser.add_argument("--only", choices=("kinematic", "walker"), default=None, help="run one of the two parts")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    result = {"device": args.device, "device_name": wp.get_device(args.device).name, "warp": wp.config.version}
    if args.only in (None, "kinematic"):
        result["kinematic_jansen"] = kinematic(args.device, args.designs, repeats=args.repeats,
                                              kernel_sizes=args.kernel_designs)
    if args.only in (None, "walker"):
        result["walker"] = walkers(args.device, args.worlds, args.duration)
    print(json.dumps(result))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, f"designs_{args.device.replace(':', '')}.json"), "w") as handle:
            json.dump(result, handle, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
