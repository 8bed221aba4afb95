"""The engine benchmark: throughput against batch size and run time against error, per scene, with
MuJoCo Warp on the same mechanisms in the same run (--peers).

    python -m benchmarks.run --device cuda [--peers] [--only fourbar mixed] [--out DIR]
    python -m benchmarks.run --device cpu --quick

Scenes and settings are data (benchmarks/scenes.py). Per scene:
- throughput: world-steps/s at each batch size of the scene (default solver settings, engine.pack's
  automatic plan: rows labelled "default"; where that plan is not maximal coordinates, the same in
  maximal coordinates beside them: "maximal", what earlier runs' "default" rows measured), CUDA graphs
  of 10 steps (engine.Stepper), median time per step after the compile and capture chunks;
  memory: the engine's arrays (model, workspace, states) and, on CUDA, the growth of Warp's memory
  pool over the run (graphs and scratch included; the peers' the same way); the scene's variants
  (other settings; maximal coordinates unless they name others) at its largest batch;
- work-precision (linkage scenes, DR Legs): each setting of the sweep (dt, step kernel, linear solver,
  tolerance, stabilization, integrator; maximal coordinates unless it names others, e.g. "reduced
  coordinates") simulates the scene's duration on the precision batch;
  errors: largest loop-closure violation [m] over all worlds and records, energy drift
  |E(t) - E(0)| / (E(0) - E_min) (passive scenes), and trajectory error: largest distance [m] of a
  body's centre of mass from the reference at records every Declared.record_dt (40 ms; quick:
  about 10 ms), which every step size must divide; the reference is MuJoCo C
  (float64, RK4 at dt / 20, the MJCF export) when installed, else our engine at dt / 10 with
  tolerance 1e-9 and 4 projections; run time as wall seconds per simulated second of the batch;
- peers (--peers): MuJoCo Warp (benchmarks/peers.py, from our MJCF export) with the same errors
  measured the same way; on scenes read from a USD file (DR Legs) Newton's SolverKamino and
  SolverMuJoCo on Newton's own import of the same file (benchmarks/peers_newton.py), in the
  work-precision sweep at the scene's peer step sizes, bodies matched to ours by name.
Writes <out>/<scene>.json (device, versions, command, every configuration), <scene>.csv and
<scene>.png (throughput and work-precision, ours and the peers' on the same axes); prints one JSON
line per configuration. --quick: small batches and short runs (CPU, CI).
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib
import platform
import re
import shlex
import sys
import time

import numpy as np
import warp as wp

from benchmarks.scenes import SCENES_DECLARED, Declared, steps_per_record
import engine
from engine import Coordinates, SolverConfig, compute_metrics

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def device_tag(device: str) -> str:
    """Folder name of a device's results: cpu, h100, h200 (else the GPU name, simplified)."""
    dev = wp.get_device(device)
    if not dev.is_cuda:
        return "cpu"
    name = dev.name.lower()
    for tag in ("h100", "h200", "b200", "a100", "l40s"):
        if tag in name:
            return tag
    return "".join(c if c.isalnum() else "_" for c in name)


def versions() -> dict:
    return {"warp": wp.config.version, "numpy": np.__version__, "python": platform.python_version()}


def write_rows(path, device: str, module: str, argv, rows: list, key: str = "results") -> None:
    """A benchmark script's rows as JSON at ``path``, with the device, the versions and the command
    (python -m ``module`` and its arguments: ``argv``, or the process's when None)."""
    device = wp.get_device(device)
    command = f"python -m {module} " + shlex.join(argv if argv is not None else sys.argv[1:])
    with open(path, "w") as f:
        json.dump({"device": str(device), "device_name": device.name, "versions": versions(), "command": command,
                   key: rows}, f, indent=1)


def array_megabytes(*objects) -> float:
    """Megabytes held by the Warp arrays that are attributes of ``objects`` (one level of nested
    objects and dataclasses, e.g. Model.work and the sparse patterns), each array counted once."""
    seen, total = set(), 0

    def visit(obj, depth):
        nonlocal total
        for value in vars(obj).values() if hasattr(obj, "__dict__") else ():
            if isinstance(value, wp.array):
                if id(value) not in seen:
                    seen.add(id(value))
                    total += value.capacity
            elif depth > 0 and hasattr(value, "__dict__") and not isinstance(value, type):
                visit(value, depth - 1)

    for obj in objects:
        visit(obj, 2)
    return total / 2**20


