"""Order of accuracy of the Moreau-Jean step: the passive four-bar's crank angle against dt.

    python benchmarks/convergence.py                          # dt 4 ms .. 0.125 ms, 2 s, CPU
    python benchmarks/convergence.py --root OTHER_CHECKOUT --tag before   # an older commit, same script

For each plan (coordinates "maximal" and "tree") and each dt: engine.rollout of
engine.scenes.fourbar (a tracked point on the crank's tip added) for --duration seconds, records
every 20 ms. Error: the largest |crank angle - reference| over the records [rad]. Energy drift: the
largest |E(t) - E(0)| over the records, relative to E(0) - E_min (engine.metrics on the bodies'
poses, as engine.testspeed reports it). Slopes: log(error) against log(dt) between neighbouring
step sizes, a least-squares fit over all and one over dt >= 1 ms (2: second order; float32
rounding floors the error at a few 1e-6 rad below 0.5 ms).

Reference (fourbar_reference): the four-bar's equations of motion in float64 (three bar angles, the
loop's two position rows by Lagrange multipliers, solved at the acceleration level) integrated by
scipy's DOP853 at rtol = atol = 1e-13; with mujoco installed it is checked against MuJoCo C (RK4 at
dt 1e-5 s, the MJCF export; benchmarks.peers.mujoco_reference) and the largest difference reported.

Prints one JSON object; writes convergence_<tag>.json, .csv and a log-log .png under
benchmarks/results/cpu/ (--out another folder). --root imports engine from another checkout (the
commit before a change measures itself with this script).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import pathlib
import subprocess
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parents[1]
GRAVITY = 9.81
FOURBAR = dict(ground=0.30, crank=0.10, coupler=0.30, rocker=0.25, crank_angle=math.radians(45.0), crank_speed=3.0)
THICKNESS = 0.01  # engine.scenes.bar's cross-section
DTS = (4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4, 1.25e-4)


def fourbar_reference(times, p=FOURBAR, rtol: float = 1e-13) -> np.ndarray:
    """Crank angle [rad] of engine.scenes.fourbar(**p) at ``times`` (from 0): bars of line density 1
    in the x-z plane turning about +y (u(phi) = (cos phi, -sin phi) in x, z), their inertia about y
    m (L^2 + t^2) / 12; M(q) q'' = sum_k J_k^T m_k (g - J'_k q') + G^T lambda with G q'' = -G' q' for
    the loop B + L2 u(phi2) = D + L3 u(phi3), from the scene's assembled start; float64, DOP853."""
    from scipy.integrate import solve_ivp

    import engine.scenes as scenes

    L = np.array([p["crank"], p["coupler"], p["rocker"]])
    start = scenes.fourbar_configuration(p["ground"], *L, p["crank_angle"], p["crank_speed"])
    mass = L.copy()
    inertia = mass * (L**2 + THICKNESS**2) / 12.0
    g = np.array([0.0, -GRAVITY])

    def rhs(_, y):
        q, v = y[:3], y[3:]
        u = [np.array([math.cos(a), -math.sin(a)]) for a in q]
        n = [np.array([-math.sin(a), -math.cos(a)]) for a in q]  # du/dphi
        J = np.zeros((3, 2, 3))  # centres of mass: crank, coupler (from B), rocker (from D)
        J[0, :, 0] = 0.5 * L[0] * n[0]
        J[1, :, 0], J[1, :, 1] = L[0] * n[0], 0.5 * L[1] * n[1]
        J[2, :, 2] = 0.5 * L[2] * n[2]
        bias = [-0.5 * L[0] * u[0] * v[0] ** 2, -L[0] * u[0] * v[0] ** 2 - 0.5 * L[1] * u[1] * v[1] ** 2,
                -0.5 * L[2] * u[2] * v[2] ** 2]  # J' q'
        M, f = np.diag(inertia), np.zeros(3)
        for k in range(3):
            M = M + mass[k] * J[k].T @ J[k]
            f += J[k].T @ (mass[k] * (g - bias[k]))
        G = np.stack([L[0] * n[0], L[1] * n[1], -L[2] * n[2]], axis=1)
        gamma = L[0] * u[0] * v[0] ** 2 + L[1] * u[1] * v[1] ** 2 - L[2] * u[2] * v[2] ** 2  # -G' q'
        K = np.block([[M, -G.T], [G, np.zeros((2, 2))]])
        return np.r_[v, np.linalg.solve(K, np.r_[f, gamma])[:3]]

    times = np.asarray(times, float)
    sol = solve_ivp(rhs, (0.0, float(times[-1])), np.r_[start["phi"], start["omega"]], method="DOP853",
                    t_eval=times, rtol=rtol, atol=rtol)
    if not sol.success:
        raise RuntimeError(f"fourbar_reference: {sol.message}")
    return sol.y[0]


def mujoco_crank(times, dt: float = 1e-5) -> np.ndarray | None:
    """The crank angle from MuJoCo C (RK4 at dt) at ``times`` (a uniform grid from 0), or None
    without mujoco."""
    try:
        import mujoco  # noqa: F401
    except ImportError:
        return None
    from benchmarks.peers import mujoco_reference
    from engine.scenes import fourbar

    spec = fourbar(**FOURBAR).spec
    record = float(times[1] - times[0])
    centres = mujoco_reference([spec], duration=float(times[-1]), record_dt=record, dt=dt)[:, 0, 0]
    offset = centres - np.asarray(spec.bodies[0].position)
    return np.arctan2(-offset[:, 2], offset[:, 0])


