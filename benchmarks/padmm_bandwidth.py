"""PADMM iteration against the memory-bandwidth floor: how close the iteration phase comes to the
time it would take just to move its data once.

    python benchmarks/padmm_bandwidth.py --device cuda --scene walker drlegs_standing --out benchmarks/results/h100
    python benchmarks/padmm_bandwidth.py --device cpu --scene fourbar --worlds 64

For each scene a batch of --worlds worlds runs the staged step (the fused step runs the whole
loop inside one kernel): --warmup eager steps, then --steps more with every kernel timed
(wp.timing on a GPU, synchronized wall time per launch on the CPU). The launches of the PADMM loop
are those after a step's padmm_start and the first factor (the solves, padmm_update and the new
factors it asks for) up to its apply_impulses or store_contacts. The bytes of an iteration are the
sizes of every array the kernels of one iteration take (recorded by wrapping wp.launch for one
call of engine.padmm.padmm_iteration), each counted once per kernel: a floor, as an array read
twice counts once; the schedule arrays shared by all worlds count too. The bandwidth is measured
in the same run with a device-to-device copy of 1 GiB (CPU: 256 MiB). Reported per scene: bytes
per iteration, time per iteration (the loop's kernel time / its trips), the floor (bytes /
bandwidth) and the fraction reached (floor / time). Prints one JSON object per scene and
writes padmm_bandwidth_<device>.csv.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import pathlib
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import pandas as pd
import warp as wp

from benchmarks.scenes import SCENES_DECLARED
from engine import SolverConfig, pack_worlds
from engine import padmm as padmm_module
from engine.step import step


def measure_bandwidth(device: str, nbytes: int, repeats: int = 5) -> float:
    """Device memory bandwidth [bytes/s]: a copy of nbytes reads and writes 2 nbytes (median)."""
    n = nbytes // 16
    src = wp.ones(n, dtype=wp.vec4, device=device)
    dst = wp.zeros(n, dtype=wp.vec4, device=device)
    wp.copy(dst, src)
    times = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        wp.copy(dst, src)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return 2.0 * n * 16 / float(np.median(times))


def _indexed_fields(kernel) -> set[str]:
    """Names indexed as ``.name[`` in the source of the kernel's module and the engine's modules it
    calls into: a struct field counts only if some kernel code reads or writes it."""
    import inspect
    import re

    texts = [inspect.getsource(inspect.getmodule(kernel.func))]
    texts += [inspect.getsource(module) for module in (padmm_module, sys.modules["engine.linalg.dense"],
                                                        sys.modules["engine.linalg.sparse"])]
    return set(re.findall(r"\.(\w+)\[", "\n".join(texts)))


def _array_bytes(value, seen: set, fields: set | None = None) -> int:
    """Bytes of the arrays in a launch argument, each once; of a struct, the array fields in
    ``fields`` (those the kernels index)."""
    if isinstance(value, wp.array):
        if id(value) in seen:
            return 0
        seen.add(id(value))
        return int(value.size * wp.types.type_size_in_bytes(value.dtype))
    if hasattr(getattr(value, "_cls", None), "vars"):  # a wp.struct instance
        return sum(_array_bytes(getattr(value, name), seen) for name in value._cls.vars
                   if fields is None or name in fields)
    return 0


@contextlib.contextmanager
def observed_launches(observe):
    """Call observe(kernel, args, kwargs, seconds) after every wp.launch / wp.launch_tiled (the
    engine's modules call them through ``wp``, so swapping the attributes reaches every launch)."""
    originals = wp.launch, wp.launch_tiled

    def wrap(original):
        def run(kernel, *args, **kwargs):
            t0 = time.perf_counter()
            out = original(kernel, *args, **kwargs)
            observe(kernel, args, kwargs, time.perf_counter() - t0)
            return out
        return run

    wp.launch, wp.launch_tiled = (wrap(f) for f in originals)
    try:
        yield
    finally:
        wp.launch, wp.launch_tiled = originals


def launch_bytes(kernel, args, kwargs) -> int:
    """Bytes of the arrays a launch takes (positional after dim, inputs, outputs), each once."""
    arrays = list(args[1:]) + list(kwargs.get("inputs") or []) + list(kwargs.get("outputs") or [])
    seen: set = set()
    fields = _indexed_fields(kernel)
    return sum(_array_bytes(a, seen, fields) for a in arrays)


def timed_launches(device: str, model, state_a, state_b, steps: int) -> list[tuple[str, float]]:
    """(kernel name, seconds) of every launch of ``steps`` steps, in launch order (GPU: kernel
    times from wp.timing; CPU: wall time per launch, a launch runs synchronously there)."""
    cuda = wp.get_device(device).is_cuda
    records = []
    if cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    with contextlib.nullcontext() if cuda else observed_launches(
            lambda kernel, args, kwargs, seconds: records.append((kernel.key, seconds))):
        for _ in range(steps):
            step(model, state_a, state_b, model.control())
            state_a, state_b = state_b, state_a
    if cuda:
        records = [(r.name.replace("forward kernel ", ""), 1e-3 * r.elapsed) for r in wp.timing_end()]
    return records


# launched between padmm_start and the loop's first solve: sparse.prepare's row map and matrix, the first factor
_BEFORE_LOOP = ("map_joint_rows", "map_contact_rows", "sparse_matrix", "staged_matrix", "sparse_factor",
                "cholesky_factor")


def loop_launches(records: list[tuple[str, float]]) -> list[tuple[str, float]]:
    """The launches inside the PADMM loops: after each step's padmm_start and the launches before
    its first solve (_BEFORE_LOOP), up to its apply_impulses or store_contacts (the factor and
    solve kernels also run before the loop and in the projection)."""
    state, loop = "outside", []
    for name, seconds in records:
        if name.startswith("padmm_start"):
            state = "before"
            continue
        if state == "before" and not name.startswith(_BEFORE_LOOP):
            state = "inside"
        if state == "inside" and name.startswith(("apply_impulses", "store_contacts")):
            state = "outside"
        if state == "inside":
            loop.append((name, seconds))
    return loop


def run_scene(name: str, device: str, worlds: int, warmup: int, steps: int, bandwidth: float, config: dict,
              assets: str | None = None) -> dict:
    declared = SCENES_DECLARED[name]
    specs = declared.build(assets).specs
    batch = [specs[w % len(specs)] for w in range(worlds)]
    # the staged step: the fused step runs the loop inside one kernel, with nothing to time apart
    staged = {**config, "tuning": {"step_kernel": "staged", **config.get("tuning", {})}}
    model = pack_worlds(batch, device=device, dt=declared.dt, config=SolverConfig(**staged))
    state_a, state_b = model.state(), model.state()
    for _ in range(warmup):
        step(model, state_a, state_b, model.control())
        state_a, state_b = state_b, state_a
    wp.synchronize_device(device)
    records: list = []
    with observed_launches(lambda kernel, args, kwargs, _: records.append(launch_bytes(kernel, args, kwargs))):
        # one iteration of every world (after a step: its data in place)
        padmm_module.padmm_iteration(model, state_a.row_lambda)
    wp.synchronize_device(device)
    iteration_bytes = sum(records)
    loop = loop_launches(timed_launches(device, model, state_a, state_b, steps))
    trips = sum(1 for name, _ in loop if name.startswith("padmm_update"))
    if trips == 0:
        raise RuntimeError(f"{name}: no PADMM iteration was launched in {steps} steps")
    per_kernel = collections.defaultdict(float)
    for kernel, seconds in loop:
        per_kernel[kernel] += seconds
    per_iteration = sum(per_kernel.values()) / trips
    floor = iteration_bytes / bandwidth
    return {
        "scene": name, "device": wp.get_device(device).name if wp.get_device(device).is_cuda else "cpu",
        "warp": wp.config.version, "worlds": model.num_worlds, "rows": model.max_rows,
        "linear_solver": model.linear_solver, "loop_trips_per_step": trips / steps,
        "bytes_per_iteration": int(iteration_bytes), "bandwidth_GBps": bandwidth / 1e9,
        "iteration_ms": 1e3 * per_iteration, "floor_ms": 1e3 * floor, "fraction_of_bandwidth": floor / per_iteration,
        "loop_kernels_ms_per_step": {k: round(1e3 * v / steps, 4) for k, v in sorted(per_kernel.items())},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scene", nargs="+", default=["walker"], choices=sorted(SCENES_DECLARED))
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--config", default="{}",
                        help='SolverConfig keywords as JSON, its knobs under "tuning" (engine.Tuning)')
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs (DR Legs scenes)")
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    try:
        config = json.loads(args.config)
        SolverConfig(**config)
    except (ValueError, TypeError) as exc:
        parser.error(f"--config: {exc}")
    cuda = wp.get_device(args.device).is_cuda
    bandwidth = measure_bandwidth(args.device, (1 << 30) if cuda else (1 << 28))
    rows = []
    for name in args.scene:
        result = run_scene(name, args.device, args.worlds, args.warmup, args.steps, bandwidth, config, args.assets)
        print(json.dumps(result), flush=True)
        rows.append({k: v for k, v in result.items() if not isinstance(v, dict)})
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows).to_csv(out / f"padmm_bandwidth_{'cuda' if cuda else 'cpu'}.csv", index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