def mempool_megabytes(device: str) -> float | None:
    """Device memory in use from Warp's CUDA memory pool [MB] once the device is idle (None on the
    CPU); the peers measure theirs with it too."""
    dev = wp.get_device(device)
    if not dev.is_cuda or not wp.is_mempool_enabled(dev):
        return None
    wp.synchronize_device(dev)
    return wp.get_mempool_used_mem_current(dev) / 2**20


def engine_run(specs, worlds: int, dt: float, steps: int, record_every: int, config: SolverConfig, device: str,
               sample: np.ndarray, potential_min=None, coordinates="maximal", pack: dict | None = None,
               ground_only: bool = False) -> dict:
    """Simulate ``worlds`` worlds (cycling through ``specs``) packed by engine.pack in ``coordinates``
    (None: its automatic plan; "maximal", "tree" or "tabulated" forced; ``pack``: its other options,
    e.g. contact_capacity; ground_only: the specs through benchmarks.scenes.ground_contacts_only) and
    stepped by engine.Stepper; time every chunk of ``record_every`` steps after the first two
    (compile, capture); record errors and sample positions per chunk. A reduced plan's loop errors
    and energy are measured by its gauge (a maximal model of the same worlds: engine.metrics on its
    body poses), its PADMM iteration and projection counts are those of the last step of each chunk."""
    from benchmarks.scenes import ground_contacts_only

    batch = [specs[w % len(specs)] for w in range(worlds)]
    if ground_only:
        batch = [ground_contacts_only(spec) for spec in batch]
    pool_before = mempool_megabytes(device)
    t0 = time.perf_counter()
    model = engine.pack(batch, device, config=config, dt=dt, coordinates=coordinates, **(pack or {}))
    pack_s = time.perf_counter() - t0
    kind = model.plan.coordinates
    gauge_mb = 0.0
    if kind is not Coordinates.MAXIMAL:  # built now, its memory left out of the run's (it only measures)
        pool_packed = mempool_megabytes(device)
        gauge = model.gauge
        gauge_mb = 0.0 if pool_packed is None else mempool_megabytes(device) - pool_packed
    else:
        gauge = model
    stepper = engine.Stepper(model, model.state(), chunk=record_every)
    inner = getattr(model, "inner", None)
    iterations, dropped, projections = [], [], []

    def measure():
        compute_metrics(gauge, stepper.state)
        work = gauge.work
        if kind is Coordinates.MAXIMAL:
            diverged = work.diverged.numpy().astype(bool)
        else:
            iterations.append(model.iterations())
            diverged = model.failure_codes() != 0
        if kind is Coordinates.TREE:
            projections.append(inner.work.projections.numpy())
            dropped.append(int(inner.work.contact_dropped.numpy().max()))
        return work.violation_linear.numpy(), work.violation_angular.numpy(), work.energy.numpy(), diverged

    row = timed_chunks(stepper, measure, dt, steps, record_every, device, sample, potential_min)
    pool_after = mempool_megabytes(device)
    row.update(pack_s=pack_s, coordinates=kind.value, cuda_graph=bool(stepper.capture),
               device_memory_mb=None if pool_before is None else pool_after - pool_before - gauge_mb)
    if kind is Coordinates.MAXIMAL:
        solved = np.maximum(stepper.solved_steps.numpy(), 1)
        row.update(padmm_iterations_mean=float((stepper.iteration_sum.numpy() / solved).mean()),
                   padmm_iterations_max=int(stepper.iteration_max.numpy().max()),
                   unconverged_step_fraction=float((stepper.unconverged_steps.numpy() / solved).mean()),
                   step_kernel=model.step_kernel, linear_solver=model.linear_solver, max_rows=model.max_rows,
                   fused_block=model.fused_block,
                   engine_arrays_mb=array_megabytes(model, model.work, stepper, *stepper._buffers))
        return row
    counts = np.array(iterations[1:] or iterations)
    row.update(padmm_iterations_mean=float(counts.mean()), padmm_iterations_max=int(counts.max()),
               step_kernel=kind.value, fused_block=None, engine_arrays_mb=array_megabytes(inner, stepper.state.inner))
    if kind is Coordinates.TREE:  # PADMM runs on contact rows only: a capped share where there are contacts
        capped = float((counts >= config.max_iterations).mean()) if inner.tile_contacts else 0.0
        row.update(unconverged_step_fraction=capped, contacts_dropped_max=max(dropped),
                   projections_mean=float(np.mean(projections[1:] or projections)),
                   contact_capacity=inner.contact_capacity, contact_working=inner.contact_working,
                   # the share of world-steps the full-capacity kernel took over (more contacts than the first holds)
                   contact_redone_share=float(inner.work.contact_redone.numpy().sum()) / (worlds * row["steps"]),
                   linear_solver="dense (reduced coordinates)", max_rows=inner.max_rows)
    else:
        row.update(unconverged_step_fraction=float((counts >= config.max_iterations).mean()),
                   linear_solver=model.plan.linear_solver, max_rows=None)
    return row


