"""The fused step's options switched on and off in one run.

    python -m benchmarks.step_variants --device cuda [--worlds 4096 16384] [--scenes fourbar sixbar]
        [--variants default split_off ...] [--repeats 2] [--assets DIR] [--out FILE]

Scenes of engine.scenes (dt 1 ms) under named variants of the fused step: "default" (everything
as pack_worlds chooses it), "split_off" (the lanes take a whole joint's rows each instead of one
part of a joint each, engine.fused.SHARE_JOINT_PARTS), "groups_off" (one lane sums a body's rows
instead of a group of lanes, SHARE_BODY_SUMS), "sharing_off" (neither), "inverse_off"
(substitutions with the Cholesky factor instead of products with G = L^-1,
engine.fused.fused_inverse), "skip_off" (no skip of projection iterations whose joint error is at
float32 rounding, Tuning.projection_skip_floor 0) and "before" (the solves, the skip and the
sharing off). The variants are interleaved and repeated; each timing is the median ms per step over
6 chunks of 10 steps replayed as CUDA graphs (engine.rollout.Stepper) after a compile and a
capture chunk, and the first repeat's rows also have the fused step's median cycles per world-step
and per stage (engine.fused.fused_profile, GPU only). With --assets: DR Legs hanging (sparse staged
step, dt 10 ms, 4096 worlds) at skip floors 0, 1e-7 and 1e-6. Prints one JSON line per measurement
and writes them all, with the device, the versions and the command, to --out.
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import warp as wp


VARIANTS = {  # (solve through L^-1 where fused_inverse allows it, projection skip floor on, the lanes' sharing
    # flags: None as fused_sharing chooses, else engine.fused.SHARE_* bits)
    "default": (True, True, None),
    "split_off": (True, True, 2),  # SHARE_BODY_SUMS only
    "groups_off": (True, True, 1),  # SHARE_JOINT_PARTS only
    "sharing_off": (True, True, 0),
    "inverse_off": (False, True, None),
    "skip_off": (True, False, None),
    "before": (False, False, 0),
}


def timed(specs, worlds: int, dt: float, config, device: str, chunks: int = 6,
          chunk: int = 10, sharing: int | None = None, profile: bool = False) -> dict:
    """Median ms per step of ``worlds`` copies of ``specs`` (cycled), whether the fused step solved
    through L^-1, how its lanes shared joints and bodies (engine.fused.SHARE_* flags as used), and
    (``profile``, fused steps) its cycles per stage."""
    from engine import pack_worlds
    from engine.fused import fused_inverse, fused_profile, sharing_used
    from engine.rollout import Stepper

    model = pack_worlds([specs[w % len(specs)] for w in range(worlds)], device=device, dt=dt,
                        config=config.tuned(fused_sharing=sharing))
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
    fused = model.step_kernel == "fused"
    out = {"step_ms": float(np.median(times) * 1e3),
           "inverse": bool(fused and fused_inverse(model.device, model.max_rows)),
           "sharing": sharing_used(model) if fused else 0}
    if profile and fused:
        out["fused_stage_cycles"] = fused_profile(model, stepper.state, model.control(), steps=5)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--scenes", nargs="+", default=["fourbar"], help="engine.scenes names")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs (adds DR Legs hanging)")
    parser.add_argument("--out", default=None, help="JSON file for all measurements")
    args = parser.parse_args(argv)
    if min(args.worlds) < 1 or args.repeats < 1:
        parser.error("--worlds and --repeats must be >= 1")
    wp.config.log_level = wp.LOG_WARNING
    import engine.fused as fused
    from engine import SolverConfig, Tuning
    from engine.scenes import SCENES, make_scene

    unknown = [name for name in args.scenes if name not in SCENES]
    if unknown:
        parser.error(f"--scenes: unknown {unknown}; engine.scenes has {sorted(SCENES)}")
    skip_on = Tuning.projection_skip_floor
    skip_on_angular = Tuning.projection_skip_floor_angular
    rows = []

    def record(**row):
        rows.append(row)
        print(json.dumps(row), flush=True)

    default_rows = fused.INVERSE_MAX_ROWS
    try:
        for repeat in range(args.repeats):
            for name in args.scenes:
                specs = [make_scene(name).spec]
                for variant in args.variants:
                    inverse, skip, sharing = VARIANTS[variant]
                    fused.INVERSE_MAX_ROWS = default_rows if inverse else 0  # fused_inverse reads it at each step
                    config = SolverConfig(tuning=Tuning(projection_skip_floor=skip_on if skip else 0.0,
                                                        projection_skip_floor_angular=skip_on_angular if skip else 0.0))
                    for worlds in args.worlds:
                        result = timed(specs, worlds, 1e-3, config, args.device, sharing=sharing,
                                       profile=repeat == 0)
                        record(scene=name, num_worlds=worlds, dt=1e-3, variant=variant,
                               projection_skip_floor=config.tuning.projection_skip_floor,
                               projection_skip_floor_angular=config.tuning.projection_skip_floor_angular, repeat=repeat,
                               **result)
    finally:
        fused.INVERSE_MAX_ROWS = default_rows
    if args.assets:
        from benchmarks.scenes import dr_legs

        legs = dr_legs(False, args.assets).specs
        for repeat in range(args.repeats):
            for skip in (0.0, skip_on, 1e-6):
                angular = skip_on_angular if skip > 0.0 else 0.0  # 0: the skip off for both kinds of error
                config = SolverConfig(tuning=Tuning(projection_skip_floor=skip, projection_skip_floor_angular=angular))
                result = timed(legs, 4096, 1e-2, config, args.device, chunks=4)
                record(scene="drlegs_hanging", num_worlds=4096, dt=1e-2, projection_skip_floor=skip, repeat=repeat,
                       step_ms=result["step_ms"])
    if args.out:
        from benchmarks.run import write_rows

        write_rows(args.out, args.device, "benchmarks.step_variants", argv, rows, key="measurements")
    return 0


if __name__ == "__main__":
    sys.exit(main())
