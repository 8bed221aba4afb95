"""What a study's coordinator spends per generation, at populations of 4 k, 16 k and 65 k walkers:
CMA-ES ask and tell, gathering the workers' results (Ray's serialization of the shards' metrics
and their scatter into one table; as arrays, morphopt.metric_table, and as one dict a design, as
before) and storing the generation (SQLite and PostgreSQL: designs per second sustained).

    python -m benchmarks.coordinator [--sizes 4096 16384 65536] [--postgres URL] [--out DIR]

The designs are the walker study's (studies/walker.toml's space), their metrics one real
evaluation's repeated with other values. Without --postgres a throwaway server is started with the
installed binaries (tests/morphopt/postgres.py). Prints one JSON line per population and writes
coordinator_cpu.json: the inputs of docs/scale.md's model.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import pathlib
import pickle
import sys
import tempfile
import time

import numpy as np

from benchmarks.run import RESULTS
from morphopt.evaluate import evaluate_dynamic
from morphopt.families import load_family
from morphopt.metric_table import MetricTable
from morphopt.optimizers import CMAES
from morphopt.storage import StudyStorage


def _metrics(family, count: int) -> list:
    """``count`` walker metric dicts: one evaluation's, its numbers scaled per design."""
    params = [{**family.space.default(), "legs_per_side": 3}]
    template = evaluate_dynamic(family, params, duration=1.3, dt=0.005, device="cpu").metrics[0]
    numbers = {k: v for k, v in template.items() if isinstance(v, float)}
    rng = np.random.default_rng(0)
    scales = rng.uniform(0.5, 1.5, count)
    return [{k: v * float(s) for k, v in numbers.items()} for s in scales]


def _time(function, repeats: int = 3) -> float:
    """Median seconds of ``repeats`` calls."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        function()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def measure(size: int, family, urls: dict) -> dict:
    space = family.space
    optimizer = CMAES(space, popsize=size, sigma0=0.25, seed=0)
    free = optimizer.ask(size)
    ask = _time(lambda: CMAES(space, popsize=size, sigma0=0.25, seed=0).ask(size), 1)
    values = np.random.default_rng(1).uniform(-1, 0, size).tolist()
    tell = _time(lambda: _tell_fresh(space, size, free, values), 1)
    dicts = _metrics(family, size)
    failures = [""] * size
    parts = np.array_split(np.arange(size), 4)  # four workers' shards
    as_dicts = [([dicts[i] for i in part], [""] * len(part), {"simulate": 1.0}, None) for part in parts]
    as_arrays = [(MetricTable.from_dicts([dicts[i] for i in part]), np.zeros(len(part), np.int32), [""],
                  {"simulate": 1.0}, None) for part in parts]

    def gather_dicts():
        out = [None] * size
        for part, shard in zip(parts, as_dicts):
            for i, m in zip(part, pickle.loads(pickle.dumps(shard, protocol=5))[0]):
                out[i] = m
        return out

    def gather_arrays():
        return MetricTable.gather(size, [(part, pickle.loads(pickle.dumps(shard, protocol=5))[0])
                                         for part, shard in zip(parts, as_arrays)])

    metrics = gather_arrays()
    row = {"population": size, "ask_s": ask, "tell_s": tell, "gather_dicts_s": _time(gather_dicts),
           "gather_arrays_s": _time(gather_arrays),
           "gather_dicts_bytes_per_design": sum(len(pickle.dumps(x, protocol=5)) for x in as_dicts) / size,
           "gather_arrays_bytes_per_design": sum(len(pickle.dumps(x, protocol=5)) for x in as_arrays) / size}
    params = [{**p, "legs_per_side": 3} for p in free]
    for kind, url in urls.items():
        storage = StudyStorage(url, f"bench_{size}")
        storage.acquire({"bench": True})
        try:
            spent = []
            for generation in range(3):
                t = time.perf_counter()
                storage.write_generation(generation, params, np.asarray(values), metrics, failures, b"",
                                         1.0, asked="", told=np.asarray(values)[:, None])
                spent.append(time.perf_counter() - t)
        finally:
            storage.release()
        row[f"store_{kind}_s"] = float(np.median(spent))
        row[f"store_{kind}_designs_per_s"] = size / float(np.median(spent))
    return row


def _tell_fresh(space, size, free, values):
    optimizer = CMAES(space, popsize=size, sigma0=0.25, seed=0)
    optimizer.ask(size)
    optimizer.tell(free, values)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[4096, 16384, 65536])
    parser.add_argument("--postgres", default=None, help="a PostgreSQL URL (default: a throwaway local server)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    family = load_family("walker")
    out = {"device": "cpu", "command": "python -m benchmarks.coordinator " + " ".join(sys.argv[1:]), "rows": []}
    with contextlib.ExitStack() as stack:
        folder = pathlib.Path(stack.enter_context(tempfile.TemporaryDirectory()))
        postgres = args.postgres
        if postgres is None:
            from tests.morphopt.postgres import throwaway_postgres
            postgres = stack.enter_context(throwaway_postgres())
        urls = {"sqlite": f"sqlite:///{folder / 'bench.sqlite'}", "postgresql": postgres}
        for size in args.sizes:
            row = measure(size, family, urls)
            out["rows"].append(row)
            print(json.dumps(row), flush=True)
    target = pathlib.Path(args.out) if args.out else RESULTS / "cpu"
    target.mkdir(parents=True, exist_ok=True)
    (target / "coordinator_cpu.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
