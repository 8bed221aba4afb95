"""Tabulated sub-chains: batches of MechanismSpecs stepped in reduced coordinates.

A world that engine.reduced.tabulated_layout accepts (a floating base carrying one-DoF planar
sub-chains, each turned by one driven revolute joint) has 6 + L coordinates: the base's pose
and the L driving coordinates, every link read from its sub-chain's table. Its loops are closed
by construction, to the tables' closure error (TabulatedModel.closure_error). The physics are the
maximal engine's (drives, ground contacts, friction cones, PADMM) with the rows reduced to the
drives and the contacts (engine.reduced.tabulated_step).

    model = pack_tabulated(specs, device="cuda", dt=2e-3)   # ValueError "world i (name): reason"
    model.step(100)                                       # in place; capturable in a CUDA graph
    points, energy, torque, speed = model.record()
    trace = rollout_tabulated(model, 1000, record_every=10)  # an engine.Trace

Of engine.SolverConfig it uses tolerance, relative_tolerance, max_iterations, contact_margin,
contact_stabilization and max_speed, and of its tuning (engine.Tuning) eta, rho (None:
engine.config.TABULATED_RHO = 1, the rows' Jacobi-preconditioned scale), rho_update_interval,
tabulated_tiled and tabulated_registers, and the integrator: Moreau-Jean (the default: the pose
and the driving coordinates by half steps, M, the bias forces, the tables and the contacts at the
midpoint with the rates extrapolated to it) or semi-implicit Euler. It has no joint rows, so no
projection.
"""

import numpy as np
import warp as wp

from engine.config import TABULATED_RHO, Integrator, SolverConfig
from engine.reduced.tabulated_kernel import (BASE_SLOTS, DIVERGED_FAST, DIVERGED_NONFINITE, KINV_VECS, MAX_GROUPS,
                                             MAX_LINKS, MAX_ROWS, NV, ROW_VECS, TILED_REGISTERS, TILED_ROUNDS,
                                             TILED_WORLDS_PER_SM, TabulatedState,
                                             TabulatedWorlds, body_poses, freeze_worlds, link_pose, rot_minus_y,
                                             tiled_max_worlds)
from engine.reduced.chains import ChainControl, check_control_arrays
from engine.reduced.tabulated_forces import TabulatedForces, pack_forces, spring_energy
from engine.reduced.tabulated_layout import tabulated_layout
from engine.reduced.tabulated_step import HISTORY, step_kernel
from engine.reduced.tabulated_tables import TABLE_SAMPLES
from engine.spec import MechanismSpec

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["TabulatedModel", "describe", "pack_tabulated", "rollout_tabulated"]


