"""step(model, state_in, state_out, control, dt): one time step of every world of a batch.

The stages, in order (each a module of the engine):
1. (Moreau-Jean only) half pose step to the midpoint configuration, and the free velocities there
   (engine.integrate.midpoint_free_velocity; semi-implicit Euler computes them in stage 3)
2. joint rows: Jacobians, biases, compliance and bounds, joint limits (engine.joints)
   collision detection and contact rows, only when the batch has shapes (engine.collide,
   engine.contacts); warm-start impulses gathered (contacts matched by key)
3. dual problem: free velocities, Delassus matrix, preconditioner (engine.dynamics); with force
   slots (engine.forces' elements, Control.joint_effort on undriven joints) the free velocities
   take their wrenches with Control.body_f, evaluated at the midpoint poses and the step's starting
   twists (Moreau-Jean; the midpoint pass's own free velocities are overwritten) or at the step's
   start (semi-implicit Euler): engine.dynamics.forced_free_velocities
4. PADMM on all worlds, per-world early exit, warm-started (engine.padmm)
5. velocity update; a whole pose step from the configuration of the dynamics, projected onto the
   joint constraints by Gauss-Newton with SHAKE's velocity update (engine.integrate). Moreau-Jean
   then reports the end of the step half-way to that next midpoint, projected onto the joints
   for output only: the offset is kept in the State and undone when the next step finds its
   midpoint, so the dynamics always run on projected midpoints. (Projecting the end of the step
   itself and recovering the midpoint by half a step leaves a neutral period-two oscillation
   along the joint normals that the velocity update feeds, draining energy.)
6. divergence guard: a world with a non-finite state is flagged and frozen (engine.integrate)
Everything that varies between steps lives in device arrays; nothing is allocated, so the whole
step can be captured once (wp.ScopedCapture) and replayed.
"""

import time

import warp as wp

from engine.collide import compact_contacts, generate_candidates
from engine.contacts import contact_rows, gather_warmstart, store_contacts
from engine.dynamics import build_dual_problem, forced_free_velocities
from engine.fused import fused_step
from engine.integrate import (
    apply_impulses,
    guard_divergence,
    integrate_poses,
    midpoint_free_velocity,
    project_positions,
)
from engine.joints import compute_joint_rows
from engine.model import Control, Integrator, Model, State
from engine.padmm import solve_padmm
from engine.grouped import GroupedModel, step_groups
from engine.reduced.model import ReducedModel

__all__ = ["StageTimer", "detect_contacts", "step"]


def detect_contacts(model: Model, body_q, body_qd) -> None:
    """Candidates per shape pair, compaction per world, and the contact rows."""
    work, device, cfg = model.work, model.device, model.config
    wp.launch(generate_candidates, dim=(model.num_worlds, model.max_pairs), device=device,
              inputs=[model.shape_arrays, float(cfg.contact_margin), body_q, work.candidates])
    wp.launch(compact_contacts, dim=model.num_worlds, device=device,
              inputs=[model.shape_arrays, model.contact_row_start, model.contact_capacity, float(cfg.contact_margin),
                      work.candidates, work.row_count, work.contact_arrays])
    wp.launch(contact_rows, dim=(model.num_worlds, model.contact_capacity), device=device,
              inputs=[model.arrays, work.arrays, work.contact_arrays, float(cfg.contact_stabilization),
                      float(cfg.restitution_threshold), body_q, body_qd])


class StageTimer:
    """Wall time per stage of step() [s], accumulated over calls (synchronizes the device at every
    stage boundary, so use it for profiling, never inside a captured graph). The staged step
    reports its six stages, the fused step one ("fused")."""

    STAGES = ("kinematics", "collision", "dual_problem", "padmm", "integrate", "projection", "fused")

    def __init__(self, device):
        self.device = device
        self.seconds = dict.fromkeys(self.STAGES, 0.0)
        self.marked = set()  # the stages of the path taken (the fused step is one stage)
        self.calls = 0
        self._last = None

    def start(self):
        """Synchronize the device and start timing a step."""
        wp.synchronize_device(self.device)
        self._last = time.perf_counter()
        self.calls += 1

    def mark(self, stage: str):
        """Synchronize the device and add the time since the last mark to ``stage``."""
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.seconds[stage] += now - self._last
        self.marked.add(stage)
        self._last = now

    def milliseconds_per_step(self) -> dict[str, float]:
        """Mean milliseconds per step of each stage the step took."""
        return {k: 1e3 * v / max(self.calls, 1) for k, v in self.seconds.items() if k in self.marked}


