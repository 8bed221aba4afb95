"""Speed and accuracy of one scene replicated over N worlds (or a heterogeneous mix).

    python -m engine.testspeed --scene fourbar --worlds 4096 --steps 1000 --dt 0.001 --device cuda --json

Steps run in chunks (a CUDA graph per chunk on GPU); each chunk is timed between two device
synchronizations and the median per-step time is reported. After every chunk (outside the timed
region) the metrics are sampled: constraint violation and energy drift relative to the energy
available above the static equilibrium (passive scenes without contacts or limits; null
otherwise). PADMM iterations, contact counts and overflow, penetration and complementarity are
accumulated on the device at every step. Finally stage_ms times each stage of step() [ms per
step] over 20 synchronized eager steps: a scene without shapes shows collision 0. A fused batch
(one launch per step) reports fused_stage_cycles instead: the cycles each stage takes inside the
kernel, as the cycle counter of each world's block reads them (medians; 0 on the CPU), from a
timed variant of the kernel compiled for it (not counted in compile_s).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import warp as wp

from engine.fused import fused_inverse, fused_profile
from engine.metrics import compute_metrics
from engine.config import Integrator, SolverConfig, Tuning
from engine.pack import pack_worlds
from engine.rollout import Stepper
from engine.scenes import SCENES, make_scene
from engine.scenes_contact import CONTACT_SCENES, walker_gait
from engine.step import StageTimer, step

ALL_SCENES = {**SCENES, **CONTACT_SCENES}

STABILIZATION = {  # name -> SolverConfig fields (tuning: engine.Tuning's)
    "shake": dict(position_iterations=2, baumgarte=0.0, tuning=dict(projection_velocity_update=True)),
    "projection": dict(position_iterations=2, baumgarte=0.0, tuning=dict(projection_velocity_update=False)),
    "baumgarte": dict(position_iterations=0, baumgarte=0.01, tuning=dict(projection_velocity_update=False)),
}


def build_batch(scene: str, num_worlds: int):
    """Specs and static-equilibrium potential energies of the batch."""
    names = list(SCENES) if scene == "mixed" else [scene]
    scenes = {name: ALL_SCENES[name]() if name in CONTACT_SCENES else make_scene(name) for name in names}
    order = [names[w % len(names)] for w in range(num_worlds)]
    return [scenes[n].spec for n in order], np.array([scenes[n].potential_min for n in order])


def set_gait(model, control, time_s: float) -> None:
    """Walker worlds follow walker_gait: diagonal strut pairs swing in opposite phase."""
    targets = np.zeros((model.num_worlds, model.max_joints), np.float32)
    targets[:, :4] = walker_gait(time_s)
    control.joint_target_position.assign(targets)


def stage_profile(model, state, control, steps: int = 20) -> dict:
    """Per-stage wall time [ms per step] over ``steps`` eager, synchronized steps."""
    timer = StageTimer(model.device)
    other = model.state()
    for _ in range(steps):
        step(model, state, other, control, timer=timer)
        state, other = other, state
    return {k: round(v, 4) for k, v in timer.milliseconds_per_step().items()}


def run(scene: str, num_worlds: int, steps: int, dt: float, device: str, *, chunk: int = 10,
        config: SolverConfig | None = None, stages: bool = True) -> dict:
    """Run the benchmark and return its JSON-able result (the fused step's lanes and register cap:
    config.tuning.fused_block, fused_registers)."""
    config = config or SolverConfig()
    specs, potential_min = build_batch(scene, num_worlds)
    conservative = all(not s.shapes and not s.ground and not any(j.has_limits or j.drive for j in s.joints)
                       for s in specs)
    gait = scene == "walker"
    t0 = time.perf_counter()
    model = pack_worlds(specs, device=device, config=config, dt=dt)
    pack_s = time.perf_counter() - t0
    state, control = model.state(), model.control()
    compute_metrics(model, state)
    energy0 = model.work.energy.numpy().copy()
    available = np.maximum(energy0 - potential_min, 1e-12)
    chunk = max(1, min(chunk, steps))
    if gait:
        set_gait(model, control, 0.0)
    stepper = Stepper(model, state, control, chunk=chunk)
    wp.synchronize_device(model.device)
    t0 = time.perf_counter()
    stepper.advance()  # compiles every kernel (eager first chunk)
    wp.synchronize_device(model.device)
    compile_s = time.perf_counter() - t0
    if stepper.capture:
        stepper.advance()  # captures the graph
    times, viol_m, viol_rad, drift = [], 0.0, 0.0, 0.0
    measured = 0
    while measured < steps:
        if gait:
            set_gait(model, control, stepper.steps_done * dt)
        wp.synchronize_device(model.device)
        t0 = time.perf_counter()
        stepper.advance()
        wp.synchronize_device(model.device)
        times.append((time.perf_counter() - t0) / chunk)
        measured += chunk
        compute_metrics(model, stepper.state)
        diverged = model.work.diverged.numpy().astype(bool)
        ok = ~diverged
        if ok.any():
            viol_m = max(viol_m, float(model.work.violation_linear.numpy()[ok].max()))
            viol_rad = max(viol_rad, float(model.work.violation_angular.numpy()[ok].max()))
            energy = model.work.energy.numpy()
            drift = max(drift, float((np.abs(energy - energy0) / available)[ok].max()))
    solved = np.maximum(stepper.solved_steps.numpy(), 1)
    step_ms = float(np.median(times) * 1e3)
    steps_done = max(stepper.steps_done, 1)
    result = {
        "scene": scene, "device": str(model.device), "device_name": model.device.name,
        "num_worlds": num_worlds, "steps": measured, "dt": dt, "integrator": config.integrator.value,
        "max_rows": model.max_rows, "step_kernel": model.step_kernel, "linear_solver": model.linear_solver,
        "pack_s": pack_s, "compile_s": compile_s, "step_ms_median": step_ms,
        "world_steps_per_s": num_worlds / (step_ms * 1e-3),
        "max_constraint_violation_m": viol_m, "max_constraint_violation_rad": viol_rad,
        "energy_drift_rel": drift if conservative else None,
        "padmm_iterations_mean": float((stepper.iteration_sum.numpy() / solved).mean()),
        "padmm_iterations_max": int(stepper.iteration_max.numpy().max()),
        "unconverged_step_fraction": float((stepper.unconverged_steps.numpy() / solved).mean()),
        "diverged_worlds": int(model.work.diverged.numpy().sum()),
        "contact_capacity": model.contact_capacity,
        "contacts_mean": float(stepper.contact_sum.numpy().mean() / steps_done),
        "contacts_max": int(stepper.contact_max.numpy().max()),
        "contact_overflow_worlds": int((stepper.overflow_steps.numpy() > 0).sum()),
        "max_penetration_m": float(max(stepper.penetration_max.numpy().max(), 0.0)),
        "complementarity_max": float(stepper.complementarity_max.numpy().max()),
        "warp_version": wp.config.version, "cuda_graph": bool(stepper.capture), "fused_block": model.fused_block, "fused_registers": model.fused_registers,
    }
    if model.step_kernel == "fused":  # solves through L^-1 (engine.fused.fused_inverse) or by substitution
        chosen = model.fused_inverse
        result["fused_inverse"] = bool(fused_inverse(model.device, model.max_rows) if chosen is None else chosen)
    if stages:
        if model.step_kernel == "fused":  # one launch per step: the stages' cycles inside it
            result["fused_stage_cycles"] = fused_profile(model, stepper.state, control)
        else:
            result["stage_ms"] = stage_profile(model, stepper.state, control)
    return result


def main(argv=None) -> int:
    """Command line entry: time one scene and print its results (one JSON object with --json)."""
    parser = argparse.ArgumentParser(prog="python -m engine.testspeed", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", choices=[*ALL_SCENES, "mixed"], default="fourbar")
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--dt", type=float, default=1e-3)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--chunk", type=int, default=10, help="steps per timed (captured) chunk")
    parser.add_argument("--integrator", choices=[i.value for i in Integrator], default=SolverConfig.integrator.value)
    parser.add_argument("--stabilization", choices=sorted(STABILIZATION), default="shake")
    parser.add_argument("--tolerance", type=float, default=SolverConfig.tolerance)
    parser.add_argument("--max-iterations", type=int, default=SolverConfig.max_iterations)
    parser.add_argument("--step-kernel", choices=["auto", "fused", "staged"], default=Tuning.step_kernel,
                        help="whole step per world in one launch (fused) or one kernel per stage (staged)")
    parser.add_argument("--fused-block", type=int, default=None, help="threads per world of the fused step")
    parser.add_argument("--fused-registers", type=int, default=None,
                        help="register cap per thread of the fused step (0: the compiler's choice)")
    parser.add_argument("--json", action="store_true", help="print only the JSON object")
    args = parser.parse_args(argv)
    if args.worlds < 1 or args.steps < 1 or not args.dt > 0.0:
        parser.error("--worlds and --steps must be >= 1 and --dt > 0")
    if args.json:
        wp.config.log_level = wp.LOG_WARNING
    config = SolverConfig(integrator=args.integrator, tolerance=args.tolerance, max_iterations=args.max_iterations,
                          **STABILIZATION[args.stabilization])
    config = config.tuned(step_kernel=args.step_kernel, fused_block=args.fused_block,
                          fused_registers=args.fused_registers)
    result = run(args.scene, args.worlds, args.steps, args.dt, args.device, chunk=args.chunk, config=config)
    result["stabilization"] = args.stabilization
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key:>30}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
