"""Building a generation's specs: in this process against worker processes (morphopt.build).

    python benchmarks/spec_build.py --designs 4096 --repeats 3 --out DIR

Samples designs of studies/walker.toml's space (its fixed parameters applied), builds their
MechanismSpecs in this process and with the worker pool (the pool's start-up is timed apart),
checks that both give the same packed arrays, and prints one JSON object (medians over the
repeats; also written to spec_build.json under --out).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

from engine import pack_worlds  # noqa: E402
from morphopt.build import build_specs, default_workers  # noqa: E402
from morphopt.families import load_family  # noqa: E402
from morphopt.study_spec import load_study_spec  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--designs", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core but one)")
    parser.add_argument("--spec", default=str(ROOT / "studies" / "walker.toml"))
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    study = load_study_spec(args.spec)
    family = load_family(study.family)
    space = study.design_space(family)
    params = [{**p, **study.fixed} for p in space.sample(np.random.default_rng(0), args.designs)]
    workers = args.workers or default_workers()
    start = time.perf_counter()
    build_specs(family, params[:workers], workers=workers)  # starts the pool
    startup = time.perf_counter() - start
    here, pooled = [], []
    for _ in range(args.repeats):
        start = time.perf_counter()
        a = build_specs(family, params, workers=1)
        here.append(time.perf_counter() - start)
        start = time.perf_counter()
        b = build_specs(family, params, workers=workers)
        pooled.append(time.perf_counter() - start)
    specs_a = [s for s in a if not isinstance(s, str)]
    specs_b = [s for s in b if not isinstance(s, str)]
    ma, mb = pack_worlds(specs_a, device="cpu"), pack_worlds(specs_b, device="cpu")
    same = [x for x in a if isinstance(x, str)] == [x for x in b if isinstance(x, str)] and all(
        np.array_equal(v.numpy(), getattr(mb, k).numpy()) for k, v in vars(ma).items() if isinstance(v, wp.array))
    report = {
        "designs": args.designs, "built": len(specs_a), "cores": os.cpu_count(), "workers": workers,
        "repeats": args.repeats, "pool_startup_s": startup,
        "here_s": statistics.median(here), "pool_s": statistics.median(pooled),
        "here_ms_per_design": 1e3 * statistics.median(here) / args.designs,
        "speedup": statistics.median(here) / statistics.median(pooled), "identical": bool(same),
    }
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "spec_build.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report))
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
