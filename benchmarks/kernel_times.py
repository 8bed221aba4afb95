"""Where a staged step spends its time: every kernel launch of a few eager steps, timed on its own.

    python -m benchmarks.kernel_times --device cuda --scenes drlegs_hanging drlegs_standing --worlds 4096 --assets DIR
        [--steps 10] [--clock host|device] [--variant LABEL] [--out FILE]

Scenes of benchmarks.scenes (their dt), with their default settings or, with ``--variant``, those of
the variant or sweep point of that label (its settings and step). After two graph chunks of 10 steps
(compile, capture, the scene settled a little), ``--steps`` eager steps run as one chunk (only the
last projects its output). With ``--clock host`` the device is synchronized before and after every
launch and each launch's host wall time is added to its kernel's total: per kernel, ms per step and
launches per step. Those times include a launch's overhead (about 25 us each on an H100 with warp
1.19), so a kernel that does little shows that floor; what counts is the difference between kernels,
and between versions measured the same way. With ``--clock device`` (CUDA) the launches run back to
back and each kernel's own time comes from CUDA events (wp.timing_begin), without that floor; the
row also lists every launch's time (launch_ms), and counts the launches Warp makes itself (array
copies and fills), which the host clock does not see. Batches the fused step takes are one launch
per step (see engine.testspeed's fused_stage_cycles instead). Prints one JSON line per scene and
writes them to --out.
"""

import argparse
import collections
import json
import os
import re
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import warp as wp


def kernel_times(specs, worlds: int, dt: float, device: str, steps: int = 5, clock: str = "host", *,
                 config=None, model=None) -> dict:
    """Per kernel: [ms per step, launches per step], sorted by time, and the model's step kernel.

    clock "host": each launch synchronized and timed on the host (its overhead included); "device"
    (CUDA only): the launches run back to back as in a chunk and each kernel's own run time is read
    from CUDA events (wp.timing_begin). Either way the steps are one chunk's: only the last
    projects its output. config: the batch's SolverConfig (default settings when None); model: a
    batch already packed from specs (then specs, worlds, dt, device and config are its own)."""
    from engine import pack_worlds, step
    from engine.rollout import Stepper

    if model is None:
        model = pack_worlds([specs[w % len(specs)] for w in range(worlds)], device=device, dt=dt, config=config)
    stepper = Stepper(model, model.state(), model.control(), chunk=10)
    stepper.advance()
    stepper.advance()
    seconds = collections.defaultdict(float)
    launches = collections.Counter()
    launch, launch_tiled = wp.launch, wp.launch_tiled

    def timed(original):
        def run(kernel, *args, **kwargs):
            wp.synchronize_device(model.device)
            t0 = time.perf_counter()
            result = original(kernel, *args, **kwargs)
            wp.synchronize_device(model.device)
            name = getattr(kernel, "key", str(kernel))
            seconds[name] += time.perf_counter() - t0
            launches[name] += 1
            return result
        return run

    state, other, control = stepper.state, model.state(), model.control()
    each = collections.defaultdict(list)  # device clock: every launch's own time [ms], in launch order
    if clock == "device":
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        for k in range(steps):
            step(model, state, other, control, project_output=k == steps - 1)
            state, other = other, state
        for result in wp.timing_end():
            # CUDA's record: "forward kernel <key>", the key of a kernel of its own module ending in its hash
            name = re.sub(r"_[0-9a-f]{8}$", "", result.name.removeprefix("forward kernel "))
            seconds[name] += 1e-3 * result.elapsed
            launches[name] += 1
            each[name].append(round(result.elapsed, 4))
    else:
        wp.launch, wp.launch_tiled = timed(launch), timed(launch_tiled)
        try:
            for k in range(steps):
                step(model, state, other, control, project_output=k == steps - 1)
                state, other = other, state
        finally:
            wp.launch, wp.launch_tiled = launch, launch_tiled
    per_kernel = {name: [round(1e3 * t / steps, 4), launches[name] / steps]
                  for name, t in sorted(seconds.items(), key=lambda kv: -kv[1])}
    return {"clock": clock, "step_kernel": model.step_kernel, "linear_solver": model.linear_solver,
            "total_ms_per_step": round(1e3 * sum(seconds.values()) / steps, 4),
            "launches_per_step": sum(launches.values()) / steps, "kernels": per_kernel,
            **({"launch_ms": dict(each)} if each else {})}


def declared_scene(parser, name: str, assets):
    """A scene of benchmarks.scenes and what it builds; a missing asset is the command line's error
    (parser.error names the scene)."""
    from benchmarks.scenes import SCENES_DECLARED

    declared = SCENES_DECLARED[name]
    try:
        return declared, declared.build(assets)
    except FileNotFoundError as error:
        parser.error(f"--scenes {name}: {error}")


def scene_arguments(parser) -> None:
    """The options of a script that steps scenes of benchmarks.scenes: --variant (read with
    variant_setting), --assets (declared_scene) and --out."""
    parser.add_argument("--variant", default=None,
                        help="each scene's variant or sweep point of this label (benchmarks.scenes), with its "
                             "settings and dt, e.g. 'no projection (Baumgarte 0.5)'; default: the default settings")
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs")
    parser.add_argument("--out", default=None, help="JSON file for the results")


def variant_setting(parser, name: str, declared, label: str | None) -> tuple[dict, float]:
    """The settings (SolverConfig keywords) and dt factor of a scene's variant or sweep point named
    ``label`` (benchmarks.scenes: Declared.variants, Declared.sweep); None: the defaults. A label the
    scene does not declare is the command line's error (parser.error lists the scene's labels)."""
    if label is None or label == "default":
        return {}, 1.0
    settings = {s["label"]: s for s in [*declared.variants, *declared.sweep]}
    if label not in settings:
        parser.error(f"--variant {label!r}: scene {name} declares {sorted(settings) or 'no variants'}")
    return dict(settings[label].get("config", {})), float(settings[label].get("dt_scale", 1.0))


def main(argv=None) -> int:
    from benchmarks.run import write_rows
    from benchmarks.scenes import SCENES_DECLARED
    from engine import SolverConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", nargs="+", default=["drlegs_hanging"], choices=sorted(SCENES_DECLARED))
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--clock", choices=("host", "device"), default="host",
                        help="host: each launch synchronized and timed with its overhead; device (CUDA): the "
                             "kernels' own run times from CUDA events, launched back to back")
    scene_arguments(parser)
    args = parser.parse_args(argv)
    if args.worlds < 1 or args.steps < 1:
        parser.error("--worlds and --steps must be >= 1")
    if args.clock == "device" and not wp.get_device(args.device).is_cuda:
        parser.error(f"--clock device needs a CUDA device, not {args.device}")
    wp.config.log_level = wp.LOG_WARNING
    rows = []
    for name in args.scenes:
        declared, scene = declared_scene(parser, name, args.assets)
        settings, dt_scale = variant_setting(parser, name, declared, args.variant)
        dt = declared.dt * dt_scale
        row = {"scene": name, "variant": args.variant or "default", "settings": settings,
               "num_worlds": args.worlds, "dt": dt,
               **kernel_times(scene.specs, args.worlds, dt, args.device, args.steps, args.clock,
                              config=SolverConfig(**settings))}
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        write_rows(args.out, args.device, "benchmarks.kernel_times", argv, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
