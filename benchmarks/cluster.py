"""The cluster path's cost: designs/s of a study run in one process and on a local Ray cluster of 1
and 2 workers, same study and seed (the stored designs are checked equal).

    python -m benchmarks.cluster [--device cpu] [--generations 6] [--out DIR]
    python -m benchmarks.cluster --device cuda --studies dynamic --workers 0 1 --dynamic-worlds 4096
    python -m benchmarks.cluster --device cuda --studies dynamic --workers 0 2 --gpus-per-worker 0.5
    python -m benchmarks.cluster --device cuda --workers 1 2 4 --dynamic-worlds 16384 --kinematic-worlds 65536 --kill

Runs a kinematic study (quickstart's Jansen leg, 256 designs a generation) and a small dynamic one
(walkers, 64 a generation, 1.3 s simulated) each way, on one Ray instance started first, every
run in a fresh process; the first generation (kernel compilation, the workers' start) is
excluded from the rate, and so from each run's milliseconds a design by stage (the workers'
build, pack, simulate and metrics as their shards report them). --gpus-per-worker 0.5
puts two workers on each GPU; --kill runs the most workers again with worker 0's process killed
in the second generation (the stored study must not change). Each run's rate over one process's
and, from 2 workers, its scaling efficiency against one worker. Prints one JSON line per study
and writes cluster_<device>.json and a plot, cluster_<device>.png.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile

import numpy as np

from benchmarks.run import RESULTS, device_tag
from morphopt.storage import read_designs
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec

ROOT = pathlib.Path(__file__).resolve().parents[1]


STUDIES = {
    "kinematic": """[study]
name = "{name}"
family = "jansen_leg"
mode = "kinematic"
seed = 0
generations = {generations}
worlds = {worlds}
device = "{device}"
[objective]
metric = "foot_stride"
direction = "maximize"
[simulation]
samples = 180
[fixed]
m = 0.015
""",
    "dynamic": """[study]
