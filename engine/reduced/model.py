"""The one face of the reduced plans: a model that engine.step, engine.Stepper and engine.rollout
drive like the maximal Model, whatever reduced coordinates the plan chose.

A reduced model steps its state in place (its kernels read and write the coordinates of one State),
so engine.step copies state_in into state_out first when they differ. Everything a Trace reports is
measured the one way the maximal path measures it: every body's pose and twist, read from the
reduced State, go through a maximal model of the same worlds that only measures (its joint rows'
residuals, energy, tracked points and drive speeds; engine.metrics), so a reduced plan's loop
closure is measured, never assumed. Drive torques come from the plan's own drive law.
"""

from __future__ import annotations

import abc

import numpy as np
import warp as wp

from engine.health import DIVERGED, EFFORT_LIMIT, JOINTS_OPEN, Health, far_flags
from engine.metrics import compute_metrics
from engine.plan import Plan

__all__ = ["GroundedPlanModel", "ReducedModel", "ReducedState", "TabulatedPlanModel", "TreeModel"]


class ReducedState:
    """A reduced plan's state: its coordinates (``inner``: the path's own state object) and, readable
    whatever the plan, every body's centre-of-mass pose body_q (W, B) transform and twist body_qd
    (W, B) spatial_vector (v, w; world frame) in each spec's body order."""

    def __init__(self, model: "ReducedModel", inner):
        self._model, self.inner = model, inner

    @property
    def body_q(self):
        """(W, B) wp.transform: every body's centre-of-mass position and orientation [m]."""
        return self._model._bodies(self)[0]

    @property
    def body_qd(self):
        """(W, B) wp.spatial_vector: every body's centre-of-mass velocity and angular velocity [m/s, rad/s]."""
        return self._model._bodies(self)[1]


