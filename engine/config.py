"""Solver settings: SolverConfig (what a user sets) and Tuning (the method's internal knobs).

``SolverConfig`` holds the settings that change what a simulation means or how far it may be
trusted: the integrator, the PADMM stopping rule, the position projection, joint limit and contact
stabilization, and the health guards. ``Tuning`` holds the knobs of the method itself (penalties,
acceleration, warm start, linear solver and kernel choices, register caps, ...), set for benchmarks
and tests; every plan reads both (engine.pack copies the per-world numbers to device arrays).

    config = SolverConfig(max_iterations=50)                       # what a user sets
    config = SolverConfig(tuning=Tuning(linear_solver="sparse"))   # a knob
    config = config.tuned(rho=1.0, step_kernel="staged")           # a copy with other knobs

A knob left at None takes the plan's own choice (Tuning.rho: each plan's starting penalty, below).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["MAXIMAL_RHO", "TABULATED_RHO", "Integrator", "LinearSolver", "ProjectionPattern", "SolverConfig",
           "SparseOrdering", "StepKernel", "Tuning"]

# the maximal plan's starting ADMM penalty (Tuning.rho None): its rows are joint rows, whose soft
# modes a small penalty leaves fast (engine.padmm)
MAXIMAL_RHO = 1.0e-3
# the tabulated plan's starting penalty: its rows are Jacobi-preconditioned to a unit diagonal, so 1
# is the matrix's own scale
TABULATED_RHO = 1.0


class Integrator(enum.Enum):
    """Time-stepping scheme."""

    SEMI_IMPLICIT_EULER = "euler"  # velocities implicit in the reactions, poses explicit
    MOREAU_JEAN = "moreau"  # half pose step, dynamics at the midpoint, half pose step


# Tuning's closed choices: string enums, so that a knob is given and compared as its string too


class LinearSolver(enum.StrEnum):
    """The maximal plan's linear solver (Tuning.linear_solver)."""

    AUTO = "auto"  # dense where the padded rows fit engine.pack.MAX_DENSE_ROWS, else sparse
    DENSE = "dense"  # a Cholesky tile per world
    SPARSE = "sparse"  # LDL^T on the matrix's pattern, one schedule per topology


class StepKernel(enum.StrEnum):
    """The maximal plan's step kernels (Tuning.step_kernel)."""

    AUTO = "auto"  # fused where it fits
    FUSED = "fused"  # one launch per step (engine.fused)
    STAGED = "staged"  # one kernel per stage (engine.step)


class ProjectionPattern(enum.StrEnum):
    """Whether the sparse projection factors the bilateral rows on a pattern of their own
    (Tuning.sparse_projection_pattern)."""

    AUTO = "auto"
    ALWAYS = "always"
    NEVER = "never"


class SparseOrdering(enum.StrEnum):
    """The sparse factor's elimination order (Tuning.sparse_ordering)."""

    MINIMUM_DEGREE = "minimum_degree"
    SHALLOW = "shallow"  # per topology, the shortest estimated schedule


def _finite(value) -> bool:
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def _check(owner: str, obj, checks: dict) -> None:
    for name, ok in checks.items():
        if not ok or not _finite(getattr(obj, name)):
            raise ValueError(f"{owner}.{name}: invalid value {getattr(obj, name)!r}")


def _optional_int(value, low: int) -> bool:
    return value is None or (isinstance(value, int) and not isinstance(value, bool) and value >= low)


