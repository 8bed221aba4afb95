"""Could a Newton finish shorten engine.legged's PADMM tail? A CPU probe on the hardest steps.

    python -m benchmarks.legged_newton_probe [--steps 30] [--skip 10] [--hardest 4] [--cap 200] [--out FILE]

The heterogeneous walkers (benchmarks.heterogeneity's 64 random designs and the default walker,
studies/walker.toml's dt and [solver] settings, the iteration cap raised to --cap) step on the CPU.
After each step past --skip, the --hardest worlds by PADMM iterations have their step's dual
problem read back from the model's scratch: the preconditioned rows J~, the mass matrix M, the
free velocity v_f~, the friction coefficients, the drive bounds and the compliance, so that
D = J~ M^-1 J~^T + diag(P^2 R); and their warm start (the last step's impulses by slot, scaled
by the preconditioner). From that warm start, a semismooth Newton method solves the natural map
F(x) = x - Pi(x - v^(x)) = 0, where v = D x + v_f~ and v^ adds the De Saxce shift mu |v_t| to each
normal row; Pi clamps drives to their bounds and projects contact triplets onto their cones. The
Jacobian is in closed form (jacobian; --jacobian difference: forward differences), in float64; a
backtracking line search keeps |F| falling.
It stops once max |F| is within the engine's tolerance at the warm start
(tolerance + relative_tolerance * max |x0|).

Per probed step it records the engine's iterations and Newton's step count, or null if Newton
did not get there in 20 steps, and, where both converged, the largest difference of the rows'
velocities D x between Newton's solution and the engine's impulses (preconditioned units). Prints
one JSON line per probed step and a summary, and writes them to --out (JSON, with a CSV and a PNG
beside it: Newton's steps against the engine's iterations).

This probes the method, not a kernel: nothing here is timed.
"""

import argparse
import csv
import dataclasses
import json
import os
import pathlib
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import warp as wp


SCRATCH = ("leg_count", "row_count", "rows", "rows_J", "mass", "slot_of", "impulse")  # what dual_problem reads


def dual_problem(scratch: dict, w: int, warm: np.ndarray) -> dict:
    """World w's last dual problem from engine.legged's scratch (``scratch``: the model's SCRATCH
    arrays as NumPy, read once after the step; preconditioned), its warm start and the engine's
    solution."""
    from engine import legged

    nv, per_row = int(legged.NV), int(legged.ROW_VECS)
    legs = int(scratch["leg_count"][w])
    n, m = 6 + legs, int(scratch["row_count"][w])
    rows = scratch["rows"][w].reshape(-1, per_row * 4)[:m].astype(float)

    def field(f):
        return rows[:, int(f)]

    J = scratch["rows_J"][w].reshape(-1, nv)[:m, :n].astype(float)
    M = scratch["mass"][w].reshape(nv, nv)[:n, :n].astype(float)
    P, R = field(legged.F_P), field(legged.F_R)
    D = J @ np.linalg.solve(M, J.T) + np.diag(P * P * R)
    slots = scratch["slot_of"][w][:m]
    return {"legs": legs, "rows": m, "D": D, "vf": field(legged.F_RHS), "mu": field(legged.F_MU),
            "lo": field(legged.F_LO), "hi": field(legged.F_HI), "x0": warm[slots] / P,
            "engine": scratch["impulse"][w][slots].astype(float) / P}


def project(p: dict, a: np.ndarray) -> np.ndarray:
    """Drives clamped to their bounds, contact triplets (normal first) projected onto their cones."""
    out = np.empty_like(a)
    legs = p["legs"]
    out[:legs] = np.clip(a[:legs], p["lo"][:legs], p["hi"][:legs])
    for r in range(legs, p["rows"], 3):
        mu, n, t = p["mu"][r], a[r], np.hypot(a[r + 1], a[r + 2])
        if t <= mu * n:
            out[r:r + 3] = a[r:r + 3]
        elif mu * t <= -n:
            out[r:r + 3] = 0.0
        else:
            normal = (n + mu * t) / (1.0 + mu * mu)
            out[r:r + 3] = (normal, mu * normal * a[r + 1] / t, mu * normal * a[r + 2] / t)
    return out


