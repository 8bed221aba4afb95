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
  coordinate: one for armature and viscous damping, one for the drive (bounded by its effort). A
  row couples a child body and a parent body (-1 = world); its velocity is J_c . u_c + J_p . u_p.
  The padded row count ``max_rows`` is the tile size of the per-world dense Delassus matrix.
- A world's dual problem (engine.padmm): D lambda + v_f in the normal cone of the row bounds, with
  D = J M^-1 J^T + R and v_f = J u_free - c, solved by PADMM in Jacobi-preconditioned variables
  x = P^-1 lambda, P = diag(D)^-1/2.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from engine.config import Integrator, SolverConfig  # re-exported: engine.model was their home

__all__ = ["Candidates", "ContactArrays", "Control", "ForceArrays", "Integrator", "Model", "ModelArrays",
           "ShapeArrays", "SolverConfig", "State", "WorkArrays", "Workspace"]

ROW_LINEAR = wp.constant(0)
ROW_ANGULAR = wp.constant(1)
ROW_DYNAMICS = wp.constant(2)
ROW_LIMIT = wp.constant(3)
ROW_CONTACT_NORMAL = wp.constant(4)
ROW_CONTACT_TANGENT = wp.constant(5)
UNBOUNDED = wp.constant(1.0e30)
# force slots (ForceArrays.force_kind): the spec's force elements (engine.forces), then one slot per
# undriven revolute or prismatic joint for Control.joint_effort (a drive takes it in its row)
FORCE_LINEAR_SPRING = wp.constant(0)
FORCE_JOINT_SPRING = wp.constant(1)
FORCE_BODY_WRENCH = wp.constant(2)
FORCE_JOINT_TORQUE = wp.constant(3)
FORCE_JOINT_EFFORT = wp.constant(4)


@wp.struct
class ModelArrays:
    """The Model's arrays that the step's kernels read, as one kernel argument (fields: the same
    array objects as the Model's attributes of the same names, documented there)."""

    body_count: wp.array(dtype=wp.int32)
    body_mass: wp.array2d(dtype=float)
    body_inv_mass: wp.array2d(dtype=float)
    body_inertia: wp.array2d(dtype=wp.mat33)
    body_inv_inertia: wp.array2d(dtype=wp.mat33)
    world_gravity: wp.array(dtype=wp.vec3)
    world_dt: wp.array(dtype=float)
    joint_count: wp.array(dtype=wp.int32)
    joint_type: wp.array2d(dtype=wp.int32)
    joint_parent: wp.array2d(dtype=wp.int32)
    joint_child: wp.array2d(dtype=wp.int32)
    joint_X_p: wp.array2d(dtype=wp.transform)
    joint_X_c: wp.array2d(dtype=wp.transform)
    joint_axis: wp.array2d(dtype=wp.vec3)
    joint_axis2: wp.array2d(dtype=wp.vec3)
    joint_row_start: wp.array2d(dtype=wp.int32)
    joint_inertia_row: wp.array2d(dtype=wp.int32)
    joint_drive_row: wp.array2d(dtype=wp.int32)
    joint_armature: wp.array2d(dtype=float)
    joint_damping: wp.array2d(dtype=float)
    joint_stiffness: wp.array2d(dtype=float)
    joint_drive_damping: wp.array2d(dtype=float)
    joint_effort_limit: wp.array2d(dtype=float)
    joint_limit_lower: wp.array2d(dtype=float)
    joint_limit_upper: wp.array2d(dtype=float)
    joint_limit_lower_row: wp.array2d(dtype=wp.int32)
    joint_limit_upper_row: wp.array2d(dtype=wp.int32)
    row_count: wp.array(dtype=wp.int32)  # as packed (joint rows); this step's: WorkArrays.row_count
    row_kind: wp.array2d(dtype=wp.int32)
    contact_row_start: wp.array(dtype=wp.int32)
    bilateral_row_count: wp.array(dtype=wp.int32)
    body_row_begin: wp.array2d(dtype=wp.int32)
    body_row_end: wp.array2d(dtype=wp.int32)
    body_row: wp.array2d(dtype=wp.int32)
    padmm_eta: wp.array(dtype=float)
    padmm_rho_init: wp.array(dtype=float)
    padmm_rho_free: wp.array(dtype=float)
    padmm_tolerance: wp.array(dtype=float)