class ReducedModel(abc.ABC):
    """A packed batch in reduced coordinates (engine.pack chose them; ``plan`` says which and why).

    num_worlds, device, dt [s], config, specs, point_names, joint_names, body_names, plan; state() a
    new State at the specs' initial poses; health() the worlds' engine.health flags."""

    def __init__(self, inner, specs: list, plan: Plan, config, dt: float, device):
        self.inner, self.specs, self.plan, self.config = inner, list(specs), plan, config
        self.dt, self.device = float(dt), wp.get_device(device)
        self.num_worlds = len(self.specs)
        self.point_names = [[p.name for p in s.points] for s in self.specs]
        self.joint_names = [[j.name for j in s.joints] for s in self.specs]
        self.body_names = [[b.name for b in s.bodies] for s in self.specs]
        self.max_points = max(1, max(len(s.points) for s in self.specs))
        self.max_joints = max(1, max(len(s.joints) for s in self.specs))
        self._gauge = None

    @property
    def gauge(self):
        """A maximal model of the same worlds that only measures (built on first use)."""
        if self._gauge is None:
            from engine.pack import pack_worlds
            self._gauge = pack_worlds(self.specs, device=self.device, dt=self.dt, measure_only=True)
        return self._gauge

    def control(self):
        """A new Control of the plan (zeros): body_f (W, B) spatial_vector, each spec body's wrench
        (force [N], torque [N m]) at its centre of mass, world frame (a body welded to the world
        takes none); joint_effort (W, J) float, each revolute spec joint's torque [N m] on its child
        and the opposite on its parent. Drive targets come from the specs."""
        return self.inner.control()

    def check_control(self, control) -> None:
        """Raise ValueError unless ``control`` carries body_f and joint_effort arrays this batch reads."""
        self.inner.check_control(control)

    # -- what a plan implements ------------------------------------------------------------------
    @abc.abstractmethod
    def state(self) -> ReducedState:
        """A State at the specs' initial poses (every world running again)."""

    @abc.abstractmethod
    def advance(self, state: ReducedState, steps: int, control=None) -> None:
        """``steps`` steps of ``state`` in place (capturable: no host work, no allocation); control:
        the plan's Control (control()) or None."""

    @abc.abstractmethod
    def copy_state(self, source: ReducedState, target: ReducedState) -> None:
        """Copy ``source``'s coordinates into ``target``."""

    @abc.abstractmethod
    def _bodies(self, state: ReducedState) -> tuple:
        """(body_q, body_qd) device arrays of the state."""

    @abc.abstractmethod
    def drive_torque(self, state: ReducedState) -> np.ndarray:
        """(W, J) every joint drive's torque [N m] (force [N]) at the state; 0 for undriven joints."""

    @abc.abstractmethod
    def iterations(self) -> np.ndarray:
        """(W,) PADMM iterations of the last step."""

    @abc.abstractmethod
    def failure_codes(self) -> np.ndarray:
        """(W,) 0 running or halted, 1 diverged, 2 a drive past its effort limit (the world stopped)."""

    @abc.abstractmethod
    def set_halted(self, halted: np.ndarray) -> None:
        """Freeze the worlds marked (W,) bool: they keep their state and cost no solver work."""

    def pack_facts(self) -> tuple:
        """Per world the largest coordinate magnitude [m] and jointed-mass ratio (engine.health's
        pack-time facts), from the gauge."""
        return self.gauge.world_extent, self.gauge.world_mass_ratio

    # -- shared ----------------------------------------------------------------------------------
    def health(self, linear_max: np.ndarray, angular_max: np.ndarray) -> Health:
        """engine.health's flags of the worlds: DIVERGED and EFFORT_LIMIT from the step, FAR from the
        pack, JOINTS_OPEN from the largest joint errors measured over the records."""
        cfg = self.config
        codes = self.failure_codes()
        extent, ratio = self.pack_facts()
        flags = far_flags(extent, cfg.health_joint_tolerance)
        flags |= np.where(codes == 1, DIVERGED, 0).astype(np.int32)
        flags |= np.where(codes == 2, EFFORT_LIMIT, 0).astype(np.int32)
        open_ = (~(linear_max <= cfg.health_joint_tolerance)) | (~(angular_max <= cfg.health_angular_tolerance))
        flags |= np.where(open_ & (codes == 0), JOINTS_OPEN, 0).astype(np.int32)
        zeros = np.zeros(self.num_worlds)
        return Health(flags=flags, linear_max=np.asarray(linear_max, float), angular_max=np.asarray(angular_max, float),
                      residual_max=zeros, residual_iterations=zeros.astype(np.int32),
                      extent=np.asarray(extent, float), mass_ratio=np.asarray(ratio, float),
                      joint_tolerance=float(cfg.health_joint_tolerance),
                      angular_tolerance=float(cfg.health_angular_tolerance),
                      residual_threshold=float(cfg.health_residual), max_speed=float(cfg.max_speed),
                      effort_detail=self.effort_detail(codes))

    def effort_detail(self, codes: np.ndarray) -> list:
        """Per world stopped at a drive's effort limit, which drive (the health reason names it)."""
        return [""] * self.num_worlds

    def points(self, state: ReducedState) -> np.ndarray:
        """The tracked points at ``state`` (W, P, 3) [m] (engine.rollout.point_positions)."""
        from engine.rollout import points_of

        return points_of(self.gauge, state.body_q)

    def step(self, state_in: ReducedState, state_out: ReducedState, control=None) -> None:
        """One step from state_in into state_out (in place when they are one State); control: the
        plan's Control (control()) or None."""
        if state_out is not state_in:
            self.copy_state(state_in, state_out)
        self.advance(state_out, 1, control)

    def measure(self, state: ReducedState) -> dict:
        """One record of ``state``: points (W, P, 3), violation_linear/angular (W,), energy (W,),
        drive_speed and drive_torque (W, J), iterations (W,), as NumPy."""
        from engine.rollout import drive_speeds

        g = self.gauge
        body_q, body_qd = state.body_q, state.body_qd
        compute_metrics(g, _Bodies(body_q, body_qd))
        points = self.points(state)
        speeds = wp.zeros((self.num_worlds, g.max_joints), dtype=float, device=self.device)
        wp.launch(drive_speeds, dim=(self.num_worlds, g.max_joints), device=self.device,
                  inputs=[g.joint_count, g.joint_type, g.joint_parent, g.joint_child, g.joint_X_p, g.joint_X_c,
                          g.joint_axis, g.joint_drive_row, body_q, g.work.no_low, body_qd],
                  outputs=[speeds])
        return {"points": points, "violation_linear": g.work.violation_linear.numpy().copy(),
                "violation_angular": g.work.violation_angular.numpy().copy(), "energy": g.work.energy.numpy().copy(),
                "drive_speed": speeds.numpy(), "drive_torque": self.drive_torque(state),
                "iterations": self.iterations()}