def natural_map(p: dict, x: np.ndarray) -> np.ndarray:
    """F(x) = x - Pi(x - v^), v^ the velocity D x + v_f with each normal row's De Saxce shift."""
    v = p["D"] @ x + p["vf"]
    for r in range(p["legs"], p["rows"], 3):
        v[r] += p["mu"][r] * np.hypot(v[r + 1], v[r + 2])
    return x - project(p, x - v)


def jacobian(p: dict, x: np.ndarray) -> np.ndarray:
    """An element of F's generalized Jacobian at x, in closed form: I - dPi(a) (I - dv^/dx) with
    a = x - v^, dv^/dx = D plus, on each normal row, mu (v_t . dv_t/dx) / |v_t|; dPi: 1 or 0 for a
    drive (inside or at its bounds), I, 0 or the derivative of the projection onto the cone's
    boundary, n = (a_n + mu t) / (1 + mu^2), y_t = mu n a_t / t (t = |a_t|), for a contact."""
    m, legs, D = p["rows"], p["legs"], p["D"]
    v = D @ x + p["vf"]
    dv = D.copy()
    for r in range(legs, m, 3):
        t = np.hypot(v[r + 1], v[r + 2])
        if t > 0.0:
            dv[r] += p["mu"][r] * (v[r + 1] * D[r + 1] + v[r + 2] * D[r + 2]) / t
    v_hat = v.copy()
    for r in range(legs, m, 3):
        v_hat[r] += p["mu"][r] * np.hypot(v[r + 1], v[r + 2])
    a = x - v_hat
    dpi = np.zeros((m, m))
    for i in range(legs):
        dpi[i, i] = 1.0 if p["lo"][i] < a[i] < p["hi"][i] else 0.0
    for r in range(legs, m, 3):
        mu, n, at = p["mu"][r], a[r], a[r + 1:r + 3]
        t = np.linalg.norm(at)
        if t <= mu * n:
            dpi[r:r + 3, r:r + 3] = np.eye(3)
        elif mu * t > -n:  # onto the boundary (the polar cone's points go to 0: dPi 0)
            e = at / t
            normal = (n + mu * t) / (1.0 + mu * mu)
            dn = np.r_[1.0, mu * e] / (1.0 + mu * mu)  # d normal / d (a_n, a_t)
            block = np.zeros((3, 3))
            block[0] = dn
            block[1:, :] = mu * np.outer(e, dn)
            block[1:, 1:] += mu * normal * (np.eye(2) - np.outer(e, e)) / t
            dpi[r:r + 3, r:r + 3] = block
    return np.eye(m) - dpi @ (np.eye(m) - dv)


def newton(p: dict, tol: float, max_steps: int = 20, analytic: bool = True, damping: float = 0.0):
    """Semismooth Newton from the warm start: (solution, steps) or (None, max_steps). analytic: the
    closed-form Jacobian (jacobian), else forward differences. damping > 0: each step solves
    (J^T J + damping |J|^2 I) dx = -J^T F by Cholesky (what a kernel would factor: symmetric
    positive definite however singular J is), else by least squares."""
    x = p["x0"].copy()
    f = natural_map(p, x)
    if np.abs(f).max() < tol:
        return x, 0
    for step in range(1, max_steps + 1):
        if analytic:
            jac = jacobian(p, x)
        else:
            jac = np.empty((len(x), len(x)))
            for j in range(len(x)):
                e = np.zeros(len(x))
                e[j] = 1e-7
                jac[:, j] = (natural_map(p, x + e) - f) / 1e-7
        if damping > 0.0:
            normal = jac.T @ jac
            normal[np.diag_indices_from(normal)] += damping * np.abs(jac).max() ** 2
            dx = -np.linalg.solve(normal, jac.T @ f)
        else:
            dx = np.linalg.lstsq(jac, -f, rcond=None)[0]
        size, t = np.abs(f).max(), 1.0
        while True:
            x_new = x + t * dx
            f_new = natural_map(p, x_new)
            if np.abs(f_new).max() < (1.0 - 1e-4 * t) * size or t < 1e-3:
                break
            t *= 0.5
        x, f = x_new, f_new
        if np.abs(f).max() < tol:
            return x, step
    return None, max_steps