@wp.struct
class ForceArrays:
    """The Model's force slots, as one kernel argument (engine.dynamics.force_wrench_of), padded to
    max_forces per world. force_kind (FORCE_*); force_body_a, force_body_b: the bodies it acts on
    (-1: the world; joint slots: the joint's child and parent); force_joint: the joint of a joint
    slot; force_point_a, force_point_b: a spring's points in the COM frames of its bodies (point_b
    in the world frame when body_b is -1) [m]; force_stiffness, force_damping, force_rest (spring
    and joint spring), force_tension_only (int32); force_force [N] and force_torque [N m] (body
    wrench, world frame); force_effort (joint torque) [N m] or [N]."""

    force_count: wp.array(dtype=wp.int32)
    force_kind: wp.array2d(dtype=wp.int32)
    force_body_a: wp.array2d(dtype=wp.int32)
    force_body_b: wp.array2d(dtype=wp.int32)
    force_joint: wp.array2d(dtype=wp.int32)
    force_point_a: wp.array2d(dtype=wp.vec3)
    force_point_b: wp.array2d(dtype=wp.vec3)
    force_stiffness: wp.array2d(dtype=float)
    force_damping: wp.array2d(dtype=float)
    force_rest: wp.array2d(dtype=float)
    force_tension_only: wp.array2d(dtype=wp.int32)
    force_force: wp.array2d(dtype=wp.vec3)
    force_torque: wp.array2d(dtype=wp.vec3)
    force_effort: wp.array2d(dtype=float)
    # each body's slots (W, B + 1) and (W, 2 max_forces): force_body_slot[w, start[w, b]:start[w, b + 1]]
    force_body_start: wp.array2d(dtype=wp.int32)
    force_body_slot: wp.array2d(dtype=wp.int32)


@wp.struct
class ShapeArrays:
    """The Model's collision arrays (shapes, ground planes, shape pairs), for engine.collide."""

    shape_type: wp.array2d(dtype=wp.int32)
    shape_body: wp.array2d(dtype=wp.int32)
    shape_X: wp.array2d(dtype=wp.transform)
    shape_size: wp.array2d(dtype=wp.vec3)
    shape_friction: wp.array2d(dtype=float)
    shape_restitution: wp.array2d(dtype=float)
    ground_normal: wp.array(dtype=wp.vec3)
    ground_offset: wp.array(dtype=float)
    ground_friction: wp.array(dtype=float)
    ground_restitution: wp.array(dtype=float)
    pair_count: wp.array(dtype=wp.int32)
    pair_shape_a: wp.array2d(dtype=wp.int32)
    pair_shape_b: wp.array2d(dtype=wp.int32)


@wp.struct
class WorkArrays:
    """The Workspace's per-step arrays of bodies, rows, the PADMM and the per-world diagnostics
    (the dense matrices and the contacts apart), as one kernel argument."""

    body_qd_free: wp.array2d(dtype=wp.spatial_vector)
    body_f_total: wp.array2d(dtype=wp.spatial_vector)
    body_q_mid: wp.array2d(dtype=wp.transform)
    body_q_mid_low: wp.array2d(dtype=wp.transform)
    no_low: wp.array2d(dtype=wp.transform)
    row_count: wp.array(dtype=wp.int32)
    row_body_c: wp.array2d(dtype=wp.int32)
    row_body_p: wp.array2d(dtype=wp.int32)
    row_J_c: wp.array2d(dtype=wp.spatial_vector)
    row_J_p: wp.array2d(dtype=wp.spatial_vector)
    row_MJ_c: wp.array2d(dtype=wp.spatial_vector)
    row_MJ_p: wp.array2d(dtype=wp.spatial_vector)
    row_bias: wp.array2d(dtype=float)
    row_compliance: wp.array2d(dtype=float)
    row_lo: wp.array2d(dtype=float)
    row_hi: wp.array2d(dtype=float)
    row_residual: wp.array2d(dtype=float)
    row_precond: wp.array2d(dtype=float)
    row_friction: wp.array2d(dtype=float)
    row_free: wp.array2d(dtype=wp.int32)
    row_shift: wp.array2d(dtype=float)
    warm: wp.array2d(dtype=float)
    v_f: wp.array2d(dtype=float)
    lo: wp.array2d(dtype=float)
    hi: wp.array2d(dtype=float)
    x: wp.array2d(dtype=float)
    x_prev: wp.array2d(dtype=float)
    y: wp.array2d(dtype=float)
    y_prev: wp.array2d(dtype=float)
    y_hat: wp.array2d(dtype=float)
    z: wp.array2d(dtype=float)
    z_prev: wp.array2d(dtype=float)
    z_hat: wp.array2d(dtype=float)
    rhs: wp.array2d(dtype=float)
    delta: wp.array2d(dtype=float)
    rho: wp.array(dtype=float)
    residual_primal: wp.array(dtype=float)
    residual_dual: wp.array(dtype=float)
    residual_complementarity: wp.array(dtype=float)
    momentum: wp.array(dtype=float)
    momentum_beta: wp.array(dtype=float)
    merit: wp.array(dtype=float)
    stall_reference: wp.array(dtype=float)
    iterations: wp.array(dtype=wp.int32)
    converged: wp.array(dtype=wp.int32)
    valid: wp.array(dtype=wp.int32)
    project: wp.array(dtype=wp.int32)
    projection_gate: wp.array(dtype=wp.int32)
    projection_mask: wp.array(dtype=wp.int32)
    active: wp.array(dtype=wp.int32)
    needs_factor: wp.array(dtype=wp.int32)
    demote: wp.array(dtype=wp.int32)
    diverged: wp.array(dtype=wp.int32)
    halted: wp.array(dtype=wp.int32)
    active_count: wp.array(dtype=wp.int32)
    violation_linear: wp.array(dtype=float)
    violation_angular: wp.array(dtype=float)
    energy: wp.array(dtype=float)
    sparse_root: wp.array2d(dtype=wp.mat33)  # the sparse solver's alone (set by engine.pack)