def step(model: Model, state_in: State, state_out: State, control: Control | None = None, dt: float | None = None, *,
         timer: StageTimer | None = None, project_output: bool = True) -> None:
    """Advance every world by one step from state_in into state_out, whatever the model's plan.

    Args:
        model: the batch (engine.pack).
        state_in, state_out: two distinct State buffers; the caller swaps them between steps. (A
            reduced plan steps one State in place: state_out may be state_in; when it is not,
            state_in is copied into it first.)
        control: drive targets, feed-forward efforts and external wrenches (maximal plans; None:
            the specs' targets). The reduced plans take efforts and wrenches (model.control()) and
            their drive targets from the specs, and so does a batch planned in groups (its
            GroupedControl gathers each group's rows).
        dt: time step [s] for all worlds; None keeps model.world_dt (per-world device array).
            Changing it writes the device array, so pass None inside a captured graph.
        timer: optional StageTimer collecting the wall time of every stage.
        project_output: (Moreau-Jean) project the end of the step onto the joints. The projection
            is for output only: the next step starts from the projected midpoint whether or not
            it ran (with the compensated state to within its low parts, ~1e-14 relative), so a
            caller that does not read state_out (engine.rollout.Stepper inside a chunk) skips it;
            the joints of an unprojected state_out are open by the drift of half a step.
    """
    if isinstance(model, GroupedModel):
        if dt is not None:
            raise ValueError("step: a batch planned in groups keeps the dt it was packed with; pack with "
                             "coordinates='maximal' for a changing dt")
        if control is not None:
            model.check_control(control)
        step_groups(model, state_in, state_out, step, control)
        return
    if isinstance(model, ReducedModel):
        if dt is not None:
            raise ValueError(f"step: the {model.plan.coordinates.value} plan keeps the dt it was packed with; pack "
                             f"with coordinates='maximal' for a changing dt")
        if control is not None:
            model.check_control(control)
        model.step(state_in, state_out, control)
        return
    if control is None:
        if getattr(model, "_default_control", None) is None:
            model._default_control = model.control()
        control = model._default_control
    mark = timer.mark if timer is not None else (lambda stage: None)
    if timer is not None:
        timer.start()
    if state_in is state_out:
        raise ValueError("step: state_in and state_out must be different State objects")
    if dt is not None:
        model.set_dt(dt)
    if model.step_kernel == "fused":  # the whole step in one launch (engine.fused)
        fused_step(model, state_in, state_out, control, project_output=project_output)
        mark("fused")
        return
    work, device, m, w = model.work, model.device, model.arrays, model.work.arrays
    bodies = (model.num_worlds, model.max_bodies)
    moreau = model.config.integrator is Integrator.MOREAU_JEAN
    compensated = int(model.config.tuning.compensated_state)
    body_q, body_q_low = state_in.body_q, state_in.body_q_low
    if moreau:  # the midpoint, and the free velocities there (stage 3's first part)
        wp.launch(midpoint_free_velocity, dim=bodies, device=device,
                  inputs=[m, w, state_in.body_q, state_in.body_q_offset, state_in.body_qd, state_in.body_q_low,
                          state_in.body_q_next, state_in.body_qd_low, control.body_f, compensated,
                          state_out.body_qd_low])
        body_q, body_q_low = work.body_q_mid, work.body_q_mid_low
    compute_joint_rows(model, body_q, state_in.body_qd, control, body_q_low)
    mark("kinematics")
    if model.has_contacts:
        detect_contacts(model, body_q, state_in.body_qd)
    mark("collision")
    warm = state_in.row_lambda  # without contacts every row's warm start is its last impulse (zero on padding)
    if model.has_contacts:
        wp.launch(gather_warmstart, dim=(model.num_worlds, model.max_rows), device=device,
                  inputs=[m, w, work.contact_arrays, state_in.row_lambda, state_in.contact_count,
                          state_in.contact_key, state_in.contact_impulse])
        warm = work.warm
    forced = getattr(model, "has_forces", False)
    if forced:  # the free velocities under body_f and the force slots, at the dynamics' configuration
        forced_free_velocities(model, body_q, state_in.body_qd, state_in.body_qd_low, control, state_out.body_qd_low)
    build_dual_problem(model, body_q, state_in.body_qd, state_in.body_qd_low, control.body_f, state_out.body_qd_low,
                       free_velocities=not moreau and not forced)
    mark("dual_problem")
    solve_padmm(model, warm, state_out.row_lambda)
    if model.has_contacts:
        wp.launch(store_contacts, dim=(model.num_worlds, model.contact_capacity), device=device,
                  inputs=[m, work.contact_arrays, state_out.row_lambda, state_out.contact_count,
                          state_out.contact_key, state_out.contact_impulse])
    mark("padmm")
    # u+, then a whole step from the configuration of the dynamics (compensated where configured): the next
    # step's (Moreau-Jean: the next midpoint), projected onto the joints with SHAKE's velocity update
    wp.launch(apply_impulses, dim=bodies, device=device,
              inputs=[m, w, state_out.row_lambda, compensated, body_q, body_q_low, state_out.body_qd, state_out.body_q,
                      state_out.body_q_low, state_out.body_qd_low])
    mark("integrate")
    project_positions(model, state_out.body_q, state_out.body_qd,
                      body_q_low=state_out.body_q_low, body_qd_low=state_out.body_qd_low)
    if moreau:  # the end of the step: half-way to the next midpoint, projected for output only, with as many
        # iterations as the midpoint's (body_q_next: the compensated end of the dynamics' step, which the
        # next midpoint starts from)
        wp.launch(integrate_poses, dim=bodies, device=device,
                  inputs=[m, 0.5, body_q, state_out.body_qd, compensated, state_out.body_q, state_out.body_q_next,
                          state_out.body_q_offset])
        if project_output:
            project_positions(model, state_out.body_q, state_out.body_qd,
                              velocity_update=False, body_q_offset=state_out.body_q_offset, prepare=False)
    wp.launch(guard_divergence, dim=model.num_worlds, device=device,
              inputs=[m, w, float(model.config.max_speed), state_in.body_q, state_in.body_qd, state_in.body_q_offset,
                      state_in.body_q_low, state_in.body_qd_low, state_in.body_q_next, state_out.body_q,
                      state_out.body_qd, state_out.body_q_offset, state_out.body_q_low, state_out.body_qd_low,
                      state_out.body_q_next])
    mark("projection")
