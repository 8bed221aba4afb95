"""Where a graph-replayed step spends its time besides its kernels, and what a launch costs in a graph.

    python -m benchmarks.graph_overhead --device cuda [--scenes drlegs_hanging drlegs_standing_newton]
        [--worlds 1 4096] [--launches 40] [--windows 7] [--variant LABEL] [--assets DIR] [--out FILE]

Steps: for each scene of benchmarks.scenes (its default settings, or with --variant those of its
variant or sweep point of that label) and batch size, one batch is packed; the kernels of one
chunk of 10 steps are timed one by one (benchmarks.kernel_times: CUDA events per kernel, launched
back to back) against the same chunk replayed as a CUDA graph (engine.rollout.Stepper, from the
initial state again), timed by CUDA events around each of --windows windows of five chunks: the
graph's ms per step (median and least of the windows), the kernels' ms per step, launches per step
and the time between kernels per launch, (graph - kernels) / launches.

Synthetic graphs, each of --launches launches of a small kernel with a thread per world (the
largest --worlds), replayed and timed the same way (us per launch: a window's time over its
launches), one change at a time:
  plain        one array argument;
  wide         a struct of 24 arrays as its argument, about 1.3 KB of parameters, like the engine's
               kernels (each array an 8-word record);
  shared       every other launch a tiled kernel holding 40 KB of shared memory, so that the
               multiprocessors' split between shared memory and L1 changes between launches;
  conditional  the launches inside wp.capture_while, its body run once per replay (the PADMM loop's
               conditional node);
  empty_loop   plain, followed by a wp.capture_while whose condition is already zero (a loop's cost
               when no world iterates).
On the CPU there are no graphs: the same launches run eagerly and are timed on the host, which
checks the script, not the costs. Prints one JSON line per measurement and writes them to --out.
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

WIDE_FIELDS = 24
SHARED_FLOATS = 10240  # 40 KB of shared memory in the 'shared' variant's tiled kernel
CHUNK = 10  # steps per replayed graph (engine.rollout.Stepper's chunk)
WINDOW_CHUNKS = 5


@wp.struct
class Wide:
    """Twenty-four arrays passed as one argument (the parameter size of the engine's kernels)."""

    a00: wp.array(dtype=float)
    a01: wp.array(dtype=float)
    a02: wp.array(dtype=float)
    a03: wp.array(dtype=float)
    a04: wp.array(dtype=float)
    a05: wp.array(dtype=float)
    a06: wp.array(dtype=float)
    a07: wp.array(dtype=float)
    a08: wp.array(dtype=float)
    a09: wp.array(dtype=float)
    a10: wp.array(dtype=float)
    a11: wp.array(dtype=float)
    a12: wp.array(dtype=float)
    a13: wp.array(dtype=float)
    a14: wp.array(dtype=float)
    a15: wp.array(dtype=float)
    a16: wp.array(dtype=float)
    a17: wp.array(dtype=float)
    a18: wp.array(dtype=float)
    a19: wp.array(dtype=float)
    a20: wp.array(dtype=float)
    a21: wp.array(dtype=float)
    a22: wp.array(dtype=float)
    a23: wp.array(dtype=float)


@wp.kernel(enable_backward=False)
def bump(x: wp.array(dtype=float)):
    """x[i] += 1."""
    i = wp.tid()
    x[i] = x[i] + 1.0


@wp.kernel(enable_backward=False)
def bump_wide(w: Wide):
    """w.a00[i] += w.a23[i] (the other arrays ride along)."""
    i = wp.tid()
    w.a00[i] = w.a00[i] + w.a23[i]


@wp.kernel(enable_backward=False)
def bump_shared(x: wp.array(dtype=float)):
    """A tiled kernel holding SHARED_FLOATS floats of shared memory; x[block] += its first."""
    block, lane = wp.tid()
    t = wp.tile_ones(shape=(SHARED_FLOATS,), dtype=float, storage="shared")
    if lane == 0:
        x[block] = x[block] + t[0]


@wp.kernel(enable_backward=False)
def set_flag(flag: wp.array(dtype=wp.int32), value: int):
    """flag[0] = value."""
    flag[0] = value


def _window_ms(run, device: str, windows: int, per_window: int) -> list[float]:
    """ms of each of ``windows`` windows of ``per_window`` calls of run (CUDA events; host clock
    on the CPU)."""
    cuda = wp.get_device(device).is_cuda
    times = []
    for _ in range(windows):
        if cuda:
            start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
            wp.record_event(start)
            for _ in range(per_window):
                run()
            wp.record_event(end)
            times.append(wp.get_event_elapsed_time(start, end))
        else:
            t0 = time.perf_counter()
            for _ in range(per_window):
                run()
            wp.synchronize_device(device)
            times.append(1e3 * (time.perf_counter() - t0))
    return times


def step_overhead(name: str, specs, worlds: int, dt: float, device: str, windows: int, config=None,
                  variant: str = "default") -> dict:
    """A scene's graph-replayed ms per step against its kernels' (benchmarks.kernel_times), one
    batch packed for both (config: its SolverConfig; variant: the label its row carries)."""
    from benchmarks.kernel_times import kernel_times
    from engine import pack_worlds
    from engine.rollout import Stepper

    cuda = wp.get_device(device).is_cuda
    model = pack_worlds([specs[w % len(specs)] for w in range(worlds)], device=device, dt=dt, config=config)
    kernels = kernel_times(specs, worlds, dt, device, steps=CHUNK, clock="device" if cuda else "host", model=model)
    stepper = Stepper(model, model.state(), model.control(), chunk=CHUNK)  # from the initial state again
    for _ in range(3):  # compile, capture both graphs, settle
        stepper.advance()
    wp.synchronize_device(device)
    per_step = [t / (WINDOW_CHUNKS * CHUNK) for t in _window_ms(stepper.advance, device, windows, WINDOW_CHUNKS)]
    graph = round(float(np.median(per_step)), 4)
    launches = kernels["launches_per_step"]
    return {"kind": "step", "scene": name, "variant": variant, "num_worlds": worlds, "dt": dt,
            "step_kernel": kernels["step_kernel"],
            "graph_ms_per_step": graph, "graph_ms_per_step_least": round(min(per_step), 4),
            "graph_ms_windows": [round(t, 4) for t in per_step],
            "kernels_ms_per_step": kernels["total_ms_per_step"], "launches_per_step": launches,
            "between_kernels_us_per_launch": round(1e3 * (graph - kernels["total_ms_per_step"]) / max(launches, 1), 2)}


def synthetic(variant: str, threads: int, launches: int, device: str, windows: int) -> dict:
    """us per launch of a graph of ``launches`` small launches (module docstring: the variants)."""
    x = wp.zeros(threads, dtype=float, device=device)
    flag = wp.zeros(1, dtype=wp.int32, device=device)
    wide = Wide()
    for k in range(WIDE_FIELDS):
        setattr(wide, f"a{k:02d}", x if k in (0, WIDE_FIELDS - 1) else wp.zeros(1, dtype=float, device=device))

    def plain():
        for _ in range(launches):
            wp.launch(bump, dim=threads, inputs=[x], device=device)

    def body():
        if variant == "wide":
            for _ in range(launches):
                wp.launch(bump_wide, dim=threads, inputs=[wide], device=device)
        elif variant == "shared":
            for k in range(launches):
                if k % 2:
                    wp.launch_tiled(bump_shared, dim=[max(1, threads // 64)], block_dim=64, inputs=[x], device=device)
                else:
                    wp.launch(bump, dim=threads, inputs=[x], device=device)
        elif variant == "conditional":
            wp.launch(set_flag, dim=1, inputs=[flag, 1], device=device)

            def once():
                plain()
                wp.launch(set_flag, dim=1, inputs=[flag, 0], device=device)

            wp.capture_while(flag, once)
        elif variant == "empty_loop":
            plain()
            wp.launch(set_flag, dim=1, inputs=[flag, 0], device=device)
            wp.capture_while(flag, plain)
        else:
            plain()

    run = body
    if wp.get_device(device).is_cuda:
        body()  # compile every kernel outside the capture
        with wp.ScopedCapture(device=device) as capture:
            body()
        graph = capture.graph

        def run():
            wp.capture_launch(graph)
    run()
    wp.synchronize_device(device)
    counted = launches + (2 if variant == "conditional" else 1 if variant == "empty_loop" else 0)
    times = _window_ms(run, device, windows, 1)
    return {"kind": "synthetic", "variant": variant, "threads": threads, "launches": counted,
            "us_per_launch": round(1e3 * float(np.median(times)) / counted, 3),
            "us_per_launch_least": round(1e3 * min(times) / counted, 3)}


VARIANTS = ("plain", "wide", "shared", "conditional", "empty_loop")


def main(argv=None) -> int:
    from benchmarks.kernel_times import declared_scene, scene_arguments, variant_setting
    from benchmarks.run import write_rows
    from benchmarks.scenes import SCENES_DECLARED
    from engine import SolverConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", nargs="*", default=["drlegs_hanging", "drlegs_standing_newton"],
                        choices=sorted(SCENES_DECLARED))
    parser.add_argument("--worlds", type=int, nargs="+", default=[1, 4096])
    parser.add_argument("--launches", type=int, default=40, help="launches of each synthetic graph")
    parser.add_argument("--windows", type=int, default=7, help="timed windows per measurement")
    scene_arguments(parser)
    args = parser.parse_args(argv)
    if min(args.worlds) < 1 or args.launches < 2 or args.windows < 1:
        parser.error("--worlds must be >= 1, --launches >= 2 and --windows >= 1")
    wp.config.log_level = wp.LOG_WARNING
    rows = []
    for name in args.scenes:
        declared, scene = declared_scene(parser, name, args.assets)
        settings, dt_scale = variant_setting(parser, name, declared, args.variant)
        for worlds in args.worlds:
            rows.append(step_overhead(name, scene.specs, worlds, declared.dt * dt_scale, args.device, args.windows,
                                      SolverConfig(**settings), args.variant or "default"))
            print(json.dumps(rows[-1]), flush=True)
    for variant in VARIANTS:
        rows.append(synthetic(variant, max(args.worlds), args.launches, args.device, args.windows))
        print(json.dumps(rows[-1]), flush=True)
    if args.out:
        write_rows(args.out, args.device, "benchmarks.graph_overhead", argv, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
