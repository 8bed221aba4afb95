"""Legged worlds in reduced coordinates: a rigid torso carrying one-DoF planar legs.

A leg whose links form a one-degree-of-freedom closed chain on the torso (a Jansen or Klann leg
turned by its crank) has one coordinate, its crank angle psi: every link's pose in the torso
frame is a function of psi. Tabulated over a crank turn (LegTable: the centre of mass and the
angle of every link, and the foot, with their first and second derivatives in psi), the whole
walker has 6 + L coordinates (torso pose, L crank angles) instead of 6 per body, and its loops
are closed by construction. engine.legged steps such worlds with the same physics as the
maximal-coordinate engine (same drives, contacts, friction cones and PADMM), with the constraint
rows reduced to the drives and the contacts:

- generalized velocity u = (v, w, psi_dot_1..L): the torso's centre-of-mass velocity and angular
  velocity (world frame) and the crank rates; a link k of leg l moves with
  v_k = v + w x d_k + e_k psi_dot_l and w_k = w + a phi_k' psi_dot_l, where d_k = R (o_l + c_k(psi)),
  e_k = R c_k'(psi), a = -R y (the legs turn about the torso's -y axis) and phi_k the link's
  planar angle;
- mass matrix M(q) = sum_k J_k^T diag(m_k, I_k) J_k and bias forces h(q, u) (gravity, the
  velocity-product terms from c_k'' and phi_k'' and the gyroscopic torques) summed link by link;
- semi-implicit Euler: u_f = u + dt M^-1 h, then the dual problem over the rows (crank drives with
  the implicit damping law and effort bounds; contact triplets with the engine's stabilization
  and Coulomb cones with the De Saxce correction) by PADMM with a Jacobi preconditioner; its
  linear solves use the Woodbury identity (D + S)^-1 = S^-1 - S^-1 J (M + J^T S^-1 J)^-1 J^T S^-1,
  so that a factor is of the (6 + L)-square matrix, never of the rows' Delassus matrix;
- then u+ = u_f + M^-1 J^T lambda, positions and the torso's orientation (exponential map)
  integrated with u+.

Of engine.SolverConfig it uses eta, rho, tolerance, relative_tolerance, max_iterations,
rho_update_interval, contact_margin, contact_stabilization and max_speed; it always integrates
with semi-implicit Euler and has no joint rows, so no projection.

Contacts: the torso box's corners and both ends of every foot's shoe capsule against the ground
plane z = 0 (the contact point on the capsule's surface below the end), kept within
SolverConfig.contact_margin; the contact candidates have fixed slots
(their warm-start keys).

On a GPU a batch of up to tiled_max_worlds(device) worlds (32 an SM) steps one warp per world:
the lanes sum the mass matrix and bias forces one leg each, lane 0 assembles the torso blocks,
factors and builds the rows, the lanes share the rows and contact triplets of the preconditioner,
the warm start and every PADMM iteration (their sums and maxima reduced as one vector each), the
entries of M + J^T S^-1 J, the rows of its (6 + L)-square inverse when it is applied, and the
impulses of the velocity update. Larger batches (and the CPU) step one thread per world, as two
kernels (the set-up through the warm start, then the Woodbury factor, the PADMM iterations and the
integration): more worlds than a GPU has warps keep it busy anyway. Both compute the same step.
The tiled step is held to TILED_REGISTERS registers per thread, so that an SM holds 32 worlds: a
world's step is a chain of dependent loads and reductions, and worlds that are not in lockstep
(different designs, or one design at different phases) hide each other's latency only when many
share an SM. Its code is large enough that the instruction cache matters (ncu: a third of the
warps' stalls wait on an instruction fetch), so the Woodbury factor has one call site. A row's
PADMM state and fields are vec4s, each loaded and stored once per iteration: with one thread per
world a warp's loads touch 32 worlds' cache lines, so the number of load instructions, not the
bytes, sets the time. A world whose state turns non-finite or whose torso moves faster than
max_speed is flagged diverged and frozen; halted worlds are frozen.
"""

import functools
import math
from typing import Any
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from engine.linalg.lanes import block_sync
from engine.config import TABULATED_RHO, SolverConfig
from engine.spec import check_inertia

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["LeggedModel", "LeggedSpec", "LeggedState", "LeggedWorlds", "LegPlacement", "LegTable", "legged_rollout",
           "pack_legged"]

MAX_LEGS = wp.constant(8)
NV = wp.constant(6 + 8)  # generalized velocities of the largest world
MAX_LINKS = wp.constant(8)  # links per leg
TORSO_CORNERS = wp.constant(8)
MAX_CONTACTS = TORSO_CORNERS + 2 * MAX_LEGS  # slot k < 8: torso corner k; 8 + 2 l + e: end e of leg l's shoe
MAX_ROWS = wp.constant(MAX_LEGS + 3 * MAX_CONTACTS)
TWO_PI = wp.constant(2.0 * math.pi)
# registers per thread of the tiled step on CUDA (LeggedModel.max_registers): left to the compiler it
# takes 255, so an SM holds 8 worlds and a step of 4096 worlds runs in four rounds, each as slow as
# its slowest world; at 64 an SM holds 32 (the most blocks it takes) and all 4096 run at once. H100,
# 4096 walkers: 64 random designs 2.71 -> 1.68 ms per step, the default walker at spread crank
# phases 2.55 -> 1.61 ms (identical copies in lockstep 0.96 -> 1.41 ms); 56, 72, 80 and 128 were slower
TILED_REGISTERS = 64
# worlds per SM the tiled step holds at once (32 blocks, the most an SM takes): a batch of up to
# this many per SM steps tiled, a larger one a thread per world (tiled_max_worlds). Past one round
# the tiled step is throughput-bound while the one-thread step barely grows (H100, 132 SMs, 64
# random designs: tiled 1.68 ms at 4096 worlds, 5.24 at 8192; one thread 3.45, 3.53 and 3.60 ms at
# 4096, 8192 and 16384)
TILED_WORLDS_PER_SM = 32


def tiled_max_worlds(device) -> int:
    """The most worlds ``device`` steps tiled (a block of lanes per world): one round of
    TILED_WORLDS_PER_SM worlds on each of its SMs; 0 on the CPU."""
    device = wp.get_device(device)
    return TILED_WORLDS_PER_SM * device.sm_count if device.is_cuda else 0


ROW_VECS = wp.constant(3)  # vec4 per row in the rows' scratch (see row_at)
# a row's fields: the first two vec4 are what the PADMM iterations read (and the row velocity they write)
F_RHS = wp.constant(0)  # free velocity v_f (preconditioned)
F_MU = wp.constant(1)  # friction mu (contacts; -1 drive)
F_PEN = wp.constant(2)  # ADMM penalty
F_INV = wp.constant(3)  # 1 / (eta + penalty + P^2 R), set with the Woodbury factor
F_LO = wp.constant(4)  # lower and upper bounds (drives, preconditioned)
F_HI = wp.constant(5)
F_COL = wp.constant(6)  # the row's crank column (6 + leg; 5, below 6, for a torso corner: none)
# 7: unused (the row velocity at the last iterate is PADMM state, in s1)
F_P = wp.constant(8)  # preconditioner P
F_R = wp.constant(9)  # compliance R (unscaled)
F_FREE = wp.constant(10)  # free drive flag
KINV_VECS = wp.constant(4)  # vec4 per row of the Woodbury inverse (NV <= 16 entries)


@dataclass
class LegTable:
    """Kinematics of one leg linkage over a crank turn, at unit length scale.

    samples crank angles psi_n = 2 pi n / N. links (N, K, 3): per link its centre of mass in the
    leg plane (x, z) [m] and its planar angle phi [rad] (counter-clockwise seen from +y... i.e. a
    rotation about the torso's -y axis); links_d1, links_d2 the derivatives in psi; foot (N, 3):
    the foot point (x, z, 0) and foot_d1, foot_d2; foot_link: the link that carries the foot.
    closure_error: the largest distance [m, unit scale] between a pivot placed by the two links
    it joins when both are read from the table between samples (linear interpolation): the
    loop-closure error the table stands for.
    """

    name: str
    links: np.ndarray
    links_d1: np.ndarray
    links_d2: np.ndarray
    foot: np.ndarray
    foot_d1: np.ndarray
    foot_d2: np.ndarray
    foot_link: int
    link_names: list = field(default_factory=list)
    closure_error: float = 0.0

    def __post_init__(self):
        n, k, three = np.shape(self.links)
        if three != 3 or not 1 <= k <= MAX_LINKS or n < 16:
            raise ValueError(f"leg table '{self.name}': links must be (N >= 16, K <= {MAX_LINKS}, 3), "
                             f"got {np.shape(self.links)}")
        for name in ("links_d1", "links_d2"):
            if np.shape(getattr(self, name)) != (n, k, 3):
                raise ValueError(f"leg table '{self.name}': {name} must be {(n, k, 3)}")
        for name in ("foot", "foot_d1", "foot_d2"):
            if np.shape(getattr(self, name)) != (n, 3):
                raise ValueError(f"leg table '{self.name}': {name} must be {(n, 3)}")
        if not 0 <= self.foot_link < k:
            raise ValueError(f"leg table '{self.name}': foot_link {self.foot_link} is not one of its {k} links")

    @property
    def samples(self) -> int:
        """Crank angles in the table (N)."""
        return int(np.shape(self.links)[0])

    def _between(self, psi: float) -> tuple:
        """The samples around crank angle psi [rad] and the weight of the second (i0, i1, f), as the
        kernels' table_index."""
        n = self.samples
        u = (psi / (2.0 * math.pi) * n) % n
        i0 = min(int(u), n - 1)
        return i0, (i0 + 1) % n, u - i0

    def at(self, psi: float) -> tuple:
        """Links (K, 3) and foot (3,) at crank angle psi [rad], interpolated as the kernels do."""
        i0, i1, f = self._between(psi)
        a, b = self.links[i0], self.links[i1]
        step = b - a
        step[:, 2] -= 2.0 * math.pi * np.round(step[:, 2] / (2.0 * math.pi))
        return a + f * step, (1.0 - f) * self.foot[i0] + f * self.foot[i1]

    def foot_at(self, psi: float) -> tuple:
        """The foot (3,) and its link's planar angle [rad] at crank angle psi, as ``at`` gives them
        (without interpolating every link: a walker's build needs only these)."""
        i0, i1, f = self._between(psi)
        a, b = float(self.links[i0, self.foot_link, 2]), float(self.links[i1, self.foot_link, 2])
        step = b - a
        step -= 2.0 * math.pi * round(step / (2.0 * math.pi))
        return (1.0 - f) * self.foot[i0] + f * self.foot[i1], a + f * step