@wp.kernel
def record_state(
    worlds: TabulatedWorlds,
    state: TabulatedState,
    point_count: wp.array(dtype=wp.int32),
    point_group: wp.array2d(dtype=wp.int32),
    point_link: wp.array2d(dtype=wp.int32),
    point_local: wp.array2d(dtype=wp.vec3),
    group_joint: wp.array2d(dtype=wp.int32),
    drive_torque: wp.array2d(dtype=float),
    fo: TabulatedForces,
    # out
    points: wp.array2d(dtype=wp.vec3),
    energy: wp.array(dtype=float),
    joint_torque: wp.array2d(dtype=float),
    joint_speed: wp.array2d(dtype=float),
):
    """Tracked points [m] (on the base: an offset from its centre in the state frame; on a link: from
    the link's centre in its table frame), the mechanical energy [J] (every link's own kinetic energy
    plus the potential of gravity and of the springs) and the drives' torques [N m] and speeds [rad/s]
    by spec joint."""
    w = wp.tid()
    p = state.position[w]
    R = wp.quat_to_matrix(state.orientation[w])
    v = state.velocity[w]
    om = state.angular_velocity[w]
    axis = -(R * wp.vec3(0.0, 1.0, 0.0))
    g = worlds.gravity[w]
    mb = worlds.base[w][0]
    Ib = R * worlds.base_inertia[w] * wp.transpose(R)
    e = 0.5 * mb * wp.dot(v, v) + 0.5 * wp.dot(om, Ib * om) - mb * wp.dot(g, p)
    for i in range(point_count[w]):
        gi = point_group[w, i]
        local = point_local[w, i]
        if gi < 0:
            points[w, i] = p + R * local
        else:
            d, e1, ang = link_pose(worlds, state, w, gi, point_link[w, i], R)
            points[w, i] = p + d + R * (rot_minus_y(ang[0]) * local)
    for j in range(joint_torque.shape[1]):
        joint_torque[w, j] = 0.0
        joint_speed[w, j] = 0.0
    for gi in range(worlds.group_count[w]):
        rate = state.coord_rate[w, gi]
        joint_torque[w, group_joint[w, gi]] = drive_torque[w, gi]
        joint_speed[w, group_joint[w, gi]] = rate
        t = worlds.group_table[w, gi]
        for k in range(worlds.table_links[t]):
            d, e1, ang = link_pose(worlds, state, w, gi, k, R)
            mk = worlds.link_mass[w, gi * MAX_LINKS + k]
            vk = v + wp.cross(om, d) + e1 * rate
            wk = om + axis * (ang[1] * rate)
            Rk = R * rot_minus_y(ang[0])
            Ik = Rk * worlds.link_inertia[w, gi * MAX_LINKS + k] * wp.transpose(Rk)
            e += 0.5 * mk * wp.dot(vk, vk) + 0.5 * wp.dot(wk, Ik * wk) - mk * wp.dot(g, p + d)
    energy[w] = e + spring_energy(worlds, state, fo, w)