@wp.struct
class ContactArrays:
    """The Workspace's contacts of this step (engine.collide.compact_contacts), as one kernel argument."""

    contact_count: wp.array(dtype=wp.int32)
    contact_dropped: wp.array(dtype=wp.int32)
    contact_key: wp.array2d(dtype=wp.int32)
    contact_body_a: wp.array2d(dtype=wp.int32)
    contact_body_b: wp.array2d(dtype=wp.int32)
    contact_point_a: wp.array2d(dtype=wp.vec3)
    contact_point_b: wp.array2d(dtype=wp.vec3)
    contact_normal: wp.array2d(dtype=wp.vec3)
    contact_distance: wp.array2d(dtype=float)
    contact_friction: wp.array2d(dtype=float)
    contact_restitution: wp.array2d(dtype=float)


@wp.struct
class Candidates:
    """Candidate contacts (W, K): valid flag, points on a and b and normal (world frame), distance."""

    valid: wp.array2d(dtype=wp.int32)
    point_a: wp.array2d(dtype=wp.vec3)
    point_b: wp.array2d(dtype=wp.vec3)
    normal: wp.array2d(dtype=wp.vec3)
    distance: wp.array2d(dtype=float)


class _Grouped:
    """Holds struct groups of its arrays (``_groups``: attribute name -> struct type), built once
    and kept in step: assigning an attribute that a group has as a field sets the field too, so a
    kernel given the group always sees the arrays the attributes hold."""

    _groups: dict = {}

    def __init__(self):
        for group, struct in self._groups.items():
            object.__setattr__(self, group, struct())

    def __setattr__(self, name, value):
        object.__setattr__(self, name, value)
        for group, struct in self._groups.items():
            if name in struct.vars:
                setattr(self.__dict__[group], name, value)