@dataclass
class LegPlacement:
    """One leg on the torso: its table, length scale, plane origin in the torso frame relative to
    the torso's centre of mass [m], initial crank angle [rad], link masses (K,) [kg] and inertias
    (K, 3, 3) about their centres in the link frame (x along the link's planar angle, y the leg
    plane's normal) [kg m^2], the crank's velocity drive (target [rad/s], damping [N m s/rad],
    effort limit [N m]) and the foot's shoe: a capsule of radius [m] and half length [m] whose
    axis makes shoe_angle [rad] with the foot link's x axis in the leg plane."""

    name: str
    table: LegTable
    scale: float
    origin: tuple
    angle: float
    link_mass: np.ndarray
    link_inertia: np.ndarray
    target_speed: float
    damping: float
    effort_limit: float
    shoe_radius: float
    shoe_half_length: float
    shoe_angle: float
    shoe_friction: float = 1.0


@dataclass
class LeggedSpec:
    """One legged world: a box torso (mass [kg], inertia about its centre in its frame [kg m^2],
    half extents [m], centre-of-mass position [m] at the start, axes aligned with the world's)
    carrying legs, on the ground plane z = 0 (ground=False: no ground)."""

    name: str
    torso_mass: float
    torso_inertia: np.ndarray
    torso_half: tuple
    torso_position: tuple
    legs: list
    torso_friction: float = 0.8
    ground_friction: float = 1.0
    ground: bool = True
    gravity: tuple = (0.0, 0.0, -9.81)

    def __post_init__(self):
        where = f"legged world '{self.name}'"
        if not 1 <= len(self.legs) <= MAX_LEGS:
            raise ValueError(f"{where}: needs 1 to {MAX_LEGS} legs, got {len(self.legs)}")
        if not (np.isfinite(self.torso_mass) and self.torso_mass > 0.0):
            raise ValueError(f"{where}: torso_mass must be positive, got {self.torso_mass}")
        self.torso_inertia = check_inertia(self.torso_inertia, f"{where}: torso")
        for leg in self.legs:
            k = np.shape(leg.table.links)[1]
            if np.shape(leg.link_mass) != (k,) or np.shape(leg.link_inertia) != (k, 3, 3):
                raise ValueError(f"{where}, leg '{leg.name}': link_mass must be ({k},) and link_inertia ({k}, 3, 3)")
            for i, inertia in enumerate(leg.link_inertia):
                check_inertia(inertia, f"{where}, leg '{leg.name}': link {i}")
            if not leg.scale > 0.0:
                raise ValueError(f"{where}, leg '{leg.name}': scale must be positive, got {leg.scale}")

    @property
    def point_names(self) -> list:
        """Tracked points: torso centre, a point one torso half-length above it, every foot."""
        return ["torso", "torso_up", *(f"{leg.name}_foot" for leg in self.legs)]


vecnv = wp.types.vector(length=NV, dtype=wp.float32)
veclegs = wp.types.vector(length=MAX_LEGS, dtype=wp.float32)
# the legs' sums of a step's set-up: mass, m d (3), the angular block (9), the torso's bias force and
# torque (6), each leg's bias force (MAX_LEGS)
vecsetup = wp.types.vector(length=19 + MAX_LEGS, dtype=wp.float32)
# an iteration's residuals (primal, dual, natural), largest impulse and merit: the first four
# reduced by their maximum, the merit by its sum (max4_sum1)
vecstats = wp.types.vector(length=5, dtype=wp.float32)


@wp.func
def max4_sum1(a: vecstats, b: vecstats):
    """The reduction of an iteration's statistics: largest of the first four, sum of the last."""
    return vecstats(wp.max(a[0], b[0]), wp.max(a[1], b[1]), wp.max(a[2], b[2]), wp.max(a[3], b[3]), a[4] + b[4])


class LeggedModel:
    """A batch of legged worlds on one device: tables, per-world parameters, state and scratch."""

    def __init__(self, specs: list, device, dt: float, config: SolverConfig):
        self.device, self.dt, self.config = wp.get_device(device), float(dt), config
        self.num_worlds = W = len(specs)
        self.specs = specs
        tables, table_index = [], {}
        for spec in specs:
            for leg in spec.legs:
                if id(leg.table) not in table_index:
                    table_index[id(leg.table)] = len(tables)
                    tables.append(leg.table)
        samples = {t.samples for t in tables}
        if len(samples) != 1:
            raise ValueError(f"pack_legged: every leg table needs the same number of samples, got {sorted(samples)}")
        N = samples.pop()
        T = len(tables)
        links = np.zeros((3, T, N, MAX_LINKS, 3), np.float32)
        foot = np.zeros((2, T, N, 3), np.float32)
        table_links = np.zeros(T, np.int32)
        table_foot_link = np.zeros(T, np.int32)
        for t, table in enumerate(tables):
            k = table.links.shape[1]
            links[0, t, :, :k], links[1, t, :, :k], links[2, t, :, :k] = table.links, table.links_d1, table.links_d2
            foot[0, t], foot[1, t] = table.foot, table.foot_d1
            table_links[t], table_foot_link[t] = k, table.foot_link
        L = MAX_LEGS
        leg_count = np.zeros(W, np.int32)
        leg_table = np.zeros((W, L), np.int32)
        leg_scale = np.ones((W, L), np.float32)
        leg_origin = np.zeros((W, L, 3), np.float32)
        leg_angle = np.zeros((W, L), np.float32)
        link_mass = np.zeros((W, L * MAX_LINKS), np.float32)
        link_inertia = np.zeros((W, L * MAX_LINKS, 3, 3), np.float32)
        drive = np.zeros((W, L, 3), np.float32)
        shoe = np.zeros((W, L, 4), np.float32)
        torso = np.zeros((W, 4), np.float32)  # mass, friction with the ground, ground on, spare
        torso_inertia = np.zeros((W, 3, 3), np.float32)
        torso_half = np.zeros((W, 3), np.float32)
        gravity = np.zeros((W, 3), np.float32)
        position = np.zeros((W, 3), np.float32)
        for w, spec in enumerate(specs):
            leg_count[w] = len(spec.legs)
            torso[w] = (spec.torso_mass, math.sqrt(spec.torso_friction * spec.ground_friction), float(spec.ground), 0)
            torso_inertia[w] = spec.torso_inertia
            torso_half[w] = spec.torso_half
            gravity[w] = spec.gravity
            position[w] = spec.torso_position
            for li, leg in enumerate(spec.legs):
                k = leg.table.links.shape[1]
                leg_table[w, li] = table_index[id(leg.table)]
                leg_scale[w, li] = leg.scale
                leg_origin[w, li] = leg.origin
                leg_angle[w, li] = leg.angle
                link_mass[w, li * MAX_LINKS:li * MAX_LINKS + k] = leg.link_mass
                link_inertia[w, li * MAX_LINKS:li * MAX_LINKS + k] = leg.link_inertia
                drive[w, li] = (leg.target_speed, leg.damping, leg.effort_limit)
                shoe[w, li] = (leg.shoe_radius, leg.shoe_half_length, leg.shoe_angle,
                              math.sqrt(leg.shoe_friction * spec.ground_friction))
        d = self.device
        self.samples = N
        self.table_links = wp.array(table_links, dtype=wp.int32, device=d)
        self.table_foot_link = wp.array(table_foot_link, dtype=wp.int32, device=d)
        self.links = [wp.array(links[i], dtype=wp.vec3, device=d) for i in range(3)]
        # the foot's position and rate (the contact rows need no second derivative of the foot)
        self.foot = [wp.array(foot[i], dtype=wp.vec3, device=d) for i in range(2)]
        self.leg_count = wp.array(leg_count, dtype=wp.int32, device=d)
        self.leg_table = wp.array(leg_table, dtype=wp.int32, device=d)
        self.leg_scale = wp.array(leg_scale, dtype=float, device=d)
        self.leg_origin = wp.array(leg_origin, dtype=wp.vec3, device=d)
        self.link_mass = wp.array(link_mass, dtype=float, device=d)
        self.link_inertia = wp.array(link_inertia, dtype=wp.mat33, device=d)
        self.drive = wp.array(drive, dtype=wp.vec3, device=d)
        self.shoe = wp.array(shoe, dtype=wp.vec4, device=d)
        self.torso = wp.array(torso, dtype=wp.vec4, device=d)
        self.torso_inertia = wp.array(torso_inertia, dtype=wp.mat33, device=d)
        self.torso_half = wp.array(torso_half, dtype=wp.vec3, device=d)
        self.gravity = wp.array(gravity, dtype=wp.vec3, device=d)
        # state
        self.position = wp.array(position, dtype=wp.vec3, device=d)
        self.orientation = wp.array(np.tile([0.0, 0.0, 0.0, 1.0], (W, 1)).astype(np.float32), dtype=wp.quat, device=d)
        self.velocity = wp.zeros(W, dtype=wp.vec3, device=d)
        self.angular_velocity = wp.zeros(W, dtype=wp.vec3, device=d)
        self.psi = wp.array(leg_angle, dtype=float, device=d)
        self.psi_dot = wp.zeros((W, L), dtype=float, device=d)
        self.impulse = wp.zeros((W, MAX_ROWS), dtype=float, device=d)  # warm start, by row slot
        self.frozen = wp.zeros(W, dtype=wp.int32, device=d)
        self.diverged = wp.zeros(W, dtype=wp.int32, device=d)
        self.iterations = wp.zeros(W, dtype=wp.int32, device=d)
        self.contacts = wp.zeros(W, dtype=wp.int32, device=d)
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
        # one warp per world on a GPU up to tiled_max_worlds (the lanes share each world's rows), one
        # thread per world beyond (more worlds than warps keep a GPU busy) and on the CPU
        self.tiled = self.device.is_cuda and W <= tiled_max_worlds(self.device)
        self.lanes = 32 if self.device.is_cuda else 1  # per world, when tiled (a block is one thread on the CPU)
        self.max_registers = TILED_REGISTERS  # per thread of the tiled step on CUDA (None: the compiler's choice)
        self.drive_torque = wp.zeros((W, MAX_LEGS), dtype=float, device=d)
        self.points = wp.zeros((W, 2 + MAX_LEGS), dtype=wp.vec3, device=d)
        self.energy = wp.zeros(W, dtype=float, device=d)

    @property
    def point_names(self) -> list:
        """Tracked point names per world (torso, torso_up, one foot per leg)."""
        return [spec.point_names for spec in self.specs]


