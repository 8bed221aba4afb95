"""Peers through Newton (PyPI ``newton``, optional ``bench`` extra): its SolverKamino and its
SolverMuJoCo (MuJoCo Warp with loops as equality constraints) on DR Legs, loaded by Newton's own USD
importer from the same file that morphopt's importer reads, in the same process as our engine.

Each solver is configured as Newton's DR Legs examples configure it (Kamino: PADMM with tolerance
1e-4, at most 200 iterations, the scene's stabilisation from the file, Newton's collision pipeline
for contacts; MuJoCo Warp: SolverMuJoCo's defaults, implicitfast, Newton's contacts). The mechanism
is the same as ours: the same file, the same pose (pelvis origin at the same height, welded for the
hanging scene), and the drive gains, effort limit, armature and joint damping of our spec of it
(joint_parameters). Steps replay captured CUDA graphs (one step each, one per direction between the
two state buffers, so that a record can fall on any step), after a first, compiling step; with
``record_bodies`` a run also records body centres of mass for the trajectory error of the
work-precision sweep (benchmarks.run).

Errors are measured here, in NumPy, from the peers' body poses and Newton's joint frames, never
from the peers' own residuals: for every revolute joint, the distance [m] between its anchor as
seen from the parent and as seen from the child, and the angle [rad] between the two hinge axes;
"loop" is the joints Newton keeps out of the articulation (the six loop closures of DR Legs).
"""

from __future__ import annotations

import time

import numpy as np

from engine.spatial import rotate as _rotate  # (N, 3) vectors by (N, 4) quaternions (x, y, z, w)

__all__ = ["available", "joint_parameters", "newton_drlegs_run"]


def available() -> str | None:
    """None when Newton and its USD importer can run here, else why not."""
    try:
        import newton  # noqa: F401
        import newton.solvers  # noqa: F401
        from pxr import Usd  # noqa: F401
    except ImportError as exc:
        return f"newton is not installed ({exc}); pip install '.[bench]'"
    return None


def joint_parameters(spec) -> dict:
    """The drive gains, effort limit, armature and damping of a spec whose joints all share them
    (Newton's builder takes one value per degree of freedom; DR Legs has one of each)."""
    drives = {tuple(float(f"{v:.6g}") for v in (j.drive.stiffness, j.drive.damping, j.drive.effort_limit))
              for j in spec.joints if j.drive is not None}
    passive = {(float(f"{j.armature:.6g}"), float(f"{j.damping:.6g}")) for j in spec.joints}
    if len(drives) > 1 or len(passive) != 1:
        raise ValueError(f"{spec.name}: the Newton peers take one drive setting and one armature and damping "
                         f"for all joints, the spec has {sorted(drives)} and {sorted(passive)}")
    stiffness, damping, effort = next(iter(drives)) if drives else (0.0, 0.0, 0.0)
    armature, joint_damping = next(iter(passive))
    return {"stiffness": float(stiffness), "damping": float(damping), "effort_limit": float(effort),
            "armature": float(armature), "joint_damping": float(joint_damping), "driven": bool(drives)}


