"""Model, State, Control and the solver workspace of a padded batch of worlds.

Conventions, used by every module of the engine:
- SI units: [m], [kg], [s], [rad], [N], [N m]. Z up; default gravity (0, 0, -9.81) m/s^2.
- Quaternions in Warp's (x, y, z, w) order. float32 on the device.
- Body poses ``body_q`` are ``wp.transform`` of the body's centre-of-mass frame: the
  translation is the centre of mass in the world frame [m], the rotation the body frame's
  orientation. Twists ``body_qd`` are ``wp.spatial_vector`` (v, w): linear velocity of the
  centre of mass then angular velocity, both world frame [m/s], [rad/s].
- Batches are padded: every per-item array has shape (num_worlds, max_X); each world stores its
  true count in ``X_count`` (num_worlds,); kernels run on (num_worlds, max_X) grids and return at
  once past a world's count.
- Constraint rows: each joint owns a fixed block of rows starting at ``joint_row_start``: its
  bilateral rows (kind LINEAR [m] or ANGULAR [rad]) then DYNAMICS rows along its free
  coordinate: one for armature and viscous damping, one for the drive (bounded by its effort). A row couples a child body and a parent body (-1 = world); its
  velocity is J_c . u_c + J_p . u_p. The padded row count ``max_rows`` is the tile size of the
  per-world dense Delassus matrix.
- A world's dual problem (ENGINE.md): D lambda + v_f in the normal cone of the row bounds, with
  D = J M^-1 J^T + R and v_f = J u_free - c, solved by PADMM in Jacobi-preconditioned variables
  x = P^-1 lambda, P = diag(D)^-1/2.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import warp as wp

from engine.collide import Candidates

__all__ = ["Control", "Integrator", "Model", "SolverConfig", "State", "Workspace"]

ROW_LINEAR = wp.constant(0)
ROW_ANGULAR = wp.constant(1)
ROW_DYNAMICS = wp.constant(2)
ROW_LIMIT = wp.constant(3)
ROW_CONTACT_NORMAL = wp.constant(4)
ROW_CONTACT_TANGENT = wp.constant(5)
UNBOUNDED = wp.constant(1.0e30)


class Integrator(enum.Enum):
    """Time-stepping scheme."""

    SEMI_IMPLICIT_EULER = "euler"  # velocities implicit in the reactions, poses explicit
    MOREAU_JEAN = "moreau"  # half pose step, dynamics at the midpoint, half pose step


@dataclass(frozen=True)
class SolverConfig:
    """Solver settings of a batch (frozen; per-world numbers are copied to device arrays).

    Attributes:
        integrator: Integrator.SEMI_IMPLICIT_EULER or Integrator.MOREAU_JEAN.
        max_iterations: PADMM iteration cap per step.
        tolerance: absolute primal and dual residual tolerance, in preconditioned units (sqrt of [J]).
        relative_tolerance: added tolerance per unit of the largest preconditioned impulse.
        eta: proximal weight (> 0; regularizes redundant constraints).
        rho: initial ADMM penalty.
        adaptive_rho: rescale rho (and refactor) when primal and dual residuals are unbalanced.
        cap_joint_penalty: give the free rows their own fixed ADMM penalty, free_rho: the bilateral
            joint rows, and the drive rows whose warm start lies within half of their effort
            limits (a drive that meets its limit during the step takes the world's penalty again,
            with a new factor). Their projection is the identity, so the penalty only slowed them:
            with the large rho that contacts and saturated drives call for, their soft modes
            converged at rho / (lambda + rho) per iteration; and a penalty driven down to RHO_MIN
            (their primal residual is zero) leaves the factor of redundant joint rows too little
            shift for float32. Off: one rho for all rows.
        free_rho: the free rows' penalty (cap_joint_penalty on); eta + free_rho is also the shift
            of the joint rows in the position projection's factor. Their soft modes (eigenvalue
            lambda of the preconditioned Delassus matrix) shrink by free_rho / (lambda + free_rho)
            per iteration, and the projection's Gauss-Newton steps are damped by as much; a
            smaller shift costs float32 digits in the factor of redundant rows. At 2e-4 instead of
            the initial rho (1e-3), on the CPU: the 10-link 1:10000 chain of benchmarks.stress S5 at
            its tolerance 1e-8 with this cap on (S5 itself runs it off) needs 31 instead of 66
            iterations per step and opens 7e-6 instead of 2.2e-5 m; the IFToMM N = 40 four-bar (S3,
            20 s) ends 4.9e-5 instead of 8.7e-4 m off its exact motion.
        rho_update_interval: iterations between penalty updates.
        stall_ratio: 0 (default) or a ratio in (0, 1): a world whose largest residual (primal or
            dual) did not fall below stall_ratio times its value STALL_WINDOW iterations earlier
            stops, counted as not converged (checked from 2 x STALL_WINDOW iterations on). The
            captured PADMM loop runs until a batch's slowest world stops; in batches of random
            walkers that world chases a near-singular direction at a fraction of a percent per
            iteration (benchmarks/results/README.md, "The PADMM tail of heterogeneous batches").
        acceleration: Nesterov momentum with restart.
        warmstart: start each step from the last step's impulses.
        warmstart_decay: share of the last step's impulses left out of the warm start. The
            proximal iterations never change an impulse's component that moves nothing (the
            redundant directions of over-constrained loops, e.g. a Bricard linkage), so a full
            warm start lets rounding pile up there step after step (an internal prestress that
            grows without bound). With 0.05: the Bricard linkage's redundant impulse stays at 3 %
            of its largest impulse over 2 s (60 % without); DR Legs standing (one world, 2 s on
            the CPU) peaks at 0.12 instead of 2.1 N s and needs 16 instead of 38 PADMM iterations.
        baumgarte: velocity-level stabilization factor (bias = -baumgarte / dt * residual).
        position_iterations: Gauss-Newton projections of the poses back onto the constraint
            manifold after each step (0 disables; reuses the factored Delassus matrix). They project the
            next configuration (Moreau-Jean: the next midpoint) with the velocity update;
            Moreau-Jean then projects the end of the step as often, for output only (engine.step).
        projection_velocity_update: add each projection displacement / dt to the velocities, so
            that the step is SHAKE-like (symplectic: energy stays bounded instead of draining).
        projection_velocity_floor: a projection iteration updates the velocities only when the
            largest bilateral joint error it corrects exceeds this [m]/[rad] (about two float32
            ulps of a coordinate of 0.5 m): below it the correction is mostly rounding of the
            poses. It was needed while Moreau-Jean projected the end of the step (rounding fed a
            neutral period-two mode, and the energy error grew as dt shrank: four-bar at 0.1 ms
            3.3 % without it); since the dynamics run on projected midpoints, the four-bar at
            0.1 ms drifts 5e-5 with or without it. 0 turns it off.
        projection_skip_floor: a projection iteration is skipped (no solve, nothing moves) in a
            world whose largest linear bilateral joint error is at or below this [m] and whose
            largest angular one is at or below projection_skip_floor_angular [rad]: its
            correction would be float32 rounding. The second Gauss-Newton iteration usually
            starts there, and on the four-bar at dt 1 ms the median step skips all four (the time
            saved: benchmarks/results/README.md, "Maximal path: design notes"). It also stops
            rounding-level corrections from being amplified near singular configurations (the parallelogram of
            benchmarks.stress S3, 20 s on the CPU: tip error 3.3e-2 -> 7.2e-3 m, energy error
            2.1e-4 -> 5.2e-5). Both floors at 0 turn the skip off.
        projection_skip_floor_angular: the angular rows' share of that test [rad]. A relative
            orientation carries more float32 rounding than a position: DR Legs keeps 4e-7 to 8e-7
            rad of angular joint error after any number of iterations, so with the linear floor
            for both it skipped nothing; with 1e-6 its second iteration is skipped on most steps
            standing (CPU, 2 s: 240 of 440 iterations; loops 6.0e-8 m, 8.6e-7 rad either way).
        limit_margin: a joint limit row turns on within this distance of the limit [rad]/[m]
            (plus the distance the joint covers in one step, so fast joints do not tunnel).
        limit_stabilization: share of a limit violation pushed back per step.
        contact_margin: contacts closer than this are kept (speculative) [m].
        contact_stabilization: share of a penetration pushed out per step.
        restitution_threshold: approach speeds below this bounce with no restitution [m/s].
        linear_solver: "dense" (per-world Cholesky tile, at most engine.pack.MAX_DENSE_ROWS
            rows: engine.linalg.dense), "sparse" (a Cholesky factor on the Delassus matrix's own
            sparsity, analysed once per topology: engine.linalg.sparse_analysis and
            engine.linalg.sparse) or "auto" (dense when the padded rows fit the tile, else
            sparse). Both solve exactly.
        max_speed: a world in which a body's centre of mass moves faster than this [m/s] is
            flagged diverged and frozen, like one whose state is no longer finite: a blow-up
            that grows over many steps is caught before its numbers overflow.
        health_joint_tolerance: a world whose largest linear joint error at a record exceeds this
            [m] is flagged (engine.health: its joints came apart); so is one packed where float32's
            spacing at its coordinates exceeds it (too far from the origin to close a joint).
        health_angular_tolerance: the same for the angular joint rows [rad]; a gross-tear guard:
            walkers' crank axes twist by up to 0.03 rad for a few records at foot impacts (24
            random walkers, 2 s, CPU) and close again.
        health_residual: a world whose PADMM stops unconverged (iteration cap or stall) with a
            residual above this (preconditioned units, sqrt [J]: about 1 m/s of error for 1 kg) is
            flagged. Walkers, whose contacts cap some steps, stopped at up to 0.075 (same run).
        step_kernel: "fused" (the whole step of a world in one warp, one launch per step:
            engine.fused; batches without contact shapes and at most engine.fused.FUSED_MAX_ROWS
            rows), "staged" (one kernel per stage, the PADMM loop as a captured while loop) or
            "auto" (fused where it fits).
        sparse_body_nodes: the sparse solver keeps a body acted on by many rows (a walker's
            torso) as six nodes of its factor instead of coupling all its rows with each other,
            where its analysis estimates a shorter schedule
            (engine.linalg.sparse_analysis.choose_body_nodes);
            off: the rows' own coupling pattern only.
        sparse_projection_pattern: with the sparse solver, a batch with rows besides its
            bilateral joint rows (drives, armature and damping, limits, contacts) cannot project
            with the PADMM factor; it factors its bilateral rows once per step, either on the
            PADMM's pattern with the other rows made identity ("never": no pattern of their own)
            or on a pattern of the bilateral rows alone (engine.linalg.sparse_analysis.
            bilateral_factor_rows; "always"), or the latter where its estimated schedule is the
            shorter one ("auto", batch_schedule_cost there: DR Legs standing as in Newton's
            example, 180 of 300 factor rows, 9.8 k instead of 12.9 k steps; not for walkers, whose
            rows are mostly bilateral). True and False read as "always" and "never".
        sparse_ordering: the sparse solver's elimination order: "minimum_degree" (greedy minimum
            degree, the least fill) or "shallow" (per topology, the shortest estimated schedule,
            engine.linalg.sparse_analysis.schedule_cost, of minimum degree and of minimum degree
            with the elimination tree's height added to each degree at the weights HEIGHT_WEIGHTS
            there: the factor's and the solves' levels run one after the other, so a shallower
            tree is a shorter chain; on paper DR Legs hanging 11.6 k -> 8.6 k steps, standing as in
            Newton's example 12.6 k -> 10.3 k, the default walker 7.5 k -> 6.3 k; not yet timed on
            a GPU, hence not the default).
        compensated_state: sum the twists and the configurations the dynamics run on with
            compensation (State.body_q_low, body_qd_low: engine.integrate) and the joint errors
            the projection corrects in float64 (engine.joints.joint_frames). Off: plain float32
            sums, about 10 % faster fused steps, a state that walks by the float32 grid of its
            values (a crank turning over for 10 s at dt 1 ms: 3.7e-3 instead of 2.3e-4 m from its
            exact motion; the IFToMM N = 20 four-bar through two flat passes in 3 s: 2.8e-4 instead
            of 1.3e-5 m).
    """

    integrator: Integrator = Integrator.MOREAU_JEAN
    max_iterations: int = 100
    tolerance: float = 1.0e-6
    relative_tolerance: float = 1.0e-4
    eta: float = 1.0e-5
    rho: float = 1.0e-3
    adaptive_rho: bool = True
    cap_joint_penalty: bool = True
    free_rho: float = 2.0e-4

    rho_update_interval: int = 4
    stall_ratio: float = 0.0
    acceleration: bool = True
    warmstart: bool = True
    warmstart_decay: float = 0.05
    baumgarte: float = 0.0
    position_iterations: int = 2
    projection_velocity_update: bool = True
    projection_velocity_floor: float = 1.0e-7
    projection_skip_floor: float = 1.0e-7
    projection_skip_floor_angular: float = 1.0e-6
    limit_margin: float = 0.02
    limit_stabilization: float = 0.2
    contact_margin: float = 0.01
    contact_stabilization: float = 0.2
    restitution_threshold: float = 0.05
    linear_solver: str = "auto"
    max_speed: float = 1.0e3
    health_joint_tolerance: float = 5.0e-3
    health_angular_tolerance: float = 0.25
    health_residual: float = 1.0
    step_kernel: str = "auto"
    sparse_body_nodes: bool = True
    sparse_projection_pattern: str = "auto"
    sparse_ordering: str = "minimum_degree"
    compensated_state: bool = True

    def __post_init__(self):
        if not isinstance(self.integrator, Integrator):
            try:
                object.__setattr__(self, "integrator", Integrator(self.integrator))
            except ValueError as exc:
                raise ValueError(f"SolverConfig.integrator: expected one of "
                                 f"{[i.value for i in Integrator]}, got {self.integrator!r}") from exc
        if self.step_kernel not in ("auto", "fused", "staged"):
            raise ValueError(f"SolverConfig.step_kernel: expected 'auto', 'fused' or 'staged', got {self.step_kernel!r}")
        if isinstance(self.sparse_projection_pattern, bool):
            choice = "always" if self.sparse_projection_pattern else "never"
            object.__setattr__(self, "sparse_projection_pattern", choice)
        if self.sparse_projection_pattern not in ("auto", "always", "never"):
            raise ValueError(f"SolverConfig.sparse_projection_pattern: expected 'auto', 'always' or 'never', "
                             f"got {self.sparse_projection_pattern!r}")
        if self.sparse_ordering not in ("minimum_degree", "shallow"):
            raise ValueError(f"SolverConfig.sparse_ordering: expected 'minimum_degree' or 'shallow', "
                             f"got {self.sparse_ordering!r}")
        if self.linear_solver not in ("auto", "dense", "sparse"):
            raise ValueError(f"SolverConfig.linear_solver: expected 'auto', 'dense' or 'sparse', "
                             f"got {self.linear_solver!r}")
        checks = {
            "projection_velocity_floor": self.projection_velocity_floor >= 0.0,
            "projection_skip_floor": self.projection_skip_floor >= 0.0,
            "projection_skip_floor_angular": self.projection_skip_floor_angular >= 0.0,
            "max_speed": self.max_speed > 0.0,
            "health_joint_tolerance": self.health_joint_tolerance > 0.0,
            "health_angular_tolerance": self.health_angular_tolerance > 0.0,
            "health_residual": self.health_residual > 0.0,
            "max_iterations": self.max_iterations >= 1,
            "tolerance": self.tolerance > 0.0,
            "relative_tolerance": self.relative_tolerance >= 0.0,
            "eta": self.eta > 0.0,
            "rho": self.rho > 0.0,
            "free_rho": self.free_rho > 0.0,
            "rho_update_interval": self.rho_update_interval >= 1,
            "stall_ratio": 0.0 <= self.stall_ratio < 1.0,
            "warmstart_decay": 0.0 <= self.warmstart_decay < 1.0,
            "baumgarte": 0.0 <= self.baumgarte <= 1.0,
            "position_iterations": self.position_iterations >= 0,
            "limit_margin": self.limit_margin >= 0.0,
            "limit_stabilization": 0.0 <= self.limit_stabilization <= 1.0,
            "contact_margin": self.contact_margin >= 0.0,
            "contact_stabilization": 0.0 <= self.contact_stabilization <= 1.0,
            "restitution_threshold": self.restitution_threshold >= 0.0,
        }
        for name, ok in checks.items():
            if not ok or not np.isfinite(float(getattr(self, name))):
                raise ValueError(f"SolverConfig.{name}: invalid value {getattr(self, name)!r}")


class Model:
    """A padded batch of worlds on one device (built by engine.pack_worlds).

    Host attributes: device, config, specs, num_worlds, max_bodies, max_joints, max_rows,
    max_points, body_names / joint_names / point_names (lists per world).

    Device arrays (shape, units, frame):
        body_count, joint_count, row_count, point_count (W,) int32
        body_mass, body_inv_mass (W, B) [kg], [1/kg]
        body_inertia, body_inv_inertia (W, B) mat33, about the COM, body-frame axes [kg m^2]
        joint_type, joint_parent, joint_child (W, J) int32 (parent -1 = world)
        joint_X_p (W, J) transform: parent anchor in the parent COM frame (world frame if no parent)
        joint_X_c (W, J) transform: child anchor in the child COM frame
        joint_axis, joint_axis2 (W, J) vec3, in the anchor frames
        joint_row_start (W, J) int32; joint_inertia_row, joint_drive_row (W, J) int32, -1 when none
        joint_armature [kg m^2]/[kg], joint_damping, joint_stiffness, joint_drive_damping,
        joint_effort_limit [N m]/[N] (W, J) float32
        row_kind, row_body_p, row_body_c (W, R) int32
        world_gravity (W,) vec3 [m/s^2]; world_dt (W,) [s]
        point_body (W, P) int32; point_local (W, P) vec3 in the COM frame [m]
        padmm_eta, padmm_rho_init, padmm_tolerance (W,) float32; padmm_rho_free (W,): the ADMM
        penalty of the free rows (SolverConfig.free_rho), 0 where they take the world's
        (engine.padmm.row_penalty)
        joint_limit_lower, joint_limit_upper (W, J) [rad]/[m]; joint_limit_lower_row,
        joint_limit_upper_row (W, J) int32, -1 when none
        shape_count (W,); shape_type, shape_body (W, S) int32; shape_X (W, S) transform in the
        body's COM frame; shape_size (W, S) vec3 [m]; shape_friction, shape_restitution (W, S)
        ground_normal (W,) vec3, ground_offset (W,) [m], ground_friction, ground_restitution (W,)
        pair_count (W,); pair_shape_a, pair_shape_b (W, max_pairs) int32 (b = -1: ground plane)
        contact_row_start (W,) int32: first contact row = number of joint, drive and limit rows
        body_row_begin, body_row_end (W, B) int32 into body_row (W, K) int32: each body's rows below
        contact_row_start in row order, coded 2 i + side (0: child, 1: parent; engine.pack.body_row_lists)
        bilateral_row_count (W,) int32: joint rows the position projection works on
    Host: world_extent (W,) the largest coordinate magnitude of a body's centre of mass or a world
    anchor when packed [m]; world_mass_ratio (W,) the largest mass ratio of two jointed bodies;
    health_init (W,) int32: engine.health's FAR flag of each world, set when packed;
    contact_capacity (contacts per world, 0 when the batch has no shapes), max_pairs,
    has_contacts, has_limits, has_bilateral_rows, has_unilateral_or_drive_rows; linear_solver;
    with the sparse solver sparse_system (the PADMM's factor schedules and buffers,
    engine.linalg.sparse_analysis.SparseSystem) and sparse_projection (the projection's, on the
    bilateral joint rows alone; None where it factors on the PADMM's pattern:
    SolverConfig.sparse_projection_pattern).
    """

    def __init__(self):
        self.work: Workspace | None = None
        self._dt_host: np.ndarray | None = None

    def state(self) -> State:
        """A new State holding the initial poses and twists of the specs."""
        state = State()
        state.body_q = wp.clone(self.body_q_init)
        state.body_qd = wp.clone(self.body_qd_init)
        state.body_q_offset = wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.spatial_vector, device=self.device)
        state.body_q_low = wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.transform, device=self.device)
        state.body_q_next = wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.transform, device=self.device)
        state.body_qd_low = wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.spatial_vector, device=self.device)
        state.row_lambda = wp.zeros((self.num_worlds, self.max_rows), dtype=float, device=self.device)
        capacity = max(self.contact_capacity, 1)
        state.contact_count = wp.zeros(self.num_worlds, dtype=wp.int32, device=self.device)
        state.contact_key = wp.zeros((self.num_worlds, capacity), dtype=wp.int32, device=self.device)
        state.contact_impulse = wp.zeros((self.num_worlds, capacity), dtype=wp.vec3, device=self.device)
        return state

    def control(self) -> Control:
        """A new Control holding the drive targets of the specs."""
        control = Control()
        control.joint_target_position = wp.clone(self.joint_target_position_init)
        control.joint_target_velocity = wp.clone(self.joint_target_velocity_init)
        control.joint_effort = wp.zeros((self.num_worlds, self.max_joints), dtype=float, device=self.device)
        control.body_f = wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.spatial_vector,
                                  device=self.device)
        return control

    def set_dt(self, dt) -> None:
        """Set the time step [s]: one float for all worlds or an array of num_worlds floats."""
        values = np.broadcast_to(np.asarray(dt, dtype=np.float32), (self.num_worlds,))
        if not np.all(np.isfinite(values)) or np.any(values <= 0.0):
            raise ValueError(f"dt must be positive and finite, got {dt!r}")
        if self._dt_host is not None and np.array_equal(values, self._dt_host):
            return
        self._dt_host = values.copy()
        self.world_dt.assign(values)


class State:
    """Time-varying quantities, double-buffered by the caller.

    body_q (W, B) transform: COM pose, world frame. body_qd (W, B) spatial_vector (v, w), world
    frame. body_q_offset (W, B) spatial_vector: how far the last Moreau-Jean step's output
    projection moved each pose onto the joints (translation [m], rotation vector [rad]); the next
    step undoes it to find its midpoint (engine.step). Zero in a new State; when body_q is set by
    hand, zero it too (a stale offset only costs the next step a correction of its own size).
    body_q_low (W, B) transform and body_qd_low (W, B) spatial_vector: the low parts of a
    compensated sum (engine.integrate), what float32 could not hold of the configuration the next
    step's dynamics start from (Moreau-Jean: its midpoint; translation [m] and raw quaternion
    components) and of the twist; of the order of 1e-7 of the values, zero in a new State (setting
    body_q or body_qd by hand leaves at most that much behind). body_q_next (W, B) transform
    (Moreau-Jean with the compensated state): the float32 part of the next step's midpoint, whose
    low part is body_q_low; the next step continues from that pair where the midpoint it finds
    from body_q, body_q_offset and body_qd matches it (engine.integrate.midpoint_pose_of), so
    that the motion does not depend on whether the output was projected; zero in a new State
    (nothing matches it). row_lambda (W, R): the last step's constraint impulses [N s] or [N m s]
    (warm start).
    contact_count (W,), contact_key (W, C), contact_impulse (W, C) vec3: the last step's contacts
    and their impulses in the world frame [N s], matched by key to warm-start the next step.
    """

    body_q: wp.array
    body_qd: wp.array
    body_q_offset: wp.array
    body_q_low: wp.array
    body_qd_low: wp.array
    body_q_next: wp.array
    row_lambda: wp.array
    contact_count: wp.array
    contact_key: wp.array
    contact_impulse: wp.array


class Control:
    """Inputs set between steps.

    joint_target_position (W, J) [rad]/[m]; joint_target_velocity (W, J) [rad/s]/[m/s];
    joint_effort (W, J) feed-forward joint torque/force [N m]/[N]; body_f (W, B) external
    wrench (force [N], torque [N m]) at the COM, world frame.
    """

    joint_target_position: wp.array
    joint_target_velocity: wp.array
    joint_effort: wp.array
    body_f: wp.array


class Workspace:
    """Preallocated per-step scratch and per-world diagnostics (no allocation after pack_worlds).

    Rows (W, R): row_J_c, row_J_p, row_MJ_c, row_MJ_p (spatial_vector; MJ = M^-1 J^T),
    row_bias (c), row_compliance (R), row_lo, row_hi (physical impulse bounds), row_residual
    (position-level residual [m]/[rad]), row_precond (P).
    Matrices (W, R, R), dense solver only: delassus (P D P), factor (its Cholesky factor with
    (eta + rho) I added). Sparse solver: its matrices and factors live in Model.sparse_system (the
    PADMM's) and Model.sparse_projection (engine.linalg.sparse_analysis.SparseSystem); sparse_root
    (W, B) the body nodes' square roots of the inverse inertias.
    PADMM vectors (W, R): v_f, lo, hi (preconditioned), x, x_prev, y, y_prev, y_hat, z, z_prev,
    z_hat, rhs, delta; row_shift (W, R): the factored matrix's diagonal shift per row (eta + the
    row's penalty: engine.padmm.row_penalty); row_free (W, R) int32: the rows on
    the free rows' penalty (SolverConfig.free_rho) this step (engine.padmm.row_is_free; 2: a drive that met its bound, to take
    the world's penalty at the next penalty update, flagged in demote (W,)). Per world (W,): rho, valid,

    iterations, residual_primal, residual_dual, converged,

    active, needs_factor, momentum, momentum_beta, merit, diverged (non-finite state: frozen),
    halted (stopped by engine.rollout's halt: frozen, not flagged as diverged); active_count (1,).
    Metrics (W,): violation_linear [m], violation_angular [rad], energy [J].
    Contacts: row_count (W,) rows of this step; candidates (collide.Candidates, (W, 4 max_pairs));
    contact_* (W, C): bodies, points, normal (from b to a), distance [m], friction, restitution,
    key; contact_count, contact_dropped (W,): kept and dropped (over capacity) contacts; warm
    (W, R) warm-start impulses; row_friction (W, R) friction coefficient on contact normal rows.
    """

    def __init__(self, num_worlds: int, max_bodies: int, max_rows: int, device, *, max_pairs: int = 0,
                 contact_capacity: int = 0, dense: bool = True):
        w, b, r = num_worlds, max_bodies, max_rows

        def zeros(shape, dtype=float):
            return wp.zeros(shape, dtype=dtype, device=device)

        self.body_qd_free = zeros((w, b), wp.spatial_vector)
        self.body_q_mid = zeros((w, b), wp.transform)
        self.body_q_mid_low = zeros((w, b), wp.transform)  # the midpoint's low part (engine.integrate)
        self.no_low = zeros((w, b), wp.transform)  # low parts of poses that have none: zeros, never written
        for name in ("row_J_c", "row_J_p", "row_MJ_c", "row_MJ_p"):
            setattr(self, name, zeros((w, r), wp.spatial_vector))
        for name in ("row_bias", "row_compliance", "row_lo", "row_hi", "row_residual", "row_precond",
                     "v_f", "lo", "hi", "x", "x_prev", "y", "y_prev", "y_hat", "z", "z_prev", "z_hat",
                     "rhs", "delta", "warm", "row_friction"):
            setattr(self, name, zeros((w, r)))
        # the dense path keeps P D P and its factor; the sparse path keeps its own (Model.sparse_system)
        self.row_shift = zeros((w, r))  # the factored matrix's diagonal shift per row
        self.row_free = zeros((w, r), wp.int32)  # rows on the free rows' penalty this step (engine.padmm)
        self.delassus = zeros((w, r, r) if dense else (w, 1, 1))
        self.factor = zeros((w, r, r) if dense else (w, 1, 1))
        for name in ("rho", "residual_primal", "residual_dual", "residual_complementarity", "momentum", "momentum_beta", "merit",
                     "stall_reference", "violation_linear", "violation_angular", "energy"):
            setattr(self, name, zeros(w))
        for name in ("iterations", "converged", "valid", "project", "projection_gate", "projection_mask", "active",
                     "needs_factor", "demote", "diverged", "halted"):
            setattr(self, name, zeros(w, wp.int32))
        self.active_count = zeros(1, wp.int32)
        self.row_count = zeros(w, wp.int32)  # rows of this step: joint, drive, limit and 3 per contact
        slots = max(4 * max_pairs, 1)
        self.candidates = Candidates()
        self.candidates.valid = zeros((w, slots), wp.int32)
        self.candidates.point_a = zeros((w, slots), wp.vec3)
        self.candidates.point_b = zeros((w, slots), wp.vec3)
        self.candidates.normal = zeros((w, slots), wp.vec3)
        self.candidates.distance = zeros((w, slots))
        capacity = max(contact_capacity, 1)
        for name in ("contact_body_a", "contact_body_b", "contact_key"):
            setattr(self, name, zeros((w, capacity), wp.int32))
        for name in ("contact_point_a", "contact_point_b", "contact_normal"):
            setattr(self, name, zeros((w, capacity), wp.vec3))
        for name in ("contact_distance", "contact_friction", "contact_restitution"):
            setattr(self, name, zeros((w, capacity)))
        self.contact_count = zeros(w, wp.int32)
        self.contact_dropped = zeros(w, wp.int32)