def probe(steps: int, skip: int, hardest: int, cap: int, designs: int | None = None, analytic: bool = True,
          damping: float = 0.0) -> list:
    from benchmarks.heterogeneity import reduced_batches
    from engine import SolverConfig
    from engine.legged import legged_step_batch, pack_legged
    from morphopt.study_spec import load_study_spec

    study = load_study_spec(pathlib.Path(__file__).resolve().parent.parent / "studies" / "walker.toml")
    batches = reduced_batches()
    specs = batches["random"][:designs] + batches["default"]
    config = dataclasses.replace(study.solver_config() or SolverConfig(), max_iterations=cap)
    model = pack_legged(specs, device="cpu", dt=study.dt, config=config)
    rows = []
    for step in range(steps):
        warm = model.impulse.numpy().astype(float)
        legged_step_batch(model, 1)
        if step < skip:
            continue
        iterations = model.iterations.numpy()
        scratch = {name: getattr(model, name).numpy() for name in SCRATCH}
        for w in np.argsort(iterations, kind="stable")[::-1][:hardest]:
            p = dual_problem(scratch, int(w), warm[int(w)])
            tol = config.tolerance + config.relative_tolerance * float(np.abs(p["x0"]).max())
            solution, count = newton(p, tol, analytic=analytic, damping=damping)
            both = solution is not None and iterations[w] < cap  # the engine converged too: compare the velocities
            row = {"step": step, "world": int(w), "rows": p["rows"], "engine_iterations": int(iterations[w]),
                   "newton_steps": None if solution is None else count, "tolerance": tol,
                   "residual": None if solution is None else float(np.abs(natural_map(p, solution)).max()),
                   "velocity_gap": float(np.abs(p["D"] @ (solution - p["engine"])).max()) if both else None}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def summary(rows: list) -> dict:
    done = [r["newton_steps"] for r in rows if r["newton_steps"] is not None]
    return {"probed_steps": len(rows), "newton_converged": len(done),
            "newton_steps_median": float(np.median(done)) if done else None,
            "newton_steps_max": max(done) if done else None,
            "engine_iterations_median": float(np.median([r["engine_iterations"] for r in rows])) if rows else None}


def plot(rows: list, path: pathlib.Path) -> None:
    """Newton's steps against the engine's PADMM iterations, one point per probed step (Newton's
    failures at the top, at 21)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 4.0))
    engine = [r["engine_iterations"] for r in rows]
    steps = [21 if r["newton_steps"] is None else r["newton_steps"] for r in rows]
    ax.scatter(engine, steps, s=12)
    ax.axhline(20.5, color="C3", lw=0.8, ls="--")
    ax.set_xlabel("engine.legged PADMM iterations of the step")
    ax.set_ylabel("Newton steps from the warm start (21: none)")
    ax.set_title("the heterogeneous walkers' hardest steps (CPU probe)", fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    from benchmarks.run import write_rows

    parser = argparse.ArgumentParser(prog="python -m benchmarks.legged_newton_probe", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=30, help="steps of the batch")
    parser.add_argument("--skip", type=int, default=10, help="steps before the probed ones (the walkers settle)")
    parser.add_argument("--hardest", type=int, default=4, help="worlds probed per step, most iterations first")
    parser.add_argument("--cap", type=int, default=200, help="the engine's PADMM iteration cap")
    parser.add_argument("--designs", type=int, default=None, help="random designs in the batch (default all 64)")
    parser.add_argument("--jacobian", choices=["analytic", "difference"], default="analytic",
                        help="Newton's Jacobian: closed form (default) or forward differences")
    parser.add_argument("--damping", type=float, default=0.0,
                        help="> 0: Newton's steps from the damped normal equations (see newton), else least squares")
    parser.add_argument("--out", default=None, help="JSON file (a CSV beside it)")
    args = parser.parse_args(argv)
    if args.steps <= args.skip or args.skip < 0 or args.hardest < 1 or args.cap < 1:
        parser.error("--steps must exceed --skip >= 0; --hardest and --cap must be >= 1")
    if args.designs is not None and args.designs < 1:
        parser.error("--designs must be >= 1")
    wp.config.quiet = True
    wp.init()
    if args.damping < 0:
        parser.error("--damping must be >= 0")
    rows = probe(args.steps, args.skip, args.hardest, args.cap, args.designs, args.jacobian == "analytic",
                 args.damping)
    total = summary(rows)
    print(json.dumps({"summary": total}), flush=True)
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_rows(out, "cpu", "benchmarks.legged_newton_probe", argv, rows + [{"summary": total}])
        with open(out.with_suffix(".csv"), "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["step"])
            writer.writeheader()
            writer.writerows(rows)
        plot(rows, out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