class _Bodies:
    """The two arrays engine.metrics reads from a State."""

    def __init__(self, body_q, body_qd):
        self.body_q, self.body_qd = body_q, body_qd


class TreeModel(ReducedModel):
    """The TREE plan: engine.reduced.chains's ChainModel (one kernel launch per step).

    It takes a Control (control(); engine.step, engine.Stepper and engine.rollout pass it on) of
    body_f (W, B) and joint_effort (W, J), the same arrays in spec order as the maximal plan's
    engine.Control: the step kernel reads them at every step (no host work; captured graphs read
    the arrays' current values). Its drive targets come from the specs: the tree Control has no
    joint_target_* arrays, and a maximal Control (which has them) is refused. joint_effort acts on
    revolute joints, tree and loop-closing alike, driven or not (on a driven joint it adds to the
    drive's torque, outside the drive's effort check)."""

    HALTED = 3  # a code of the chains kernel's stop flag that freezes a world without a failure

    def __init__(self, inner, specs, plan, config, dt, device):
        super().__init__(inner, specs, plan, config, dt, device)
        self._drives = []  # (world, tree entry, spec joint) of every driven tree joint
        for w, (lay, spec) in enumerate(zip(inner.layouts, self.specs)):
            for k in range(lay.n):
                j = lay.joint[k]
                if j is not None and j >= 0 and spec.joints[j].drive is not None:
                    self._drives.append((w, k, j))

    def state(self) -> ReducedState:
        """A new ChainState at the initial poses, every world running again."""
        self.inner.work.diverged.zero_()  # a new trajectory: every world runs again
        return ReducedState(self, self.inner.state())

    def advance(self, state: ReducedState, steps: int, control=None) -> None:
        self._last = state.inner
        for _ in range(steps):
            self.inner.step(state.inner, control=control)

    def copy_state(self, source: ReducedState, target: ReducedState) -> None:
        """Copy the coordinates, rates, roots and body poses of ``source`` into ``target``."""
        for name in ("q", "u", "root", "body_q", "body_qd"):
            wp.copy(getattr(target.inner, name), getattr(source.inner, name))

    def _bodies(self, state: ReducedState) -> tuple:
        return state.inner.body_q, state.inner.body_qd

    def drive_torque(self, state: ReducedState) -> np.ndarray:
        """The drives' law at the state: kp (q_target - q) + kd (v_target - u) [N m] (a velocity drive's
        torque is exactly the implicit law the step applied; a position drive's leaves out the part of
        the step its angle still moves)."""
        out = np.zeros((self.num_worlds, self.max_joints), np.float32)
        if not self._drives:
            return out
        torque = self._drive_law(state.inner)
        for w, k, j in self._drives:
            out[w, j] = torque[w, k]
        return out

    def _drive_law(self, chain_state) -> np.ndarray:
        """(W, N) kp (q_target - q) + kd (v_target - u) of every tree entry at a ChainState."""
        a = self.inner.arrays
        kp, kd, qt, vt = (getattr(a, k).numpy() for k in ("kp", "kd", "q_target", "v_target"))
        return kp * (qt - chain_state.q.numpy()) + kd * (vt - chain_state.u.numpy())

    def iterations(self) -> np.ndarray:
        return self.inner.work.iterations.numpy().copy()

    def effort_detail(self, codes: np.ndarray) -> list:
        """The drive whose law, at the state the world stopped in, is furthest past its limit."""
        out = [""] * self.num_worlds
        if not (codes == 2).any():
            return out
        torque, effort = self._drive_law(self._last), self.inner.arrays.effort.numpy()
        for w, k, j in self._drives:
            if codes[w] != 2:
                continue
            ratio = abs(torque[w, k]) / max(float(effort[w, k]), 1e-30)
            if not out[w] or ratio > out[w][0]:
                name = self.specs[w].joints[j].name
                out[w] = (ratio, f"the drive of joint '{name}' ({float(effort[w, k]):g} N m)")
        return [d[1] if d else "" for d in out]

    def failure_codes(self) -> np.ndarray:
        codes = self.inner.work.diverged.numpy().copy()
        codes[codes == self.HALTED] = 0
        return codes

    def set_halted(self, halted: np.ndarray) -> None:
        codes = self.inner.work.diverged.numpy()
        codes[np.asarray(halted, bool) & (codes == 0)] = self.HALTED
        self.inner.work.diverged.assign(codes)