class Model(_Grouped):
    """A padded batch of worlds on one device (built by engine.pack_worlds).

    Host attributes: device, config, specs, num_worlds, max_bodies, max_joints, max_rows,
    max_points, body_names / joint_names / point_names (lists per world).

    Device arrays (shape, units, frame), grouped for the kernels in ``arrays`` (ModelArrays) and
    ``shape_arrays`` (ShapeArrays):
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
        penalty of the free rows (Tuning.free_rho), 0 where they take the world's
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
    Force slots (``force_arrays``, ForceArrays; engine.forces): force_count (W,) int32 and the
    per-slot arrays (W, max_forces); has_forces: whether any world has a slot (the step then adds
    their wrenches to body_f); force_summary: the spec elements counted by kind, for the plan.
    Host: world_extent (W,) the largest coordinate magnitude of a body's centre of mass or a world
    anchor when packed [m]; world_mass_ratio (W,) the largest mass ratio of two jointed bodies;
    health_init (W,) int32: engine.health's FAR flag of each world, set when packed;
    contact_capacity (contacts per world, 0 when the batch has no shapes), max_pairs,
    has_contacts, has_limits, has_bilateral_rows, has_unilateral_or_drive_rows; linear_solver;
    with the sparse solver sparse_system (the PADMM's factor schedules and buffers,
    engine.linalg.sparse_analysis.SparseSystem) and sparse_projection (the projection's, on the
    bilateral joint rows alone; None where it factors on the PADMM's pattern:
    Tuning.sparse_projection_pattern).
    """

    _groups = {"arrays": ModelArrays, "shape_arrays": ShapeArrays, "force_arrays": ForceArrays}

    def __init__(self):
        super().__init__()
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
    joint_effort (W, J) feed-forward joint torque/force [N m]/[N] (a drive's row takes it within
    its effort limit; on an undriven revolute or prismatic joint it is applied as a force slot,
    engine.dynamics.force_wrench_of; joints of several degrees of freedom (spherical, universal,
    cylindrical) and fixed ones have no single coordinate and do not read it: apply body_f
    instead); body_f (W, B) external wrench (force [N], torque [N m]) at the COM, world frame.
    The tree plan has a Control of its own (engine.reduced.model.TreeModel: body_f, joint_effort).
    """

    joint_target_position: wp.array
    joint_target_velocity: wp.array
    joint_effort: wp.array
    body_f: wp.array


class Workspace(_Grouped):
    """Preallocated per-step scratch and per-world diagnostics (no allocation after pack_worlds);
    ``arrays`` (WorkArrays) and ``contact_arrays`` (ContactArrays) group them for the kernels.

    Rows (W, R): row_body_c, row_body_p (this step's: contact rows change them), row_J_c, row_J_p,
    row_MJ_c, row_MJ_p (spatial_vector; MJ = M^-1 J^T), row_bias (c), row_compliance (R), row_lo,
    row_hi (physical impulse bounds), row_residual (position-level residual [m]/[rad]), row_precond
    (P), row_friction (friction coefficient on contact normal rows), warm (warm-start impulses).
    Matrices (W, R, R), dense solver only: delassus (P D P), factor (its Cholesky factor with the
    shift added). Sparse solver: its matrices and factors live in Model.sparse_system (the PADMM's)
    and Model.sparse_projection (engine.linalg.sparse_analysis.SparseSystem); sparse_root (W, B)
    the body nodes' square roots of the inverse inertias.
    PADMM vectors (W, R): v_f, lo, hi (preconditioned), x, x_prev, y, y_prev, y_hat, z, z_prev,
    z_hat, rhs, delta; row_shift: the factored matrix's diagonal shift per row (eta + the row's
    penalty: engine.padmm.row_penalty); row_free (int32): the rows on the free rows' penalty this
    step (engine.padmm.row_is_free; 2: a drive that met its bound, to take the world's penalty at
    the next penalty update, flagged in demote (W,)). Per world (W,): rho, valid, iterations,
    residual_primal, residual_dual, residual_complementarity, converged, active, needs_factor,
    momentum, momentum_beta, merit, stall_reference, project, projection_gate, projection_mask,
    diverged (non-finite state: frozen), halted (stopped by engine.rollout's halt: frozen, not
    flagged as diverged); active_count (1,).
    Metrics (W,): violation_linear [m], violation_angular [rad], energy [J].
    body_f_total (W, B): Control.body_f plus the force slots' wrenches of this step.
    Contacts: row_count (W,) rows of this step; candidates (Candidates, (W, 4 max_pairs));
    contact_* (W, C): bodies, points, normal (from b to a), distance [m], friction, restitution,
    key; contact_count, contact_dropped (W,): kept and dropped (over capacity) contacts.
    """

    _groups = {"arrays": WorkArrays, "contact_arrays": ContactArrays}

    def __init__(self, num_worlds: int, max_bodies: int, max_rows: int, device, *, max_pairs: int = 0,
                 contact_capacity: int = 0, dense: bool = True):
        super().__init__()
        w, b, r = num_worlds, max_bodies, max_rows

        def zeros(shape, dtype=float):
            return wp.zeros(shape, dtype=dtype, device=device)

        self.body_qd_free = zeros((w, b), wp.spatial_vector)
        self.body_f_total = zeros((w, b), wp.spatial_vector)  # body_f plus the force slots' wrenches
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
        for name in ("rho", "residual_primal", "residual_dual", "residual_complementarity", "momentum", "momentum_beta",
                     "merit", "stall_reference", "violation_linear", "violation_angular", "energy"):
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
