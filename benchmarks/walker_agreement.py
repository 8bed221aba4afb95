"""Walking speed on the tabulated plan against the maximal plan, walker by walker.

    python benchmarks/walker_agreement.py --designs 64 --device cpu --out benchmarks/results/cpu

Random designs of studies/walker.toml (three legs per side, both leg families, seed 0) evaluated
as the study evaluates them (morphopt.evaluate.evaluate_dynamic, 2 s at the study's dt and solver
settings), once with coordinates="tabulated" and once with coordinates="maximal". Reported: the
walkers feasible in both, the median and 90th percentile of |speed difference| [m/s] and of it
relative to the maximal speed, and how many fail in one plan only. Walkers on contact are
sensitive to any difference of method, so this measures agreement, not an error against truth.
Prints one JSON object; writes walker_agreement_<device>.json under --out.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402


def designs(count: int, seed: int = 0) -> list[dict]:
    """``count`` valid random walker designs (three legs per side)."""
    from morphopt.families import load_family

    family = load_family("walker")
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        for p in family.space.sample(rng, count):
            try:
                out.append(family.space.validate({**p, "legs_per_side": 3}))
            except ValueError:
                continue
    return out[:count]


def study_settings():
    """(duration, dt, SolverConfig) of studies/walker.toml."""
    from morphopt.study_spec import load_study_spec

    study = load_study_spec(pathlib.Path(__file__).resolve().parents[1] / "studies" / "walker.toml")
    return study.duration, study.dt, study.solver_config()


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--designs", type=int, default=64)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from morphopt.evaluate import evaluate_dynamic
    from morphopt.families import load_family

    family = load_family("walker")
    params = designs(args.designs)
    duration, dt, config = study_settings()
    speeds, failed, seconds = {}, {}, {}
    for coordinates in ("tabulated", "maximal"):
        t = time.perf_counter()
        evaluation = evaluate_dynamic(family, params, duration=duration, dt=dt, device=args.device, config=config,
                                      coordinates=coordinates)
        seconds[coordinates] = time.perf_counter() - t
        speeds[coordinates] = np.array([m.get("walking_speed", np.nan) if m else np.nan for m in evaluation.metrics])
        failed[coordinates] = ~np.asarray(evaluation.feasible, bool)
    both = ~failed["tabulated"] & ~failed["maximal"]
    diff = np.abs(speeds["tabulated"] - speeds["maximal"])[both]
    relative = diff / np.maximum(np.abs(speeds["maximal"][both]), 1e-3)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=pathlib.Path(__file__).parent).stdout.strip()
    result = {"commit": commit, "device": args.device, "designs": args.designs, "duration_s": duration, "dt": dt,
              "feasible_both": int(both.sum()),
              "failed_tabulated_only": int((failed["tabulated"] & ~failed["maximal"]).sum()),
              "failed_maximal_only": int((failed["maximal"] & ~failed["tabulated"]).sum()),
              "speed_diff_median_m_s": float(np.median(diff)) if diff.size else None,
              "speed_diff_p90_m_s": float(np.percentile(diff, 90)) if diff.size else None,
              "speed_diff_relative_median": float(np.median(relative)) if diff.size else None,
              "speed_maximal_median_m_s": float(np.median(speeds["maximal"][both])) if diff.size else None,
              "seconds": seconds}
    print(json.dumps(result))
    if args.out:
        path = pathlib.Path(args.out)
        path.mkdir(parents=True, exist_ok=True)
        (path / f"walker_agreement_{args.device}.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