def _multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternion products a b (x, y, z, w), row by row (the row-wise counterpart of the single
    product in morphopt.formats.usd)."""
    av, aw = a[..., :3], a[..., 3:4]
    bv, bw = b[..., :3], b[..., 3:4]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), aw * bw - np.sum(av * bv, -1, keepdims=True)], -1)


class JointErrors:
    """Revolute joints' anchor distance and hinge-axis angle from body poses (NumPy, float64)."""

    def __init__(self, model):
        import newton

        self.parent = model.joint_parent.numpy()
        self.child = model.joint_child.numpy()
        kinds = model.joint_type.numpy()
        self.revolute = kinds == int(newton.JointType.REVOLUTE)
        xp = model.joint_X_p.numpy().astype(np.float64)
        xc = model.joint_X_c.numpy().astype(np.float64)
        self.xp_p, self.xp_q = xp[:, :3], xp[:, 3:]
        self.xc_p, self.xc_q = xc[:, :3], xc[:, 3:]
        start = model.joint_qd_start.numpy()
        axis = model.joint_axis.numpy().astype(np.float64)
        self.axis = np.zeros((len(kinds), 3))
        self.axis[self.revolute] = axis[start[:-1][self.revolute]]
        self.loop = model.joint_articulation.numpy() < 0

    def __call__(self, body_q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        bq = body_q.astype(np.float64)
        bq[:, 3:] /= np.linalg.norm(bq[:, 3:], axis=1, keepdims=True)
        has_parent = self.parent >= 0
        pp = np.where(has_parent[:, None], bq[np.maximum(self.parent, 0), :3], 0.0)
        pq = np.where(has_parent[:, None], bq[np.maximum(self.parent, 0), 3:], np.array([0.0, 0.0, 0.0, 1.0]))
        cp, cq = bq[self.child, :3], bq[self.child, 3:]
        anchor_p = pp + _rotate(pq, self.xp_p)
        anchor_c = cp + _rotate(cq, self.xc_p)
        linear = np.linalg.norm(anchor_p - anchor_c, axis=1)
        axis_p = _rotate(_multiply(pq, self.xp_q), self.axis)
        axis_c = _rotate(_multiply(cq, self.xc_q), self.axis)
        angular = np.arctan2(np.linalg.norm(np.cross(axis_p, axis_c), axis=1), np.sum(axis_p * axis_c, axis=1))
        linear[~self.revolute] = 0.0
        angular[~self.revolute] = 0.0
        return linear, angular


def _build(path, standing: bool, worlds: int, joints: dict, device: str):
    import newton
    import warp as wp

    robot = newton.ModelBuilder(up_axis=newton.Axis.Z)
    newton.solvers.SolverKamino.register_custom_attributes(robot)
    newton.solvers.SolverMuJoCo.register_custom_attributes(robot)
    robot.default_shape_cfg.margin = 1e-6
    robot.default_shape_cfg.gap = 1e-2
    height = 0.265 if standing else 0.5
    robot.add_usd(str(path), xform=wp.transform(wp.vec3(0.0, 0.0, height), wp.quat_identity()),
                  floating=None if standing else False, joint_ordering=None, collapse_fixed_joints=False,
                  enable_self_collisions=False, force_position_velocity_actuation=True, hide_collision_shapes=True)
    dofs = robot.joint_dof_count
    robot.joint_armature = [joints["armature"]] * dofs
    robot.joint_damping = [joints["joint_damping"]] * dofs
    if joints["driven"]:
        none = int(newton.JointTargetMode.NONE)
        ke, kd = joints["stiffness"], joints["damping"]
        robot.joint_target_ke = [ke if int(m) != none else 0.0 for m in robot.joint_target_mode]
        robot.joint_target_kd = [kd if int(m) != none else 0.0 for m in robot.joint_target_mode]
        robot.joint_effort_limit = [joints["effort_limit"]] * dofs
    else:
        robot.joint_target_mode = [int(newton.JointTargetMode.NONE)] * dofs
        robot.joint_target_ke = [0.0] * dofs
        robot.joint_target_kd = [0.0] * dofs
    builder = newton.ModelBuilder(up_axis=newton.Axis.Z)
    builder.default_shape_cfg.margin = 1e-6
    builder.default_shape_cfg.gap = 1e-2
    for _ in range(worlds):
        builder.add_world(robot)
    if standing:
        builder.add_ground_plane()
    model = builder.finalize(device=device, skip_validation_joints=True)
    # contact capacity: the Kamino example's 72 per world standing; one slot per world without
    # contacts (else the solver sizes dead contact rows from Newton's estimate)
    model.rigid_contact_max = (72 if standing else 1) * worlds
    return model


def _solver(model, name: str, standing: bool):
    import newton

    if name == "kamino":
        kamino = newton.solvers.SolverKamino
        config = kamino.Config.from_model(model)  # the file's stabilisation and tolerances
        config.use_collision_detector = False
        config.use_fk_solver = False
        config.constraints.delta = 1e-3
        config.padmm.max_iterations = 200
        config.padmm.primal_tolerance = config.padmm.dual_tolerance = config.padmm.compl_tolerance = 1e-4
        config.validate()
        settings = {"solver": "SolverKamino (PADMM, dense LLT)", "tolerance": 1e-4, "max_iterations": 200,
                    "integrator": config.integrator, "alpha": config.constraints.alpha}
        return kamino(model, config=config), settings
    kwargs = dict(kinematic_switchable_roots=False)
    kwargs.update(use_mujoco_contacts=False) if standing else kwargs.update(disable_contacts=True)
    solver = newton.solvers.SolverMuJoCo(model, **kwargs)
    settings = {"solver": "SolverMuJoCo (MuJoCo Warp)", "integrator": "implicitfast (default)",
                "loops": "equality constraints (2 CONNECT per revolute loop joint), MuJoCo's default softness"}
    return solver, settings


def _body_indices(model, names: list[str]) -> np.ndarray:
    """Newton's indices of world 0's bodies named ``names`` (our spec's order), matched on the last
    part of Newton's body labels (the USD prim paths)."""
    world = model.body_world.numpy()
    tails = {}
    for index, label in enumerate(model.body_label):
        if world[index] == 0:
            tails.setdefault(str(label).rstrip("/").rsplit("/", 1)[-1], index)
    missing = [name for name in names if name not in tails]
    if missing:
        raise ValueError(f"bodies {missing} of our spec are not among Newton's bodies of world 0 "
                         f"({sorted(tails)[:6]} ...)")
    return np.array([tails[name] for name in names])


def newton_drlegs_run(path, *, standing: bool, solver: str, worlds: int, dt: float, steps: int, record_every: int,
                      device: str, joints: dict, record_bodies: list[str] | None = None) -> dict:
    """Step DR Legs (the USD file ``path``, standing on the ground or hanging from a welded pelvis,
    ``joints`` from joint_parameters of our spec of it) on Newton's ``solver`` ("kamino" or "mujoco")
    for ``steps`` steps from t = 0 and measure the joints' errors every ``record_every`` steps. The
    first step compiles; each later step replays one of two captured graphs (one per direction
    between the two states), so records fall on any step. Time per step: the median over the
    chunks between records, the first chunk (the compiling step) left out. ``record_bodies``
    (names of our spec's bodies): also return their centres of mass in world 0 at every record,
    ``positions`` (records, 1, bodies, 3) [m], as engine runs record them."""
    import newton
    import warp as wp

    from benchmarks.run import mempool_megabytes

    pool_before = mempool_megabytes(device)
    t0 = time.perf_counter()
    with wp.ScopedDevice(device):
        model = _build(path, standing, worlds, joints, device)
        engine, settings = _solver(model, solver, standing)
        errors = JointErrors(model)
        bodies = None if record_bodies is None else _body_indices(model, record_bodies)
        body_com = model.body_com.numpy().astype(np.float64)
        states = [model.state(), model.state()]
        control = model.control()
        newton.eval_fk(model, model.joint_q, model.joint_qd, states[0])
        wp.copy(states[1].body_q, states[0].body_q)
        wp.copy(states[1].body_qd, states[0].body_qd)
        pipeline = contacts = None
        if standing:
            pipeline = newton.CollisionPipeline(model)
            contacts = pipeline.contacts()

        def step(a, b):
            a.clear_forces()
            if pipeline is not None:
                pipeline.collide(a, contacts)
            engine.step(a, b, control, contacts, dt)

        times, positions, loop_m, loop_rad, joint_m, finite = [], [], 0.0, 0.0, 0.0, True

        def record(body_q) -> bool:
            nonlocal loop_m, loop_rad, joint_m
            if not np.isfinite(body_q).all():
                return False
            if bodies is not None:
                q = body_q[bodies].astype(np.float64)
                positions.append(q[:, :3] + _rotate(q[:, 3:] / np.linalg.norm(q[:, 3:], axis=1, keepdims=True),
                                                    body_com[bodies]))
            linear, angular = errors(body_q)
            joint_m = max(joint_m, float(linear.max()))
            loop_m = max(loop_m, float(linear[errors.loop].max(initial=0.0)))
            loop_rad = max(loop_rad, float(angular[errors.loop].max(initial=0.0)))
            return True

        record(states[0].body_q.numpy())
        setup_s = time.perf_counter() - t0
        t = time.perf_counter()
        step(states[0], states[1])  # step 1: compiles; the state is now states[1]
        wp.synchronize_device(device)
        first_s = time.perf_counter() - t
        done = 1
        if done % record_every == 0 and not record(states[1].body_q.numpy()):
            finite = False
        graphs = None
        if wp.get_device(device).is_cuda:
            graphs = []
            for a, b in ((states[1], states[0]), (states[0], states[1])):
                with wp.ScopedCapture() as capture:
                    step(a, b)
                graphs.append(capture.graph)
        chunk_start = t
        while finite and (done < steps or done % record_every):
            if done % record_every == 0:
                wp.synchronize_device(device)
                chunk_start = time.perf_counter()
            if graphs is not None:
                wp.capture_launch(graphs[(done + 1) % 2])
            elif done % 2:
                step(states[1], states[0])
            else:
                step(states[0], states[1])
            done += 1
            if done % record_every == 0:
                wp.synchronize_device(device)
                if done > record_every:  # the first chunk holds the compiling step
                    times.append((time.perf_counter() - chunk_start) / record_every)
                if not record(states[done % 2].body_q.numpy()):
                    finite = False
                    break
        if finite and not times:
            raise ValueError(f"{steps} steps recorded every {record_every} leave no timed chunk")
        step_s = float(np.median(times)) if times else float("nan")
        row = {"engine": "kamino" if solver == "kamino" else "mujoco_warp", "num_worlds": worlds, "dt": dt,
               "steps": done, "step_ms_median": step_s * 1e3, "world_steps_per_s": worlds / step_s,
               "wall_s_per_simulated_s": step_s / dt, "loop_error_m": loop_m, "loop_error_rad": loop_rad,
               "joint_error_m": joint_m, "finite": finite,
               "device_memory_mb": None if pool_before is None else mempool_megabytes(device) - pool_before,
               "first_step_s": first_s, "setup_s": setup_s,
               "cuda_graph": graphs is not None, "settings": settings, "joints": joints,
               "loop_joints_per_world": int(errors.loop.sum()) // worlds,
               "newton_version": getattr(newton, "__version__", "?")}
        if bodies is not None:
            row["positions"] = np.array(positions)[:, None]
        if solver == "kamino":
            status = engine.status.numpy()
            row["padmm_iterations_mean"] = float(status["iterations"].mean())
            row["padmm_converged_fraction"] = float(status["converged"].mean())
        else:
            row["mujoco_iterations_mean"] = float(engine.mjw_data.solver_niter.numpy().mean())
    return row
