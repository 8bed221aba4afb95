"""Numerical stability stress suite: one command, one JSON object per case, non-zero exit on a failure.

    python -m benchmarks.stress --device cpu            # CI sizes (a few minutes on two cores)
    python -m benchmarks.stress --device cuda --full    # the full sizes, on a GPU
    python -m benchmarks.stress --device cpu --only S1 S6

Every case is declared as data (``CASES``): an id, what it does, its pass criterion and a function
that runs it at CI or full size and returns what it measured and whether it passed. The oracles
are analytic (Freudenstein's equation, free fall, conservation of angular momentum and energy),
a one-degree-of-freedom equation integrated with scipy at tight tolerance, or the engine's own
invariants (joint separation, quaternion norms, bit-identical neighbours), never an earlier run.

Cases: S1 driven four-bar against Freudenstein; S2 passive four-bar energy against dt; S3 singular
configurations (a parallelogram through its flat position, IFToMM A02's N four-bar); S4 redundant
loops (a double parallelogram, IFToMM A04's Bricard linkage); S5 chains with extreme mass ratios; S6 a free body spinning about
its intermediate axis; S7 impacts (a crank driven into its joint limit, a walker dropped on the
ground); S8 the largest stable time step of every case; S9 batch health (random over-limit
torques, one world forced to diverge, its neighbours bit-identical to a run without it); S10
jamming (a design that locks mid-cycle, or whose motor is too weak, fails as jammed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import warp as wp

from engine import Joint, JointDrive, MechanismSpec, SolverConfig, TrackedPoint, Tuning, pack_worlds, rollout
from engine.rollout import Stepper
from engine.scenes import Y_AXIS, bar, chain, fourbar, pin, u

GRAVITY = 9.81


@dataclass
class Case:
    id: str
    title: str
    criterion: str
    run: Callable[[str, bool], dict]  # (device, full) -> {"measured": {...}, "pass": bool}


def _planar_angle(vec: np.ndarray) -> np.ndarray:
    """Angle phi of vectors (..., 3) in the x-z plane with u(phi) along them (CCW in (x, -z))."""
    return np.arctan2(-vec[..., 2], vec[..., 0])


def _wrap(angle):
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


# ---------------------------------------------------------------- S1: Freudenstein


def driven_fourbar(a=0.2, b=0.5, c=0.4, d=0.5, speed=2.0 * math.pi, damping=1.0e3, limit_upper=math.inf,
                   effort_limit=math.inf) -> MechanismSpec:
    """The four-bar of engine.scenes with crank a, coupler b, rocker c, ground d, its crank on a
    velocity drive (and optionally a joint limit), tracked points at the crank and rocker tips."""
    spec = fourbar(ground=d, crank=a, coupler=b, rocker=c, crank_angle=math.radians(45.0), crank_speed=speed).spec
    joints = list(spec.joints)
    joints[0] = dataclasses.replace(joints[0], drive=JointDrive(damping=damping, target_velocity=speed,
                                                                effort_limit=effort_limit),
                                    limit_upper=limit_upper)
    points = [TrackedPoint("B", "crank", (a, 0.0, 0.0)), TrackedPoint("C", "rocker", (c, 0.0, 0.0))]
    return MechanismSpec(spec.bodies, joints, points, name="driven_fourbar")


def freudenstein_rocker(theta2: np.ndarray, a, b, c, d, branch: int) -> np.ndarray:
    """Rocker angle from crank angle (ground pivots at 0 and (d, 0)) by Freudenstein's equation
    K1 cos t4 - K2 cos t2 + K3 = cos(t2 - t4), branch +1 or -1."""
    k1, k2, k3 = d / a, d / c, (a * a - b * b + c * c + d * d) / (2.0 * a * c)
    p = np.cos(theta2) - k1
    q = np.sin(theta2)
    s = k3 - k2 * np.cos(theta2)
    return np.arctan2(q, p) + branch * np.arccos(np.clip(s / np.hypot(p, q), -1.0, 1.0))


def case_s1(device: str, full: bool) -> dict:
    a, b, c, d = 0.2, 0.5, 0.4, 0.5
    duration, dt = (5.0 if full else 1.5), 1e-3
    spec = driven_fourbar(a, b, c, d)
    model = pack_worlds([spec], device=device, dt=dt)
    trace, _ = rollout(model, model.state(), model.control(), round(duration / dt), record_every=10)
    A, D = np.zeros(3), np.array([d, 0.0, 0.0])
    theta2 = _planar_angle(trace.points[:, 0, 0] - A)
    theta4 = _planar_angle(trace.points[:, 0, 1] - D)
    branches = [freudenstein_rocker(theta2[:1], a, b, c, d, s)[0] for s in (1, -1)]
    branch = 1 if abs(_wrap(branches[0] - theta4[0])) < abs(_wrap(branches[1] - theta4[0])) else -1
    error = np.abs(_wrap(theta4 - freudenstein_rocker(theta2, a, b, c, d, branch)))
    turns = float(np.sum(np.abs(np.diff(np.unwrap(theta2)))) / (2.0 * math.pi))
    measured = {"duration_s": duration, "dt": dt, "crank_turns": turns,
                "rocker_error_deg": float(np.degrees(error.max())),
                "loop_closure_m": float(trace.violation_linear.max()), "finite": bool(np.isfinite(theta4).all())}
    ok = (measured["finite"] and measured["rocker_error_deg"] < 0.1 and measured["loop_closure_m"] < 1e-5
          and turns > 0.9 * duration)
    return {"measured": measured, "pass": bool(ok)}


# ---------------------------------------------------------------- S2: energy against dt


def energy_drift(spec: MechanismSpec, potential_min: float, device: str, dt: float, duration: float,
                 config: SolverConfig | None = None) -> tuple[float, float, bool]:
    """(max |E - E0| / (E0 - E_min), largest joint separation [m], finite) over ``duration``."""
    model = pack_worlds([spec], device=device, dt=dt, config=config)
    steps = round(duration / dt)
    trace, _ = rollout(model, model.state(), model.control(), steps, record_every=max(1, steps // 200))
    energy = trace.energy[:, 0]
    finite = bool(np.isfinite(energy).all() and not trace.diverged[0])
    drift = float(np.max(np.abs(energy - energy[0])) / max(energy[0] - potential_min, 1e-12)) if finite else math.inf
    return drift, float(np.nanmax(trace.violation_linear)), finite


def case_s2(device: str, full: bool) -> dict:
    scene = fourbar()
    duration = 5.0 if full else 1.0
    rows = {}
    for dt in (0.5e-3, 1e-3, 2.5e-3, 5e-3):
        drift, loop, finite = energy_drift(scene.spec, scene.potential_min, device, dt, duration)
        rows[f"{dt * 1e3:g} ms"] = {"energy_drift": drift, "loop_closure_m": loop, "finite": finite}
    ok = all(r["finite"] and r["energy_drift"] < 0.02 for r in rows.values()) and rows["1 ms"]["energy_drift"] < 1e-3
    return {"measured": {"duration_s": duration, "by_dt": rows}, "pass": bool(ok)}


# ---------------------------------------------------------------- S3: singular configurations


def n_fourbar(n: int, theta0: float = -0.5 * math.pi, speed: float = 1.0) -> MechanismSpec:
    """IFToMM A02: n four-bars in a row, every rod 1 m and 1 kg: n + 1 cranks on ground pivots
    1 m apart, n couplers joining their tips; cranks at theta0 (u(theta0), engine.scenes: -pi/2
    points up), turning at ``speed`` [rad/s] (the tips at ``speed`` m/s). One degree of freedom (all cranks parallel)
    except where the cranks lie along the ground, where the mobility jumps to n + 1. The loops are
    closed by inline joints (the crank tip stays on the coupler's pivot axis): planar closures
    without redundant out-of-plane rows."""
    omega = speed  # tip speed / crank length
    bodies, joints = [], []
    for k in range(n + 1):
        origin = np.array([float(k), 0.0, 0.0])
        bodies.append(bar(f"crank{k}", 1.0, origin, theta0, omega))
        joints.append(pin(f"ground{k}", None, f"crank{k}", origin))
    tip_velocity = omega * np.cross(np.array(Y_AXIS), u(theta0))
    for k in range(n):
        start = np.array([float(k), 0.0, 0.0]) + u(theta0)
        bodies.append(bar(f"coupler{k}", 1.0, start, 0.0, 0.0, tip_velocity))
        joints.append(pin(f"left{k}", f"crank{k}", f"coupler{k}", (1.0, 0.0, 0.0)))
        joints.append(Joint(f"right{k}", "inline", f"coupler{k}", f"crank{k + 1}", parent_position=(1.0, 0.0, 0.0),
                            child_position=(1.0, 0.0, 0.0), axis=Y_AXIS))
    return MechanismSpec(bodies, joints, [TrackedPoint("tip", "crank0", (1.0, 0.0, 0.0))], name=f"n_fourbar_{n}")


def crank_reference(theta0: float, speed: float, times: np.ndarray, inertia: float, torque: float) -> np.ndarray:
    """Crank angle of a one-degree-of-freedom parallel linkage (cranks parallel, couplers
    translating), integrated by scipy at tight tolerance: the height of a point at distance r
    along a crank is -r sin theta (engine.scenes' u), so inertia theta'' = torque cos theta, with
    inertia and torque per unit crank mass, length and gravity summed over the links."""
    from scipy.integrate import solve_ivp

    sol = solve_ivp(lambda _, y: [y[1], torque * math.cos(y[0]) / inertia], (0.0, float(times[-1])),
                    [theta0, speed], t_eval=times, rtol=1e-12, atol=1e-12, method="DOP853")
    return sol.y[0]


def parallel_linkage_constants(spec: MechanismSpec) -> tuple[float, float]:
    """(inertia, torque) of crank_reference for an n_fourbar spec, from its bodies: each crank
    turns about its pivot (the body origin), inertia I_yy about its centre of mass plus m |com|^2
    (the bars' thickness included), each coupler translates with the crank tips (1 m out), so it
    counts with its mass; torque: gravity times the first moments about the pivots."""
    inertia = torque = 0.0
    for body in spec.bodies:
        mass, com = float(body.mass), np.asarray(body.com, dtype=float)
        if body.name.startswith("crank"):
            tensor = np.asarray(body.inertia, dtype=float)  # 3x3, or its diagonal
            inertia += float(tensor[1, 1] if tensor.ndim == 2 else tensor[1])
            inertia += mass * float(com @ com)
            torque += GRAVITY * mass * float(np.linalg.norm(com))
        else:
            inertia += mass
            torque += GRAVITY * mass
    return inertia, torque


def case_s3(device: str, full: bool) -> dict:
    n, duration, dt = (40, 20.0, 1e-3) if full else (2, 4.0, 1e-3)
    theta0, speed = -0.5 * math.pi, 1.0  # cranks up, tips at 1 m/s: the cranks turn over and over
    measured = {}
    ok = True
    for label, count in (("parallelogram", 1), (f"n_fourbar_{n}", n)):
        spec = n_fourbar(count, theta0, speed)
        spec.points.extend(TrackedPoint(f"tip{k}", f"crank{k}", (1.0, 0.0, 0.0)) for k in range(1, count + 1))
        model = pack_worlds([spec], device=device, dt=dt)
        steps = round(duration / dt)
        trace, _ = rollout(model, model.state(), model.control(), steps, record_every=20)
        tip = trace.points[:, 0, 0]
        # (count + 1) cranks (m l^2 / 3 plus their thickness's share about their pivots) and
        # count translating couplers
        reference = crank_reference(theta0, speed, trace.time, *parallel_linkage_constants(spec))
        expected = np.stack([np.cos(reference), np.zeros_like(reference), -np.sin(reference)], axis=1)
        error = np.linalg.norm(tip - expected, axis=1)
        flat = int(np.sum(np.diff(np.sign(np.sin(reference))) != 0))  # passes through the flat position
        # branch: every crank parallel to the first (a flipped branch turns some crank away by up to pi)
        tips = trace.points[:, 0, :count + 1] - np.arange(count + 1)[None, :, None] * np.array([1.0, 0.0, 0.0])
        angles = np.arctan2(-tips[..., 2], tips[..., 0])
        spread = float(np.nanmax(np.abs(np.angle(np.exp(1j * (angles - angles[:, :1]))))))
        finite = bool(np.isfinite(tip).all() and not trace.diverged[0])
        measured[label] = {"duration_s": duration, "dt": dt, "bodies": len(spec.bodies),
                           "flat_passes": flat, "tip_error_m": float(np.nanmax(error)), "crank_spread_rad": spread,
                           "loop_closure_m": float(np.nanmax(trace.violation_linear)), "finite": finite}
        ok = ok and finite and measured[label]["tip_error_m"] < 1e-3 and flat >= 1 and spread < 1e-3
    # the floor under the criterion: one crank on one pin (no loop, no singular pass) against the
    # same kind of reference: what the integrator and the float32 arithmetic of the dynamics
    # leave with the state summed with compensation (not part of the pass criterion)
    spec = n_fourbar(0, theta0, speed)
    model = pack_worlds([spec], device=device, dt=dt)
    trace, _ = rollout(model, model.state(), model.control(), round(duration / dt), record_every=20)
    reference = crank_reference(theta0, speed, trace.time, *parallel_linkage_constants(spec))
    expected = np.stack([np.cos(reference), np.zeros_like(reference), -np.sin(reference)], axis=1)
    energy = trace.energy[:, 0]
    measured["lone_crank_floor"] = {
        "tip_error_m": float(np.nanmax(np.linalg.norm(trace.points[:, 0, 0] - expected, axis=1))),
        "energy_error_relative": float(np.nanmax(np.abs(energy - energy[0])) / abs(energy[0]))}
    return {"measured": measured, "pass": bool(ok)}


# ---------------------------------------------------------------- S4: redundant loops


def double_parallelogram(theta0: float, speed: float) -> MechanismSpec:
    """Three 1 m, 1 kg cranks on ground pivots 1 m apart under one rigid 2 m, 2 kg coupler:
    Gruebler's count in the plane gives 0 degrees of freedom, the mechanism has 1 (the third
    crank is redundant). The coupler is pinned to the first crank and held on the other two by
    inline joints."""
    bodies = [bar(f"crank{k}", 1.0, (float(k), 0.0, 0.0), theta0, speed) for k in range(3)]
    tip_velocity = speed * np.cross(np.array(Y_AXIS), u(theta0))
    bodies.append(bar("coupler", 2.0, u(theta0), 0.0, 0.0, tip_velocity))
    joints = [pin(f"ground{k}", None, f"crank{k}", (float(k), 0.0, 0.0)) for k in range(3)]
    joints.append(pin("left", "crank0", "coupler", (1.0, 0.0, 0.0)))
    for k in (1, 2):
        joints.append(Joint(f"inline{k}", "inline", "coupler", f"crank{k}", parent_position=(float(k), 0.0, 0.0),
                            child_position=(1.0, 0.0, 0.0), axis=Y_AXIS))
    return MechanismSpec(bodies, joints, [TrackedPoint("tip", "crank0", (1.0, 0.0, 0.0))], name="double_parallelogram")


def bricard(side: float = 0.1) -> MechanismSpec:
    """IFToMM A04's Bricard linkage: five 1 m, 1 kg rods of square section ``side`` and the ground
    closed into a loop by six revolute joints, every joint axis normal to both rods it joins
    (consecutive axes at right angles: the orthogonal Bricard 6R). It starts at rest along the
    edges of a unit cube, O (0, 0, 0) -> (1, 0, 0) -> (1, 1, 0) -> (1, 1, 1) -> (0, 1, 1) ->
    (0, 0, 1) -> O, with gravity along -y. Gruebler's count gives 0 degrees of freedom (30 joint
    rows for 30 body coordinates), the linkage has 1: one row is redundant. Tracked points: P3
    (the fourth vertex)."""
    from engine import Body

    P = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 1, 1), (0, 1, 1), (0, 0, 1)], float)
    axes = [np.cross(P[(k + 1) % 6] - P[k], P[k - 1] - P[k]) for k in range(6)]
    bodies = []
    for k in range(5):
        along = P[k + 1] - P[k]
        inertia = np.full(3, (1.0 + side**2) / 12.0)
        inertia[np.argmax(np.abs(along))] = 2.0 * side**2 / 12.0
        bodies.append(Body(f"rod{k}", 1.0, np.diag(inertia), com=0.5 * along, position=P[k]))
    joints = [Joint("O", "revolute", None, "rod0", parent_position=P[0], axis=axes[0])]
    joints += [Joint(f"J{k}", "revolute", f"rod{k - 1}", f"rod{k}", parent_position=P[k] - P[k - 1], axis=axes[k])
               for k in range(1, 5)]
    joints.append(Joint("E", "revolute", None, "rod4", parent_position=P[5], child_position=P[5] - P[4],
                        axis=axes[5]))
    return MechanismSpec(bodies, joints, [TrackedPoint("P3", "rod3", (0.0, 0.0, 0.0))], gravity=(0.0, -GRAVITY, 0.0),
                         name="bricard")


def redundant_impulse(model, row_lambda: np.ndarray) -> tuple[float, float, int]:
    """World 0's joint impulses in the solver's preconditioned variables y = P^-1 lambda
    (P = diag(J M^-1 J^T)^-1/2, which also makes linear and angular rows commensurable): the norm
    of their component along the redundant directions (the null space of (P J)^T at the last
    step: impulses there move nothing, and a minimum-norm solution has none), the norm of y, and
    the number of redundant directions."""
    count = int(model.work.row_count.numpy()[0])
    precond = model.work.row_precond.numpy()[0, :count].astype(np.float64)
    J = np.zeros((count, 6 * model.max_bodies))
    body_c, body_p = model.work.row_body_c.numpy()[0], model.work.row_body_p.numpy()[0]
    J_c, J_p = model.work.row_J_c.numpy()[0], model.work.row_J_p.numpy()[0]
    for i in range(count):
        for body, block in ((body_c[i], J_c[i]), (body_p[i], J_p[i])):
            if body >= 0:
                J[i, 6 * body:6 * body + 6] += block
    _, sigma, vt = np.linalg.svd((precond[:, None] * J).T, full_matrices=True)
    null = vt[np.sum(sigma > 1e-6 * sigma[0]):]
    y = row_lambda[:count].astype(np.float64) / precond
    return float(np.linalg.norm(null @ y)), float(np.linalg.norm(y)), int(null.shape[0])


def case_s4_bricard(device: str, duration: float, dt: float) -> dict:
    from engine.metrics import compute_metrics

    spec = bricard()
    model = pack_worlds([spec], device=device, dt=dt)
    stepper = Stepper(model, model.state(), model.control(), chunk=10)
    coms = np.array([body.com for body in spec.bodies])
    energy, potential, loop, loop_rad, p3 = [], [], [], [], []
    redundant_parts, largest, largest_impulse, finite = [], 0.0, 0.0, True
    for record in range(round(duration / dt) // 10 + 1):
        if record:
            stepper.advance()
        state = stepper.state
        compute_metrics(model, state)
        energy.append(float(model.work.energy.numpy()[0]))
        loop.append(float(model.work.violation_linear.numpy()[0]))
        loop_rad.append(float(model.work.violation_angular.numpy()[0]))
        poses = state.body_q.numpy()[0, :len(coms)].astype(np.float64)
        heights = [pose[1] + (_rotation(pose[3:7]) @ com)[1] for pose, com in zip(poses, coms)]
        potential.append(GRAVITY * sum(heights))  # 1 kg rods, gravity along -y
        p3.append(poses[3, :3])  # rod3's frame origin is the vertex P3
        row_lambda = state.row_lambda.numpy()[0]
        finite = finite and bool(np.isfinite(row_lambda).all() and np.isfinite(poses).all())
        largest_impulse = max(largest_impulse, float(np.abs(row_lambda).max()))
        if record:  # the redundant share, relative to the run's largest impulse (near zero load,
            # any share of nothing is large)
            part, norm, redundant = redundant_impulse(model, row_lambda)
            redundant_parts.append(part)
            largest = max(largest, norm)
    energy = np.array(energy)
    kinetic_peak = float((energy - np.array(potential)).max())
    travel = np.array(p3) - p3[0]
    return {
        "duration_s": duration, "dt": dt, "loop_closure_m": float(np.nanmax(loop)),
        "loop_closure_rad": float(np.nanmax(loop_rad)),
        "p3_travel_m": float(np.linalg.norm(travel, axis=1).max()), "kinetic_energy_peak_j": kinetic_peak,
        "energy_drift": float(np.abs(energy - energy[0]).max() / kinetic_peak),
        "redundant_directions": redundant,
        "redundant_impulse_over_largest": float(max(redundant_parts) / max(largest, 1e-30)),
        "largest_impulse_over_weight_impulse": largest_impulse / (5.0 * GRAVITY * dt),
        "finite": finite,
    }


def case_s4(device: str, full: bool) -> dict:
    duration, dt = (10.0 if full else 2.0), 1e-3
    theta0, speed = 0.5 * math.pi - 0.8, 0.0  # released 0.8 rad from hanging: swings, never flat
    spec = double_parallelogram(theta0, speed)
    model = pack_worlds([spec], device=device, dt=dt)
    steps = round(duration / dt)
    trace, state = rollout(model, model.state(), model.control(), steps, record_every=10)
    # one degree of freedom: three cranks (1/3 m l^2 each) and the translating 2 kg coupler
    reference = crank_reference(theta0, speed, trace.time, 3.0 / 3.0 + 2.0, GRAVITY * (3 * 0.5 + 2.0))
    expected = np.stack([np.cos(reference), np.zeros_like(reference), -np.sin(reference)], axis=1)
    energy = trace.energy[:, 0]
    impulses = state.row_lambda.numpy()[0]
    weight_impulse = 5.0 * GRAVITY * dt  # the whole mechanism's weight over one step
    measured = {
        "duration_s": duration, "loop_closure_m": float(np.nanmax(trace.violation_linear)),
        "tip_error_m": float(np.nanmax(np.linalg.norm(trace.points[:, 0, 0] - expected, axis=1))),
        # relative to the energy above the hanging equilibrium (cranks down: -g (3 * 0.5 + 2 * 1))
        "energy_drift": float(np.max(np.abs(energy - energy[0])) / (energy[0] + GRAVITY * 3.5)),
        "largest_impulse_over_weight_impulse": float(np.abs(impulses).max() / weight_impulse),
        "finite": bool(np.isfinite(impulses).all() and np.isfinite(trace.points).all()),
    }
    ok = (measured["finite"] and measured["loop_closure_m"] < 1e-4 and measured["tip_error_m"] < 1e-3
          and measured["largest_impulse_over_weight_impulse"] < 10.0 and measured["energy_drift"] < 0.01)
    brick = case_s4_bricard(device, duration, dt)
    ok = ok and (brick["finite"] and brick["loop_closure_m"] < 1e-4 and brick["p3_travel_m"] > 0.5
                 and brick["redundant_directions"] >= 1 and brick["redundant_impulse_over_largest"] < 0.1
                 and brick["largest_impulse_over_weight_impulse"] < 10.0 and brick["energy_drift"] < 0.02)
    return {"measured": {"double_parallelogram": measured, "bricard": brick}, "pass": bool(ok)}


# ---------------------------------------------------------------- S5: mass ratios


def mass_ratio_chain(links: int, ratio: float) -> MechanismSpec:
    """engine.scenes' chain with its links alternating between line densities 1 and ``ratio``."""
    return chain(links, densities=[ratio if k % 2 else 1.0 for k in range(links)]).spec


# PADMM solved to tolerance: the default tolerances are relative to the largest impulse, which the
# 1000 kg links set, so a 0.1 kg link's rows count as converged after one iteration and its joints
# drift (50 links, 1:10000, default tolerances: 6e-4 m on the H100). The joint rows share the
# world's penalty (cap_joint_penalty off), which falls to where the soft modes of a 1:10000 chain
# converge: with their own fixed penalty the 50-link chain took 89 iterations per step (at most 189,
# cap 200) and opened its joints 7.6e-5 m at free_rho 2e-4, 160 iterations and 3.7e-4 m at 1e-3
# (CPU; benchmarks/results/README.md, "The free rows' penalty lowered to 2e-4")
S5_CONFIG = SolverConfig(tolerance=1e-8, relative_tolerance=1e-8, max_iterations=200,
                         tuning=Tuning(stall_ratio=0.0, cap_joint_penalty=False))


def case_s5(device: str, full: bool) -> dict:
    """Both mass ratios of a chain length in one batch (two worlds: each world's PADMM stops on its
    own, so the batch takes about as long as its slower chain and the chains' motions are those of
    separate runs)."""
    sizes, duration, dt = ((10, 50), 10.0, 1e-3) if full else ((10,), 1.0, 1e-3)
    ratios = (100.0, 1e4)
    measured, ok = {}, True
    for links in sizes:
        model = pack_worlds([mass_ratio_chain(links, ratio) for ratio in ratios], device=device, dt=dt,
                            config=S5_CONFIG)
        steps = round(duration / dt)
        trace, _ = rollout(model, model.state(), model.control(), steps, record_every=max(1, steps // 100))
        for w, ratio in enumerate(ratios):
            finite = bool(np.isfinite(trace.points[:, w]).all() and not trace.diverged[w])
            row = {"duration_s": duration, "loop_closure_m": float(np.nanmax(trace.violation_linear[:, w])),
                   "padmm_iterations_mean": float(trace.iterations[1:, w].mean()),
                   "padmm_iterations_max": int(trace.iterations[1:, w].max()), "finite": finite}
            measured[f"{links} links 1:{ratio:g}"] = row
            ok = ok and finite and row["loop_closure_m"] < 1e-4
    return {"measured": measured, "pass": bool(ok)}


# ---------------------------------------------------------------- S6: gyroscopic


def case_s6(device: str, full: bool) -> dict:
    """A free body (principal inertias 1, 2, 3 kg m^2, no gravity) spinning at 5 rad/s about its
    intermediate axis with a 1 % perturbation, drifting at 0.5 m/s: it flips (Dzhanibekov); its
    angular momentum about the centre of mass is conserved and the centre moves on a straight line
    at constant speed. (Falling under gravity for 10 s would take it 470 m down, where a float32
    coordinate's ulp is 3e-5 m: a constant increment added 10000 times there drifts by centimetres,
    whatever the integrator.)"""
    from engine import Body

    duration, dt = (10.0 if full else 4.0), 1e-3
    inertia = np.diag([1.0, 2.0, 3.0])
    omega0 = np.array([0.05, 5.0, 0.0])
    velocity0 = np.array([0.3, 0.0, 0.4])
    spec = MechanismSpec([Body("top", 1.0, inertia, velocity=velocity0, angular_velocity=omega0)],
                         gravity=(0.0, 0.0, 0.0), name="spinning_top")
    model = pack_worlds([spec], device=device, dt=dt)
    stepper = Stepper(model, model.state(), model.control(), chunk=10)
    times, positions, momenta, axes, norms = [], [], [], [], []
    for k in range(round(duration / dt / 10) + 1):
        if k:
            stepper.advance()
        q = stepper.state.body_q.numpy()[0, 0].copy()  # a copy: on the CPU numpy() is a view
        qd = stepper.state.body_qd.numpy()[0, 0].copy()
        rot = _rotation(q[3:7])
        times.append(stepper.steps_done * dt)
        positions.append(q[:3])
        momenta.append(rot @ inertia @ rot.T @ qd[3:6])
        axes.append(rot[:, 1])
        norms.append(float(np.linalg.norm(q[3:7])))
    times, positions, momenta, axes = map(np.asarray, (times, positions, momenta, axes))
    expected = velocity0 * times[:, None]
    L0 = momenta[0]
    measured = {
        "duration_s": duration, "dt": dt,
        "momentum_error": float(np.max(np.linalg.norm(momenta - L0, axis=1)) / np.linalg.norm(L0)),
        "com_error_m": float(np.max(np.linalg.norm(positions - expected, axis=1))),
        "flips": int(np.sum(np.diff(np.sign(axes @ axes[0])) != 0)),
        "quaternion_norm_error": float(np.max(np.abs(np.asarray(norms) - 1.0))),
    }
    ok = measured["momentum_error"] < 5e-3 and measured["com_error_m"] < 1e-3 and measured["flips"] >= 1
    return {"measured": measured, "pass": bool(ok)}


def _rotation(q) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


# ---------------------------------------------------------------- S7: impacts


def case_s7(device: str, full: bool) -> dict:
    """The S1 four-bar's crank driven at 20 rad/s into a joint limit 1 rad ahead (the limit row
    must stop it within 5 mm at the crank tip), and a walker dropped from 0.2 m onto the ground
    (no contact deeper than 5 mm)."""
    measured, ok = {}, True
    a, dt = 0.2, 1e-3
    start = math.radians(45.0)
    spec = driven_fourbar(speed=20.0, damping=1e3, limit_upper=start + 1.0, effort_limit=200.0)
    model = pack_worlds([spec], device=device, dt=dt)
    trace, _ = rollout(model, model.state(), model.control(), 300, record_every=1)
    theta2 = np.unwrap(_planar_angle(trace.points[:, 0, 0]))
    over = float(np.max(theta2 - (start + 1.0)))
    finite = bool(np.isfinite(theta2).all() and not trace.diverged[0])
    measured["crank_limit"] = {"impact_speed_rad_s": 20.0, "overshoot_m": max(over, 0.0) * a, "finite": finite,
                               "loop_closure_m": float(np.nanmax(trace.violation_linear))}
    ok = ok and finite and measured["crank_limit"]["overshoot_m"] < 5e-3

    from morphopt.families import load_family

    family = load_family("walker")
    walker = family.build_spec(family.space.validate(family.space.default()))
    lifted = dataclasses.replace(walker, bodies=[dataclasses.replace(b, position=b.position + [0.0, 0.0, 0.2])
                                                 for b in walker.bodies])
    wdt = 2e-3
    model = pack_worlds([lifted], device=device, dt=wdt)
    stepper = Stepper(model, model.state(), model.control(), chunk=5)
    deepest = 0.0
    for _ in range(int((1.0 if full else 0.4) / wdt / 5)):
        stepper.advance()
        count = int(model.work.contact_count.numpy()[0])
        if count:
            deepest = min(deepest, float(model.work.contact_distance.numpy()[0, :count].min()))
    body_q = stepper.state.body_q.numpy()
    finite = bool(np.isfinite(body_q).all() and not model.work.diverged.numpy()[0])
    measured["walker_drop"] = {"height_m": 0.2, "penetration_m": -deepest, "finite": finite}
    ok = ok and finite and -deepest < 5e-3
    return {"measured": measured, "pass": bool(ok)}


# ---------------------------------------------------------------- S8: large time steps


def _stable(spec: MechanismSpec, device: str, dt: float, duration: float) -> tuple[bool, float]:
    """(finite and joints held within 1e-3 m, largest joint separation) over ``duration``."""
    model = pack_worlds([spec], device=device, dt=dt)
    steps = max(1, round(duration / dt))
    trace, state = rollout(model, model.state(), model.control(), steps, record_every=max(1, steps // 50))
    finite = bool(np.isfinite(state.body_q.numpy()).all() and not trace.diverged[0])
    loop = float(np.nanmax(trace.violation_linear)) if finite else math.inf
    return finite and loop < 1e-3, loop


def case_s8(device: str, full: bool) -> dict:
    """Every case's mechanism at dt x 1, 2, 4, 8 (base 1 ms; the walker 2 ms): the largest dt at
    which it stays finite with its joints held within 1e-3 m."""
    from morphopt.families import load_family

    duration = 2.0 if full else 0.5
    family = load_family("walker")
    mechanisms = {
        "S1 driven four-bar": (driven_fourbar(), 1e-3),
        "S2 passive four-bar": (fourbar().spec, 1e-3),
        "S3 parallelogram": (n_fourbar(1), 1e-3),
        "S4 double parallelogram": (double_parallelogram(0.5 * math.pi - 0.8, 0.0), 1e-3),
        "S5 chain 10 links 1:10000": (mass_ratio_chain(10, 1e4), 1e-3),
        "S7 crank into its limit": (driven_fourbar(speed=20.0, limit_upper=math.radians(45.0) + 1.0,
                                                   effort_limit=200.0), 1e-3),
        "S7 walker": (family.build_spec(family.space.validate(family.space.default())), 2e-3),
    }
    measured, ok = {}, True
    for label, (spec, base) in mechanisms.items():
        largest, loops = None, {}
        for factor in (1, 2, 4, 8):
            stable, loop = _stable(spec, device, base * factor, duration)
            loops[f"{base * factor * 1e3:g} ms"] = loop
            if not stable:
                break
            largest = base * factor
        measured[label] = {"largest_stable_dt_ms": None if largest is None else largest * 1e3, "loop_closure_m": loops}
        ok = ok and largest is not None
    return {"measured": measured, "pass": bool(ok)}


# ---------------------------------------------------------------- S9: batch health


def linkage_batch(worlds: int) -> list[MechanismSpec]:
    """Heterogeneous worlds: the default designs of the linkage families (four-bar, Watt six-bar,
    Jansen and Klann legs) in turn, each with its crank on a velocity drive with an effort limit."""
    from morphopt.families import load_family
    from morphopt.linkage import to_spec

    kinds = []
    for name in ("four_bar", "watt_sixbar", "jansen_leg", "klann_leg"):
        family = load_family(name)
        kinds.append(to_spec(family.generate(family.space.validate(family.space.default()))))
    return [kinds[w % len(kinds)] for w in range(worlds)]


def _torque_run(specs, device, dt, steps, every, seed, poison: int | None):
    """Random drive torques up to 3x the effort limits (new ones every ``every`` steps); world
    ``poison`` (if any) gets a non-finite external force from the start. Returns the model, the
    final poses, the per-record non-converged counts and the worst quaternion-norm error."""
    model = pack_worlds(specs, device=device, dt=dt)
    control = model.control()
    driven = np.zeros((model.num_worlds, model.max_joints))
    for w, spec in enumerate(specs):
        for j, joint in enumerate(spec.joints):
            if joint.drive is not None:
                driven[w, j] = joint.drive.effort_limit
    if poison is not None:
        force = np.zeros((model.num_worlds, model.max_bodies, 6), np.float32)
        force[poison, 0, :] = np.nan
        control.body_f.assign(force)
    real = np.arange(model.max_bodies)[None, :] < model.body_count.numpy()[:, None]  # not padding
    if poison is not None:
        real[poison] = False
    rng = np.random.default_rng(seed)
    stepper = Stepper(model, model.state(), control, chunk=every)
    unconverged, quaternion = [], 0.0
    for _ in range(steps // every):
        control.joint_effort.assign((rng.uniform(-3.0, 3.0, driven.shape) * driven).astype(np.float32))
        stepper.advance()
        unconverged.append(int((model.work.iterations.numpy() >= model.config.max_iterations).sum()))
        error = np.abs(np.linalg.norm(stepper.state.body_q.numpy()[:, :, 3:7], axis=2) - 1.0)
        quaternion = max(quaternion, float(error[real].max()))
    return model, stepper.state.body_q.numpy().copy(), unconverged, quaternion


def case_s9(device: str, full: bool) -> dict:
    worlds, duration, dt = (4096, 10.0, 1e-3) if full else (16, 0.5, 1e-3)
    specs = linkage_batch(worlds)
    steps, every, poison = round(duration / dt), 50, 1
    clean_model, clean_q, unconverged, quaternion = _torque_run(specs, device, dt, steps, every, 7, None)
    model, poisoned_q, _, _ = _torque_run(specs, device, dt, steps, every, 7, poison)
    diverged = model.work.diverged.numpy().astype(bool)
    others = np.arange(worlds) != poison
    nan_worlds = int((~np.isfinite(clean_q.reshape(worlds, -1))).any(axis=1).sum())
    initial = model.body_q_init.numpy()[poison]
    measured = {
        "worlds": worlds, "duration_s": duration, "nan_worlds": nan_worlds,
        "diverged_flags_clean_run": int(clean_model.work.diverged.numpy().sum()),
        "quaternion_norm_error": quaternion,
        "unconverged_worlds_per_record_max": int(max(unconverged)),
        "unconverged_worlds_per_record_mean": float(np.mean(unconverged)),
        "forced_world_flagged": bool(diverged[poison]), "other_worlds_flagged": int(diverged[others].sum()),
        "forced_world_frozen": bool(np.array_equal(poisoned_q[poison], initial)),
        "neighbours_bit_identical": bool(np.array_equal(poisoned_q[others], clean_q[others])),
    }
    ok = (nan_worlds == 0 and quaternion < 1e-3 and measured["forced_world_flagged"]
          and measured["other_worlds_flagged"] == 0 and measured["forced_world_frozen"]
          and measured["neighbours_bit_identical"] and measured["diverged_flags_clean_run"] == 0)
    return {"measured": measured, "pass": bool(ok)}


# ---------------------------------------------------------------- S10: jamming


def jam_hook(spec: MechanismSpec, params: dict) -> MechanismSpec:
    """evaluate_dynamic's spec_hook for S10, keyed on the four-bar's point_v: 0.11 puts a stop
    at 1.2 rad on the coupler-rocker joint (it swings 0.72 to 1.62 rad in a turn: the linkage locks
    mid-cycle); 0.12 gives the crank a motor of 0.02 N m (the design needs 0.1 N m); else as is."""
    joints = list(spec.joints)
    if math.isclose(params["point_v"], 0.11):
        k = next(k for k, j in enumerate(joints) if j.name == "C_coupler_rocker")
        joints[k] = dataclasses.replace(joints[k], limit_upper=1.2)
    elif math.isclose(params["point_v"], 0.12):
        drive = dataclasses.replace(joints[0].drive, effort_limit=0.02)
        joints[0] = dataclasses.replace(joints[0], drive=drive)
    return dataclasses.replace(spec, joints=joints)


def case_s10(device: str, full: bool) -> dict:
    from morphopt.evaluate import evaluate_dynamic
    from morphopt.families import load_family

    family = load_family("four_bar")
    base = family.space.default()
    params = [dict(base, point_v=0.1), dict(base, point_v=0.11), dict(base, point_v=0.12)]
    duration = 3.0 if full else 1.5
    evaluation = evaluate_dynamic(family, params, duration=duration, dt=1e-3, device=device, spec_hook=jam_hook)
    healthy, locked, weak = evaluation.failures
    measured = {"duration_s": duration, "healthy": healthy or "feasible", "locked_mid_cycle": locked,
                "motor_too_weak": weak,
                "healthy_torque_peak_nm": evaluation.metrics[0].get("torque_peak")}
    # the maximal plan enforces effort limits and the jam rule finds the stall; the tree plan stops a
    # world at its drive's limit: either way the design fails with its drive and limit named
    stalled = ("jammed:", "effort limit: the drive of joint")
    ok = (not healthy and locked.startswith(stalled) and "O_crank" in locked
          and weak.startswith(stalled) and "O_crank" in weak)
    return {"measured": measured, "pass": bool(ok)}


CASES = [
    Case("S1", "driven four-bar against Freudenstein's equation (a, b, c, d = 0.2, 0.5, 0.4, 0.5 m, 1 rev/s)",
         "rocker angle within 0.1 deg of the analytic one, loop closure < 1e-5 m", case_s1),
    Case("S2", "passive four-bar energy against dt (0.5, 1, 2.5, 5 ms; 5 s, CI 1 s)",
         "finite; energy drift < 2 % at every dt and < 0.1 % at 1 ms", case_s2),
    Case("S3", "singular configurations: a parallelogram through its flat position; IFToMM A02 N four-bar "
         "(N = 40, 20 s; CI N = 2, 4 s) against its one-degree-of-freedom motion (scipy, rtol 1e-12)",
         "first crank tip within 1e-3 m of the reference, passes the flat position, every crank within 1e-3 rad of "
         "the first (no branch flip), no NaN", case_s3),
    Case("S4", "redundant loops: a double parallelogram (3 cranks, one rigid coupler) swinging, against its "
         "one-degree-of-freedom motion (scipy); IFToMM A04's Bricard linkage (5 rods, 6 revolute joints, mobility 1 "
         "against Gruebler's 0) falling from rest; 10 s (CI 2 s)",
         "loops closed < 1e-4 m; impulses finite, below 10 weight impulses, and (Bricard) their component in the "
         "redundant directions below 10 % of the run's largest impulse (near minimum norm; 60 % without the warm-start decay); parallelogram: crank tip within 1e-3 m of the reference, "
         "energy drift < 1 %; Bricard: moves (P3 travels > 0.5 m), energy drift < 2 % of its peak kinetic energy",
         case_s4),
    Case("S5", "chains of 10 and 50 links (CI: 10) with mass ratios 1:100 and 1:10000, 10 s (CI 1 s), PADMM "
         "solved to tolerance 1e-8 with the joint rows on the world's penalty",
         "joint separation < 1e-4 m, no NaN; PADMM iterations to tolerance reported",
         case_s5),
    Case("S6", "free body spinning about its intermediate axis (inertias 1, 2, 3), no gravity, drifting at 0.5 m/s, "
         "10 s (CI 4 s)", "flips; angular momentum conserved to 0.5 %; centre of mass within 1e-3 m of its straight "
         "line", case_s6),
    Case("S7", "impacts: a crank driven at 20 rad/s into its joint limit; a walker dropped from 0.2 m",
         "overshoot and penetration below 5 mm, no NaN", case_s7),
    Case("S8", "large time steps: every case's mechanism at dt x 1, 2, 4, 8 for 2 s (CI 0.5 s)",
         "each stable at its base dt (finite, joints within 1e-3 m); the largest stable dt reported", case_s8),
    Case("S9", "batch health: 4096 heterogeneous linkages (CI 16) under random drive torques up to 3x their "
         "effort limits for 10 s (CI 0.5 s); one world forced to diverge (non-finite force)",
         "no NaN world, quaternion norms within 1e-3, the forced world flagged and frozen, its neighbours "
         "bit-identical to a run without it; non-converged worlds counted", case_s9),
    Case("S10", "jamming: three four-bars in one batch through the study evaluation (morphopt.evaluate_dynamic): "
         "a healthy one, one with a stop that locks it mid-cycle, one whose motor is too weak; 3 s (CI 1.5 s)",
         "both stalled designs fail with the drive and its effort limit named (as jammed in maximal "
         "coordinates, at the limit in tree coordinates, which stop there), the healthy one stays feasible",
         case_s10),
]


def run_case(case: Case, device: str, full: bool) -> dict:
    t0 = time.perf_counter()
    try:
        result = case.run(device, full)
    except Exception as exc:  # noqa: BLE001 - a crashing case is a failed case, reported with its reason
        result = {"measured": {"error": f"{type(exc).__name__}: {exc}"}, "pass": False}
    return {"case": case.id, "title": case.title, "criterion": case.criterion, "measured": result["measured"],
            "pass": bool(result["pass"]), "seconds": round(time.perf_counter() - t0, 2)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda")
    parser.add_argument("--full", action="store_true", help="the full sizes (minutes on a GPU) instead of CI sizes")
    parser.add_argument("--only", nargs="+", metavar="CASE", help="run only these cases (e.g. S1 S6)")
    args = parser.parse_args(argv)
    known = {case.id for case in CASES}
    unknown = sorted(set(args.only or []) - known)
    if unknown:
        parser.error(f"--only: unknown case {', '.join(unknown)}; expected some of {', '.join(sorted(known))}")
    wp.config.quiet = True  # stdout holds only the cases' JSON: no Warp banner
    wp.config.log_level = wp.LOG_WARNING
    try:
        wp.get_device(args.device)
    except (RuntimeError, ValueError) as exc:
        parser.error(f"--device: {exc}")
    failed = []
    for case in CASES:
        if args.only and case.id not in args.only:
            continue
        result = run_case(case, args.device, args.full)
        print(json.dumps(result), flush=True)
        if not result["pass"]:
            failed.append(case.id)
    if failed:
        print(f"stress: failed {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
