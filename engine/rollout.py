"""Multi-step loops: a Stepper that replays captured chunks of steps, and rollout() -> Trace.

On CUDA a chunk of steps (with the per-step solver statistics) is captured once into a CUDA graph
and replayed; the two State buffers alternate inside the chunk, so a chunk of odd length gets
one graph per starting buffer. Elsewhere the same calls run eagerly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from engine.health import Health, check_joints, note_residual
from engine.joints import body_twist, joint_coordinate_row, joint_frames
from engine.metrics import compute_metrics
from engine.model import ContactArrays, Control, Model, ModelArrays, State, WorkArrays
from engine.grouped import GroupedModel, GroupedState, _scatter, rollout_groups
from engine.reduced.model import ReducedModel
from engine.step import step

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["Stepper", "Trace", "rollout"]


@wp.kernel
def accumulate_step_stats(
    w: WorkArrays,
    c: ContactArrays,
    residual_threshold: float,
    # in/out
    iteration_sum: wp.array(dtype=wp.int32),
    iteration_max: wp.array(dtype=wp.int32),
    unconverged_steps: wp.array(dtype=wp.int32),
    solved_steps: wp.array(dtype=wp.int32),
    contact_sum: wp.array(dtype=wp.int32),
    contact_max: wp.array(dtype=wp.int32),
    overflow_steps: wp.array(dtype=wp.int32),
    penetration_max: wp.array(dtype=float),
    complementarity_max: wp.array(dtype=float),
    health: wp.array(dtype=wp.int32),
    residual_max: wp.array(dtype=float),
    residual_iterations: wp.array(dtype=wp.int32),
):
    """Per world: PADMM iterations (sum, max, capped steps), contacts (sum, max, steps with
    dropped contacts), deepest penetration [m] and largest complementarity residual; an
    unconverged stop's residual and engine.health's UNCONVERGED flag."""
    world = wp.tid()
    count = c.contact_count[world]
    contact_sum[world] = contact_sum[world] + count
    contact_max[world] = wp.max(contact_max[world], count)
    if c.contact_dropped[world] > 0:
        overflow_steps[world] = overflow_steps[world] + 1
    for k in range(count):
        penetration_max[world] = wp.max(penetration_max[world], -c.contact_distance[world, k])
    if w.valid[world] == 0:
        return
    complementarity_max[world] = wp.max(complementarity_max[world], w.residual_complementarity[world])
    its = w.iterations[world]
    iteration_sum[world] = iteration_sum[world] + its
    iteration_max[world] = wp.max(iteration_max[world], its)
    solved_steps[world] = solved_steps[world] + 1
    if w.converged[world] == 0:
        unconverged_steps[world] = unconverged_steps[world] + 1
    note_residual(world, w.converged[world], its, wp.max(w.residual_primal[world], w.residual_dual[world]),
                  residual_threshold, health, residual_max, residual_iterations)


class Stepper:
    """Advance a batch chunk by chunk, replaying a captured graph on CUDA. Only the state after a
    chunk is readable, so only the chunk's last step projects the end of the step for output
    (engine.step's project_output); the motion does not depend on the chunk length.

    Attributes: state (the current State), steps_done, and per-world statistics (device arrays
    (W,)): iteration_sum, iteration_max, unconverged_steps, solved_steps, contact_sum,
    contact_max, overflow_steps, penetration_max [m], complementarity_max; engine.health's
    flags (health: FAR from the pack, UNCONVERGED from every step, JOINTS_OPEN and DIVERGED from
    check_joints, which rollout calls at every record), joint_error_max [m],
    joint_error_angular_max [rad], residual_max and residual_iterations. health_report() reads
    them back as an engine.health.Health.
    """

    def __init__(self, model: Model, state: State, control: Control | None = None, chunk: int = 1, *,
                 capture: bool | None = None):
        if chunk < 1:
            raise ValueError(f"Stepper: chunk must be >= 1, got {chunk}")
        self.model, self.control, self.chunk = model, control, chunk
        self.grouped = isinstance(model, GroupedModel)  # a Stepper per group (engine.grouped)
        if self.grouped:
            if control is not None:
                model.check_control(control)
            self._parts = [Stepper(part, part_state, None if control is None else control.parts[k], chunk,
                                   capture=capture)
                           for k, ((_, part), part_state) in enumerate(zip(model.groups, state.parts))]
            self.steps_done = 0
            return
        self.reduced = isinstance(model, ReducedModel)  # steps one State in place (engine.reduced.model)
        self._buffers = [state] if self.reduced else [state, model.state()]
        self._current = 0
        self.steps_done = 0
        self._graphs: dict[int, wp.Graph] = {}
        device = model.device
        self.capture = device.is_cuda if capture is None else (capture and device.is_cuda)
        if self.reduced:
            if control is not None:
                model.check_control(control)
            return
        if control is None:
            self.control = model.control()
        zeros = lambda dtype=wp.int32: wp.zeros(model.num_worlds, dtype=dtype, device=device)  # noqa: E731
        self.iteration_sum, self.iteration_max = zeros(), zeros()
        self.unconverged_steps, self.solved_steps = zeros(), zeros()
        self.contact_sum, self.contact_max, self.overflow_steps = zeros(), zeros(), zeros()
        self.penetration_max, self.complementarity_max = zeros(float), zeros(float)
        self.health = wp.array(model.health_init, dtype=wp.int32, device=device)
        self.joint_error_max, self.joint_error_angular_max = zeros(float), zeros(float)
        self.residual_max, self.residual_iterations = zeros(float), zeros()

    @property
    def state(self) -> State:
        """The state after the last step (the buffer the next step reads)."""
        if self.grouped:
            return GroupedState([part.state for part in self._parts])
        return self._buffers[self._current]

    def _run(self, start: int):
        model = self.model
        if self.reduced:
            model.advance(self._buffers[0], self.chunk, self.control)
            return
        for k in range(self.chunk):
            src = self._buffers[(start + k) % 2]
            dst = self._buffers[(start + k + 1) % 2]
            # the end of a step is projected for output only: only the chunk's last state is read
            step(model, src, dst, self.control, project_output=k == self.chunk - 1)
            wp.launch(accumulate_step_stats, dim=model.num_worlds, device=model.device,
                      inputs=[model.work.arrays, model.work.contact_arrays, float(model.config.health_residual)],
                      outputs=[self.iteration_sum, self.iteration_max, self.unconverged_steps, self.solved_steps,
                               self.contact_sum, self.contact_max, self.overflow_steps, self.penetration_max,
                               self.complementarity_max, self.health, self.residual_max, self.residual_iterations])

    def check_joints(self) -> None:
        """Measure the current state's joint errors (engine.metrics: model.work.violation_*, energy)
        and update the health flags from them (on the device, no synchronization)."""
        model, cfg = self.model, self.model.config
        compute_metrics(model, self.state)
        work = model.work
        wp.launch(check_joints, dim=model.num_worlds, device=model.device,
                  inputs=[work.violation_linear, work.violation_angular, work.diverged,
                          float(cfg.health_joint_tolerance), float(cfg.health_angular_tolerance)],
                  outputs=[self.health, self.joint_error_max, self.joint_error_angular_max])

    def health_report(self) -> Health:
        """The health flags and their measures, read back to the host."""
        model, cfg = self.model, self.model.config
        return Health(flags=self.health.numpy().copy(), linear_max=self.joint_error_max.numpy().copy(),
                      angular_max=self.joint_error_angular_max.numpy().copy(),
                      residual_max=self.residual_max.numpy().copy(),
                      residual_iterations=self.residual_iterations.numpy().copy(),
                      extent=np.asarray(model.world_extent, float).copy(),
                      mass_ratio=np.asarray(model.world_mass_ratio, float).copy(),
                      joint_tolerance=float(cfg.health_joint_tolerance),
                      angular_tolerance=float(cfg.health_angular_tolerance),
                      residual_threshold=float(cfg.health_residual), max_speed=float(cfg.max_speed))

    def advance(self) -> None:
        """Run one chunk of steps."""
        if self.grouped:
            for k, part in enumerate(self._parts):
                if self.control is not None:
                    self.control.gather(k)  # the group's rows into its part's Control, then its chunk
                part.advance()
            self.steps_done += self.chunk
            return
        start = self._current
        if self.capture:
            if start not in self._graphs:
                if not self._graphs:  # first use: run eagerly once to compile every kernel
                    self._run(start)
                    self._current = 0 if self.reduced else (start + self.chunk) % 2
                    self.steps_done += self.chunk
                    return
                with wp.ScopedCapture(device=self.model.device) as capture:
                    self._run(start)
                self._graphs[start] = capture.graph
            wp.capture_launch(self._graphs[start])
        else:
            self._run(start)
        self._current = 0 if self.reduced else (start + self.chunk) % 2
        self.steps_done += self.chunk


@dataclass
class Trace:
    """What a rollout recorded, as NumPy arrays (T records, W worlds, P points).

    time (T,) [s]; points (T, W, P, 3) tracked points, world frame [m];
    violation_linear (T, W) [m]; violation_angular (T, W) [rad]; energy (T, W) [J];
    iterations (T, W) PADMM iterations of the last step before the record; drive_torque
    (T, W, J) torque [N m] (force [N]) of every joint drive in that step (0 without a drive);
    drive_speed (T, W, J) the driven joints' speeds [rad/s] ([m/s]) at the record (0 without a drive);
    diverged (W,) bool; point_names (list per world); halted_at (W,) time [s] at which rollout's
    halt froze the world (-1: never); health: engine.health.Health, the worlds flagged as not
    simulated faithfully and why (None where the path that made the trace has no such check).
    """

    time: np.ndarray
    points: np.ndarray
    violation_linear: np.ndarray
    violation_angular: np.ndarray
    energy: np.ndarray
    iterations: np.ndarray
    drive_torque: np.ndarray
    drive_speed: np.ndarray
    diverged: np.ndarray
    point_names: list
    halted_at: np.ndarray | None = None
    health: Health | None = None


@wp.kernel
def tracked_points(point_count: wp.array(dtype=wp.int32), point_body: wp.array2d(dtype=wp.int32),
                   point_local: wp.array2d(dtype=wp.vec3), body_q: wp.array2d(dtype=wp.transform),
                   points_out: wp.array2d(dtype=wp.vec3)):
    """World positions of the tracked points [m] (bare arrays: engine.reduced's gauge calls it too)."""
    world, p = wp.tid()
    if p >= point_count[world]:
        return
    points_out[world, p] = wp.transform_point(body_q[world, point_body[world, p]], point_local[world, p])


def point_positions(model, state) -> np.ndarray:
    """World positions [m] of every world's tracked points at ``state``, (W, P, 3) NumPy, P the
    batch's most points (a world's rows past its own count are zero), in the order of
    ``model.point_names``. Any plan: the positions come from the State's body poses (for a reduced
    plan the bodies its step wrote; for a grouped batch each group's, in world order). One kernel
    launch and a copy to the host."""
    if isinstance(model, GroupedModel):
        parts = [point_positions(part, part_state) for (_, part), part_state in zip(model.groups, state.parts)]
        return _scatter(parts, model.groups, model.num_worlds, 0)
    if isinstance(model, ReducedModel):
        return model.points(state)
    return points_of(model, state.body_q)


def points_of(model: Model, body_q: wp.array) -> np.ndarray:
    """The tracked points of ``model``'s specs on the body poses ``body_q`` (W, B), (W, P, 3) NumPy."""
    points = wp.zeros((model.num_worlds, model.max_points), dtype=wp.vec3, device=model.device)
    wp.launch(tracked_points, dim=(model.num_worlds, model.max_points), device=model.device,
              inputs=[model.point_count, model.point_body, model.point_local, body_q], outputs=[points])
    return points.numpy().reshape(model.num_worlds, model.max_points, 3)


@wp.kernel
def drive_torques(m: ModelArrays, row_lambda: wp.array2d(dtype=float), torque_out: wp.array2d(dtype=float)):
    """Drive torque [N m] = drive row impulse / dt; 0 for joints without a drive."""
    world, j = wp.tid()
    value = 0.0
    if j < m.joint_count[world] and m.joint_drive_row[world, j] >= 0:
        value = row_lambda[world, m.joint_drive_row[world, j]] / m.world_dt[world]
    torque_out[world, j] = value


@wp.kernel
def drive_speeds(joint_count: wp.array(dtype=wp.int32), joint_type: wp.array2d(dtype=wp.int32),
                 joint_parent: wp.array2d(dtype=wp.int32), joint_child: wp.array2d(dtype=wp.int32),
                 joint_X_p: wp.array2d(dtype=wp.transform), joint_X_c: wp.array2d(dtype=wp.transform),
                 joint_axis: wp.array2d(dtype=wp.vec3), joint_drive_row: wp.array2d(dtype=wp.int32),
                 body_q: wp.array2d(dtype=wp.transform), body_q_low: wp.array2d(dtype=wp.transform),
                 body_qd: wp.array2d(dtype=wp.spatial_vector), speed_out: wp.array2d(dtype=float)):
    """Speed [rad/s] or [m/s] of every driven joint's coordinate; 0 for joints without a drive
    (bare arrays: engine.reduced's gauge calls it too)."""
    world, j = wp.tid()
    value = 0.0
    if j < joint_count[world] and joint_drive_row[world, j] >= 0:
        parent = joint_parent[world, j]
        child = joint_child[world, j]
        X_wp, X_wc, r_p, r_c, d = joint_frames(body_q, body_q_low, world, parent, child, joint_X_p[world, j],
                                               joint_X_c[world, j], 0)
        J_c, J_p, q = joint_coordinate_row(joint_type[world, j], X_wp, X_wc, r_p, r_c, d, joint_axis[world, j])
        value = wp.dot(J_c, body_twist(body_qd, world, child)) + wp.dot(J_p, body_twist(body_qd, world, parent))
    speed_out[world, j] = value


def rollout(model: Model, state: State, control: Control, steps: int, *, dt: float | None = None,
            record_every: int = 1, halt=None) -> tuple[Trace, State]:
    """Run ``steps`` steps, recording tracked points and metrics every ``record_every`` steps.

    halt: optional callable(points, start) -> bool array (W,), called after every record with the
    tracked points of that record and of record 0 (each (W, P, 3)); the worlds it marks are frozen
    from then on (they cost no solver work and keep their last state, like diverged worlds, but
    are not flagged as diverged): an evaluation that already knows a world's outcome (a walker
    that fell) stops simulating it. The other worlds are unaffected.

    Returns the Trace (record 0 is the initial state) and the final State.
    """
    if steps < 0 or record_every < 1:
        raise ValueError(f"rollout: steps must be >= 0 and record_every >= 1, got {steps}, {record_every}")
    if isinstance(model, (ReducedModel, GroupedModel)):
        if dt is not None and float(dt) != model.dt:
            raise ValueError(f"rollout: the {model.plan.coordinates.value} plan steps with the dt it was packed "
                             f"with ({model.dt:g} s); pack again for dt {dt:g} s")
        if isinstance(model, GroupedModel):
            if control is not None:
                model.check_control(control)
            return rollout_groups(model, state, steps, record_every, halt, rollout, control)
        return _rollout_reduced(model, state, control, steps, record_every, halt)
    if dt is not None:
        model.set_dt(dt)
    stepper = Stepper(model, state, control, chunk=record_every)
    points = wp.zeros((model.num_worlds, model.max_points), dtype=wp.vec3, device=model.device)
    torques = wp.zeros((model.num_worlds, model.max_joints), dtype=float, device=model.device)
    speeds = wp.zeros((model.num_worlds, model.max_joints), dtype=float, device=model.device)
    records = {name: [] for name in ("points", "violation_linear", "violation_angular", "energy", "iterations",
                                     "drive_torque", "drive_speed")}
    times = []

    def record(current: State):
        stepper.check_joints()  # engine.metrics on the current state, and the health flags from it
        wp.launch(tracked_points, dim=(model.num_worlds, model.max_points), device=model.device,
                  inputs=[model.point_count, model.point_body, model.point_local, current.body_q], outputs=[points])
        records["points"].append(points.numpy().copy())
        wp.launch(drive_torques, dim=(model.num_worlds, model.max_joints), device=model.device,
                  inputs=[model.arrays, current.row_lambda, torques])
        records["drive_torque"].append(torques.numpy().copy())
        wp.launch(drive_speeds, dim=(model.num_worlds, model.max_joints), device=model.device,
                  inputs=[model.joint_count, model.joint_type, model.joint_parent, model.joint_child, model.joint_X_p,
                          model.joint_X_c, model.joint_axis, model.joint_drive_row, current.body_q, model.work.no_low,
                          current.body_qd],
                  outputs=[speeds])
        records["drive_speed"].append(speeds.numpy().copy())
        for name in ("violation_linear", "violation_angular", "energy", "iterations"):
            records[name].append(getattr(model.work, name).numpy().copy())

    model.work.halted.zero_()
    halted = np.zeros(model.num_worlds, dtype=bool)
    halted_at = np.full(model.num_worlds, -1.0)

    def check_halt():
        marked = np.asarray(halt(records["points"][-1], records["points"][0]), dtype=bool).reshape(model.num_worlds)
        new = marked & ~halted
        if new.any():
            halted[new] = True
            halted_at[new] = times[-1]
            model.work.halted.assign(halted.astype(np.int32))

    record(stepper.state)
    times.append(0.0)
    dt_host = model._dt_host
    for _ in range(steps // record_every):
        stepper.advance()
        record(stepper.state)
        times.append(stepper.steps_done * float(dt_host[0]))
        if halt is not None:
            check_halt()
    trace = Trace(time=np.asarray(times), points=np.stack(records["points"]),
                  violation_linear=np.stack(records["violation_linear"]),
                  violation_angular=np.stack(records["violation_angular"]), energy=np.stack(records["energy"]),
                  iterations=np.stack(records["iterations"]), drive_torque=np.stack(records["drive_torque"]),
                  drive_speed=np.stack(records["drive_speed"]),
                  diverged=model.work.diverged.numpy().astype(bool), point_names=model.point_names,
                  halted_at=halted_at, health=stepper.health_report())
    return trace, stepper.state


def _rollout_reduced(model: ReducedModel, state, control, steps: int, record_every: int, halt) -> tuple:
    """rollout() of a reduced plan: the same records, measured through the plan's gauge (every body's
    pose and twist into engine.metrics, as for the maximal path); health from the plan's stop flags
    and the joint errors of every record."""
    stepper = Stepper(model, state, control, chunk=record_every)
    records = {name: [] for name in ("points", "violation_linear", "violation_angular", "energy", "iterations",
                                     "drive_torque", "drive_speed")}
    times = []
    halted = np.zeros(model.num_worlds, dtype=bool)
    halted_at = np.full(model.num_worlds, -1.0)

    def record():
        for name, value in model.measure(stepper.state).items():
            records[name].append(value)

    record()
    times.append(0.0)
    for _ in range(steps // record_every):
        stepper.advance()
        record()
        times.append(stepper.steps_done * model.dt)
        if halt is not None:
            marked = np.asarray(halt(records["points"][-1], records["points"][0]), dtype=bool).reshape(model.num_worlds)
            new = marked & ~halted
            if new.any():
                halted[new] = True
                halted_at[new] = times[-1]
                model.set_halted(halted)
    stacked = {name: np.stack(values) for name, values in records.items()}
    worst = {k: np.where(np.isfinite(stacked[k]), stacked[k], np.inf).max(axis=0)  # non-finite: fully open
             for k in ("violation_linear", "violation_angular")}
    health = model.health(worst["violation_linear"], worst["violation_angular"])
    trace = Trace(time=np.asarray(times), **stacked, diverged=model.failure_codes() == 1,
                  point_names=model.point_names, halted_at=halted_at, health=health)
    return trace, stepper.state