@dataclass(frozen=True)
class Tuning:
    """The solver's internal knobs (frozen), for benchmarks and tests: the defaults are the measured
    choices, and a change here changes speed or rounding, not what is simulated. What each was
    measured to do: benchmarks/results/README.md, "Solver tuning: what each knob was measured to do".
    None means "the plan's choice".

    Attributes:
        eta: proximal weight (> 0); regularizes redundant constraints.
        rho: starting ADMM penalty; None: each plan's own (maximal MAXIMAL_RHO = 1e-3, tree
            engine.reduced.chains.CONTACT_RHO = 1, tabulated TABULATED_RHO = 1).
        adaptive_rho: rescale the penalty (and refactor) when primal and dual residuals are unbalanced.
        rho_update_interval: PADMM iterations between penalty updates.
        acceleration: Nesterov momentum with restart.
        warmstart: start each step from the last step's impulses.
        warmstart_decay: share of the last step's impulses left out of the warm start, in [0, 1)
            (keeps rounding from piling up in redundant directions of over-constrained loops).
        cap_joint_penalty: give the free rows (bilateral joint rows, drives well inside their limits)
            their own fixed penalty free_rho; off: one penalty for all rows.
        free_rho: the free rows' penalty (cap_joint_penalty on); eta + free_rho also shifts the joint
            rows of the position projection's factor.
        stall_ratio: 0 (off) or in (0, 1): a world whose largest residual did not fall below this
            share of its value engine.padmm.STALL_WINDOW iterations earlier stops (not converged).
        projection_velocity_update: add each projection displacement / dt to the velocities (SHAKE-like).
        projection_velocity_floor: a projection iteration updates the velocities only when the largest
            joint error it corrects exceeds this [m]/[rad]; 0: always.
        projection_skip_floor: a projection iteration is skipped in a world whose linear joint errors
            are all at or below this [m] (and angular ones at or below the next); 0 with it: no skip.
            The defaults sit at float32 rounding: keep them. At 0 the maximal plan applies
            rounding-sized corrections every step and, through the velocity update, lost 300x
            accuracy on the four-bar (benchmarks/results/cpu/skip_floors_fourbar.json).
        projection_skip_floor_angular: the angular rows' share of that test [rad].
        linear_solver: "auto" (dense where the padded rows fit engine.pack.MAX_DENSE_ROWS, else
            sparse), "dense" (per-world Cholesky tile) or "sparse" (Cholesky on the matrix's pattern).
        step_kernel: "auto" (fused where it fits), "fused" (engine.fused: one launch per step; no
            contacts, at most engine.fused.FUSED_MAX_ROWS rows) or "staged" (one kernel per stage).
        sparse_body_nodes: the sparse factor keeps a body acted on by many rows as six nodes where
            its analysis estimates a shorter schedule (engine.linalg.sparse_analysis.choose_body_nodes).
        sparse_projection_pattern: "auto", "always" or "never" (True / False read as these): the
            sparse projection factors the bilateral rows on a pattern of their own.
        sparse_ordering: "minimum_degree" or "shallow" (per topology, the shortest estimated
            schedule): the sparse factor's elimination order.
        compensated_state: compensated sums of the twists and configurations, joint errors in float64;
            off: plain float32 sums (about 10 % faster fused steps, more drift).
        fused_block: lanes per world of the maximal fused step; None: engine.fused.fused_block.
        fused_registers: register cap per thread of the fused step; None: engine.fused.FUSED_REGISTERS;
            0: the compiler's choice.
        fused_inverse: the fused step solves through L^-1 (True) or by substitution (False);
            None: engine.fused.fused_inverse.
        fused_sharing: how the fused step's lanes share joints and bodies (engine.fused.SHARE_* bit
            flags); None: engine.fused.fused_sharing.
        tree_registers: register cap per thread of the tree plan's kernel; None:
            engine.reduced.chain_kernel.MAX_REGISTERS; 0: the compiler's choice.
        tree_contact_working: contacts the tree kernel's tiles hold (>= 1; a world with more steps
            again on tiles for its capacity); None: the most any world has at its initial pose.
        tabulated_tiled: the tabulated plan steps a block of lanes (True) or one thread (False) per
            world; None: a block on a GPU up to engine.reduced.tabulated_kernel.tiled_max_worlds.
        tabulated_registers: register cap per thread of the tiled tabulated step; None:
            engine.reduced.tabulated_kernel.TILED_REGISTERS; 0: the compiler's choice.
    """

    eta: float = 1.0e-5
    rho: float | None = None
    adaptive_rho: bool = True
    rho_update_interval: int = 4
    acceleration: bool = True
    warmstart: bool = True
    warmstart_decay: float = 0.05
    cap_joint_penalty: bool = True
    free_rho: float = 2.0e-4
    stall_ratio: float = 0.0
    projection_velocity_update: bool = True
    projection_velocity_floor: float = 1.0e-7
    projection_skip_floor: float = 1.0e-7
    projection_skip_floor_angular: float = 1.0e-6
    linear_solver: LinearSolver = LinearSolver.AUTO
    step_kernel: StepKernel = StepKernel.AUTO
    sparse_body_nodes: bool = True
    sparse_projection_pattern: ProjectionPattern = ProjectionPattern.AUTO
    sparse_ordering: SparseOrdering = SparseOrdering.MINIMUM_DEGREE
    compensated_state: bool = True
    fused_block: int | None = None
    fused_registers: int | None = None
    fused_inverse: bool | None = None
    fused_sharing: int | None = None
    tree_registers: int | None = None
    tree_contact_working: int | None = None
    tabulated_tiled: bool | None = None
    tabulated_registers: int | None = None

    def __post_init__(self):
        if isinstance(self.sparse_projection_pattern, bool):
            choice = "always" if self.sparse_projection_pattern else "never"
            object.__setattr__(self, "sparse_projection_pattern", choice)
        for name, kind in (("step_kernel", StepKernel), ("sparse_projection_pattern", ProjectionPattern),
                           ("sparse_ordering", SparseOrdering), ("linear_solver", LinearSolver)):
            value = getattr(self, name)
            if not isinstance(value, str) or value not in kind._value2member_map_:
                choices = [member.value for member in kind]
                expected = ", ".join(repr(c) for c in choices[:-1]) + f" or {choices[-1]!r}"
                raise ValueError(f"Tuning.{name}: expected {expected}, got {value!r}")
            object.__setattr__(self, name, kind(value))
        if self.rho is not None and not (_finite(self.rho) and self.rho > 0.0):
            raise ValueError(f"Tuning.rho: expected None (the plan's own) or a positive number, got {self.rho!r}")
        for name, low in (("fused_block", 1), ("fused_registers", 0), ("fused_sharing", 0), ("tree_registers", 0),
                          ("tree_contact_working", 1), ("tabulated_registers", 0)):
            if not _optional_int(getattr(self, name), low):
                raise ValueError(f"Tuning.{name}: expected None (the plan's choice) or an integer >= {low}, "
                                 f"got {getattr(self, name)!r}")
        for name in ("fused_inverse", "tabulated_tiled"):
            if getattr(self, name) not in (None, True, False):
                raise ValueError(f"Tuning.{name}: expected None (the plan's choice), True or False, "
                                 f"got {getattr(self, name)!r}")
        _check("Tuning", self, {
            "eta": self.eta > 0.0,
            "free_rho": self.free_rho > 0.0,
            "rho_update_interval": self.rho_update_interval >= 1,
            "stall_ratio": 0.0 <= self.stall_ratio < 1.0,
            "warmstart_decay": 0.0 <= self.warmstart_decay < 1.0,
            "projection_velocity_floor": self.projection_velocity_floor >= 0.0,
            "projection_skip_floor": self.projection_skip_floor >= 0.0,
            "projection_skip_floor_angular": self.projection_skip_floor_angular >= 0.0,
        })

    def rho_or(self, plan_default: float) -> float:
        """The starting ADMM penalty: rho where set, else ``plan_default`` (the plan's own)."""
        return float(plan_default if self.rho is None else self.rho)