class TabulatedModel:
    """A batch of tabulated worlds on one device: the tables, every world's parameters, its state
    and the step's scratch (built by pack_tabulated).

    layouts: the worlds' TabulatedLayouts; specs: their MechanismSpecs; point_names: per world,
    the spec's tracked point names in its order; closure_error: the largest closure error of the
    batch's tables at their scales [m]; world_closure_error (W,) [m] per world; tiled: one block
    of lanes per world (see tiled_max_worlds) or one thread. State arrays (warp, W first):
    position, orientation, velocity, angular_velocity (the base's centre of mass and the state
    frame: TabulatedLayout), coord and coord_rate (W, MAX_GROUPS): the driving coordinates [rad]
    and rates [rad/s] in sub-chain order; frozen and diverged (0, or DIVERGED_NONFINITE or
    DIVERGED_FAST) per world; impulse (W, MAX_ROWS): the last step's impulses by slot."""

    def __init__(self, layouts: list, device, dt: float, config: SolverConfig):
        self.device, self.dt, self.config = wp.get_device(device), float(dt), config
        self.layouts = layouts
        self.specs = [lay.spec for lay in layouts]
        self.num_worlds = W = len(layouts)
        tables, table_index = [], {}
        for lay in layouts:
            for chain in lay.groups:
                if id(chain.table) not in table_index:
                    table_index[id(chain.table)] = len(tables)
                    tables.append(chain.table)
        samples = {t.samples for t in tables} or {TABLE_SAMPLES}
        if len(samples) != 1:
            raise ValueError(f"pack_tabulated: every table needs the same number of samples, got {sorted(samples)}")
        N = samples.pop()
        T = max(len(tables), 1)
        links = np.zeros((3, T, N, MAX_LINKS, 3), np.float32)
        contact = np.zeros((2, T, N, 3), np.float32)
        table_links = np.zeros(T, np.int32)
        table_contact_link = np.zeros(T, np.int32)
        for t, table in enumerate(tables):
            k = table.links.shape[1]
            links[0, t, :, :k], links[1, t, :, :k], links[2, t, :, :k] = table.links, table.links_d1, table.links_d2
            contact[0, t], contact[1, t] = table.contact, table.contact_d1
            table_links[t], table_contact_link[t] = k, table.contact_link
        G = MAX_GROUPS
        P = max(max(len(lay.points) for lay in layouts), 1)
        B = max(len(lay.bodies) for lay in layouts)
        self.max_joints = J = max(max(len(lay.spec.joints) for lay in layouts), 1)
        fields = {  # name: (shape, warp dtype) of every per-world parameter and state array
            "group_count": (W, wp.int32), "group_table": ((W, G), wp.int32), "group_scale": ((W, G), float),
            "group_origin": ((W, G, 3), wp.vec3), "link_mass": ((W, G * MAX_LINKS), float),
            "link_inertia": ((W, G * MAX_LINKS, 3, 3), wp.mat33), "drive": ((W, G, 3), wp.vec3),
            "group_shape": ((W, G, 4), wp.vec4), "base": ((W, 4), wp.vec4), "base_inertia": ((W, 3, 3), wp.mat33),
            "base_slot": ((W, BASE_SLOTS, 4), wp.vec4), "base_slot_mu": ((W, BASE_SLOTS), float),
            "gravity": ((W, 3), wp.vec3), "relief": ((W, 4), wp.vec4), "position": ((W, 3), wp.vec3), "orientation": ((W, 4), wp.quat),
            "velocity": ((W, 3), wp.vec3), "angular_velocity": ((W, 3), wp.vec3), "coord": ((W, G), float),
            "coord_rate": ((W, G), float), "group_joint": ((W, G), wp.int32), "point_count": (W, wp.int32),
            "point_group": ((W, P), wp.int32), "point_link": ((W, P), wp.int32),
            "point_local": ((W, P, 3), wp.vec3), "body_count": (W, wp.int32), "body_group": ((W, B), wp.int32),
            "body_link": ((W, B), wp.int32), "body_frame": ((W, B, 4), wp.quat)}
        h = {name: np.zeros(shape, np.int32 if dtype == wp.int32 else np.float32)
             for name, (shape, dtype) in fields.items()}
        h["group_shape"][..., 0] = -1.0  # no contact shape
        h["base_slot"][..., 3] = -1.0  # empty slot
        h["body_frame"][..., 3] = 1.0
        self.world_closure_error = np.zeros(W)
        for w, lay in enumerate(layouts):
            h["group_count"][w] = len(lay.groups)
            h["base"][w] = (lay.base_mass, float(lay.ground is not None), lay.ground[0] if lay.ground else 0.0, 0.0)
            h["base_inertia"][w] = lay.base_inertia
            for k, (point, radius, mu, _) in enumerate(lay.base_slots):
                h["base_slot"][w, k] = (*point, radius)
                h["base_slot_mu"][w, k] = mu
            h["gravity"][w] = lay.gravity
            relief = lay.spec.ground.relief if lay.spec.ground is not None else None
            if relief is not None:
                h["relief"][w] = (relief.amplitude, 2.0 * np.pi / relief.wavelength, *relief.phase)
            h["position"][w], h["orientation"][w] = lay.position, lay.orientation
            h["velocity"][w], h["angular_velocity"][w] = lay.velocity, lay.angular_velocity
            for g, chain in enumerate(lay.groups):
                k = len(chain.bodies)
                h["group_table"][w, g] = table_index[id(chain.table)]
                h["group_scale"][w, g] = chain.scale
                h["group_origin"][w, g] = chain.origin
                h["link_mass"][w, g * MAX_LINKS:g * MAX_LINKS + k] = chain.link_mass
                h["link_inertia"][w, g * MAX_LINKS:g * MAX_LINKS + k] = chain.link_inertia
                h["drive"][w, g] = chain.drive
                if chain.shape is not None:
                    h["group_shape"][w, g] = chain.shape[1:]
                h["coord"][w, g], h["coord_rate"][w, g] = chain.angle, chain.rate
                h["group_joint"][w, g] = chain.joint
            h["point_count"][w] = len(lay.points)
            for i, (g, k, local) in enumerate(lay.points):
                h["point_group"][w, i], h["point_link"][w, i], h["point_local"][w, i] = g, k, local
            h["body_count"][w] = len(lay.bodies)
            for i, (g, k, frame) in enumerate(lay.bodies):
                h["body_group"][w, i], h["body_link"][w, i], h["body_frame"][w, i] = g, k, frame
            self.world_closure_error[w] = lay.closure_error
        d = self.device
        self.samples = N
        self.table_links = wp.array(table_links, dtype=wp.int32, device=d)
        self.table_contact_link = wp.array(table_contact_link, dtype=wp.int32, device=d)
        self.links = [wp.array(links[i], dtype=wp.vec3, device=d) for i in range(3)]
        # the contact centre's position and rate (the contact rows need no second derivative)
        self.contact = [wp.array(contact[i], dtype=wp.vec3, device=d) for i in range(2)]
        for name, value in h.items():
            setattr(self, name, wp.array(value, dtype=fields[name][1], device=d))
        self.impulse = wp.zeros((W, MAX_ROWS), dtype=float, device=d)  # warm start, by row slot
        self.frozen = wp.zeros(W, dtype=wp.int32, device=d)
        self.diverged = wp.zeros(W, dtype=wp.int32, device=d)
        self.iterations = wp.zeros(W, dtype=wp.int32, device=d)
        self.contacts = wp.zeros(W, dtype=wp.int32, device=d)
        self.drive_torque = wp.zeros((W, MAX_GROUPS), dtype=float, device=d)
        # scratch of the step, per world
        self.rows_J = wp.zeros((W, MAX_ROWS * NV), dtype=float, device=d)
        self.rows_Jc = wp.zeros((W, MAX_ROWS * 2), dtype=wp.vec4, device=d)  # compact rows (see row_dot)
        self.rows = wp.zeros((W, MAX_ROWS * ROW_VECS), dtype=wp.vec4, device=d)
        self.mass = wp.zeros((W, NV * NV), dtype=float, device=d)
        self.mass_factor = wp.zeros((W, NV * NV), dtype=float, device=d)  # Cholesky factor of M
        self.factor = wp.zeros((W, NV * NV), dtype=float, device=d)  # of M + J^T S^-1 J
        # PADMM's per-row state, loaded and stored 16 bytes at a time: (x, x before, the row's
        # velocity at x, S^-1 b) and (y, z, y and z before)
        self.work = [wp.zeros((W, MAX_ROWS), dtype=wp.vec4, device=d) for _ in range(2)]
        self.row_inverse = wp.zeros((W, MAX_ROWS), dtype=float, device=d)  # 1 / S, for the Woodbury factor
        self.slot_of = wp.zeros((W, MAX_ROWS), dtype=wp.int32, device=d)
        self.row_count = wp.zeros(W, dtype=wp.int32, device=d)
        self.ufree = wp.zeros((W, NV), dtype=float, device=d)
        self.factor_inverse = wp.zeros((W, NV * KINV_VECS), dtype=wp.vec4, device=d)
        # Moreau-Jean's history (tabulated_step.HISTORY): the last step's rates and end; NaN: none yet
        self.history = wp.array(np.full((W, HISTORY), np.nan, np.float32), dtype=float, device=d)
        # outputs of record() and body_poses()
        self.points = wp.zeros((W, P), dtype=wp.vec3, device=d)
        self.energy = wp.zeros(W, dtype=float, device=d)
        self.joint_torque = wp.zeros((W, J), dtype=float, device=d)
        self.joint_speed = wp.zeros((W, J), dtype=float, device=d)
        self.body_q = wp.zeros((W, B), dtype=wp.transform, device=d)
        self.body_qd = wp.zeros((W, B), dtype=wp.spatial_vector, device=d)
        self._halted = wp.zeros(W, dtype=wp.int32, device=d)
        # one block of lanes per world on a GPU up to tiled_max_worlds (the lanes share each world's
        # rows), one thread per world beyond and on the CPU
        self.tiled = self.device.is_cuda and W <= tiled_max_worlds(self.device)
        self.lanes = 32 if self.device.is_cuda else 1  # per world, when tiled (a block is one thread on the CPU)
        self.max_registers = TILED_REGISTERS  # per thread of the tiled step on CUDA (None: the compiler's choice)
        self.max_bodies = B
        # force elements and a Control (tabulated_forces), compiled into the step only where used
        self.force_arrays = pack_forces(layouts, B, J, d)  # (where a Control acts: on its first use)
        self._control_ready = False
        self.forces = any(lay.spec.forces for lay in layouts)
        # the ground relief's code compiled into the step only where some world has relief
        self.has_relief = any(lay.spec.ground is not None and lay.spec.ground.relief is not None for lay in layouts)
        self._no_body_f = wp.zeros((1, 1), dtype=wp.spatial_vector, device=d)
        self._no_effort = wp.zeros((1, 1), dtype=float, device=d)

    def control(self) -> ChainControl:
        """A new Control (zeros): body_f (W, B) each spec body's wrench (force [N], torque [N m]; world
        frame) at its centre of mass, joint_effort (W, J) each revolute spec joint's torque [N m] on
        its child (the opposite on its parent), driven or not."""
        self._prepare_control()
        return ChainControl(wp.zeros((self.num_worlds, self.max_bodies), dtype=wp.spatial_vector, device=self.device),
                            wp.zeros((self.num_worlds, self.max_joints), dtype=float, device=self.device))

    def check_control(self, control) -> None:
        """chains.check_control_arrays for this batch (host work: once, not per step)."""
        check_control_arrays(control, "tabulated", self.num_worlds, self.max_bodies, self.max_joints, self.device)
        self._prepare_control()

    def _prepare_control(self) -> None:
        """Where a Control acts (TabulatedForces.control_*), packed on first use (host work)."""
        if not self._control_ready:
            self.force_arrays = pack_forces(self.layouts, self.max_bodies, self.max_joints, self.device, control=True)
            self._control_ready = True

    @property
    def point_names(self) -> list:
        """Tracked point names per world, in each spec's order."""
        return [lay.point_names for lay in self.layouts]

    @property
    def closure_error(self) -> float:
        """The largest closure error of the batch's tables at their scales [m]."""
        return float(self.world_closure_error.max(initial=0.0))

    def _structs(self) -> tuple:
        worlds, state = TabulatedWorlds(), TabulatedState()
        for name in TabulatedWorlds.vars:
            source = {"links0": self.links[0], "links1": self.links[1], "links2": self.links[2],
                      "contact0": self.contact[0], "contact1": self.contact[1]}.get(name)
            setattr(worlds, name, getattr(self, name) if source is None else source)
        for name in TabulatedState.vars:
            setattr(state, name, getattr(self, name))
        return worlds, state

    def _step_inputs(self) -> list:
        c = self.config
        return [self.dt, c.tuning.eta, c.tuning.rho_or(TABULATED_RHO), c.tolerance, c.relative_tolerance,
                c.max_iterations, c.tuning.rho_update_interval,
                c.contact_margin, c.contact_stabilization, c.max_speed, *self._structs(),
                self.impulse, self.frozen, self.diverged, self.iterations, self.contacts, self.drive_torque,
                self.rows_J, self.rows_Jc, self.rows, self.mass, self.mass_factor, self.factor, *self.work,
                self.row_inverse, self.slot_of, self.row_count, self.ufree, self.factor_inverse, self.history]

    @property
    def midpoint(self) -> bool:
        """Whether the step is Moreau-Jean's (SolverConfig.integrator), else semi-implicit Euler."""
        return self.config.integrator is Integrator.MOREAU_JEAN

    def step(self, steps: int = 1, control=None):
        """Advance every world ``steps`` steps of dt in place (kernel launches only: capturable in a
        CUDA graph). Frozen worlds (diverged or halted) stay as they are. control: a Control (control();
        check_control) whose arrays the step reads, or None."""
        if control is not None:
            self._prepare_control()  # (done already by control() or check_control(): no host work here)
        inputs = self._step_inputs()
        inputs += [self.force_arrays, self._no_body_f if control is None else control.body_f,
                   self._no_effort if control is None else control.joint_effort]
        extra = (self.forces, control is not None, self.has_relief)
        if self.tiled:
            kernel = step_kernel(True, "all", self.max_registers, self.midpoint, *extra)
            for _ in range(steps):
                wp.launch_tiled(kernel, dim=[self.num_worlds], block_dim=self.lanes, inputs=inputs, device=self.device)
            return
        # one thread per world: the set-up and the solve as two kernels; on the CPU their arguments
        # are packed once per call and the launches replayed step by step (the packing cost as much
        # host time as a walker's step); on a GPU rollout_tabulated captures the steps in a graph
        setup, solve = step_kernel(False, "setup", None, self.midpoint, *extra), step_kernel(False, "solve", None,
                                                                                              self.midpoint)
        if self.device.is_cuda:
            for _ in range(steps):
                wp.launch(setup, dim=self.num_worlds, inputs=inputs, device=self.device)
                wp.launch(solve, dim=self.num_worlds, inputs=inputs, device=self.device)
            return
        setup, solve = (wp.launch(kernel, dim=self.num_worlds, inputs=inputs, device=self.device, record_cmd=True)
                        for kernel in (setup, solve))
        for _ in range(steps):
            setup.launch()
            solve.launch()

    def record(self, numpy: bool = True) -> tuple:
        """The current state's tracked points (W, P, 3) [m] (each world's in its spec's order, zero
        past its count), mechanical energy (W,) [J], and the drives' last torque [N m] and current
        speed [rad/s] (W, J) by spec joint index (0 for undriven joints and past a world's joints).
        numpy=False: the device arrays (points (W, P) vec3), without a copy or a synchronization."""
        wp.launch(record_state, dim=self.num_worlds, device=self.device,
                  inputs=[*self._structs(), self.point_count, self.point_group, self.point_link, self.point_local,
                          self.group_joint, self.drive_torque, self.force_arrays],
                  outputs=[self.points, self.energy, self.joint_torque, self.joint_speed])
        if not numpy:
            return self.points, self.energy, self.joint_torque, self.joint_speed
        return self.points.numpy(), self.energy.numpy(), self.joint_torque.numpy(), self.joint_speed.numpy()

    def body_poses(self, numpy: bool = True) -> tuple:
        """Every spec body's pose and twist from the reduced state, in each spec's body order:
        body_q (W, B, 7): centre of mass [m] and body frame orientation (x, y, z, qx, qy, qz, qw);
        body_qd (W, B, 6): centre-of-mass velocity [m/s] then angular velocity [rad/s], world
        frame (engine.model's convention). Zero past a world's bodies. numpy=False: the device
        arrays (W, B) of wp.transform and wp.spatial_vector, without a copy (capturable)."""
        W, B = self.body_q.shape
        wp.launch(body_poses, dim=(W, B), device=self.device,
                  inputs=[*self._structs(), self.body_count, self.body_group, self.body_link, self.body_frame],
                  outputs=[self.body_q, self.body_qd])
        if not numpy:
            return self.body_q, self.body_qd
        return self.body_q.numpy().reshape(W, B, 7), self.body_qd.numpy().reshape(W, B, 6)

    def failure_reasons(self) -> list:
        """Per world '' (fine) or why its simulation stopped: a diverged world is frozen."""
        codes = self.diverged.numpy()
        reasons = {0: "", int(DIVERGED_NONFINITE): "diverged: the state turned non-finite",
                   int(DIVERGED_FAST): f"diverged: the base moved faster than {self.config.max_speed:g} m/s "
                                       f"(SolverConfig.max_speed)"}
        return [reasons.get(int(c), f"diverged (code {int(c)})") for c in codes]

    def halt(self, mask):
        """Freeze the worlds where ``mask`` (W,) is true; they keep their state from now on."""
        mask = np.asarray(mask, bool).reshape(self.num_worlds)
        self._halted.assign(mask.astype(np.int32))
        wp.launch(freeze_worlds, dim=self.num_worlds, inputs=[self._halted, self.frozen], device=self.device)


