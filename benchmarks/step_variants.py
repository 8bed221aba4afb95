"""The fused step's solve form and the projection's rounding skip, switched on and off in one run.

    python -m benchmarks.step_variants --device cuda [--worlds 4096 16384] [--repeats 2] [--assets DIR]
        [--out FILE]

Four-bar (engine.scenes, dt 1 ms): every combination of the fused step's solves through G = L^-1
(engine.fused.fused_inverse; off: substitutions with the Cholesky factor) and of the projection's
skip of iterations whose joint error is at float32 rounding (SolverConfig.projection_skip_floor 1e-7;
off: 0), at each batch size, the combinations interleaved and repeated. With --assets: DR Legs
hanging (sparse staged step, dt 10 ms, 4096 worlds) at skip floors 0, 1e-7 and 1e-6. Each timing
is the median ms per step over 6 chunks of 10 steps replayed as CUDA graphs (engine.rollout.Stepper)
after a compile and a capture chunk. Prints one JSON line per measurement and writes them all, with
the device, the versions and the command, to --out.
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import warp as wp


def timed(specs, worlds: int, dt: float, config, device: str, chunks: int = 6,
          chunk: int = 10) -> tuple[float, bool]:
    """Median ms per step of ``worlds`` copies of ``specs`` (cycled), and whether the fused step
    solved through L^-1."""
    from engine import pack_worlds
    from engine.fused import fused_inverse
    from engine.rollout import Stepper

    model = pack_worlds([specs[w % len(specs)] for w in range(worlds)], device=device, dt=dt, config=config)
    stepper = Stepper(model, model.state(), model.control(), chunk=chunk)
    stepper.advance()  # compiles
    stepper.advance()  # captures the graph (CUDA)
    times = []
    for _ in range(chunks):
        wp.synchronize_device(model.device)
        t0 = time.perf_counter()
        stepper.advance()
        wp.synchronize_device(model.device)
        times.append((time.perf_counter() - t0) / chunk)
    inverse = model.step_kernel == "fused" and fused_inverse(model.device, model.max_rows)
    return float(np.median(times) * 1e3), bool(inverse)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs (adds DR Legs hanging)")
    parser.add_argument("--out", default=None, help="JSON file for all measurements")
    args = parser.parse_args(argv)
    if min(args.worlds) < 1 or args.repeats < 1:
        parser.error("--worlds and --repeats must be >= 1")
    wp.config.log_level = wp.LOG_WARNING
    import engine.fused as fused
    from engine import SolverConfig
    from engine.scenes import make_scene

    skip_on = SolverConfig().projection_skip_floor
    rows = []

    def record(**row):
        rows.append(row)
        print(json.dumps(row), flush=True)

    fourbar = [make_scene("fourbar").spec]
    default_rows = fused.INVERSE_MAX_ROWS
    try:
        for repeat in range(args.repeats):
            for allow in (True, False):  # the CPU never solves through L^-1 (engine.fused.fused_inverse)
                fused.INVERSE_MAX_ROWS = default_rows if allow else 0  # fused_inverse reads it at each step
                for skip in (skip_on, 0.0):
                    for worlds in args.worlds:
                        config = SolverConfig(projection_skip_floor=skip)
                        ms, inverse = timed(fourbar, worlds, 1e-3, config, args.device)
                        record(scene="fourbar", num_worlds=worlds, dt=1e-3, inverse=inverse,
                               projection_skip_floor=skip, repeat=repeat, step_ms=ms)
    finally:
        fused.INVERSE_MAX_ROWS = default_rows
    if args.assets:
        from benchmarks.scenes import dr_legs

        legs = dr_legs(False, args.assets).specs
        for repeat in range(args.repeats):
            for skip in (0.0, skip_on, 1e-6):
                ms, _ = timed(legs, 4096, 1e-2, SolverConfig(projection_skip_floor=skip), args.device, chunks=4)
                record(scene="drlegs_hanging", num_worlds=4096, dt=1e-2, projection_skip_floor=skip, repeat=repeat,
                       step_ms=ms)
    if args.out:
        device = wp.get_device(args.device)
        result = {"device": str(device), "device_name": device.name, "versions": {"warp": wp.config.version},
                  "command": "python -m benchmarks.step_variants "
                             + " ".join(argv if argv is not None else sys.argv[1:]),
                  "measurements": rows}
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