TUNING_FIELDS = tuple(f.name for f in dataclasses.fields(Tuning))


@dataclass(frozen=True)
class SolverConfig:
    """Solver settings of a batch (frozen; per-world numbers are copied to device arrays). The
    method's internal knobs are in ``tuning`` (engine.Tuning; ``tuned(...)`` makes a copy with
    other knobs).

    Attributes:
        integrator: Integrator.MOREAU_JEAN ("moreau", default: dynamics at the projected midpoint)
            or SEMI_IMPLICIT_EULER ("euler"); change it when comparing with a first-order engine.
        max_iterations: PADMM iterations per step at most [count]; lower it when the step's cost
            matters more than its residual (walkers: 30-50), raise it when health flags worlds
            stopped at the cap.
        tolerance: absolute primal and dual residual at which a world's PADMM stops, in
            preconditioned units [sqrt(J)]; raise it (1e-4) when contacts dominate and speed
            matters, lower it for reference runs.
        relative_tolerance: added tolerance per unit of the largest preconditioned impulse
            [dimensionless]; raise it when large impulses make the absolute tolerance too strict.
        position_iterations: Gauss-Newton projections of the poses onto the joints after each step
            [count] (0 disables; Moreau-Jean projects the end of the step as often, for output);
            set 0 with baumgarte when loops need not close to rounding.
        baumgarte: velocity-level stabilization, bias = -baumgarte / dt * residual [dimensionless,
            0..1]; use it when position_iterations is 0.
        limit_margin: a joint limit row turns on within this distance of the limit [rad]/[m] (plus
            what the joint covers in a step); raise it when fast joints overshoot their limits.
        limit_stabilization: share of a limit violation pushed back per step [0..1]; lower it when
            limits bounce.
        contact_margin: contacts closer than this are kept (speculative) [m]; raise it when fast
            bodies tunnel into the ground.
        contact_stabilization: share of a penetration pushed out per step [0..1]; lower it when
            resting contacts jitter.
        restitution_threshold: approach speeds below this bounce with no restitution [m/s]; raise it
            when resting bodies keep bouncing.
        max_speed: a world in which a body's centre of mass moves faster than this [m/s] is flagged
            diverged and frozen; lower it when blow-ups should stop early, raise it for fast
            mechanisms.
        health_joint_tolerance: a world whose largest linear joint error at a record exceeds this
            [m] is flagged (engine.health; also one packed too far from the origin for float32 to
            close a joint); change it when your joints tolerate more or less opening.
        health_angular_tolerance: the same for the angular joint rows [rad] (a gross-tear guard:
            walkers twist by up to 0.03 rad at ground impacts); change it when your joints twist more.
        health_residual: a world whose PADMM stops unconverged (cap or stall) with a residual above
            this [sqrt(J)], about 1 m/s of error for 1 kg, is flagged; raise it when capped contact
            steps are acceptable (walkers stopped at up to 0.075).
        tuning: the method's internal knobs (engine.Tuning; a mapping of its fields is read as one);
            change them when benchmarking or testing the method: they change speed and rounding,
            not what is simulated.

    Accuracy: with Moreau-Jean both the maximal and the tree plan are second order in dt on
    passive mechanisms (benchmarks/convergence.py), so halving dt is the way to a more accurate
    run, down to the float32 floor (about 1e-6 rad on a four-bar's crank, reached near dt 0.25 ms).
    Lower tolerance / relative_tolerance (and raise max_iterations) where contacts or limits leave
    worlds unconverged (Trace.health says so); mechanisms with only joint rows are solved directly.
    """

    integrator: Integrator = Integrator.MOREAU_JEAN
    max_iterations: int = 100
    tolerance: float = 1.0e-6
    relative_tolerance: float = 1.0e-4
    position_iterations: int = 2
    baumgarte: float = 0.0
    limit_margin: float = 0.02
    limit_stabilization: float = 0.2
    contact_margin: float = 0.01
    contact_stabilization: float = 0.2
    restitution_threshold: float = 0.05
    max_speed: float = 1.0e3
    health_joint_tolerance: float = 5.0e-3
    health_angular_tolerance: float = 0.25
    health_residual: float = 1.0
    tuning: Tuning = Tuning()

    def __post_init__(self):
        if not isinstance(self.integrator, Integrator):
            try:
                object.__setattr__(self, "integrator", Integrator(self.integrator))
            except ValueError as exc:
                raise ValueError(f"SolverConfig.integrator: expected one of "
                                 f"{[i.value for i in Integrator]}, got {self.integrator!r}") from exc
        if isinstance(self.tuning, Mapping):
            unknown = sorted(set(self.tuning) - set(TUNING_FIELDS))
            if unknown:
                raise ValueError(f"SolverConfig.tuning: unknown Tuning field {unknown[0]!r}; "
                                 f"expected one of {list(TUNING_FIELDS)}")
            object.__setattr__(self, "tuning", Tuning(**self.tuning))
        if not isinstance(self.tuning, Tuning):
            raise ValueError(f"SolverConfig.tuning: expected an engine.Tuning, got {type(self.tuning).__name__}")
        _check("SolverConfig", self, {
            "max_iterations": self.max_iterations >= 1,
            "tolerance": self.tolerance > 0.0,
            "relative_tolerance": self.relative_tolerance >= 0.0,
            "position_iterations": self.position_iterations >= 0,
            "baumgarte": 0.0 <= self.baumgarte <= 1.0,
            "limit_margin": self.limit_margin >= 0.0,
            "limit_stabilization": 0.0 <= self.limit_stabilization <= 1.0,
            "contact_margin": self.contact_margin >= 0.0,
            "contact_stabilization": 0.0 <= self.contact_stabilization <= 1.0,
            "restitution_threshold": self.restitution_threshold >= 0.0,
            "max_speed": self.max_speed > 0.0,
            "health_joint_tolerance": self.health_joint_tolerance > 0.0,
            "health_angular_tolerance": self.health_angular_tolerance > 0.0,
            "health_residual": self.health_residual > 0.0,
        })

    def __getattr__(self, name):
        if name in TUNING_FIELDS:
            raise AttributeError(f"SolverConfig.{name} moved to engine.Tuning: read config.tuning.{name}")
        raise AttributeError(f"'SolverConfig' object has no attribute {name!r}")

    def tuned(self, **changes) -> SolverConfig:
        """A copy whose ``tuning`` has ``changes`` (Tuning field names, e.g. tuned(rho=1.0)); the
        other settings unchanged. ValueError naming a name that is not a Tuning field."""
        for name in changes:
            if name not in TUNING_FIELDS:
                where = (" (a SolverConfig field: use dataclasses.replace)" if name in SETTING_FIELDS else "")
                raise ValueError(f"SolverConfig.tuned: {name!r} is not a field of engine.Tuning{where}; "
                                 f"expected one of {list(TUNING_FIELDS)}")
        return dataclasses.replace(self, tuning=dataclasses.replace(self.tuning, **changes))


SETTING_FIELDS = tuple(f.name for f in dataclasses.fields(SolverConfig))


def _refuse_moved_keywords(init):
    """SolverConfig's __init__, refusing the knobs it once held with a message naming Tuning."""

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        moved = [name for name in kwargs if name in TUNING_FIELDS]
        if moved:
            names = ", ".join(moved)
            raise TypeError(f"SolverConfig: {names} {'is a field' if len(moved) == 1 else 'are fields'} of "
                            f"engine.Tuning, not SolverConfig: SolverConfig(tuning=Tuning({moved[0]}=...)) or "
                            f"config.tuned({moved[0]}=...)")
        init(self, *args, **kwargs)

    return __init__


SolverConfig.__init__ = _refuse_moved_keywords(SolverConfig.__init__)
