"""What a heterogeneous batch costs against a homogeneous batch of its largest member.

    python -m benchmarks.heterogeneity --device cuda [--worlds 4096] [--caps 100 50] [--stall-ratios 0 0.5]
                                       [--free-rhos 2e-4 1e-3] [--orderings minimum_degree shallow]
                                       [--model maximal|reduced] [--registers 64 0] [--out FILE]

Random walkers (benchmarks.scenes.walkers: Jansen and Klann legs, random geometry, the maximal
model on the sparse solver) against copies of the default walker (the family's largest topology:
the same 304 factor rows and schedule as the random Jansen walkers), dt 2 ms, at each PADMM
iteration cap (SolverConfig.max_iterations), stall ratio (Tuning.stall_ratio, 0: off),
free rows' penalty (Tuning.free_rho) and the sparse factor's elimination order
(Tuning.sparse_ordering):
after --warmup chunks of 10 steps (the walkers settle), the median ms per step over 4 chunks
replayed as CUDA graphs (engine.rollout.Stepper),
the mean PADMM iterations over worlds and the largest world's at the end of each timed chunk. The
captured PADMM loop runs until the batch's slowest world stops, so the ratio follows the largest
world's iterations, not the mean. Prints one JSON line per run and writes them to --out.

--model reduced: the same designs in the coordinates engine.pack plans for them (TABULATED: the
torso and one crank angle per leg), as the walker study runs them (studies/walker.toml's dt and
[solver] settings, the cap from --caps), where each world iterates inside its own warp (a thread
above engine.reduced.tabulated_kernel.tiled_max_worlds, where a slow world holds up the 32 worlds
of its warp) instead of in a loop shared by the whole batch. It adds
a third batch, "default, phases spread": the default walker's copies with each world's cranks
turned by a random angle of its own (spread_phases). Identical copies step in lockstep, every
world the same loads and iterations at the same time, which a batch of designs never does; this
batch is the same design without that. --registers: the tiled step's register cap per thread
(Tuning.tabulated_registers; engine.reduced.tabulated_kernel.TILED_REGISTERS by default; 0: the
compiler's choice), each at every cap.
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import warp as wp


def time_chunks(advance, iterations, device, warmup: int) -> dict:
    """Run ``warmup`` chunks of 10 steps, then time four: the median ms per step, the mean
    iterations over worlds and the largest world's at the end of each timed chunk (``iterations``:
    the model's per-world iteration counts)."""
    for _ in range(warmup):
        advance()
    times, largest, mean = [], [], []
    for _ in range(4):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        advance()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t0) / 10 * 1e3)
        counts = iterations.numpy()
        largest.append(int(counts.max()))
        mean.append(float(counts.mean()))
    return {"step_ms": float(np.median(times)), "iterations_mean": float(np.mean(mean)),
            "iterations_largest_world": largest}


def run(specs, worlds: int, cap: int, device: str, warmup: int, stall_ratio: float = 0.0,
        free_rho: float | None = None, ordering: str = "minimum_degree") -> dict:
    from engine import SolverConfig, pack_worlds
    from engine.rollout import Stepper

    model = pack_worlds([specs[w % len(specs)] for w in range(worlds)], device=device, dt=2e-3,
                        config=SolverConfig(max_iterations=cap).tuned(
                            stall_ratio=stall_ratio, sparse_ordering=ordering,
                            **({} if free_rho is None else {"free_rho": free_rho})))
    stepper = Stepper(model, model.state(), model.control(), chunk=10)
    return {**time_chunks(stepper.advance, model.work.iterations, model.device, warmup),
            "patterns": len(model.sparse_system.analyses) if model.sparse_system else 0,
            "free_rho_used": float(model.padmm_rho_free.numpy()[0])}


def spread_phases(model, seed: int = 0) -> None:
    """Turn every world's cranks by one random angle of its own (its legs keep their relative
    phases), so that copies of one design no longer step in lockstep. ``model``: a packed
    TABULATED plan (engine.reduced.model.TabulatedPlanModel), whose state lives in its ``inner``
    model: call it after model.state(), which resets the state."""
    inner = model.inner
    coord = inner.coord.numpy()
    groups = inner.group_count.numpy()
    turn = np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi, size=(coord.shape[0], 1))
    used = np.arange(coord.shape[1])[None, :] < groups[:, None]  # each world's sub-chains, not the padding
    coord = np.where(used, np.mod(coord + turn, 2.0 * np.pi), coord)
    inner.coord.assign(coord.astype(np.float32))