def crank_run(coordinates: str, dt: float, duration: float, record: float = 0.02, config=None):
    """engine.rollout of the four-bar: (crank angles, relative energy drifts) at every record
    (``config``: an engine.SolverConfig, None for the default)."""
    import engine
    from engine.scenes import fourbar
    from engine.spec import TrackedPoint

    scene = fourbar(**FOURBAR)
    spec = dataclasses.replace(scene.spec, points=list(scene.spec.points)
                               + [TrackedPoint("crank_tip", "crank", (FOURBAR["crank"], 0.0, 0.0))])
    model = engine.pack([spec], "cpu", dt=dt, coordinates=coordinates, config=config)
    every = round(record / dt)
    control = model.control() if coordinates == "maximal" else None
    trace, _ = engine.rollout(model, model.state(), control, every * round(duration / record), record_every=every)
    tip = np.asarray(trace.points)[:, 0, len(spec.points) - 1] - np.asarray(spec.bodies[0].position)
    energy = np.asarray(trace.energy)[:, 0]
    return np.arctan2(-tip[:, 2], tip[:, 0]), (energy - energy[0]) / (energy[0] - scene.potential_min)


def slopes(dts, errors, coarse: float = 1e-3) -> dict:
    """log-log slopes of error against dt: between neighbours, a least-squares fit over all and one
    over dt >= coarse (clear of float32's floor; None with fewer than two such steps)."""
    x, y = np.log(np.asarray(dts)), np.log(np.asarray(errors))
    pairs = [float((y[k] - y[k + 1]) / (x[k] - x[k + 1])) for k in range(len(x) - 1)]
    keep = np.asarray(dts) >= coarse * (1 - 1e-9)
    above = float(np.polyfit(x[keep], y[keep], 1)[0]) if keep.sum() >= 2 else None
    return {"pairwise": pairs, "fit": float(np.polyfit(x, y, 1)[0]), "fit_dt_ge_1ms": above}


def _commit(root: pathlib.Path) -> str:
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, check=True)
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dts", type=float, nargs="+", default=list(DTS))
    parser.add_argument("--duration", type=float, default=2.0)
    parser.add_argument("--plans", nargs="+", default=["maximal", "tree"])
    parser.add_argument("--root", default=str(HERE), help="the checkout whose engine is measured")
    parser.add_argument("--tag", default="cpu", help="the output files' suffix")
    parser.add_argument("--commit", default=None, help="the commit measured (default: --root's HEAD)")
    parser.add_argument("--out", default=str(HERE / "benchmarks" / "results" / "cpu"))
    parser.add_argument("--no-mujoco", action="store_true", help="skip the MuJoCo check of the reference")
    args = parser.parse_args()
    root = pathlib.Path(args.root).resolve()
    sys.path.insert(0, str(root))
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # (stdout: the JSON alone)
    times = np.arange(round(args.duration / 0.02) + 1) * 0.02
    reference = fourbar_reference(times)
    result = {"commit": args.commit or _commit(root), "duration_s": args.duration, "record_s": 0.02,
              "reference": "DOP853 float64, rtol 1e-13", "plans": {}}
    if not args.no_mujoco:
        mj = mujoco_crank(times)
        if mj is not None:
            result["reference_vs_mujoco_rk4_1e-5_rad"] = float(np.abs(mj - reference).max())
    rows = []
    for plan in args.plans:
        errors, drifts = [], []
        for dt in args.dts:
            angles, drift = crank_run(plan, dt, args.duration)
            error = float(np.abs((angles - reference + math.pi) % (2 * math.pi) - math.pi).max())
            errors.append(error)
            drifts.append(float(np.abs(drift).max()))
            rows.append({"plan": plan, "dt_s": dt, "crank_error_rad": error, "energy_drift_rel": drifts[-1],
                         "energy_drift_end_rel": float(drift[-1])})
        result["plans"][plan] = {"dt_s": list(args.dts), "crank_error_rad": errors, "energy_drift_rel": drifts,
                                 "slopes": slopes(args.dts, errors)}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"convergence_{args.tag}"
    with open(f"{stem}.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with open(f"{stem}.json", "w") as fh:
        json.dump(result, fh, indent=1)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 4.2))
        for plan, data in result["plans"].items():
            above = data["slopes"]["fit_dt_ge_1ms"]
            ax.loglog(np.array(data["dt_s"]) * 1e3, data["crank_error_rad"], "o-",
                      label=f"{plan} (slope {above if above is None else round(above, 2)} for dt >= 1 ms)")
        dts = np.array(args.dts) * 1e3
        first = result["plans"][args.plans[0]]["crank_error_rad"][0]
        ax.loglog(dts, first * (dts / dts[0]) ** 2, "k:", lw=0.8, label="slope 2")
        ax.set_xticks(dts, [f"{d:g}" for d in dts])
        ax.minorticks_off()
        ax.set_xlabel("dt [ms]")
        ax.set_ylabel("crank angle error, max over 0-2 s [rad]")
        ax.set_title(f"passive four-bar vs float64 reference ({result['commit']})", fontsize=9)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(f"{stem}.png", dpi=120)
    except ImportError:
        result["png"] = "matplotlib missing"
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