def pack_legged(specs: list, *, device="cpu", dt: float = 2e-3, config: SolverConfig | None = None,
                tiled: bool | None = None) -> LeggedModel:
    """One batch of legged worlds (see LeggedSpec) on ``device``, stepped with ``dt`` [s].
    tiled: one block of lanes per world (default on a GPU up to tiled_max_worlds worlds) or one
    thread per world; both compute the same step (on the CPU a block is one thread)."""
    if not specs:
        raise ValueError("pack_legged: needs at least one world")
    if not dt > 0.0:
        raise ValueError(f"pack_legged: dt must be positive, got {dt}")
    model = LeggedModel(list(specs), device, dt, config or SolverConfig())
    if tiled is not None:
        model.tiled = bool(tiled)
    return model


@wp.struct
class LeggedWorlds:
    """The batch's leg tables (value, first and second derivative in the crank angle) and every
    world's parameters, as the kernels read them (see LeggedModel)."""

    samples: int
    table_links: wp.array(dtype=wp.int32)
    table_foot_link: wp.array(dtype=wp.int32)
    links0: wp.array3d(dtype=wp.vec3)
    links1: wp.array3d(dtype=wp.vec3)
    links2: wp.array3d(dtype=wp.vec3)
    foot0: wp.array2d(dtype=wp.vec3)
    foot1: wp.array2d(dtype=wp.vec3)
    leg_count: wp.array(dtype=wp.int32)
    leg_table: wp.array2d(dtype=wp.int32)
    leg_scale: wp.array2d(dtype=float)
    leg_origin: wp.array2d(dtype=wp.vec3)
    link_mass: wp.array2d(dtype=float)
    link_inertia: wp.array2d(dtype=wp.mat33)
    drive: wp.array2d(dtype=wp.vec3)
    shoe: wp.array2d(dtype=wp.vec4)
    torso: wp.array(dtype=wp.vec4)
    torso_inertia: wp.array(dtype=wp.mat33)
    torso_half: wp.array(dtype=wp.vec3)
    gravity: wp.array(dtype=wp.vec3)


@wp.struct
class LeggedState:
    """Every world's state: torso centre-of-mass position, orientation, velocity and angular
    velocity (world frame), crank angles and rates."""

    position: wp.array(dtype=wp.vec3)
    orientation: wp.array(dtype=wp.quat)
    velocity: wp.array(dtype=wp.vec3)
    angular_velocity: wp.array(dtype=wp.vec3)
    psi: wp.array2d(dtype=float)
    psi_dot: wp.array2d(dtype=float)


# -- kernels ---------------------------------------------------------------------------------------


@wp.func
def table_read(table: wp.array3d(dtype=wp.vec3), t: int, i0: int, i1: int, f: float, k: int):
    """Entry k of table t between samples i0 and i1 (weight f on i1), linearly."""
    return table[t, i0, k] * (1.0 - f) + table[t, i1, k] * f


@wp.func
def link_read(table: wp.array3d(dtype=wp.vec3), t: int, i0: int, i1: int, f: float, k: int):
    """A link's (x, z, angle) between two samples; the angle steps by its difference wrapped to
    (-pi, pi] (a crank's angle wraps once per turn between the last sample and the first)."""
    a = table[t, i0, k]
    b = table[t, i1, k]
    d = b[2] - a[2]
    d = d - TWO_PI * wp.round(d / TWO_PI)
    return wp.vec3(a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * d)


@wp.func
def foot_read(table: wp.array2d(dtype=wp.vec3), t: int, i0: int, i1: int, f: float):
    """The foot entry of table t between samples i0 and i1, linearly."""
    return table[t, i0] * (1.0 - f) + table[t, i1] * f


@wp.func
def plane(R: wp.mat33, p: wp.vec3):
    """Leg-plane vector (x, z, .) in the world frame: torso R times (x, 0, z)."""
    return R * wp.vec3(p[0], 0.0, p[1])


@wp.func
def rot_minus_y(angle: float):
    """Rotation by ``angle`` about -y (counter-clockwise in the leg plane)."""
    c = wp.cos(angle)
    s = wp.sin(angle)
    return wp.mat33(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c)


@wp.func
def cholesky(a: wp.array2d(dtype=float), w: int, n: int, out: wp.array2d(dtype=float)):
    """Lower Cholesky factor of a's leading n x n block into out (row-major, NV columns)."""
    for j in range(n):
        s = a[w, j * NV + j]
        for k in range(j):
            s -= out[w, j * NV + k] * out[w, j * NV + k]
        d = wp.sqrt(wp.max(s, 1.0e-20))
        out[w, j * NV + j] = d
        for i in range(j + 1, n):
            t = a[w, i * NV + j]
            for k in range(j):
                t -= out[w, i * NV + k] * out[w, j * NV + k]
            out[w, i * NV + j] = t / d


@wp.func
def chol_solve(L: wp.array2d(dtype=float), w: int, n: int, b: vecnv):
    """(L L^T)^-1 b for the lower factor L of world w (its leading n x n block)."""
    y = b
    for i in range(n):
        s = y[i]
        for k in range(i):
            s -= L[w, i * NV + k] * y[k]
        y[i] = s / L[w, i * NV + i]
    for ii in range(n):
        i = n - 1 - ii
        s = y[i]
        for k in range(i + 1, n):
            s -= L[w, k * NV + i] * y[k]
        y[i] = s / L[w, i * NV + i]
    return y


@wp.func
def forward_norm2(L: wp.array2d(dtype=float), w: int, n: int, b: vecnv, first: int):
    """|L^-1 b|^2 = b^T (L L^T)^-1 b for the lower factor L of world w, b zero before index first
    (so is L^-1 b: the forward substitution starts there)."""
    y = b
    total = float(0.0)
    for i in range(first, n):
        s = y[i]
        for k in range(first, i):
            s -= L[w, i * NV + k] * y[k]
        y[i] = s / L[w, i * NV + i]
        total += y[i] * y[i]
    return total


# row scratch layout: three vec4 per row, fields F_RHS ... F_FREE (an iteration reads the first
# two: (v_f, mu, penalty, 1 / S) and (lower, upper, crank column, velocity)). A drive row's
# Jacobian is zero but in its crank column, a contact row's but in the torso's six columns and
# its crank column: the PADMM iterations read a compact copy of the preconditioned rows, two vec4
# per row (the torso's six entries, the crank column's, 0; row_dot, row_add).
@wp.func
def row_at(rows: wp.array2d(dtype=wp.vec4), w: int, r: int, c: int):
    """Field c of row r of world w in the rows' scratch."""
    return rows[w, r * ROW_VECS + c / 4][c % 4]


