"""A batch whose worlds take different plans: one packed model per group of worlds.

engine.pack plans each world in the fastest coordinates it admits; when a batch's worlds differ (a
walker beside a four-bar beside a box stack), each group is packed on its own plan and the groups
step one after another. Worlds never interact, so a world's motion is the one its group's plan
gives it alone. The Trace of a grouped rollout is in the batch's world order, padded to the
largest group's points and joints.
"""

from __future__ import annotations

import dataclasses

from typing import Any

import numpy as np
import warp as wp

from engine.health import Health
from engine.plan import Coordinates, Plan

__all__ = ["GroupedControl", "GroupedModel", "GroupedState"]


@wp.kernel
def gather_rows(source: wp.array2d(dtype=Any), worlds: wp.array(dtype=wp.int32), target: wp.array2d(dtype=Any)):
    """target[i, j] = source[worlds[i], j]: a group's rows of a batch array."""
    i, j = wp.tid()
    target[i, j] = source[worlds[i], j]


class GroupedControl:
    """A Control of a grouped batch: body_f (W, B) spatial_vector and joint_effort (W, J) float in the
    batch's world order and spec order (as every plan's), and per group its own plan's Control
    (``parts``), into which gather() copies the group's rows before the group steps. The groups'
    drive targets come from their specs."""

    def __init__(self, model: "GroupedModel"):
        W, device = model.num_worlds, model.device
        self.body_f = wp.zeros((W, max(len(s.bodies) for s in model.specs)), dtype=wp.spatial_vector, device=device)
        self.joint_effort = wp.zeros((W, max(1, max(len(s.joints) for s in model.specs))), dtype=float,
                                     device=device)
        self.parts = [part.control() for _, part in model.groups]
        self._worlds = [wp.array(np.asarray(indices, np.int32), dtype=wp.int32, device=device)
                        for indices, _ in model.groups]

    def gather(self, k: int):
        """Group k's Control with the group's rows of body_f and joint_effort (kernel launches only)."""
        part, worlds = self.parts[k], self._worlds[k]
        for name in ("body_f", "joint_effort"):
            target = getattr(part, name)
            wp.launch(gather_rows, dim=(target.shape[0], min(target.shape[1], getattr(self, name).shape[1])),
                      inputs=[getattr(self, name), worlds], outputs=[target], device=target.device)
        return part


class GroupedState:
    """One State per group (``parts``), in the order of GroupedModel.groups."""

    def __init__(self, parts: list):
        self.parts = parts


class GroupedModel:
    """The groups of a batch: ``groups`` is a list of (world indices, packed model); ``plan`` the
    batch's Plan (coordinates MIXED, each group's own plan in plan.groups)."""

    def __init__(self, groups: list, specs: list, plan: Plan, config, dt: float, device):
        self.groups, self.specs, self.plan, self.config = groups, list(specs), plan, config
        self.dt, self.device, self.num_worlds = float(dt), device, len(specs)
        self.point_names = [[p.name for p in s.points] for s in self.specs]
        self.joint_names = [[j.name for j in s.joints] for s in self.specs]
        self.body_names = [[b.name for b in s.bodies] for s in self.specs]

    def state(self) -> GroupedState:
        """A State per group at the specs' initial poses."""
        return GroupedState([model.state() for _, model in self.groups])

    def control(self) -> GroupedControl:
        """A new GroupedControl (zeros): body_f and joint_effort for the whole batch."""
        return GroupedControl(self)

    def check_control(self, control) -> None:
        """Raise ValueError unless ``control`` is this batch's GroupedControl (control())."""
        if not isinstance(control, GroupedControl) or control.body_f.shape[0] != self.num_worlds \
                or len(control.parts) != len(self.groups):
            raise ValueError("control: a batch planned in groups reads a GroupedControl of its own (model.control(): "
                             "body_f and joint_effort in world order; drive targets come from the specs)")


