"""Walker work-precision: what each solver setting costs and how far it moves the study's metric.

    python benchmarks/walker_precision.py --device cuda --worlds 256 --duration 1.0 --out benchmarks/results/h200
    python benchmarks/walker_precision.py --device cpu --worlds 8 --duration 1.0 --out benchmarks/results/cpu

Random walkers of studies/walker.toml (three legs per side, both leg families; world 0 is the
family's default design) run for --duration seconds under every setting in SETTINGS. The
reference is dt 1 ms with tight PADMM tolerances. For each setting: time per step and
per simulated second, the walking-speed error against the reference (the study's objective: torso
x velocity over the last three quarters of the run; median and 90th percentile over the walkers),
the torso's final position error, and the largest joint separation. A walker on contact is
sensitive to small differences, so even the reference's own dt 2 ms run differs from it: compare
settings with each other, not with zero. Writes walker_precision_<device>.json and .png.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

from benchmarks.walker_steps import walkers  # noqa: E402
from engine import SolverConfig, pack_worlds, rollout  # noqa: E402
from morphopt.families import load_family  # noqa: E402

# name: (dt [s], SolverConfig keywords; its knobs under "tuning": engine.Tuning's)
SETTINGS = {
    "reference": (0.001, {"relative_tolerance": 1e-5, "max_iterations": 300}),
    "default dt 1 ms": (0.001, {}),
    "default": (0.002, {}),
    "cap 50": (0.002, {"max_iterations": 50}),
    "relative tol 1e-3": (0.002, {"relative_tolerance": 1e-3}),
    "relative tol 1e-3, cap 40": (0.002, {"relative_tolerance": 1e-3, "max_iterations": 40}),
    "dt 3 ms": (0.003, {}),
    "dt 4 ms": (0.004, {}),
    "rho interval 8": (0.002, {"tuning": {"rho_update_interval": 8}}),
    "dt 3 ms, rho interval 8": (0.003, {"tuning": {"rho_update_interval": 8}}),
    "dt 3 ms, rho interval 8, cap 50": (0.003, {"max_iterations": 50, "tuning": {"rho_update_interval": 8}}),
    "joint penalty uncapped": (0.002, {"tuning": {"cap_joint_penalty": False}}),
    "free rho 1e-3": (0.002, {"tuning": {"free_rho": 1e-3}}),
}


def pose_at(time: np.ndarray, path: np.ndarray, t: float) -> np.ndarray:
    """Points (W, 3) at time t, linear between the two records around it (a step size that does
    not divide the duration ends its records a few ms away from it: dt 3 ms, every 21 ms, at 1.008 s)."""
    k = int(np.clip(np.searchsorted(time, t) - 1, 0, len(time) - 2))
    share = (t - time[k]) / (time[k + 1] - time[k])
    return (1.0 - share) * path[k] + share * path[k + 1]


def run_setting(specs, device: str, dt: float, config: dict, duration: float) -> dict:
    model = pack_worlds(specs, device=device, dt=dt, config=SolverConfig(**config))
    record_every = max(1, int(round(0.02 / dt)))
    steps = int(round(duration / dt / record_every)) * record_every
    rollout(model, model.state(), model.control(), record_every, record_every=record_every)  # compile
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    trace, _ = rollout(model, model.state(), model.control(), steps, record_every=record_every)
    wp.synchronize_device(device)
    seconds = time.perf_counter() - t0
    torso = model.point_names[0].index("torso")
    path = trace.points[:, :, torso]  # (T, W, 3)
    quarter = len(trace.time) // 4
    speed = (path[-1, :, 0] - path[quarter, :, 0]) / (trace.time[-1] - trace.time[quarter])
    return {"dt": dt, "config": config, "steps": steps, "seconds": seconds, "ms_per_step": 1e3 * seconds / steps,
            "s_per_simulated_s": seconds / duration, "speed": speed, "final": pose_at(trace.time, path, duration),
            "joint_separation_max": float(np.nanmax(trace.violation_linear)),
            "diverged": int(trace.diverged.sum())}


def plot(report: dict, path) -> None:
    """Walking-speed error (median, bar to the 90th percentile) against wall time per simulated
    second, one point per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in report["settings"] if r["setting"] != "reference"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for row in rows:
        ax.errorbar(row["s_per_simulated_s"], row["speed_error_median"], fmt="o",
                    yerr=[[0.0], [row["speed_error_p90"] - row["speed_error_median"]]], capsize=3)
        ax.annotate(row["setting"], (row["s_per_simulated_s"], row["speed_error_median"]), fontsize=8,
                    xytext=(4, 4), textcoords="offset points")
    ax.set_xlim(0.0, 1.15 * max(r["s_per_simulated_s"] for r in rows))
    ax.set_ylim(0.0, 1.1 * max(r["speed_error_p90"] for r in rows))
    ax.grid(alpha=0.3)
    ax.set_xlabel(f"wall time per simulated second, {report['worlds']} walkers [s]")
    ax.set_ylabel("walking-speed error vs reference [m/s]\n(median, bar to 90th percentile)")
    ax.set_title(f"Walker work-precision ({report['device']}, warp {report['warp']})")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=8)
    parser.add_argument("--duration", type=float, default=1.0)
    parser.add_argument("--only", nargs="*", default=None, help="setting names (the reference always runs)")
    parser.add_argument("--out", default=".")
    parser.add_argument("--replot", default=None, help="redraw the PNG of a written JSON and exit")
    args = parser.parse_args(argv)
    if args.replot:
        plot(json.loads(pathlib.Path(args.replot).read_text()), pathlib.Path(args.replot).with_suffix(".png"))
        return 0
    wp.config.log_level = wp.LOG_WARNING
    names = ["reference"] + [n for n in (args.only or SETTINGS) if n != "reference"]
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        parser.error(f"unknown settings {unknown}; known: {list(SETTINGS)}")
    family = load_family("walker")
    specs = walkers(args.worlds, 3, seed=5)
    specs[0] = family.build_spec(family.space.validate({**family.space.default(), "legs_per_side": 3}))
    runs = {}
    for name in names:
        dt, config = SETTINGS[name]
        runs[name] = run_setting(specs, args.device, dt, config, args.duration)
        print(f"{name:28s} {runs[name]['ms_per_step']:8.2f} ms/step", flush=True)
    reference = runs["reference"]
    rows = []
    for name, run in runs.items():
        error = np.abs(run["speed"] - reference["speed"])
        rows.append({
            "setting": name, "dt": run["dt"], "config": run["config"], "ms_per_step": run["ms_per_step"],
            "s_per_simulated_s": run["s_per_simulated_s"],
            "speed_error_median": float(np.nanmedian(error)), "speed_error_p90": float(np.nanpercentile(error, 90)),
            "torso_final_error_median": float(np.nanmedian(np.linalg.norm(run["final"] - reference["final"], axis=1))),
            "joint_separation_max": run["joint_separation_max"], "diverged": run["diverged"],
        })
    report = {"device": wp.get_device(args.device).name if args.device != "cpu" else "cpu",
              "warp": wp.config.version, "worlds": len(specs), "duration_s": args.duration,
              "reference_speed_median": float(np.median(reference["speed"])), "settings": rows}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = "walker_precision_" + ("cuda" if args.device.startswith("cuda") else "cpu")
    (out / f"{stem}.json").write_text(json.dumps(report, indent=1))
    plot(report, out / f"{stem}.png")
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