@wp.func
def set_row(rows: wp.array2d(dtype=wp.vec4), w: int, r: int, c: int, value: float):
    """Set field c of row r of world w in the rows' scratch."""
    v = rows[w, r * ROW_VECS + c / 4]
    v[c % 4] = value
    rows[w, r * ROW_VECS + c / 4] = v


@wp.func
def penalty(rows: wp.array2d(dtype=wp.vec4), w: int, r: int):
    """A row's ADMM penalty."""
    return rows[w, r * ROW_VECS][F_PEN]


@wp.func
def set_penalties(rows: wp.array2d(dtype=wp.vec4), w: int, m: int, rho: float, rho0: float):
    """Every row's penalty: rho, or min(rho, rho0) for a free drive row."""
    for r in range(m):
        value = rho
        if row_at(rows, w, r, F_FREE) == 1.0:
            value = wp.min(rho, rho0)
        set_row(rows, w, r, F_PEN, value)


@wp.func
def row_dot(Jc: wp.array2d(dtype=wp.vec4), w: int, r: int, contact: bool, col: int, u: vecnv):
    """Row r of world w's (preconditioned) Jacobian times u, from its compact copy: a contact
    row's torso columns, and the crank column ``col`` (below 6: none)."""
    b = Jc[w, 2 * r + 1]
    s = float(0.0)
    if contact:
        a = Jc[w, 2 * r]
        s = a[0] * u[0] + a[1] * u[1] + a[2] * u[2] + a[3] * u[3] + b[0] * u[4] + b[1] * u[5]
    if col >= 6:
        uc = float(0.0)
        for c in range(6, NV):  # a select over constant indices keeps u in registers
            if c == col:
                uc = u[c]
        s += b[2] * uc
    return s


@wp.func
def row_add(Jc: wp.array2d(dtype=wp.vec4), w: int, r: int, contact: bool, col: int, t: float, g: vecnv):
    """g + t times row r of world w's (preconditioned) Jacobian (see row_dot)."""
    out = g
    b = Jc[w, 2 * r + 1]
    if contact:
        a = Jc[w, 2 * r]
        out[0] += a[0] * t
        out[1] += a[1] * t
        out[2] += a[2] * t
        out[3] += a[3] * t
        out[4] += b[0] * t
        out[5] += b[1] * t
    if col >= 6:
        v = b[2] * t
        for c in range(6, NV):
            if c == col:
                out[c] += v
    return out


@wp.func
def jrow_dot(J: wp.array2d(dtype=float), w: int, r: int, n: int, u: vecnv):
    """Row r of world w's Jacobian times u."""
    s = float(0.0)
    for c in range(NV):
        s += J[w, r * NV + c] * u[c]
    return s


@wp.func
def project_row(rows: wp.array2d(dtype=wp.vec4), w: int, r: int, a: float, b: float, c: float):
    """Projection of a row's value (a drive: clamp) or a contact triplet's (a, b, c) onto its cone;
    returns the projected triplet (drives use the first component only)."""
    mu = row_at(rows, w, r, F_MU)
    if mu < 0.0:
        return wp.vec3(wp.clamp(a, row_at(rows, w, r, F_LO), row_at(rows, w, r, F_HI)), 0.0, 0.0)
    return project_cone(mu, a, b, c)


@wp.func
def project_cone(mu: float, a: float, b: float, c: float):
    """Projection of a contact triplet (normal a, tangents b, c) onto the cone of friction mu."""
    t = wp.sqrt(b * b + c * c)
    if t <= mu * a:
        return wp.vec3(a, b, c)
    if mu * t <= -a:
        return wp.vec3(0.0, 0.0, 0.0)
    n = (a + mu * t) / (1.0 + mu * mu)
    return wp.vec3(n, mu * n * b / t, mu * n * c / t)