def timed_chunks(stepper, measure, dt: float, steps: int, record_every: int, device: str, sample: np.ndarray,
                 potential_min=None) -> dict:
    """The runs' common loop: ``stepper.advance()`` (a chunk of ``record_every`` steps) timed between
    device synchronizations until ``steps``, the median over the chunks after the first two (compile,
    capture); after each chunk ``measure()`` -> per world (loop error [m], [rad], energy [J],
    diverged) gives the largest loop errors and energy drift over the worlds that did not diverge,
    and the sample worlds' body positions are recorded."""
    _, _, energy0, diverged = measure()
    energy0 = energy0.copy()
    worlds = len(energy0)
    available = None
    if potential_min is not None:
        pmin = np.array([potential_min[w % len(potential_min)] for w in range(worlds)])
        available = np.maximum(energy0 - pmin, 1e-12)
    positions = [stepper.state.body_q.numpy()[sample, :, :3].copy()]
    times, loop_m, loop_rad, drift, done = [], 0.0, 0.0, 0.0, 0
    t_first = time.perf_counter()
    while done < steps:
        wp.synchronize_device(device)
        t = time.perf_counter()
        stepper.advance()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t) / record_every)
        done += record_every
        lin, ang, energy, diverged = measure()
        ok = ~diverged
        if ok.any():
            loop_m = max(loop_m, float(lin[ok].max()))
            loop_rad = max(loop_rad, float(ang[ok].max()))
            if available is not None:
                drift = max(drift, float((np.abs(energy - energy0) / available)[ok].max()))
        positions.append(stepper.state.body_q.numpy()[sample, :, :3].copy())
    timed = times[2:] if len(times) > 2 else times
    step_s = float(np.median(timed))
    return {
        "num_worlds": worlds, "dt": dt, "steps": done, "step_ms_median": step_s * 1e3,
        "world_steps_per_s": worlds / step_s, "wall_s_per_simulated_s": step_s / dt,
        "first_chunks_s": [round(x * record_every, 4) for x in times[:2]],
        "loop_error_m": loop_m, "loop_error_rad": loop_rad,
        "energy_drift_rel": drift if available is not None else None,
        "diverged_worlds": int(diverged.sum()),
        "positions": np.array(positions), "run_s": time.perf_counter() - t_first,
    }


def trajectory_error(positions: np.ndarray, reference: np.ndarray, sample: np.ndarray, specs) -> float:
    """Largest body-position distance [m] between a run's sample worlds and the reference worlds
    of the same mechanisms, over the common records."""
    records = min(len(positions), len(reference))
    worst = 0.0
    for k, w in enumerate(sample):
        kind = w % len(specs)
        n = len(specs[kind].bodies)
        diff = positions[:records, k, :n] - reference[:records, kind, :n]
        worst = max(worst, float(np.linalg.norm(diff, axis=-1).max()))
    return worst


def peer_trajectory_error(positions: np.ndarray, reference: np.ndarray, bodies: int) -> float:
    """Largest body-position distance [m] between a peer's recorded worlds (records, worlds, bodies,
    3), all of the scene's first mechanism, and the reference's, over the common records."""
    records = min(len(positions), len(reference))
    return float(np.linalg.norm(positions[:records, :, :bodies] - reference[:records, :1, :bodies], axis=-1).max())


def clean(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in ("positions", "energy")}


def placement(setting: dict) -> dict:
    """engine_run's coordinates, pack and ground_only of a declared variant or sweep point (benchmarks.scenes:
    maximal coordinates unless it names others)."""
    return {"coordinates": setting.get("coordinates", "maximal"), "pack": setting.get("pack"),
            "ground_only": setting.get("ground_only", False)}


