"""engine: a Warp rigid multi-body engine for batches of different closed-chain mechanisms.

One face: ``model = engine.pack(specs, device=..., config=..., dt=...)`` plans the batch itself
(``print(model.plan)``: coordinates, kernel, solver, stages, launch shape and why), then
``engine.step(model, state_in, state_out)``, ``engine.Stepper`` (CUDA graph replay) and
``engine.rollout(...) -> (Trace, State)`` run it whatever the plan. Every plan solves the same
Proximal-ADMM dual problem over joints, loops, limits and frictional contact; a Trace's health
names the worlds it cannot vouch for and why (engine.health). See engine.model for units, frames
and array conventions, engine.config for the settings (SolverConfig) and the solver's knobs (Tuning).
"""

from engine.config import Integrator, SolverConfig, Tuning
from engine.health import Health
from engine.metrics import compute_metrics, metrics_numpy
from engine.model import Control, Model, State
from engine.pack import pack, pack_worlds
from engine.plan import Coordinates, Plan, prepare
from engine.rollout import Stepper, Trace, point_positions, rollout
from engine.forces import BodyWrench, JointSpring, JointTorque, LinearSpring
from engine.spec import (Body, GroundPlane, Joint, JointDrive, JointType, MechanismSpec, Relief, Shape, ShapeType,
                         TrackedPoint)
from engine.step import StageTimer, step

__all__ = [
    "Body", "BodyWrench", "Control", "Coordinates", "GroundPlane", "Health", "Integrator", "Joint", "JointDrive",
    "JointSpring", "JointTorque", "JointType", "LinearSpring", "MechanismSpec", "Model", "Plan", "Relief", "Shape", "ShapeType",
    "SolverConfig", "StageTimer", "State", "Stepper",
    "Trace", "TrackedPoint", "Tuning", "compute_metrics", "metrics_numpy", "pack", "pack_worlds",
    "point_positions", "prepare", "rollout", "step",
]