@functools.cache
def step_kernel(tiled: bool, phase: str = "all", registers: int | None = None):
    """The step kernel: tiled (launch_tiled, one block of lanes per world, lanes sharing the
    PADMM rows) or one thread per world (wp.launch; no block operations). phase: the whole step
    ("all"), or its set-up (through the warm start, "setup") and the Woodbury factor, the PADMM
    iterations and the integration ("solve") as two kernels, each with the registers it needs.
    registers: at most this many registers per thread on CUDA (None: the compiler's choice; see
    TILED_REGISTERS)."""

    @wp.func
    def sync():
        """Barrier of the world's lanes (tiled only)."""
        if wp.static(tiled):
            block_sync()

    @wp.func
    def reduce_vector(value: Any):
        """Sum of a vector over the world's lanes, in one reduction."""
        if wp.static(tiled):
            return wp.tile_extract(wp.tile_reduce(wp.add, wp.tile(value, preserve_type=True)), 0)
        return value

    @wp.func
    def reduce_stats(value: vecstats):
        """An iteration's statistics over the world's lanes (max4_sum1), in one reduction."""
        if wp.static(tiled):
            return wp.tile_extract(wp.tile_reduce(max4_sum1, wp.tile(value, preserve_type=True)), 0)
        return value

    @wp.func
    def woodbury_factor(J: wp.array2d(dtype=float), rows: wp.array2d(dtype=wp.vec4), M: wp.array2d(dtype=float),
                        K: wp.array2d(dtype=float), Kinv: wp.array2d(dtype=wp.vec4), w: int, m: int, n: int,
                        sigma_base: float, tmp: wp.array2d(dtype=float), lane: int, lanes: int):
        """Kinv <- (M + J^T S^-1 J)^-1 (K holds its Cholesky factor on the way; the rows' 1 / S go
        to their field F_INV and to tmp). The lanes share the rows, then the matrix's entries, then
        the inverse's columns; lane 0 factors. Every lane of the block must call it."""
        for r in range(lane, m, lanes):
            p = row_at(rows, w, r, F_P)
            inverse = 1.0 / (sigma_base + penalty(rows, w, r) + p * p * row_at(rows, w, r, F_R))
            tmp[w, r] = inverse
            set_row(rows, w, r, F_INV, inverse)
        sync()
        entries = n * (n + 1) / 2
        for e in range(lane, entries, lanes):
            i = int((wp.sqrt(8.0 * float(e) + 1.0) - 1.0) * 0.5)
            while i * (i + 1) / 2 > e:
                i -= 1
            while (i + 1) * (i + 2) / 2 <= e:
                i += 1
            j = e - i * (i + 1) / 2
            acc = M[w, i * NV + j]
            for r in range(m):
                acc += J[w, r * NV + i] * J[w, r * NV + j] * tmp[w, r]
            K[w, i * NV + j] = acc
        sync()
        if lane == 0:
            cholesky(K, w, n, K)  # in place: each entry is read before it is overwritten
        sync()
        for j in range(lane, NV, lanes):
            col = vecnv()
            if j < n:
                col[j] = 1.0
                col = chol_solve(K, w, n, col)
            for kv in range(KINV_VECS):  # symmetric: column j is row j, written whole by its lane
                part = wp.vec4()
                for t in range(4):
                    if 4 * kv + t < NV:
                        part[t] = col[4 * kv + t]
                Kinv[w, j * KINV_VECS + kv] = part
        sync()

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=registers)
    def legged_step(
        dt: float,
        eta: float,
        rho0: float,
        tolerance: float,
        relative_tolerance: float,
        max_iterations: int,
        rho_update_interval: int,
        margin: float,
        stabilization: float,
        max_speed: float,
        worlds: LeggedWorlds,
        state: LeggedState,
        impulse: wp.array2d(dtype=float),
        frozen: wp.array(dtype=wp.int32),
        diverged: wp.array(dtype=wp.int32),
        # out
        iterations_out: wp.array(dtype=wp.int32),
        contacts_out: wp.array(dtype=wp.int32),
        drive_torque: wp.array2d(dtype=float),
        # scratch
        J: wp.array2d(dtype=float),
        Jc: wp.array2d(dtype=wp.vec4),
        rows: wp.array2d(dtype=wp.vec4),
        M: wp.array2d(dtype=float),
        LM: wp.array2d(dtype=float),
        K: wp.array2d(dtype=float),
        s1: wp.array2d(dtype=wp.vec4),
        s2: wp.array2d(dtype=wp.vec4),
        tmp: wp.array2d(dtype=float),
        slot_of: wp.array2d(dtype=wp.int32),
        row_count: wp.array(dtype=wp.int32),
        ufree: wp.array2d(dtype=float),
        Kinv: wp.array2d(dtype=wp.vec4),
    ):
        """One step of every legged world (a block of lanes or one thread per world): mass matrix and bias forces,
        free velocity, drive and contact rows, preconditioned PADMM with Woodbury solves, velocity
        update and integration; a non-finite or too fast world is flagged diverged and frozen."""
        if wp.static(tiled):
            w, lane = wp.tid()
            lanes = wp.block_dim()
        else:
            w = wp.tid()
            lane = 0
            lanes = 1
        if frozen[w] != 0:
            return
        samples = worlds.samples
        table_links = worlds.table_links
        table_foot_link = worlds.table_foot_link
        links0 = worlds.links0
        links1 = worlds.links1
        links2 = worlds.links2
        foot0 = worlds.foot0
        foot1 = worlds.foot1
        leg_count = worlds.leg_count
        leg_table = worlds.leg_table
        leg_scale = worlds.leg_scale
        leg_origin = worlds.leg_origin
        link_mass = worlds.link_mass
        link_inertia = worlds.link_inertia
        drive = worlds.drive
        shoe = worlds.shoe
        torso = worlds.torso
        torso_inertia = worlds.torso_inertia
        torso_half = worlds.torso_half
        gravity = worlds.gravity
        position = state.position
        orientation = state.orientation
        velocity = state.velocity
        angular_velocity = state.angular_velocity
        psi = state.psi
        psi_dot = state.psi_dot
        L = leg_count[w]
        n = 6 + L
        if wp.static(phase != "solve"):
            # set-up: every leg's column of M and its share of the torso blocks and bias forces, one leg
            # per lane (summed over the lanes as one vector); then on lane 0 the torso blocks, the
            # factor of M, the free velocity and the rows
            p = position[w]
            q = orientation[w]
            v = velocity[w]
            om = angular_velocity[w]
            R = wp.quat_to_matrix(q)
            axis = -(R * wp.vec3(0.0, 1.0, 0.0))
            g = gravity[w]
            mt = torso[w][0]
            for i in range(lane, NV * NV, lanes):
                M[w, i] = 0.0
            sync()
            m_part = float(0.0)  # this lane's legs: sum of m_k
            md_part = wp.vec3()  # sum of m_k d_k
            rot_part = wp.mat33()  # angular block
            f_part = wp.vec3()  # bias force on the torso
            t_part = wp.vec3()  # bias torque on the torso
            h_legs = veclegs()  # each leg's bias force (its own lane's entry)
            for li in range(lane, L, lanes):
                t = leg_table[w, li]
                s = leg_scale[w, li]
                ang = psi[w, li]
                rate = psi_dot[w, li]
                ix = table_index(ang, samples)
                i0 = int(ix[0])
                i1 = int(ix[1])
                f = ix[2]
                col = 6 + li
                o = leg_origin[w, li]
                me_sum = wp.vec3()  # the leg's column: linear part
                mw_sum = wp.vec3()  # angular part
                mjj = float(0.0)
                hj = float(0.0)
                for k in range(table_links[t]):
                    c0 = link_read(links0, t, i0, i1, f, k)
                    c1 = table_read(links1, t, i0, i1, f, k)
                    c2 = table_read(links2, t, i0, i1, f, k)
                    mk = link_mass[w, li * MAX_LINKS + k]
                    d = R * (o + wp.vec3(s * c0[0], 0.0, s * c0[1]))
                    e = plane(R, c1) * s
                    e2 = plane(R, c2) * s
                    Rk = R * rot_minus_y(c0[2])
                    Ik = Rk * link_inertia[w, li * MAX_LINKS + k] * wp.transpose(Rk)
                    ax = axis * c1[2]
                    m_part += mk
                    md_part += mk * d
                    rot_part += Ik + mk * (wp.dot(d, d) * wp.identity(n=3, dtype=float) - wp.outer(d, d))
                    me_sum += mk * e
                    mw_sum += mk * wp.cross(d, e) + Ik * ax
                    mjj += mk * wp.dot(e, e) + wp.dot(ax, Ik * ax)
                    wk = om + ax * rate
                    acc = wp.cross(om, wp.cross(om, d)) + 2.0 * rate * wp.cross(om, e) + e2 * (rate * rate)
                    alpha = rate * wp.cross(om, ax) + axis * (c2[2] * rate * rate)
                    f_lin = mk * (g - acc)
                    f_ang = -(Ik * alpha) - wp.cross(wk, Ik * wk)
                    f_part += f_lin
                    t_part += wp.cross(d, f_lin) + f_ang
                    hj += wp.dot(e, f_lin) + wp.dot(ax, f_ang)
                for c in range(MAX_LEGS):  # a select over constant indices keeps h_legs in registers
                    if c == li:
                        h_legs[c] = hj
                for i in range(3):
                    M[w, i * NV + col] = me_sum[i]
                    M[w, col * NV + i] = me_sum[i]
                    M[w, (3 + i) * NV + col] = mw_sum[i]
                    M[w, col * NV + 3 + i] = mw_sum[i]
                M[w, col * NV + col] = mjj
            part = vecsetup()
            part[0] = m_part
            for i in range(3):
                part[1 + i] = md_part[i]
                part[13 + i] = f_part[i]
                part[16 + i] = t_part[i]
                for j in range(3):
                    part[4 + 3 * i + j] = rot_part[i, j]
            for c in range(MAX_LEGS):
                part[19 + c] = h_legs[c]
            total = reduce_vector(part)
            sync()  # every lane's leg columns are in M
            if lane == 0:
                h = vecnv()
                It = R * torso_inertia[w] * wp.transpose(R)
                gyro = -wp.cross(om, It * om)
                for i in range(3):
                    h[i] = mt * g[i] + total[13 + i]
                    h[3 + i] = gyro[i] + total[16 + i]
                for c in range(MAX_LEGS):
                    h[6 + c] = total[19 + c]
                m_sum = mt + total[0]
                md_sum = wp.vec3(total[1], total[2], total[3])
                rot_sum = It + wp.mat33(total[4], total[5], total[6], total[7], total[8], total[9], total[10],
                                        total[11], total[12])
                # M_vv = m I, M_vw = -[sum m d]x, M_ww = the angular sum
                cross = wp.skew(md_sum)
                for i in range(3):
                    M[w, i * NV + i] = m_sum
                    for j in range(3):
                        M[w, i * NV + 3 + j] = -cross[i, j]
                        M[w, (3 + i) * NV + j] = cross[i, j]
                        M[w, (3 + i) * NV + 3 + j] = rot_sum[i, j]
                cholesky(M, w, n, LM)
                uu = vecnv()
                for i in range(3):
                    uu[i] = v[i]
                    uu[3 + i] = om[i]
                for li in range(L):
                    uu[6 + li] = psi_dot[w, li]
                acc_free = chol_solve(LM, w, n, h)
                uf = uu + dt * acc_free
                # rows: drives, then contacts within the margin
                m = int(0)
                for li in range(L):
                    dr = drive[w, li]
                    for c in range(NV):
                        J[w, m * NV + c] = 0.0
                    J[w, m * NV + 6 + li] = 1.0
                    kd = dr[1]
                    bound = dt * dr[2]
                    compliance = 1.0e6
                    if kd > 0.0:
                        compliance = 1.0 / (dt * kd)
                    set_row(rows, w, m, F_R, compliance)
                    set_row(rows, w, m, F_RHS, uf[6 + li] - dr[0] * wp.min(1.0, kd * 1.0e6))
                    set_row(rows, w, m, F_MU, -1.0)
                    set_row(rows, w, m, F_LO, -bound)
                    set_row(rows, w, m, F_HI, bound)
                    set_row(rows, w, m, F_COL, float(6 + li))
                    slot_of[w, m] = li
                    m += 1
                count = int(0)
                if torso[w][2] > 0.0:
                    half = torso_half[w]
                    for k in range(TORSO_CORNERS + 2 * L):
                        arm = wp.vec3()
                        lin = wp.vec3()  # the point's velocity per unit crank rate (shoe ends)
                        leg = int(-1)
                        mu = torso[w][1]
                        dist = float(0.0)
                        if k < TORSO_CORNERS:
                            sx = float(1.0)
                            sy = float(1.0)
                            sz = float(1.0)
                            if k % 2 == 1:
                                sx = -1.0
                            if (k / 2) % 2 == 1:
                                sy = -1.0
                            if k >= 4:
                                sz = -1.0
                            arm = R * wp.vec3(sx * half[0], sy * half[1], sz * half[2])
                            dist = p[2] + arm[2]
                        else:
                            leg = (k - TORSO_CORNERS) / 2
                            end = float(1.0)
                            if (k - TORSO_CORNERS) % 2 == 1:
                                end = -1.0
                            t = leg_table[w, leg]
                            s = leg_scale[w, leg]
                            ix = table_index(psi[w, leg], samples)
                            i0 = int(ix[0])
                            i1 = int(ix[1])
                            f = ix[2]
                            fl = table_foot_link[t]
                            sh = shoe[w, leg]
                            phi = link_read(links0, t, i0, i1, f, fl)
                            phi1 = table_read(links1, t, i0, i1, f, fl)
                            beta = phi[2] + sh[2]
                            dirn = wp.vec3(wp.cos(beta), wp.sin(beta), 0.0)
                            perp = wp.vec3(-wp.sin(beta), wp.cos(beta), 0.0)
                            fp = foot_read(foot0, t, i0, i1, f) * s + dirn * (end * sh[1])
                            fv = foot_read(foot1, t, i0, i1, f) * s + perp * (end * sh[1] * phi1[2])
                            # the contact point: on the shoe's surface, one radius below its end's
                            # centre; it moves with the foot link (turning at axis * phi' per unit
                            # crank rate about the end's centre)
                            down = wp.vec3(0.0, 0.0, -sh[0])
                            arm = R * leg_origin[w, leg] + plane(R, fp) + down
                            lin = plane(R, fv) + wp.cross(axis * phi1[2], down)
                            dist = p[2] + arm[2]
                            mu = sh[3]
                        if dist < margin:
                            count += 1
                            for comp in range(3):
                                nrm = wp.vec3(0.0, 0.0, 1.0)
                                if comp == 1:
                                    nrm = wp.vec3(1.0, 0.0, 0.0)
                                if comp == 2:
                                    nrm = wp.vec3(0.0, 1.0, 0.0)
                                rxn = wp.cross(arm, nrm)
                                for c in range(NV):
                                    J[w, m * NV + c] = 0.0
                                for i in range(3):
                                    J[w, m * NV + i] = nrm[i]
                                    J[w, m * NV + 3 + i] = rxn[i]
                                if leg >= 0:
                                    J[w, m * NV + 6 + leg] = wp.dot(nrm, lin)
                                vrow = jrow_dot(J, w, m, n, uf)
                                if comp == 0:
                                    if dist > 0.0:
                                        vrow += dist / dt
                                    else:
                                        vrow += stabilization * dist / dt
                                set_row(rows, w, m, F_R, 0.0)
                                set_row(rows, w, m, F_RHS, vrow)
                                set_row(rows, w, m, F_MU, mu)
                                set_row(rows, w, m, F_COL, float(6 + leg))  # -1 + 6 < 6 for a torso corner
                                slot_of[w, m] = MAX_LEGS + 3 * k + comp
                                m += 1
                contacts_out[w] = count
                for c in range(NV):
                    ufree[w, c] = uf[c]
                row_count[w] = m
            sync()
            m = row_count[w]
            units = L + (m - L) / 3
            # Jacobi preconditioner P = diag(J M^-1 J^T + R)^-1/2 (one value per contact triplet), the
            # compact copy of the preconditioned rows, and the warm start from the last step's impulses
            # by slot, unit by unit over the lanes (LM holds the factor of M). A drive row whose warm
            # start lies within half its bounds keeps the penalty at or below rho0 (its projection is
            # then the identity, and a large penalty only slows it).
            rho = rho0
            gyl = vecnv()
            unit = lane
            while unit < units:
                r = unit
                span = int(1)
                if unit >= L:
                    r = L + 3 * (unit - L)
                    span = 3
                dsum = float(0.0)
                for rr in range(r, r + span):
                    jr = vecnv()
                    for c in range(NV):
                        jr[c] = J[w, rr * NV + c]
                    first = int(0)  # a drive row: zero before its crank column
                    if row_at(rows, w, rr, F_MU) < 0.0:
                        first = int(row_at(rows, w, rr, F_COL))
                    dsum += forward_norm2(LM, w, n, jr, first) + row_at(rows, w, rr, F_R)
                pr = 1.0 / wp.sqrt(wp.max(dsum / float(span), 1.0e-12))
                xs = wp.vec3()
                for c in range(span):
                    rr = r + c
                    set_row(rows, w, rr, F_P, pr)
                    set_row(rows, w, rr, F_RHS, pr * row_at(rows, w, rr, F_RHS))
                    set_row(rows, w, rr, F_LO, row_at(rows, w, rr, F_LO) / pr)
                    set_row(rows, w, rr, F_HI, row_at(rows, w, rr, F_HI) / pr)
                    set_row(rows, w, rr, F_PEN, rho0)
                    for k in range(NV):
                        J[w, rr * NV + k] = pr * J[w, rr * NV + k]
                    col = int(row_at(rows, w, rr, F_COL))
                    crank = float(0.0)
                    for k in range(6, NV):
                        if k == col:
                            crank = J[w, rr * NV + k]
                    base = rr * NV
                    Jc[w, 2 * rr] = wp.vec4(J[w, base], J[w, base + 1], J[w, base + 2], J[w, base + 3])
                    Jc[w, 2 * rr + 1] = wp.vec4(J[w, base + 4], J[w, base + 5], crank, 0.0)
                    xs[c] = impulse[w, slot_of[w, rr]] / pr
                pj = project_row(rows, w, r, xs[0], xs[1], xs[2])
                for c in range(span):
                    s1[w, r + c] = wp.vec4(xs[c], xs[c], 0.0, 0.0)
                    s2[w, r + c] = wp.vec4(pj[c], 0.0, pj[c], 0.0)  # y and its last value; z below
                    for k in range(NV):
                        gyl[k] += J[w, (r + c) * NV + k] * pj[c]
                free = float(0.0)
                if span == 1 and wp.abs(xs[0]) < 0.5 * row_at(rows, w, r, F_HI):
                    free = 1.0
                set_row(rows, w, r, F_FREE, free)
                unit += lanes
            # the dual variable from the warm start: z = -(D y + v_f + s), the (shifted) velocity it
            # gives, so that an unchanged contact set starts at its fixed point
            gy = reduce_vector(gyl)
            my = chol_solve(LM, w, n, gy)
            unit = lane
            while unit < units:
                r = unit
                span = int(1)
                if unit >= L:
                    r = L + 3 * (unit - L)
                    span = 3
                vels = wp.vec3()
                for c in range(span):
                    i = r + c
                    pr = row_at(rows, w, i, F_P)
                    vc = (jrow_dot(J, w, i, n, my) + pr * pr * row_at(rows, w, i, F_R) * s2[w, i][0]
                          + row_at(rows, w, i, F_RHS))
                    prior = s1[w, i]
                    s1[w, i] = wp.vec4(prior[0], prior[1], vc, prior[3])
                    vels[c] = vc
                shift = float(0.0)
                if span == 3:
                    shift = row_at(rows, w, r, F_MU) * wp.sqrt(vels[1] * vels[1] + vels[2] * vels[2])
                for c in range(span):
                    zc = -vels[c]
                    if c == 0:
                        zc -= shift
                    prior = s2[w, r + c]
                    s2[w, r + c] = wp.vec4(prior[0], zc, prior[2], zc)
                unit += lanes
        if wp.static(phase == "setup"):
            return
        m = row_count[w]  # (again, for the solve phase's kernel)
        units = L + (m - L) / 3
        rho = rho0
        its = int(0)
        converged = int(0)
        momentum = float(1.0)
        merit = float(1.0e30)
        beta = float(0.0)
        refactor = int(1)  # the Woodbury factor at the first iteration and after a new penalty
        while its < max_iterations and converged == 0 and m > 0:
            if refactor != 0:
                # one call site: the factor's code is large, and a second inlined copy costs the
                # instruction cache more than the branch costs
                sync()  # every lane is done with the rows (their set-up or the new penalties)
                woodbury_factor(J, rows, M, K, Kinv, w, m, n, eta, tmp, lane, lanes)
                refactor = 0
            # each lane takes units (a drive row or a contact triplet) lane, lane + lanes, ...: the
            # right-hand side b at the extrapolated (y, z) with the De Saxce shift from the velocity
            # at the last iterate, t = S^-1 b and its share of J^T t. A row's PADMM state is two
            # vec4, (x, x before, its velocity at x, t) and (y, z, y and z before), its fields
            # read from two (drive rows) or one: each loaded once per pass, stored once (second
            # pass only, which computes b and t again rather than read them back)
            gl = vecnv()
            unit = lane
            while unit < units:
                if unit < L:
                    i = unit
                    a1 = s1[w, i]
                    a2 = s2[w, i]
                    f0 = rows[w, ROW_VECS * i]  # v_f, mu, penalty, 1 / S
                    yh = a2[0] + beta * (a2[0] - a2[2])
                    zh = a2[1] + beta * (a2[1] - a2[3])
                    bi = -f0[0] + eta * a1[0] + f0[2] * yh - zh
                    gl = row_add(Jc, w, i, False, 6 + i, bi * f0[3], gl)  # drive row i turns leg i
                else:
                    r0 = L + 3 * (unit - L)
                    col = int(rows[w, ROW_VECS * r0 + 1][2])
                    mu = float(0.0)
                    bs = wp.vec3()
                    vts = wp.vec3()
                    invs = wp.vec3()
                    for c in range(3):
                        i = r0 + c
                        a1 = s1[w, i]
                        a2 = s2[w, i]
                        f0 = rows[w, ROW_VECS * i]
                        if c == 0:
                            mu = f0[1]
                        yh = a2[0] + beta * (a2[0] - a2[2])
                        zh = a2[1] + beta * (a2[1] - a2[3])
                        bs[c] = -f0[0] + eta * a1[0] + f0[2] * yh - zh
                        vts[c] = a1[2]  # the velocity at the last iterate
                        invs[c] = f0[3]
                    bs[0] = bs[0] - mu * wp.sqrt(vts[1] * vts[1] + vts[2] * vts[2])
                    for c in range(3):
                        gl = row_add(Jc, w, r0 + c, True, col, bs[c] * invs[c], gl)
                unit += lanes
            # Woodbury: x = t - S^-1 J (M + J^T S^-1 J)^-1 J^T t, the small inverse applied to the sum
            # (its rows and columns past n are zero)
            gsum = reduce_vector(gl)
            yv = vecnv()
            if lanes >= NV:
                # a lane per entry: lane k takes row k of the inverse (four entries per load), the
                # lanes share the entries through one tile
                yk = float(0.0)
                if lane < n:
                    for kv in range(KINV_VECS):
                        kq = Kinv[w, lane * KINV_VECS + kv]
                        for t in range(4):
                            if 4 * kv + t < NV:
                                yk += kq[t] * gsum[4 * kv + t]
                entries = wp.tile(yk)
                for k in range(NV):
                    yv[k] = wp.tile_extract(entries, k)
            else:
                # one lane (the CPU, or a thread per world): the symmetric inverse's lower triangle
                # read once
                for k in range(NV):
                    if k < n:
                        for kv in range(KINV_VECS):
                            if 4 * kv <= k:
                                kq = Kinv[w, k * KINV_VECS + kv]
                                for t in range(4):
                                    j = 4 * kv + t
                                    if j < k:
                                        yv[k] += kq[t] * gsum[j]
                                        yv[j] += kq[t] * gsum[k]
                                    elif j == k:
                                        yv[k] += kq[t] * gsum[k]
            rp = float(0.0)
            rd = float(0.0)
            rn = float(0.0)
            ymax = float(0.0)
            change = float(0.0)
            unit = lane
            while unit < units:
                # b and t again as in the first pass (the state is not written there), x, the
                # projection of x + z / rho, the velocities at the new x, D x + v_f =
                # b - (eta + rho) x + v_f, the natural residual x - Pi(x - v^) (v^ with the De Saxce
                # shift: in the dual cone at a solution), then y, z and the residuals
                if unit < L:
                    i = unit
                    a1 = s1[w, i]
                    a2 = s2[w, i]
                    f0 = rows[w, ROW_VECS * i]
                    f1 = rows[w, ROW_VECS * i + 1]
                    pen = f0[2]
                    yh = a2[0] + beta * (a2[0] - a2[2])
                    zh = a2[1] + beta * (a2[1] - a2[3])
                    bi = -f0[0] + eta * a1[0] + pen * yh - zh
                    tv = bi * f0[3]
                    xr = tv - row_dot(Jc, w, i, False, 6 + i, yv) * f0[3]
                    yn = wp.clamp(xr + zh / pen, f1[0], f1[1])
                    vd = bi - (eta + pen) * xr + f0[0]
                    rn = wp.max(rn, wp.abs(xr - wp.clamp(xr - vd, f1[0], f1[1])))
                    zn = zh + pen * (xr - yn)
                    dy = yn - yh
                    dz = zn - zh
                    rp = wp.max(rp, wp.abs(xr - yn))
                    rd = wp.max(rd, wp.abs(eta * (xr - a1[0]) + pen * dy))
                    change += pen * dy * dy + dz * dz / pen
                    s2[w, i] = wp.vec4(yn, zn, a2[0], a2[1])
                    s1[w, i] = wp.vec4(xr, a1[0], vd, tv)
                    ymax = wp.max(ymax, wp.abs(yn))
                else:
                    r0 = L + 3 * (unit - L)
                    col = int(rows[w, ROW_VECS * r0 + 1][2])
                    mu = float(0.0)
                    pen = float(0.0)
                    xs = wp.vec3()
                    xps = wp.vec3()
                    bs = wp.vec3()
                    ts = wp.vec3()
                    yo = wp.vec3()
                    zo = wp.vec3()
                    yhs = wp.vec3()
                    zhs = wp.vec3()
                    rhs = wp.vec3()
                    vts = wp.vec3()
                    invs = wp.vec3()
                    for c in range(3):
                        i = r0 + c
                        a1 = s1[w, i]
                        a2 = s2[w, i]
                        f0 = rows[w, ROW_VECS * i]
                        if c == 0:
                            mu = f0[1]
                            pen = f0[2]
                        yh = a2[0] + beta * (a2[0] - a2[2])
                        zh = a2[1] + beta * (a2[1] - a2[3])
                        bs[c] = -f0[0] + eta * a1[0] + f0[2] * yh - zh
                        vts[c] = a1[2]
                        invs[c] = f0[3]
                        rhs[c] = f0[0]
                        xps[c] = a1[0]
                        yo[c] = a2[0]
                        zo[c] = a2[1]
                        yhs[c] = yh
                        zhs[c] = zh
                    bs[0] = bs[0] - mu * wp.sqrt(vts[1] * vts[1] + vts[2] * vts[2])
                    for c in range(3):
                        ts[c] = bs[c] * invs[c]
                        xs[c] = ts[c] - row_dot(Jc, w, r0 + c, True, col, yv) * invs[c]
                    pj = project_cone(mu, xs[0] + zhs[0] / pen, xs[1] + zhs[1] / pen, xs[2] + zhs[2] / pen)
                    vel = wp.vec3()
                    for c in range(3):
                        vel[c] = bs[c] - (eta + pen) * xs[c] + rhs[c]
                    vels3 = wp.vec3(vel[0], vel[1], vel[2])  # kept for the next iteration's De Saxce shift
                    vel[0] = vel[0] + mu * wp.sqrt(vel[1] * vel[1] + vel[2] * vel[2])
                    nat = xs - project_cone(mu, xs[0] - vel[0], xs[1] - vel[1], xs[2] - vel[2])
                    rn = wp.max(rn, wp.max(wp.abs(nat[0]), wp.max(wp.abs(nat[1]), wp.abs(nat[2]))))
                    for c in range(3):
                        yn = pj[c]
                        xr = xs[c]
                        zn = zhs[c] + pen * (xr - yn)
                        dy = yn - yhs[c]
                        dz = zn - zhs[c]
                        rp = wp.max(rp, wp.abs(xr - yn))
                        rd = wp.max(rd, wp.abs(eta * (xr - xps[c]) + pen * dy))
                        change += pen * dy * dy + dz * dz / pen
                        s2[w, r0 + c] = wp.vec4(yn, zn, yo[c], zo[c])
                        s1[w, r0 + c] = wp.vec4(xr, xps[c], vels3[c], ts[c])
                        ymax = wp.max(ymax, wp.abs(yn))
                unit += lanes
            stats = reduce_stats(vecstats(rp, rd, rn, ymax, change))
            rp = stats[0]
            rd = stats[1]
            rn = stats[2]
            ymax = stats[3]
            change = stats[4]
            its += 1
            tol = tolerance + relative_tolerance * ymax
            if rp < tol and rd < tol and rn < tol:
                converged = 1
            else:
                beta = 0.0
                if change < 0.999 * merit:
                    a_next = 0.5 * (1.0 + wp.sqrt(1.0 + 4.0 * momentum * momentum))
                    beta = (momentum - 1.0) / a_next
                    momentum = a_next
                else:
                    momentum = 1.0
                merit = change
                if its % rho_update_interval == 0:
                    new_rho = rho
                    if rp > 10.0 * rd:
                        new_rho = wp.min(rho * 4.0, 1.0e3)
                    elif rd > 10.0 * rp:
                        new_rho = wp.max(rho / 4.0, 1.0e-5)
                    if new_rho != rho:
                        sync()  # every lane is done with the rows and the inverse
                        if lane == 0:
                            set_penalties(rows, w, m, new_rho, rho0)
                            for i in range(m):  # z is the unscaled multiplier: it stays; the momentum restarts
                                prior = s2[w, i]
                                s2[w, i] = wp.vec4(prior[0], prior[1], prior[0], prior[1])
                        refactor = 1  # at the next iteration, if there is one
                        rho = new_rho
                        momentum = 1.0
                        merit = 1.0e30
                        beta = 0.0
        sync()
        # the impulses by slot and J^T lambda, the rows over the lanes (summed as one vector); then
        # the velocity update and the integration on lane 0
        for i in range(lane, MAX_ROWS, lanes):
            impulse[w, i] = 0.0
        sync()
        jl = vecnv()
        for r in range(lane, m, lanes):
            yr = s2[w, r][0]
            f0 = rows[w, ROW_VECS * r]
            impulse[w, slot_of[w, r]] = yr * row_at(rows, w, r, F_P)
            # the compact rows are preconditioned: J~^T y = J^T lambda
            jl = row_add(Jc, w, r, f0[F_MU] >= 0.0, int(row_at(rows, w, r, F_COL)), yr, jl)
        jl = reduce_vector(jl)
        if lane != 0:
            return
        iterations_out[w] = its
        uf = vecnv()
        for c in range(NV):
            uf[c] = ufree[w, c]
        un = uf + chol_solve(LM, w, n, jl)
        p = position[w]
        q = orientation[w]
        for li in range(L):
            drive_torque[w, li] = impulse[w, li] / dt
        v = wp.vec3(un[0], un[1], un[2])
        om = wp.vec3(un[3], un[4], un[5])
        p = p + dt * v
        spin = wp.length(om)
        if spin > 1.0e-12:
            q = wp.normalize(wp.quat_from_axis_angle(om / spin, spin * dt) * q)
        ok = wp.isfinite(p) and wp.isfinite(v) and wp.isfinite(om) and wp.length(v) < max_speed
        for li in range(L):
            rate = un[6 + li]
            ang = psi[w, li] + dt * rate
            ang = ang - TWO_PI * wp.floor(ang / TWO_PI)
            psi[w, li] = ang
            psi_dot[w, li] = rate
            if not (wp.isfinite(ang) and wp.isfinite(rate)):
                ok = False
        position[w] = p
        orientation[w] = q
        velocity[w] = v
        angular_velocity[w] = om
        if not ok:
            diverged[w] = 1
            frozen[w] = 1

    return legged_step