def pack_tabulated(specs: list, *, device="cpu", dt: float = 2e-3, config: SolverConfig | None = None,
                   samples: int = TABLE_SAMPLES, layouts: list | None = None) -> TabulatedModel:
    """One batch of worlds (MechanismSpecs) on ``device``, stepped with ``dt`` [s]. Raises
    ValueError "world i (name): reason" for the first world the tabulated path cannot take.
    layouts: the specs' TabulatedLayouts when the caller has them already (tabulated_layout; the
    analysis is not repeated). config.tuning.tabulated_tiled: one block of lanes per world (None: on
    a GPU up to tiled_max_worlds worlds) or one thread per world; both compute the same step;
    config.tuning.tabulated_registers: the tiled step's register cap (None: TILED_REGISTERS). samples: per
    table turn."""
    specs = list(specs)
    if not specs:
        raise ValueError("pack_tabulated: needs at least one world")
    if not dt > 0.0:
        raise ValueError(f"pack_tabulated: dt must be positive, got {dt}")
    if layouts is not None and len(layouts) != len(specs):
        raise ValueError(f"pack_tabulated: {len(layouts)} layouts for {len(specs)} specs")
    built = []
    for i, spec in enumerate(specs):
        if layouts is not None:
            built.append(layouts[i])
            continue
        if not isinstance(spec, MechanismSpec):
            raise ValueError(f"world {i}: expected a MechanismSpec, got {type(spec).__name__}")
        try:
            built.append(tabulated_layout(spec, samples=samples))
        except ValueError as exc:
            raise ValueError(f"world {i} ({spec.name}): {exc}") from None
    model = TabulatedModel(built, device, dt, config or SolverConfig())
    tuning = model.config.tuning  # None: the model's own choice
    if tuning.tabulated_tiled is not None:
        model.tiled = bool(tuning.tabulated_tiled)
    if tuning.tabulated_registers is not None:
        model.max_registers = tuning.tabulated_registers or None  # 0: the compiler's choice
    return model


