"""What a resume costs: rebuilding an optimizer by replaying its stored generations (morphopt.checkpoint).

    python benchmarks/resume_replay.py --repeats 3 --out DIR

For each optimizer and batch size, drives the optimizer through its generations on a test function
(a shifted sphere in the unit cube of a 12-parameter space, one design in 16 failing), keeping the
log a study stores, then times a fresh optimizer's replay of that log with the summary check
(Optuna's TPE takes the stored designs and then its random states, as morphopt.study does), next
to the time the original run spent in ask and tell. Prints one JSON object (medians over the
repeats; also written to resume_replay.json and resume_replay.csv under --out).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import pathlib
import platform
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from morphopt import checkpoint  # noqa: E402
from morphopt.design_space import Choice, DesignSpace, Float, Int  # noqa: E402
from morphopt.optimizers import CMAES, OptunaSampler, RandomSearch  # noqa: E402

SPACE = DesignSpace({**{f"x{k}": Float(0.0, 1.0) for k in range(10)}, "n": Int(1, 4), "c": Choice(("a", "b"))})
CASES = [  # (name, factory, designs per generation, generations)
    ("cma", lambda n: CMAES(SPACE, popsize=n, seed=1), 4096, 100),
    ("cma bipop", lambda n: CMAES(SPACE, popsize=n, seed=1, restarts=4, restart_strategy="bipop"), 4096, 100),
    ("random", lambda n: RandomSearch(SPACE, seed=1), 4096, 100),
    ("optuna tpe", lambda n: OptunaSampler(SPACE, sampler="tpe", seed=1), 64, 30),
    ("optuna nsga2", lambda n: OptunaSampler(SPACE, sampler="nsga2", seed=1), 256, 30),
]


def objective(designs) -> np.ndarray:
    unit = np.array([SPACE.to_unit(d) for d in designs])
    values = ((unit - 0.3) ** 2).sum(axis=1)
    values[::16] = math.inf  # failed designs
    return values


def run_case(factory, designs: int, generations: int) -> dict:
    optimizer, log, spent, asked_designs = factory(designs), [], 0.0, []
    for generation in range(generations):
        start = time.perf_counter()
        asked = optimizer.ask(designs)
        spent += time.perf_counter() - start
        values = objective(asked)
        start = time.perf_counter()
        optimizer.tell(asked, values.tolist())
        spent += time.perf_counter() - start
        log.append((generation, checkpoint.designs_digest(asked), values[:, None]))
        asked_designs.append(asked)
    blob = checkpoint.encode({"optimizer": "bench"}, checkpoint.summary(optimizer))
    start = time.perf_counter()
    _, arrays = checkpoint.decode(blob, "bench")
    rebuilt = factory(designs)
    stored = getattr(rebuilt, "takes_stored_designs", False)  # as morphopt.study does: TPE takes the designs
    checkpoint.replay(rebuilt, log, "bench", asked_designs if stored else None)
    if stored:
        checkpoint.restore_random_states(rebuilt, arrays, "bench")
    checkpoint.check_summary(rebuilt, arrays, "bench")
    return {"replay_s": time.perf_counter() - start, "run_ask_tell_s": spent, "checkpoint_bytes": len(blob),
            "log_bytes": sum(told.nbytes + 64 for _, _, told in log)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    rows = []
    for name, factory, designs, generations in CASES:
        runs = [run_case(factory, designs, generations) for _ in range(args.repeats)]
        rows.append({"optimizer": name, "designs_per_generation": designs, "generations": generations,
                     **{key: statistics.median(r[key] for r in runs) for key in runs[0]}})
        print(f"{name}: replay {rows[-1]['replay_s']:.3f} s", file=sys.stderr)
    result = {"benchmark": "resume_replay", "machine": f"{platform.machine()} {os.cpu_count()} cores (CPU only)",
              "repeats": args.repeats, "rows": rows}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "resume_replay.json").write_text(json.dumps(result, indent=2))
    with open(out / "resume_replay.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
