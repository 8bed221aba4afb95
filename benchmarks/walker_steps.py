"""Walker steps: time per step of a batch of random walkers, per stage and per kernel.

    python benchmarks/walker_steps.py --device cuda --worlds 4096 --out benchmarks/results/h200
    python benchmarks/walker_steps.py --device cpu --worlds 16 --out benchmarks/results/cpu
    python benchmarks/walker_steps.py --device cuda --config '{"max_iterations": 50}' --label cap50

Random designs of the walker family (both leg families, --legs-per-side legs per side, as in
studies/walker.toml) in one heterogeneous batch, standing on the ground with their cranks driven.
After --warmup steps (kernels compiled, the walkers settled on their feet), --steps steps run in
CUDA graphs of 10 steps (engine.rollout.Stepper, as studies run them) and are timed; then a few
eager steps report the time of every stage (synchronized) and, on a GPU, of every kernel. Prints
one JSON object and writes walker_steps_<device>[_<label>].json.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

from engine import SolverConfig, pack_worlds  # noqa: E402
from engine.rollout import Stepper  # noqa: E402
from engine.step import StageTimer, step  # noqa: E402
from morphopt.families import load_family  # noqa: E402


def walkers(count: int, legs_per_side: int, seed: int) -> list:
    """Mechanism specs of ``count`` random walkers (designs that cannot be built are skipped)."""
    family = load_family("walker")
    specs = []
    for params in family.space.sample(np.random.default_rng(seed), count):
        try:
            specs.append(family.build_spec(family.space.validate({**params, "legs_per_side": legs_per_side})))
        except ValueError:
            continue
    return specs


def run(device: str, worlds: int, legs_per_side: int, dt: float, warmup: int, steps: int, config: dict,
        seed: int = 1) -> dict:
    specs = walkers(worlds, legs_per_side, seed)
    t0 = time.perf_counter()
    model = pack_worlds(specs, device=device, dt=dt, config=SolverConfig(**config))
    pack_seconds = time.perf_counter() - t0
    chunk = 10
    stepper = Stepper(model, model.state(), model.control(), chunk=chunk)
    t0 = time.perf_counter()
    for _ in range(max(1, warmup // chunk)):
        stepper.advance()
    wp.synchronize_device(device)
    warmup_seconds = time.perf_counter() - t0
    chunk_seconds = []
    for _ in range(max(1, steps // chunk)):
        t0 = time.perf_counter()
        stepper.advance()
        wp.synchronize_device(device)
        chunk_seconds.append(time.perf_counter() - t0)
    per_step = float(np.median(chunk_seconds)) / chunk
    iterations = stepper.iteration_sum.numpy() / max(stepper.steps_done, 1)
    # a few eager steps: stages, PADMM iteration counts, kernels
    state_a, state_b = stepper.state, model.state()
    timer = StageTimer(device)
    padmm, capped = [], []
    for _ in range(3):
        step(model, state_a, state_b, model.control(), timer=timer)
        state_a, state_b = state_b, state_a
        its = model.work.iterations.numpy()
        padmm.append(its.mean())
        capped.append(float(np.mean(its >= model.config.max_iterations)))
    kernels = {}
    if wp.get_device(device).is_cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        for _ in range(2):
            step(model, state_a, state_b, model.control())
            state_a, state_b = state_b, state_a
        totals = collections.defaultdict(float)
        for record in wp.timing_end():
            totals[record.name.replace("forward kernel ", "")] += record.elapsed / 2.0
        kernels = dict(sorted(((k, round(v, 4)) for k, v in totals.items()), key=lambda kv: -kv[1])[:12])
    body_q = state_a.body_q.numpy()
    return {
        "device": wp.get_device(device).name if device != "cpu" else "cpu", "warp": wp.config.version,
        "worlds": model.num_worlds, "legs_per_side": legs_per_side, "rows": model.max_rows,
        "bodies": model.max_bodies, "linear_solver": model.linear_solver, "dt": dt, "config": config,
        "ms_per_step": 1e3 * per_step, "world_steps_per_s": model.num_worlds / per_step,
        "simulated_s_per_s": model.num_worlds * dt / per_step, "pack_s": pack_seconds,
        "warmup_steps": stepper.steps_done - len(chunk_seconds) * chunk, "warmup_s": warmup_seconds,
        "padmm_iterations_mean": float(np.mean(padmm)), "padmm_capped_share": float(np.mean(capped)),
        "padmm_iterations_mean_timed": float(iterations.mean()),
        "stage_ms": {k: round(v, 3) for k, v in timer.milliseconds_per_step().items()},
        "kernel_ms_per_step": kernels, "nan_worlds": int((~np.isfinite(body_q.reshape(model.num_worlds, -1))).any(1).sum()),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--legs-per-side", type=int, default=3)
    parser.add_argument("--dt", type=float, default=0.002)
    parser.add_argument("--warmup", type=int, default=30, help="steps before timing (rounded to 10)")
    parser.add_argument("--steps", type=int, default=30, help="timed steps (rounded to 10)")
    parser.add_argument("--config", default="{}",
                        help='SolverConfig keywords as JSON, its knobs under "tuning" (engine.Tuning)')
    parser.add_argument("--label", default="")
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    try:
        config = json.loads(args.config)
        SolverConfig(**config)
    except (ValueError, TypeError) as exc:
        parser.error(f"--config: {exc}")
    result = run(args.device, args.worlds, args.legs_per_side, args.dt, args.warmup, args.steps, config)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "walker_steps_" + ("cuda" if args.device.startswith("cuda") else "cpu") + (f"_{args.label}" if args.label else "")
    (out / f"{name}.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