def describe(plan, model: TabulatedModel):
    """Fill an engine.plan.Plan with what a packed TabulatedModel runs, and the accuracy it stands for."""
    cuda = model.device.is_cuda
    groups = [len(lay.groups) for lay in model.layouts]
    tables = {id(chain.table) for lay in model.layouts for chain in lay.groups}
    plan.analysis.append(f"largest world: {6 + max(groups)} coordinates (base pose and {max(groups)} driving "
                         f"coordinates); {sum(groups)} sub-chains read from {len(tables)} table"
                         f"{'s' if len(tables) != 1 else ''} of {model.samples} samples per turn")
    if model.config.tuning.tabulated_tiled is not None:
        why = " (forced by Tuning.tabulated_tiled)"
    elif cuda:
        why = (f" ({model.num_worlds} worlds: tiled up to {tiled_max_worlds(model.device):,} on this GPU, "
               f"{TILED_ROUNDS:g} rounds of {TILED_WORLDS_PER_SM} worlds on each of its {model.device.sm_count} "
               f"SMs, the faster side of the measured switch)")
    else:
        why = ""
    if model.tiled:
        plan.kernel = "fused: the whole step in one launch, a block of lanes per world (tiled)"
        plan.launch = f"one block of {model.lanes} lane{'s' if model.lanes != 1 else ''} per world" + why
        plan.registers = model.max_registers if cuda else None
    else:
        plan.kernel = "two launches per step (set-up through the warm start; factor, PADMM, integration)"
        plan.launch = "one thread per world" + why
        plan.registers = None
    plan.linear_solver = ("Cholesky of the (6 + L)-square mass matrix; PADMM solves by the Woodbury identity "
                          "(a factor of M + J^T S^-1 J, never of the rows' Delassus matrix)")
    contacts = any(lay.ground is not None and (lay.base_slots or any(c.shape for c in lay.groups))
                   for lay in model.layouts)
    plan.stages = {
        "contact rows": (contacts, (f"the shapes' {BASE_SLOTS} base slots and 2 per sub-chain against the ground"
                                    + (", on relief: its tangent plane at each contact point" if model.has_relief
                                       else "")) if contacts else "no ground or no shapes"),
        "PADMM iterations": (True, "the drive rows and the contact triplets"),
        "limit rows": (False, "no joint limits (the layout refuses them)"),
        "position projection": (False, "no loop rows: the tables close the loops"),
        "forces": (model.forces, _forces(model) if model.forces else "none"),
    }
    plan.control = ("a Control's body_f and joint_effort per step (model.control; compiled in only when stepped "
                    "with one), the specs' drive targets")
    plan.integrator = ("Moreau-Jean midpoint (pose and driving coordinates by half steps; M, bias forces, tables and "
                       "contacts at the midpoint, rates extrapolated to it)" if model.midpoint else "semi-implicit Euler")
    plan.accuracy = (f"loops closed by construction, to the tables' closure error (linear interpolation between "
                     f"samples): at most {model.closure_error:.3g} m")
    return plan