def step_groups(model: GroupedModel, state_in: GroupedState, state_out: GroupedState, step, control=None) -> None:
    """engine.step for each group (``step`` is engine.step), with its rows of ``control``."""
    for k, ((_, part), a, b) in enumerate(zip(model.groups, state_in.parts, state_out.parts)):
        step(part, a, b, None if control is None else control.gather(k))


def _scatter(arrays: list, groups: list, worlds: int, axis: int) -> np.ndarray:
    """Per-group arrays (world axis ``axis``) into one array in world order, later axes padded."""
    shape = list(arrays[0].shape)
    for a in arrays:
        shape = [max(x, y) for x, y in zip(shape, a.shape)]
    shape[axis] = worlds
    out = np.zeros(shape, dtype=arrays[0].dtype)
    for a, (indices, _) in zip(arrays, groups):
        index = [slice(0, n) for n in a.shape]
        index[axis] = np.asarray(indices)
        out[tuple(index)] = a
    return out


def rollout_groups(model: GroupedModel, state: GroupedState, steps: int, record_every: int, halt, rollout,
                   control=None) -> tuple:
    """engine.rollout of every group (``rollout`` is engine.rollout) with its rows of ``control``,
    merged in world order. halt sees the whole batch's points, each group's worlds filled in and the
    others at their start."""
    traces, finals = [], []
    starts = None
    for k, ((indices, part), part_state) in enumerate(zip(model.groups, state.parts)):
        group_halt = None
        if halt is not None:
            def group_halt(points, start, indices=indices):
                nonlocal starts
                full_start = _padded_points(starts, start, indices, model.num_worlds)
                full = full_start.copy()
                full[indices, :points.shape[1]] = points
                return np.asarray(halt(full, full_start), bool).reshape(model.num_worlds)[indices]
        part_control = None if control is None else control.gather(k)
        trace, final = rollout(part, part_state, part_control, steps, record_every=record_every, halt=group_halt)
        if halt is not None:
            starts = _padded_points(starts, trace.points[0], indices, model.num_worlds)
        traces.append(trace)
        finals.append(final)
    groups = model.groups
    merged = {name: _scatter([getattr(t, name) for t in traces], groups, model.num_worlds, 1)
              for name in ("points", "violation_linear", "violation_angular", "energy", "iterations",
                           "drive_torque", "drive_speed")}
    health = traces[0].health
    fields = {f.name: _scatter([getattr(t.health, f.name) for t in traces], groups, model.num_worlds, 0)
              for f in dataclasses.fields(Health) if isinstance(getattr(health, f.name), np.ndarray)}
    detail = [""] * model.num_worlds  # which drive stopped a world, where a group's plan knows
    for t, (indices, _) in zip(traces, groups):
        for k, w in enumerate(indices):
            detail[w] = (t.health.effort_detail or [""] * len(indices))[k]
    health = dataclasses.replace(health, **fields, effort_detail=detail)
    trace = dataclasses.replace(traces[0], **merged, health=health, point_names=model.point_names,
                                diverged=_scatter([t.diverged for t in traces], groups, model.num_worlds, 0),
                                halted_at=_scatter([t.halted_at for t in traces], groups, model.num_worlds, 0))
    return trace, GroupedState(finals)


def _padded_points(known, start, indices, worlds: int) -> np.ndarray:
    """The batch's record-0 points so far: ``known`` (or zeros) with ``start`` at ``indices``."""
    P = start.shape[1] if known is None else max(start.shape[1], known.shape[1])
    out = np.zeros((worlds, P, 3), np.float32)
    if known is not None:
        out[:, :known.shape[1]] = known
    out[indices, :start.shape[1]] = start
    return out


def grouped_plan(plans: list, sizes: list, device) -> Plan:
    """The batch's Plan: coordinates MIXED, the groups' plans in ``groups``."""
    plan = Plan(Coordinates.MIXED, sum(sizes), str(device))
    plan.groups = list(zip(sizes, plans))
    return plan