@wp.func
def table_index(ang: float, samples: int):
    """Sample pair and weight of a crank angle: (i0, i1, f) packed as a vec3."""
    u = ang * float(samples) / TWO_PI
    u = u - float(samples) * wp.floor(u / float(samples))
    i0 = int(u)
    if i0 >= samples:
        i0 = samples - 1
    i1 = i0 + 1
    if i1 >= samples:
        i1 = 0
    return wp.vec3(float(i0), float(i1), u - float(i0))


@wp.kernel
def legged_record(
    worlds: LeggedWorlds,
    state: LeggedState,
    # out
    points: wp.array2d(dtype=wp.vec3),
    energy: wp.array(dtype=float),
):
    """Tracked points (torso centre, torso_up, feet) and the mechanical energy [J], link by link:
    kinetic energy of every link's own velocity plus the potential of gravity."""
    w = wp.tid()
    samples = worlds.samples
    table_links = worlds.table_links
    links0 = worlds.links0
    links1 = worlds.links1
    foot0 = worlds.foot0
    leg_count = worlds.leg_count
    leg_table = worlds.leg_table
    leg_scale = worlds.leg_scale
    leg_origin = worlds.leg_origin
    link_mass = worlds.link_mass
    link_inertia = worlds.link_inertia
    torso = worlds.torso
    torso_inertia = worlds.torso_inertia
    torso_half = worlds.torso_half
    gravity = worlds.gravity
    position = state.position
    orientation = state.orientation
    velocity = state.velocity
    angular_velocity = state.angular_velocity
    psi = state.psi
    psi_dot = state.psi_dot
    p = position[w]
    R = wp.quat_to_matrix(orientation[w])
    v = velocity[w]
    om = angular_velocity[w]
    axis = -(R * wp.vec3(0.0, 1.0, 0.0))
    g = gravity[w]
    mt = torso[w][0]
    It = R * torso_inertia[w] * wp.transpose(R)
    e = 0.5 * mt * wp.dot(v, v) + 0.5 * wp.dot(om, It * om) - mt * wp.dot(g, p)
    points[w, 0] = p
    points[w, 1] = p + R * wp.vec3(0.0, 0.0, torso_half[w][0])
    for li in range(leg_count[w]):
        t = leg_table[w, li]
        s = leg_scale[w, li]
        ix = table_index(psi[w, li], samples)
        i0 = int(ix[0])
        i1 = int(ix[1])
        f = ix[2]
        rate = psi_dot[w, li]
        o = leg_origin[w, li]
        points[w, 2 + li] = p + R * o + plane(R, foot_read(foot0, t, i0, i1, f)) * s
        for k in range(table_links[t]):
            c0 = link_read(links0, t, i0, i1, f, k)
            c1 = table_read(links1, t, i0, i1, f, k)
            mk = link_mass[w, li * MAX_LINKS + k]
            d = R * (o + wp.vec3(s * c0[0], 0.0, s * c0[1]))
            vk = v + wp.cross(om, d) + plane(R, c1) * (s * rate)
            wk = om + axis * (c1[2] * rate)
            Rk = R * rot_minus_y(c0[2])
            Ik = Rk * link_inertia[w, li * MAX_LINKS + k] * wp.transpose(Rk)
            e += 0.5 * mk * wp.dot(vk, vk) + 0.5 * wp.dot(wk, Ik * wk) - mk * wp.dot(g, p + d)
    energy[w] = e