name = "{name}"
family = "walker"
mode = "dynamic"
seed = 0
generations = {generations}
worlds = {worlds}
device = "{device}"
[objective]
metric = "walking_speed"
direction = "maximize"
[simulation]
duration = 1.3
dt = 0.005
[fixed]
legs_per_side = 3
""",
}


def measure(folder: pathlib.Path, kind: str, device: str, generations: int, workers: int, worlds: int,
            address: str, share: float = 1.0, kill: bool = False) -> dict:
    """Designs/s of generations 2 .. ``generations`` of one run from scratch in a fresh process (as
    cold as a fresh Ray worker), timed from the end of the first generation (the workers' start and
    the kernels' compilation fall in it), with that span's milliseconds a design by stage. kill:
    worker 0's process is killed in the second generation (morphopt.cluster's test hook)."""
    name = f"{kind}_{workers}" + ("_killed" if kill else "")
    path = folder / f"{name}.toml"
    path.write_text(STUDIES[kind].format(name=name, generations=generations, device=device, worlds=worlds))
    done = subprocess.run([sys.executable, "-m", "benchmarks.cluster", "--one", str(path), str(workers), address,
                           str(share)], stdout=subprocess.PIPE, check=True, cwd=ROOT,
                          env={**{k: v for k, v in os.environ.items() if k != "MORPHOPT_TEST_KILL_WORKER"},
                               **({"MORPHOPT_TEST_KILL_WORKER": "1:0"} if kill else {})})
    marks = json.loads(done.stdout.decode().strip().splitlines()[-1])  # per generation: (seconds, stages)
    (first, first_stages), (last, last_stages) = marks[0], marks[-1]
    designs = (generations - 1) * worlds
    # the workers' stages (build, pack, simulate, metrics) as the shards report them
    per_design = {stage: round(1e3 * (last_stages[stage] - first_stages.get(stage, 0.0)) / designs, 4)
                  for stage in last_stages}
    values = read_designs(load_study_spec(path).storage_url, name)["value"].to_numpy()
    return {"workers": workers, "gpus_per_worker": share if workers and device.startswith("cuda") else None,
            "designs_per_s": designs / (last - first), "first_generation_s": first,
            "stage_ms_per_design": per_design, "values": values}


def _one(path: str, workers: int, address: str, share: float) -> None:
    """measure's run, in this (fresh) process: prints [seconds so far, stages so far] per generation as JSON."""
    spec = load_study_spec(path)
    if workers:
        spec = spec.with_overrides(cluster=address, workers=workers,
                                   gpus_per_worker=share if spec.device.startswith("cuda") else None)
    marks = []
    run_study(spec, progress=False, on_generation=lambda generation, seconds, stages: marks.append((seconds, stages)))
    print(json.dumps(marks), flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--generations", type=int, default=6)
    parser.add_argument("--out", default=None)
    parser.add_argument("--studies", nargs="+", choices=sorted(STUDIES), default=list(STUDIES))
    parser.add_argument("--workers", nargs="+", type=int, default=[0, 1, 2],
                        help="worker counts to run (0: this process); on CUDA one GPU per worker")
    parser.add_argument("--kinematic-worlds", type=int, default=256)
    parser.add_argument("--dynamic-worlds", type=int, default=64)
    parser.add_argument("--num-cpus", type=int, default=2, help="CPUs the local Ray instance offers")
    parser.add_argument("--gpus-per-worker", type=float, default=1.0,
                        help="a CUDA study's share of a GPU per worker (0.5: two workers on each GPU)")
    parser.add_argument("--kill", action="store_true",
                        help="also run the most workers asked for with worker 0 killed mid-generation")
    parser.add_argument("--one", nargs=4, default=None, help=argparse.SUPPRESS)  # measure's fresh process
    args = parser.parse_args(argv)
    if args.generations < 2:
        parser.error("--generations must be at least 2 (the first one is not timed)")
    if args.one:
        return _one(args.one[0], int(args.one[1]), args.one[2], float(args.one[3]))
    out = {"device": device_tag(args.device), "machine": platform.processor() or platform.machine(),
           "command": "python -m benchmarks.cluster " + " ".join(sys.argv[1:]), "studies": {}}
    import ray

    ray.init(num_cpus=args.num_cpus, include_dashboard=False, log_to_driver=False,
             configure_logging=False)  # one for all runs
    address = ray.get_runtime_context().gcs_address
    worlds = {"kinematic": args.kinematic_worlds, "dynamic": args.dynamic_worlds}
    with tempfile.TemporaryDirectory() as folder:
        for kind in args.studies:
            rows = [measure(pathlib.Path(folder), kind, args.device, args.generations, w, worlds[kind], address,
                            args.gpus_per_worker)
                    for w in args.workers]
            if args.kill and max(args.workers) > 0:
                rows.append(measure(pathlib.Path(folder), kind, args.device, args.generations, max(args.workers),
                                    worlds[kind], address, args.gpus_per_worker, kill=True) | {"killed": True})
            same = all(np.array_equal(r["values"], rows[0]["values"], equal_nan=True) for r in rows)
            base = rows[0]["designs_per_s"]  # the first worker count asked for (default 0: this process)
            one = next((r["designs_per_s"] for r in rows if r["workers"] == 1), None)
            out["studies"][kind] = {"worlds": worlds[kind], "same_results": bool(same), "runs": [
                {k: v for k, v in r.items() if k != "values"} | {"over_single_process": r["designs_per_s"] / base}
                | ({"efficiency": r["designs_per_s"] / (r["workers"] * one)}
                   if one and r["workers"] and not r.get("killed") else {})
                for r in rows]}
            print(json.dumps({kind: out["studies"][kind]}), flush=True)
    folder = pathlib.Path(args.out) if args.out else RESULTS / out["device"]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"cluster_{out['device']}.json").write_text(json.dumps(out, indent=1))
    plot(out, folder / f"cluster_{out['device']}.png")


def plot(out: dict, path: pathlib.Path) -> None:
    """Designs/s against workers per study, beside perfect scaling from one worker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    studies = out["studies"]
    fig, axes = plt.subplots(1, len(studies), figsize=(5 * len(studies), 3.8), squeeze=False)
    for ax, (kind, study) in zip(axes[0], studies.items()):
        runs = [r for r in study["runs"] if not r.get("killed")]
        alone = [r for r in runs if r["workers"] == 0]
        spread = sorted((r for r in runs if r["workers"] > 0), key=lambda r: r["workers"])
        if spread:
            n = [r["workers"] for r in spread]
            ax.plot(n, [r["designs_per_s"] for r in spread], "o-", label="Ray workers")
            one = next((r["designs_per_s"] for r in spread if r["workers"] == 1), None)
            if one:
                ax.plot(n, [one * k for k in n], ":", color="grey", label="perfect scaling")
        if alone:
            ax.axhline(alone[0]["designs_per_s"], color="k", lw=0.8, label="one process, no Ray")
        ax.set(xlabel="workers", ylabel="designs / s", title=f"{kind}, {study['worlds']} designs a generation")
        ax.legend(fontsize=8)
    fig.suptitle(f"morphopt studies on a local Ray cluster ({out['device']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
