"""The walker study end to end: designs per second, the best design and how much it beats the default.

    python benchmarks/walker_study.py --device cuda --worlds 4096 --generations 3 --out DIR
    python benchmarks/walker_study.py --device cpu --worlds 64 --generations 1 --out DIR

Runs studies/walker.toml (with the given device, worlds and generations; storage under --out),
then simulates the family's default design and the best design found side by side in one batch
with the study's settings. Prints one JSON object and writes walker_study_<device>.json, with the
simulated seconds per wall second of the whole study and their ratio to leggedsnake's, and the
coordinates the engine planned for the pair (engine.pack chooses them; a study file no longer
sets a model).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import warp as wp  # noqa: E402

import engine  # noqa: E402
from morphopt.evaluate import evaluate_dynamic  # noqa: E402
from morphopt.families import load_family  # noqa: E402
from morphopt.study import run_study  # noqa: E402
from morphopt.study_spec import load_study_spec  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
LEGGEDSNAKE_SIMULATED_S_PER_S = 40.0 / 0.6  # a 2-D pymunk walker: 40 s simulated in 0.6 s on one core


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--generations", type=int, default=1)
    parser.add_argument("--spec", default=str(ROOT / "studies" / "walker.toml"))
    parser.add_argument("--out", default=".")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_study_spec(args.spec).with_overrides(
        device=args.device, worlds=args.worlds, generations=args.generations,
        storage=f"sqlite:///{(out / 'walker_study.sqlite').resolve()}")
    family = load_family(spec.family)
    # compile the kernels outside the timed study
    default = {**family.space.default(), **spec.fixed}
    warm = evaluate_dynamic(family, [default], duration=4 * spec.dt, dt=spec.dt, device=spec.device,
                            config=spec.solver_config())
    if warm.plan is not None and warm.plan.coordinates is engine.Coordinates.TABULATED:
        # both of the plan's step kernels (a batch of one world takes the one-warp kernel)
        one = [family.build_spec(default, crank_speed=spec.crank_speed)]
        config = spec.solver_config() or engine.SolverConfig()
        for tiled in (True, False):
            model = engine.pack(one, spec.device, dt=spec.dt, config=config.tuned(tabulated_tiled=tiled))
            state = model.state()
            engine.step(model, state, state)
    t0 = time.perf_counter()
    result = run_study(spec, progress=True)
    seconds = time.perf_counter() - t0
    pair = evaluate_dynamic(family, [default, result.best_params], duration=spec.duration, dt=spec.dt,
                            device=spec.device, config=spec.solver_config())
    speeds = [m.get("walking_speed", float("nan")) for m in pair.metrics]
    report = {
        "device": wp.get_device(args.device).name if args.device != "cpu" else "cpu", "worlds": args.worlds,
        "generations": args.generations, "evaluations": result.evaluations, "seconds": seconds,
        "designs_per_s": result.evaluations / seconds, "overhead_share": result.overhead,
        "seconds_by_stage": result.stages,
        "simulated_s_per_design": spec.duration, "dt": spec.dt, "solver": spec.solver,
        "coordinates": None if pair.plan is None else pair.plan.coordinates.value,
        "simulated_s_per_s": result.evaluations * spec.duration / seconds,
        "over_leggedsnake": result.evaluations * spec.duration / seconds / LEGGEDSNAKE_SIMULATED_S_PER_S,
        "best_walking_speed": result.best_value, "best_params": result.best_params,
        "default_walking_speed": speeds[0], "best_rechecked_walking_speed": speeds[1],
        "best_over_default": speeds[1] / speeds[0] if speeds[0] > 0 else float("inf"),
        "failures_of_pair": pair.failures, "warp": wp.config.version,
    }
    stem = out / f"walker_study_{args.device.split(':')[0]}"
    stem.with_suffix(".json").write_text(json.dumps(report, indent=1))
    write_stages(result.stages, seconds, report["device"], stem)
    print(json.dumps(report))
    return 0


def write_stages(stages: dict, seconds: float, device: str, stem: pathlib.Path) -> None:
    """The study's time by stage as CSV (stage, seconds, share of the study) and a bar chart (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted(stages.items(), key=lambda item: -item[1])
    lines = ["stage,seconds,share"] + [f"{name},{spent:.6g},{spent / seconds:.6g}" for name, spent in rows]
    stem.with_name(stem.name + "_stages.csv").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(6.4, 0.4 * len(rows) + 1.2))
    ax.barh([name for name, _ in rows][::-1], [spent for _, spent in rows][::-1], color="tab:blue")
    for k, (_, spent) in enumerate(rows[::-1]):
        ax.annotate(f"{spent:.3g} s ({100 * spent / seconds:.1f} %)", (spent, k), xytext=(4, 0),
                    textcoords="offset points", va="center", fontsize=8)
    ax.set_xlabel("wall seconds")
    ax.set_title(f"walker study, time by stage ({device}, {seconds:.1f} s in all)", fontsize=10)
    ax.set_xlim(0, 1.3 * max(spent for _, spent in rows))
    fig.tight_layout()
    fig.savefig(stem.with_name(stem.name + "_stages.png"), dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