def run_scene(name: str, declared: Declared, args) -> dict:
    scene = declared.build(args.assets)
    specs = scene.specs
    quick = args.quick
    result = {"scene": name, "note": scene.note, "device": args.device, "device_name": wp.get_device(args.device).name,
              "versions": versions(), "command": "python -m benchmarks.run " + shlex.join(sys.argv[1:]),
              "bodies": [len(s.bodies) for s in specs], "joints": [len(s.joints) for s in specs],
              "throughput": [], "precision": [], "peers": [], "reference": None}
    dt = declared.dt
    worlds_list = declared.quick_worlds if quick else declared.throughput_worlds
    if getattr(args, "worlds", None):  # the batch sizes asked for (variants at the largest, peers at each)
        worlds_list = sorted(args.worlds)
    steps = 20 if quick else declared.throughput_steps
    chunk = 10 if steps >= 30 else max(1, steps // 4)
    for worlds in (worlds_list if "throughput" in args.parts else []):
        sample = np.arange(min(worlds, len(specs)))
        # "default": engine.pack's automatic plan; "maximal" beside it where that plan is another (the label
        # earlier runs' "default" rows compare with)
        for label, coordinates in (("default", None), ("maximal", "maximal")):
            row = engine_run(specs, worlds, dt, steps + 2 * chunk, chunk, SolverConfig(), args.device, sample,
                             scene.potential_min, coordinates)
            row.update(kind="throughput", engine="morphopt", label=label)
            result["throughput"].append(clean(row))
            print(json.dumps({"scene": name, **clean(row)}), flush=True)
            if row["coordinates"] == "maximal":
                break
    chosen = getattr(args, "settings", None)

    def picked(settings: list) -> list:
        return [s for s in settings if not chosen or s["label"] in chosen]

    for variant in (picked(declared.variants) if "throughput" in args.parts and worlds_list else []):
        worlds = worlds_list[-1]
        try:
            row = engine_run(specs, worlds, dt, steps + 2 * chunk, chunk, SolverConfig(**variant["config"]),
                             args.device, np.arange(min(worlds, len(specs))), scene.potential_min, **placement(variant))
        except ValueError as exc:  # e.g. coordinates this scene's mechanisms do not fit
            result["throughput"].append({"label": variant["label"], "error": str(exc)})
            continue
        row.update(kind="throughput", engine="morphopt", label=variant["label"], settings=variant["config"])
        result["throughput"].append(clean(row))
        print(json.dumps({"scene": name, **clean(row)}), flush=True)
    peer_reason = None
    if args.peers and declared.peers:
        from benchmarks.peers import available
        peer_reason = available()
    if declared.duration > 0 and "precision" in args.parts:
        duration = 0.2 if quick else declared.duration
        record_dt = record_interval(declared, quick)
        worlds = 8 if quick else declared.precision_worlds
        sample = np.arange(min(worlds, 2 * len(specs)))
        reference = None  # a scene without a trustworthy reference reports loop error and run time only
        if declared.reference is not None:
            reference, result["reference"] = reference_run(specs, scene, duration, record_dt, dt, declared, args)
        sweep = picked(declared.sweep)[:5] if quick else picked(declared.sweep)
        for setting in sweep:
            step_dt = dt * setting["dt_scale"]
            every = steps_per_record(record_dt, step_dt)  # a misaligned record interval is the runner's fault
            try:
                config = SolverConfig(**setting.get("config", {}))
                row = engine_run(specs, worlds, step_dt, round(duration / step_dt), every, config, args.device,
                                 sample, scene.potential_min, **placement(setting))
            except ValueError as exc:  # e.g. a setting this batch cannot take
                result["precision"].append({"label": setting["label"], "error": str(exc)})
                continue
            row.update(kind="precision", engine="morphopt", label=setting["label"], settings=setting.get("config", {}),
                       trajectory_error_m=None if reference is None else trajectory_error(row["positions"], reference,
                                                                                           sample, specs))
            result["precision"].append(clean(row))
            print(json.dumps({"scene": name, **clean(row)}), flush=True)
        if args.peers and declared.peers and scene.usd is not None:
            result["peers"] += newton_precision(scene, worlds, dt, duration, record_dt, reference, declared, args)
        elif args.peers and declared.peers and peer_reason is None:
            result["peers"] += peer_precision(specs, scene, worlds, dt, duration, record_dt, reference, args)
    if args.peers and declared.peers and "throughput" in args.parts:
        # the peers at every batch size asked for (--worlds), else at the scene's two largest
        peer_worlds = worlds_list if getattr(args, "worlds", None) else worlds_list[-2:]
        if scene.usd is not None:
            result["peers"] += newton_throughput(scene, peer_worlds, dt, steps, args)
        elif peer_reason is not None:
            result["peers"].append({"engine": "mujoco_warp", "error": peer_reason})
        else:
            result["peers"] += peer_throughput(specs, peer_worlds, dt, steps, args)
    return result


def newton_throughput(scene, worlds_list, dt, steps, args) -> list:
    """Kamino and MuJoCo Warp through Newton on a scene read from a USD file, Newton loading the
    same file (benchmarks/peers_newton.py)."""
    from benchmarks.peers_newton import available, joint_parameters, newton_drlegs_run

    reason = available()
    if reason is not None:
        return [{"engine": engine, "error": reason} for engine in ("kamino", "mujoco_warp")]
    joints = joint_parameters(scene.specs[0])
    rows = []
    for solver, label in (("mujoco", "MuJoCo Warp (Newton)"), ("kamino", "Kamino (Newton)")):
        if solver not in args.peer_solvers:
            continue
        for worlds in worlds_list:
            try:
                row = newton_drlegs_run(scene.usd, standing=scene.standing, solver=solver, worlds=worlds, dt=dt,
                                        steps=steps, record_every=10, device=args.device, joints=joints)
            except Exception as exc:  # noqa: BLE001  (a peer failing is a result, not a crash of the benchmark)
                row = {"engine": "kamino" if solver == "kamino" else "mujoco_warp", "num_worlds": worlds,
                       "error": repr(exc)}
            row.update(kind="throughput", label=label)
            rows.append(row)
            print(json.dumps(row, default=str), flush=True)
    return rows


def newton_precision(scene, worlds, dt, duration, record_dt, reference, declared, args) -> list:
    """Work-precision points of the Newton peers on a scene read from a USD file: each peer at the
    step sizes of declared.peer_dt_scales, the same duration, records and batch as our sweep, the
    trajectory error against the same reference (world 0's bodies matched to ours by name)."""
    from benchmarks.peers_newton import available, joint_parameters, newton_drlegs_run

    reason = available()
    if reason is not None:
        return [{"engine": engine, "kind": "precision", "error": reason} for engine in ("kamino", "mujoco_warp")]
    spec = scene.specs[0]
    names = [b.name for b in spec.bodies]
    joints = joint_parameters(spec)
    rows = []
    for solver, scales in declared.peer_dt_scales.items():
        if solver not in args.peer_solvers:
            continue
        label = "MuJoCo Warp" if solver == "mujoco" else "Kamino"
        for scale in scales:
            step_dt = dt * scale
            try:
                row = newton_drlegs_run(scene.usd, standing=scene.standing, solver=solver, worlds=worlds, dt=step_dt,
                                        steps=round(duration / step_dt),
                                        record_every=steps_per_record(record_dt, step_dt),
                                        device=args.device, joints=joints, record_bodies=names)
            except Exception as exc:  # noqa: BLE001  (a peer failing is a result, not a crash of the benchmark)
                rows.append({"engine": "kamino" if solver == "kamino" else "mujoco_warp", "kind": "precision",
                             "label": f"{label}, dt x{scale:g}", "dt": step_dt, "error": repr(exc)})
                print(json.dumps(rows[-1]), flush=True)
                continue
            traj = None
            if reference is not None and row.get("finite", True):
                traj = peer_trajectory_error(row["positions"], reference, len(names))
            row.update(kind="precision", label=f"{label}, dt x{scale:g}", trajectory_error_m=traj)
            rows.append(clean(row))
            print(json.dumps(clean(row), default=str), flush=True)
    return rows


def reference_run(specs, scene, duration, record_dt, dt, declared, args):
    """Body positions of every distinct mechanism at the record times, from MuJoCo C (float64, RK4,
    dt / 20) when it is installed, else from our engine at dt / 10 with tight tolerances (float32:
    its rounding limits how small an error it can resolve)."""
    try:
        from benchmarks.peers import mujoco_reference

        t0 = time.perf_counter()
        positions = mujoco_reference(specs, duration=duration, record_dt=record_dt, dt=dt / 20)
        return positions, {"engine": "mujoco C (float64)", "integrator": "RK4", "dt": dt / 20,
                           "loops": "MJCF export equality constraints, time constant 2 dt",
                           "run_s": time.perf_counter() - t0}
    except ImportError:
        ref_dt = dt / 10
        ref = declared.reference
        row = engine_run(specs, len(specs), ref_dt, round(duration / ref_dt), steps_per_record(record_dt, ref_dt),
                         SolverConfig(**ref["config"]), args.device, np.arange(len(specs)), scene.potential_min)
        return row["positions"], {**clean(row), "engine": "morphopt (float32)", "settings": ref["config"]}


def record_interval(declared: Declared, quick: bool) -> float:
    """Seconds between the records of a scene's precision runs: Declared.record_dt, or with --quick
    about 10 ms on a multiple of the longest step of the quick sweep (its first five settings; the
    step sizes are dt times powers of two, so the others divide it too)."""
    if not quick:
        return declared.record_dt
    longest = declared.dt * max(x["dt_scale"] for x in declared.sweep[:5])
    return longest * max(1, round(0.01 / longest))


# MuJoCo Warp's work-precision points on scenes built from our MJCF export: integrator, multiple of dt
MUJOCO_WARP_POINTS = (("Euler", 0.5), ("Euler", 1.0), ("Euler", 2.0), ("Euler", 4.0), ("RK4", 1.0), ("RK4", 2.0),
                      ("RK4", 4.0))


def peer_precision(specs, scene, worlds, dt, duration, record_dt, reference, args) -> list:
    from benchmarks.peers import mujoco_warp_run

    rows = []
    spec = specs[0]
    names = [b.name for b in spec.bodies]
    for integrator, scale in MUJOCO_WARP_POINTS:
        step_dt = dt * scale
        try:
            row = mujoco_warp_run(spec, worlds=worlds, dt=step_dt, steps=round(duration / step_dt),
                                  record_every=steps_per_record(record_dt, step_dt), integrator=integrator,
                                  device=args.device, body_names=names)
        except Exception as exc:  # noqa: BLE001  (a peer failing is a result, not a crash of the benchmark)
            rows.append({"engine": "mujoco_warp", "integrator": integrator, "dt": step_dt, "error": repr(exc)})
            continue
        energy = row["energy"]
        drift = None
        if scene.potential_min is not None:
            available = np.maximum(energy[0] - scene.potential_min[0], 1e-12)
            drift = float((np.abs(energy - energy[0]) / available).max())
        traj = peer_trajectory_error(row["positions"], reference, len(names))
        row.update(kind="precision", label=f"MuJoCo Warp {integrator}, dt x{scale:g}", energy_drift_rel=drift,
                   trajectory_error_m=traj, wall_s_per_simulated_s=row["step_ms_median"] * 1e-3 / step_dt)
        rows.append(clean(row))
        print(json.dumps(clean(row)), flush=True)
    return rows


def peer_throughput(specs, worlds_list, dt, steps, args) -> list:
    from benchmarks.peers import mujoco_warp_run

    rows = []
    spec = specs[0]
    integrator = "Euler" if not spec.shapes and not any(j.drive for j in spec.joints) else "implicitfast"
    for worlds in worlds_list:
        try:
            row = mujoco_warp_run(spec, worlds=worlds, dt=dt, steps=steps, record_every=10, integrator=integrator,
                                  device=args.device, body_names=[b.name for b in spec.bodies])
        except Exception as exc:  # noqa: BLE001
            rows.append({"engine": "mujoco_warp", "integrator": integrator, "num_worlds": worlds, "error": repr(exc)})
            continue
        row.update(kind="throughput", label=f"MuJoCo Warp {integrator}")
        rows.append(clean(row))
        print(json.dumps(clean(row)), flush=True)
    return rows


CSV_FIELDS = ["kind", "engine", "label", "coordinates", "integrator", "num_worlds", "dt", "steps", "step_ms_median",
              "device_memory_mb", "engine_arrays_mb",
              "world_steps_per_s", "wall_s_per_simulated_s", "loop_error_m", "loop_error_rad", "energy_drift_rel",
              "trajectory_error_m", "padmm_iterations_mean", "padmm_iterations_max", "step_kernel", "linear_solver",
              "max_rows", "diverged_worlds", "error"]


def write(result: dict, out: pathlib.Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    name = result["scene"]
    (out / f"{name}.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    rows = result["throughput"] + result["precision"] + result["peers"]
    with open(out / f"{name}.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({"engine": "morphopt", **row})
    plot(result, out / f"{name}.png")


def _throughput_panel(ax, result: dict, ours: list, variants: list, maximal: list = ()) -> None:
    ax.loglog([r["num_worlds"] for r in ours], [r["world_steps_per_s"] for r in ours], "o-", label="morphopt")
    if maximal:  # the default settings in maximal coordinates, where the automatic plan is another
        ax.loglog([r["num_worlds"] for r in maximal], [r["world_steps_per_s"] for r in maximal], "o:", color="C0",
                  alpha=0.6, label="morphopt, maximal")
    for k, r in enumerate(variants):
        ax.loglog([r["num_worlds"]], [r["world_steps_per_s"]], "^", color=f"C{k + 3}", label=f"morphopt, {r['label']}")
    for j, label in enumerate(sorted({r["label"] for r in result["peers"] if r.get("kind") == "throughput"})):
        rows = [r for r in result["peers"] if r.get("kind") == "throughput" and r.get("label") == label]
        ax.loglog([r["num_worlds"] for r in rows], [r["world_steps_per_s"] for r in rows], "s--", color=f"C{j + 1}",
                  label=label)
    ax.set_xlabel("worlds")
    ax.set_ylabel("world-steps / s")
    ax.set_title(f"{result['scene']}: throughput")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)


def _series(label: str) -> str:
    """The setting a work-precision point belongs to, its step size left out: "dt x2" and "default"
    are the maximal plan's, "reduced coordinates, dt x4" the reduced one's, "MuJoCo Warp Euler, dt
    x2" MuJoCo Warp's Euler."""
    base = re.sub(r",? *dt x[0-9.]+$", "", label).strip()
    return "maximal" if base in ("", "default") else base


def plot(result: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    peer_rows = [r for r in result["peers"] if r.get("kind") == "throughput" and "error" not in r]
    ours = [r for r in result["throughput"] if "error" not in r and r.get("label", "default") == "default"]
    maximal = [r for r in result["throughput"] if "error" not in r and r.get("label") == "maximal"]
    variants = [r for r in result["throughput"] if "error" not in r
                and r.get("label", "default") not in ("default", "maximal")]
    # the throughput panel only where there are throughput rows (a --parts precision run has none);
    # a work-precision panel per error that some row has (no trajectory error without a reference)
    throughput_panel = bool(ours or peer_rows or not result["precision"])
    measured = result["precision"] + [r for r in result["peers"] if r.get("kind") == "precision"]
    errors = [(key, unit) for key, unit in (("trajectory_error_m", "trajectory error [m]"),
                                            ("loop_error_m", "loop-closure error [m]"))
              if any(r.get(key) is not None for r in measured)]
    panels = int(throughput_panel) + (len(errors) if result["precision"] else (1 if peer_rows else 0))
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 4.0), squeeze=False)
    axes = list(axes[0])
    if throughput_panel:
        _throughput_panel(axes.pop(0), result, ours, variants, maximal)
    if not result["precision"] and peer_rows:  # time per step against loop error, each engine's batches
        ax = axes[0]
        # the colours and markers of the throughput panel: peers C1, C2 ... squares, variants triangles
        peer_labels = sorted({r["label"] for r in peer_rows})
        engines = ([("morphopt", ours, "o", "C0")] + ([("morphopt, maximal", maximal, "x", "C0")] if maximal else [])
                   + [(label, [r for r in peer_rows if r.get("label") == label], "s", f"C{j + 1}")
                      for j, label in enumerate(peer_labels)]
                   + [(f"morphopt, {r['label']}", [r], "^", f"C{k + 3}") for k, r in enumerate(variants)])
        for label, rows, marker, color in engines:
            rows = [r for r in rows if r.get("loop_error_m") is not None]
            ax.loglog([r["step_ms_median"] for r in rows], [max(r["loop_error_m"], 1e-9) for r in rows],
                      marker, color=color, label=label)
            for r in rows:
                ax.annotate(f"{r['num_worlds']}", (r["step_ms_median"], max(r["loop_error_m"], 1e-9)), fontsize=6)
        ax.set_xlabel("ms per step (labels: worlds)")
        ax.set_ylabel("loop-closure error [m]")
        ax.set_title(f"{result['scene']}: error against time per step", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    if result["precision"]:
        peer_precision_rows = [r for r in result["peers"] if r.get("kind") == "precision"]
        groups = [("morphopt", result["precision"], "o", "C0")] + [
            (name, [r for r in peer_precision_rows if str(r.get("engine", "")).startswith(engine)], "s", color)
            for engine, name, color in (("mujoco_warp", "MuJoCo Warp", "C1"), ("kamino", "Kamino", "C2"))]
        line_colors = iter(f"C{k}" for k in range(3, 10))
        series_color = {}
        for ax, (key, unit) in zip(axes, errors):
            for name, rows, marker, color in groups:
                rows = [r for r in rows if "error" not in r and r.get(key) is not None]
                for k, r in enumerate(rows):
                    ax.loglog(r["wall_s_per_simulated_s"], max(r[key], 1e-9), marker, color=color,
                              label=name if k == 0 else None)
                    ax.annotate(r["label"], (r["wall_s_per_simulated_s"], max(r[key], 1e-9)), fontsize=6)
                # a line through each step-size sweep of one setting (maximal, reduced coordinates, a peer's
                # integrator): the work-precision curve
                by_series = {}
                for r in rows:
                    by_series.setdefault(_series(r["label"]), []).append(r)
                for series, points in by_series.items():
                    if len(points) < 2:
                        continue
                    points.sort(key=lambda r: r["wall_s_per_simulated_s"])
                    tag = f"{name}: {series}" if name == "morphopt" else series
                    if tag not in series_color:
                        series_color[tag] = next(line_colors, "0.5")
                    ax.loglog([r["wall_s_per_simulated_s"] for r in points], [max(r[key], 1e-9) for r in points], "-",
                              color=series_color[tag], alpha=0.7, lw=1.2, label=tag)
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # (labels of 2x .. 9x overlap)
            ax.set_xlabel(f"wall s per simulated s ({result['precision'][0].get('num_worlds', '')} worlds)")
            ax.set_ylabel(unit)
            ax.set_title(f"{result['scene']}: {unit.split(' [')[0]} against run time", fontsize=8)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    fig.suptitle(f"{result['device_name']}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--quick", action="store_true", help="small batches and short runs (CPU, CI)")
    parser.add_argument("--peers", action="store_true",
                        help="also run the peers (MuJoCo Warp; Kamino on USD scenes) on the same mechanisms")
    parser.add_argument("--peer-solvers", nargs="+", choices=["mujoco", "kamino"], default=["mujoco", "kamino"],
                        help="which Newton peers run on USD scenes with --peers (default both; Kamino takes "
                             "minutes per DR Legs scene)")
    parser.add_argument("--parts", nargs="+", choices=["throughput", "precision"], default=["throughput", "precision"],
                        help="what to measure (default both)")
    parser.add_argument("--only", nargs="+", choices=sorted(SCENES_DECLARED), default=None, help="scenes to run")
    parser.add_argument("--settings", nargs="+", default=None, metavar="LABEL",
                        help="only the variants and sweep points of these labels (benchmarks.scenes; the default "
                             "settings' throughput still runs), e.g. 'reduced coordinates'")
    parser.add_argument("--worlds", nargs="+", type=int, default=None, metavar="N",
                        help="throughput batch sizes instead of the scene's (the variants run at the largest, the "
                             "peers at each)")
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs (DR Legs scenes)")
    parser.add_argument("--out", default=None, help="results folder (default benchmarks/results/<device>)")
    args = parser.parse_args(argv)
    if args.settings:
        known = {s["label"] for name in (args.only or SCENES_DECLARED) for s in
                 SCENES_DECLARED[name].variants + SCENES_DECLARED[name].sweep}
        unknown = [label for label in args.settings if label not in known]
        if unknown:
            parser.error(f"--settings: no variant or sweep point is labelled {unknown} in these scenes; "
                         f"labels: {sorted(known)}")
        if not args.out:
            parser.error("--settings writes a partial result: give it its own --out folder")
    if args.worlds:
        if min(args.worlds) < 1:
            parser.error(f"--worlds: batch sizes must be at least 1, got {args.worlds}")
        if not args.out:
            parser.error("--worlds writes a partial result: give it its own --out folder")
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    try:
        wp.get_device(args.device)
    except (RuntimeError, ValueError) as exc:
        parser.error(f"--device {args.device}: {exc}")
    out = pathlib.Path(args.out) if args.out else RESULTS / device_tag(args.device)
    names = args.only or list(SCENES_DECLARED)
    failed = []
    for name in names:
        try:
            result = run_scene(name, SCENES_DECLARED[name], args)
        except FileNotFoundError as exc:  # a scene whose data is not on this machine
            print(json.dumps({"scene": name, "skipped": str(exc)}), flush=True)
            continue
        except Exception as exc:  # noqa: BLE001  (report, go on with the other scenes, fail at the end)
            print(json.dumps({"scene": name, "error": repr(exc)}), flush=True)
            failed.append(name)
            continue
        write(result, out)
    if failed:
        print(f"failed scenes: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
