"""Host time of a walker study's generation: build, pack and simulate seconds and designs per second.

    python benchmarks/walker_host.py --designs 256 --repeats 3
    python benchmarks/walker_host.py --root OTHER_CHECKOUT --designs 256   # an older commit, same script
    python benchmarks/walker_host.py --designs 256 --profile walker.prof   # cProfile of one timed generation
    python benchmarks/walker_host.py --designs 1024 --workers 2 --duration 0.05   # the host's share alone
    python benchmarks/walker_host.py --study jansen_stride.toml --designs 2048      # another dynamic study

Evaluates generations of ``--designs`` walkers of studies/walker.toml's family as ``morphopt study
run`` does (morphopt.evaluate.evaluate_dynamic with the study's duration, dt, crank speed and
solver settings; the [fixed] parameters applied to designs sampled from the study's space). A
first generation compiles the kernels and fills the engine's caches, as a study's first
generation does; each timed generation then draws new designs (a new seed), as a study's later
generations do. Prints one JSON object: per generation the stage seconds (wall), designs per
second and per CPU second of this process (the evaluation runs on one core: on a shared machine
the CPU time moves less with the load than the wall time), and their medians. ``--duration``
shortens the simulated time (the study's by default): with a few steps, this process's CPU time
is the host work a GPU run waits on (receiving the built specs, packing, metrics), and
``--workers`` above 1 builds in worker processes as a GPU machine's cores do. ``--root`` imports
engine and morphopt from another checkout (and its own study files), so that the commit before a
change measures itself with this script.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parents[1]


def _commit(root: pathlib.Path) -> str:
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             check=True)
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _designs(study, family, count: int, seed: int) -> list:
    """``count`` designs of the study's space (its [fixed] parameters applied), drawn with ``seed``."""
    import numpy as np

    space = study.design_space(family)
    return [{**p, **study.fixed} for p in space.sample(np.random.default_rng(seed), count)]


def _evaluate(study, family, params, workers=None, duration=None):
    from morphopt.evaluate import evaluate_dynamic

    kwargs = dict(duration=study.duration if duration is None else duration, dt=study.dt, device=study.device,
                  crank_speed=study.crank_speed,
                  config=study.solver_config())
    if workers is not None:  # build processes (None: evaluate_dynamic's choice, one per core on a GPU machine)
        kwargs["workers"] = workers
    if getattr(study, "model", None) is not None:  # commits before the engine planned itself
        kwargs["model"] = study.model
    return evaluate_dynamic(family, params, **kwargs)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--designs", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3, help="timed generations (the median is reported)")
    parser.add_argument("--root", default=str(HERE), help="the checkout to measure")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--profile", default=None, help="write cProfile stats of the first timed generation here")
    parser.add_argument("--workers", type=int, default=None,
                        help="processes that build the specs (default: evaluate_dynamic's; a GPU machine's 16 cores "
                             "use 15, whose specs come back pickled)")
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the study's)")
    parser.add_argument("--study", default="walker.toml",
                        help="a dynamic study file of the checkout's studies/ folder "
                             "(jansen_stride.toml: the tree plan)")
    args = parser.parse_args(argv)
    root = pathlib.Path(args.root).resolve()
    sys.path.insert(0, str(root))
    import warp as wp

    wp.config.quiet = True
    from morphopt.families import load_family
    from morphopt.study_spec import load_study_spec
    from morphopt.warp_setup import quiet_warp

    quiet_warp()
    study = load_study_spec(root / "studies" / args.study).with_overrides(device=args.device)
    family = load_family(study.family)
    warm = _evaluate(study, family, _designs(study, family, args.designs, 1000), args.workers, args.duration)
    runs = []
    for repeat in range(args.repeats):
        params = _designs(study, family, args.designs, repeat)
        profiler = None
        if args.profile and repeat == 0:
            import cProfile
            profiler = cProfile.Profile()
            profiler.enable()
        start, cpu = time.perf_counter(), time.process_time()
        evaluation = _evaluate(study, family, params, args.workers, args.duration)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
        if profiler is not None:
            profiler.disable()
            profiler.dump_stats(args.profile)
        runs.append({"seconds": round(seconds, 4), "designs_per_s": round(len(params) / seconds, 2),
                     "cpu_seconds": round(cpu, 4), "designs_per_cpu_s": round(len(params) / cpu, 2),
                     "stages": {k: round(v, 4) for k, v in evaluation.timings.items()},
                     "feasible": int(sum(evaluation.feasible))})
    stages = sorted({k for run in runs for k in run["stages"]})
    report = {
        "commit": _commit(root), "device": args.device, "designs": args.designs, "repeats": args.repeats,
        "study": args.study, "workers": args.workers,
        "duration": study.duration if args.duration is None else args.duration,
        "plan": None if getattr(warm, "plan", None) is None else warm.plan.coordinates.value,
        "designs_per_s": statistics.median(run["designs_per_s"] for run in runs),
        "designs_per_cpu_s": statistics.median(run["designs_per_cpu_s"] for run in runs),
        "stages": {k: round(statistics.median(run["stages"].get(k, 0.0) for run in runs), 4) for k in stages},
        "runs": runs,
    }
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