@wp.kernel
def freeze_worlds(halted: wp.array(dtype=wp.int32), frozen: wp.array(dtype=wp.int32)):
    """Freeze the worlds that rollout's halt stopped."""
    w = wp.tid()
    if halted[w] != 0:
        frozen[w] = 1


def _structs(model: LeggedModel) -> tuple:
    """The LeggedWorlds and LeggedState of ``model`` (their arrays are the model's own)."""
    worlds, state = LeggedWorlds(), LeggedState()
    for name in LeggedWorlds.vars:
        source = {"links0": model.links[0], "links1": model.links[1], "links2": model.links[2],
                  "foot0": model.foot[0], "foot1": model.foot[1]}.get(name)
        setattr(worlds, name, getattr(model, name) if source is None else source)
    for name in LeggedState.vars:
        setattr(state, name, getattr(model, name))
    return worlds, state


def _step_inputs(model: LeggedModel) -> list:
    c = model.config
    return [model.dt, c.tuning.eta, c.tuning.rho_or(TABULATED_RHO), c.tolerance, c.relative_tolerance,
            c.max_iterations, c.tuning.rho_update_interval,
            c.contact_margin, c.contact_stabilization, c.max_speed, *_structs(model),
            model.impulse, model.frozen, model.diverged,
            model.iterations, model.contacts, model.drive_torque,
            model.rows_J, model.rows_Jc, model.rows, model.mass, model.mass_factor, model.factor, *model.work,
            model.row_inverse, model.slot_of,
            model.row_count, model.ufree, model.factor_inverse]