def _forces(model: TabulatedModel) -> str:
    """The batch's force elements and where the step evaluates them."""
    from engine.pack import force_summary
    point = "midpoint pose, rates extrapolated to it" if model.midpoint else "starting pose and rates"
    return (f"{force_summary(model.specs)}; generalized forces of the wrenches on the base and the links beside "
            f"the bias forces (tabulated_forces.applied_forces), at the {point}")


def rollout_tabulated(model: TabulatedModel, steps: int, record_every: int = 10, halt=None):
    """Step ``model`` ``steps`` times (a positive multiple of record_every), recording every
    record_every steps: an engine.Trace (points by spec order, drive torques and speeds by spec
    joint index, energy, PADMM iterations; violation_linear is each world's closure error [m], the
    loop-closure error its tables stand for; violation_angular zero). halt(points (W, P, 3), start)
    -> (W,) bool freezes worlds, as engine.rollout's halt does. On CUDA a chunk of record_every
    steps is captured once as a graph and replayed."""
    from engine.rollout import Trace

    if steps < record_every or steps % record_every:
        raise ValueError(f"rollout_tabulated: steps ({steps}) must be a positive multiple of "
                         f"record_every ({record_every})")
    W = model.num_worlds
    records = steps // record_every + 1
    P, J = model.points.shape[1], model.max_joints
    points = np.zeros((records, W, P, 3), np.float32)
    energy = np.zeros((records, W), np.float32)
    torque = np.zeros((records, W, J), np.float32)
    speed = np.zeros((records, W, J), np.float32)
    iterations = np.zeros((records, W), np.int32)
    halted_at = np.full(W, -1.0)
    points[0], energy[0], _, speed[0] = model.record()
    graph, steps_done = None, 0
    if model.device.is_cuda:
        model.step(1)  # compile, outside the capture
        wp.synchronize_device(model.device)
        with wp.ScopedCapture(device=model.device) as capture:
            model.step(record_every)
        graph, steps_done = capture.graph, 1
    for r in range(1, records):
        if graph is not None and r == 1:
            model.step(record_every - steps_done)
        elif graph is not None:
            wp.capture_launch(graph)
        else:
            model.step(record_every)
        points[r], energy[r], torque[r], speed[r] = model.record()
        iterations[r] = model.iterations.numpy()
        if halt is not None:
            stop = np.asarray(halt(points[r], points[0])) & (halted_at < 0)
            if stop.any():
                halted_at[stop] = r * record_every * model.dt
                model.halt(stop)
    diverged = model.diverged.numpy().astype(bool)
    closure = np.broadcast_to(model.world_closure_error.astype(np.float32), (records, W)).copy()
    return Trace(np.arange(records) * record_every * model.dt, points, closure, np.zeros((records, W), np.float32),
                 energy, iterations, torque, speed, diverged, model.point_names, halted_at)