def run_reduced(specs, worlds: int, cap: int, device: str, warmup: int, study, phases: bool = False,
                registers: int | None = None) -> dict:
    """run() in the coordinates engine.pack plans for the walkers (TABULATED: the base and one crank
    angle per leg), with the walker study's dt and solver settings (``study``); phases:
    spread_phases first; registers: Tuning.tabulated_registers (None: the plan's default, 0: the
    compiler's choice). Two chunks run before the warmup (compile, capture)."""
    import dataclasses

    import engine

    config = dataclasses.replace(study.solver_config() or engine.SolverConfig(), max_iterations=cap)
    if registers is not None:
        config = config.tuned(tabulated_registers=registers)
    model = engine.pack([specs[w % len(specs)] for w in range(worlds)], device, dt=study.dt, config=config)
    state = model.state()
    if phases:
        spread_phases(model)
    stepper = engine.Stepper(model, state, chunk=10)
    stepper.advance()  # compile
    stepper.advance()  # capture (CUDA)
    inner = model.inner
    return {**time_chunks(stepper.advance, inner.iterations, model.device, warmup), "dt": study.dt,
            "coordinates": model.plan.coordinates.value, "tiled": bool(inner.tiled),
            "max_registers": inner.max_registers, "diverged": int((model.failure_codes() != 0).sum())}


def pair(batches: dict, settings: dict, measure) -> list:
    """One row per batch (the random batch, the default's, and any other), ``settings`` plus
    ``measure(name, specs)`` each; every row but the default's carries the ratio of its time to the
    default's. Printed as they come."""
    rows = [{"batch": name, **settings, **measure(name, specs)} for name, specs in batches.items()]
    default = next(row for row in rows if row["batch"] == "default")
    for row in rows:
        if row is not default:
            row["ratio_to_default"] = row["step_ms"] / default["step_ms"]
        print(json.dumps(row), flush=True)
    return rows


def main(argv=None) -> int:
    from benchmarks.run import write_rows
    from benchmarks.scenes import walker_default, walkers
    from engine import Tuning

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--caps", type=int, nargs="+", default=[100, 50])
    parser.add_argument("--stall-ratios", type=float, nargs="+", default=None,
                        help="Tuning.stall_ratio values (0: off, the default), each at every cap; "
                             "maximal model only")
    parser.add_argument("--free-rhos", type=float, nargs="+", default=None,
                        help="Tuning.free_rho values, each at every cap and stall ratio (default: its "
                             "default; maximal model only)")
    parser.add_argument("--model", choices=["maximal", "reduced"], default="maximal",
                        help="maximal coordinates (the sparse solver) or the reduced ones engine.pack plans "
                             "(tabulated)")
    parser.add_argument("--orderings", nargs="+", choices=["minimum_degree", "shallow"], default=None,
                        help="Tuning.sparse_ordering values, each at every other setting (default: its "
                             "default; maximal model only)")
    parser.add_argument("--registers", type=int, nargs="+", default=None,
                        help="Tuning.tabulated_registers values, each at every cap (0: the compiler's choice; "
                             "default: the plan's; reduced model only)")
    parser.add_argument("--warmup", type=int, default=20, help="chunks of 10 steps before timing")
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    if args.worlds < 1 or args.warmup < 0 or min(args.caps) < 1:
        parser.error("--worlds and --caps must be >= 1, --warmup >= 0")
    if args.registers is not None and (args.model != "reduced" or min(args.registers) < 0):
        parser.error("--registers applies to the reduced model only and must be >= 0")
    if args.model == "reduced" and (args.stall_ratios is not None or args.free_rhos is not None
                                    or args.orderings is not None):
        parser.error("--stall-ratios, --free-rhos and --orderings apply to the maximal model only (the tabulated "
                     "plan has no joint rows, no stall test and no sparse factor)")
    args.orderings = [Tuning.sparse_ordering] if args.orderings is None else args.orderings
    args.stall_ratios = [0.0] if args.stall_ratios is None else args.stall_ratios
    args.free_rhos = [Tuning.free_rho] if args.free_rhos is None else args.free_rhos
    if not all(0.0 <= r < 1.0 for r in args.stall_ratios):
        parser.error("--stall-ratios must lie in [0, 1)")
    if min(args.free_rhos) <= 0.0:
        parser.error("--free-rhos must be > 0")
    wp.config.log_level = wp.LOG_WARNING
    rows = []
    if args.model == "reduced":  # the study's [solver] settings, its cap from --caps
        import pathlib

        from morphopt.study_spec import load_study_spec

        study = load_study_spec(pathlib.Path(__file__).resolve().parents[1] / "studies" / "walker.toml")
        batches = {"random": walkers().specs, "default": walker_default().specs}
        batches["default, phases spread"] = batches["default"]
        for registers in args.registers or [None]:
            for cap in args.caps:
                rows += pair(batches, {"model": "reduced", "max_iterations": cap, "num_worlds": args.worlds},
                             lambda name, specs: run_reduced(specs, args.worlds, cap, args.device, args.warmup, study,
                                                             phases=name.endswith("phases spread"),
                                                             registers=registers))
    else:
        batches = {"random": walkers().specs, "default": walker_default().specs}
        for ordering in args.orderings:
            for free_rho in args.free_rhos:
                for stall in args.stall_ratios:
                    for cap in args.caps:
                        settings = {"model": "maximal", "max_iterations": cap, "stall_ratio": stall,
                                    "free_rho": free_rho, "sparse_ordering": ordering, "num_worlds": args.worlds}
                        rows += pair(batches, settings, lambda name, specs: run(specs, args.worlds, cap, args.device,
                                                                                args.warmup, stall, free_rho,
                                                                                ordering))
    if args.out:
        write_rows(args.out, args.device, "benchmarks.heterogeneity", argv, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