def legged_step_batch(model: LeggedModel, steps: int = 1):
    """Advance every world of ``model`` by ``steps`` steps."""
    inputs = _step_inputs(model)
    if model.tiled:
        kernel = step_kernel(True, "all", model.max_registers)
        for _ in range(steps):
            wp.launch_tiled(kernel, dim=[model.num_worlds], block_dim=model.lanes, inputs=inputs,
                            device=model.device)
        return
    setup, solve = step_kernel(False, "setup"), step_kernel(False, "solve")
    for _ in range(steps):  # one thread per world: the set-up and the solve as two kernels (see step_kernel)
        wp.launch(setup, dim=model.num_worlds, inputs=inputs, device=model.device)
        wp.launch(solve, dim=model.num_worlds, inputs=inputs, device=model.device)


def legged_points(model: LeggedModel) -> tuple:
    """Tracked points (W, 2 + max legs, 3) [m] and energy (W,) [J] of the current state."""
    wp.launch(legged_record, dim=model.num_worlds, device=model.device,
              inputs=[*_structs(model)],
              outputs=[model.points, model.energy])
    return model.points.numpy(), model.energy.numpy()


def legged_rollout(model: LeggedModel, steps: int, *, record_every: int = 10, halt=None):
    """Step ``model`` ``steps`` times (a multiple of record_every), recording every record_every
    steps: returns an engine.Trace (points, drive torques and speeds per leg, energy; the loops
    are closed by construction, so the violations are zero). halt(points (W, P, 3), start) -> (W,)
    bool freezes worlds, as engine.rollout's halt does. On CUDA a chunk of record_every steps is
    captured once as a graph and replayed."""
    from engine.rollout import Trace

    if steps < record_every or steps % record_every:
        raise ValueError(f"legged_rollout: steps ({steps}) must be a positive multiple of "
                         f"record_every ({record_every})")
    W = model.num_worlds
    records = steps // record_every + 1
    names = model.point_names
    P = 2 + MAX_LEGS
    points = np.zeros((records, W, P, 3), np.float32)
    energy = np.zeros((records, W), np.float32)
    torque = np.zeros((records, W, MAX_LEGS), np.float32)
    speed = np.zeros((records, W, MAX_LEGS), np.float32)
    iterations = np.zeros((records, W), np.int32)
    halted_at = np.full(W, -1.0)
    points[0], energy[0] = legged_points(model)
    speed[0] = model.psi_dot.numpy()
    graph = None
    if model.device.is_cuda:
        legged_step_batch(model, 1)  # compile, outside the capture
        wp.synchronize_device(model.device)
        with wp.ScopedCapture(device=model.device) as capture:
            legged_step_batch(model, record_every)
        graph = capture.graph
        steps_done = 1
    else:
        steps_done = 0
    halted = wp.zeros(W, dtype=wp.int32, device=model.device)
    for r in range(1, records):
        if graph is not None and r == 1:
            legged_step_batch(model, record_every - steps_done)
        elif graph is not None:
            wp.capture_launch(graph)
        else:
            legged_step_batch(model, record_every)
        points[r], energy[r] = legged_points(model)
        torque[r] = model.drive_torque.numpy()
        speed[r] = model.psi_dot.numpy()
        iterations[r] = model.iterations.numpy()
        if halt is not None:
            stop = np.asarray(halt(points[r], points[0])) & (halted_at < 0)
            if stop.any():
                halted_at[stop] = r * record_every * model.dt
                halted.assign(stop.astype(np.int32))
                wp.launch(freeze_worlds, dim=W, inputs=[halted, model.frozen], device=model.device)
    diverged = model.diverged.numpy().astype(bool)
    zeros = np.zeros((records, W), np.float32)
    return Trace(np.arange(records) * record_every * model.dt, points, zeros, zeros.copy(), energy, iterations,
                 torque, speed, diverged, names, halted_at)