class TabulatedPlanModel(ReducedModel):
    """The TABULATED plan: engine.reduced.tabulated's TabulatedModel. Its state lives in the model
    (its kernels take it as a struct), so every State of it is the one state: state() resets it to
    the specs' initial poses, and steps run in place."""

    STATE = ("position", "orientation", "velocity", "angular_velocity", "coord", "coord_rate", "impulse", "frozen",
             "diverged")

    def __init__(self, inner, specs, plan, config, dt, device):
        super().__init__(inner, specs, plan, config, dt, device)
        self._initial = {name: wp.clone(getattr(inner, name)) for name in self.STATE}

    def state(self) -> ReducedState:
        """The model's one state, reset to the specs' initial poses."""
        for name, value in self._initial.items():
            wp.copy(getattr(self.inner, name), value)
        return ReducedState(self, None)

    def advance(self, state: ReducedState, steps: int, control=None) -> None:
        self.inner.step(steps, control)

    def copy_state(self, source: ReducedState, target: ReducedState) -> None:
        """Refused: the plan's one state lives in the model."""
        raise ValueError("step: the tabulated plan keeps one state in the model; step it in place "
                         "(state_out = state_in)")

    def _bodies(self, state: ReducedState) -> tuple:
        return self.inner.body_poses(numpy=False)

    def drive_torque(self, state: ReducedState) -> np.ndarray:
        torque = self.inner.record(numpy=False)[2].numpy()
        out = np.zeros((self.num_worlds, self.max_joints), np.float32)
        J = min(out.shape[1], torque.shape[1])
        out[:, :J] = torque[:, :J]
        return out

    def iterations(self) -> np.ndarray:
        return self.inner.iterations.numpy().copy()

    def failure_codes(self) -> np.ndarray:
        return np.where(self.inner.diverged.numpy() != 0, 1, 0)

    def set_halted(self, halted: np.ndarray) -> None:
        self.inner.halt(halted)

    def points(self, state: ReducedState) -> np.ndarray:
        """The tracked points [m] (W, P, 3) of the plan's state (the tabulated step keeps one state,
        which ``state`` stands for), from the path's own kernel."""
        return self.inner.record()[0].copy()

    def measure(self, state: ReducedState) -> dict:
        """One record from the path's own kernel (points, energy, drive torques and speeds by spec
        joint): the loops are closed by the tables, so a record's joint error is each world's table
        closure error [m], measured when the tables were made (at the midpoints between samples).
        No maximal gauge is built: a study's generation of walkers spends its host time here."""
        points, energy, torque, speed = (a.copy() for a in self.inner.record())  # CPU arrays are views
        J = min(self.max_joints, torque.shape[1])
        drive_torque = np.zeros((self.num_worlds, self.max_joints), np.float32)
        drive_speed = np.zeros_like(drive_torque)
        drive_torque[:, :J], drive_speed[:, :J] = torque[:, :J], speed[:, :J]
        closure = self.inner.world_closure_error.astype(np.float32)
        return {"points": points, "violation_linear": closure.copy(), "violation_angular": np.zeros_like(closure),
                "energy": energy, "drive_speed": drive_speed, "drive_torque": drive_torque,
                "iterations": self.iterations()}

    def pack_facts(self) -> tuple:
        """engine.health's pack-time facts from the specs: the largest body or world-anchor coordinate
        [m] and the largest mass ratio of two jointed bodies."""
        return pack_facts(self.specs)


