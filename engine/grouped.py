"""A batch whose worlds take different plans: one packed model per group of worlds.

engine.pack plans each world in the fastest coordinates it admits; when a batch's worlds differ (a
walker beside a four-bar beside a box stack), each group is packed on its own plan and the groups
step one after another. Worlds never interact, so a world's motion is the one its group's plan
gives it alone. The Trace of a grouped rollout is in the batch's world order, padded to the
largest group's points and joints.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from engine.health import Health
from engine.plan import Coordinates, Plan

__all__ = ["GroupedModel", "GroupedState"]


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

    def control(self):
        """None: a grouped batch takes its drive targets from the specs (like a reduced plan)."""
        return None


def step_groups(model: GroupedModel, state_in: GroupedState, state_out: GroupedState, step) -> None:
    """engine.step for each group (``step`` is engine.step)."""
    for (_, part), a, b in zip(model.groups, state_in.parts, state_out.parts):
        step(part, a, b, None)


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


def rollout_groups(model: GroupedModel, state: GroupedState, steps: int, record_every: int, halt, rollout) -> tuple:
    """engine.rollout of every group (``rollout`` is engine.rollout), merged in world order. halt
    sees the whole batch's points, each group's worlds filled in and the others at their start."""
    traces, finals = [], []
    starts = None
    for (indices, part), part_state in zip(model.groups, state.parts):
        group_halt = None
        if halt is not None:
            def group_halt(points, start, indices=indices):
                nonlocal starts
                full_start = _padded_points(starts, start, indices, model.num_worlds)
                full = full_start.copy()
                full[indices, :points.shape[1]] = points
                return np.asarray(halt(full, full_start), bool).reshape(model.num_worlds)[indices]
        trace, final = rollout(part, part_state, None, steps, record_every=record_every, halt=group_halt)
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