def pack_facts(specs: list) -> tuple:
    """Per spec the largest |coordinate| of a body position [m] and the largest mass ratio of two
    jointed bodies (1 without joints), for all specs in a few array operations: maxima and
    quotients of the same numbers as spec by spec, so the same to the last bit."""
    counts = [len(spec.bodies) for spec in specs]
    if not all(counts):
        raise ValueError("pack_facts: a spec without bodies")
    bodies = [b for spec in specs for b in spec.bodies]
    position = np.abs(np.array([b.position for b in bodies], dtype=float).reshape(-1, 3)).max(axis=1)
    starts = np.cumsum([0] + counts[:-1])
    extent = np.maximum.reduceat(position, starts) if bodies else np.zeros(0)
    mass = np.array([float(b.mass) for b in bodies])
    parent, child, world = [], [], []
    for w, (spec, start) in enumerate(zip(specs, starts.tolist())):
        index = spec.body_index
        for j in spec.joints:
            if j.parent is not None:
                parent.append(start + index[j.parent])
                child.append(start + index[j.child])
                world.append(w)
    ratio = np.ones(len(specs))
    if world:
        a, b = mass[parent], mass[child]
        np.maximum.at(ratio, np.array(world), np.maximum(a / b, b / a))
    return extent, ratio


class GroundedPlanModel(ReducedModel):
    """The GROUNDED plan: engine.reduced.grounded's GroundedModel (one launch per advance, however
    many steps). It takes the tree plan's Control (body_f, joint_effort; drive targets from the
    specs). Its body poses are read from the link tables' splines, and a Trace measures them
    through the maximal gauge like the tree plan's."""

    def __init__(self, inner, specs, plan, config, dt, device):
        super().__init__(inner, specs, plan, config, dt, device)
        driven = [(w, lay.coordinate) for w, lay in enumerate(inner.layouts)
                  if self.specs[w].joints[lay.coordinate].drive is not None]
        self._driven = tuple(np.array(c, np.int64) for c in zip(*driven)) if driven else None  # (worlds, joints)

    def state(self) -> ReducedState:
        """A new state at the initial poses, every world running again."""
        return ReducedState(self, self.inner.state())

    def advance(self, state: ReducedState, steps: int, control=None) -> None:
        self.inner.step(state.inner, steps, control)

    def copy_state(self, source: ReducedState, target: ReducedState) -> None:
        """Copy the coordinate, its rate and the last drive torque."""
        for name in ("q", "v", "torque"):
            wp.copy(getattr(target.inner, name), getattr(source.inner, name))

    def _bodies(self, state: ReducedState) -> tuple:
        return self.inner.bodies(state.inner)

    def drive_torque(self, state: ReducedState) -> np.ndarray:
        """The coordinate joint's drive torque of the last step [N m] (the implicit law, clamped)."""
        out = np.zeros((self.num_worlds, self.max_joints), np.float32)
        if self._driven is not None:
            worlds, joints = self._driven
            out[worlds, joints] = state.inner.torque.numpy()[worlds]
        return out

    def iterations(self) -> np.ndarray:
        return np.zeros(self.num_worlds, np.int32)

    def failure_codes(self) -> np.ndarray:
        from engine.reduced.grounded import DIVERGED
        return np.where(self.inner.stop.numpy() == DIVERGED, 1, 0)

    def set_halted(self, halted: np.ndarray) -> None:
        from engine.reduced.grounded import HALTED, RUNNING
        codes = self.inner.stop.numpy()
        codes[np.asarray(halted, bool) & (codes == RUNNING)] = HALTED
        self.inner.stop.assign(codes)
