"""engine: a Warp rigid multi-body engine for batches of different closed-chain mechanisms.

Maximal coordinates, every joint (loop closures included) a block of constraint rows, one
Proximal-ADMM solve per world per step, all worlds of a padded batch stepped together on the
CPU or a GPU. See engine.model for units, frames and array conventions; a rollout's Trace.health
flags the worlds it cannot vouch for, with the reason (engine.health).
"""

from engine.health import Health
from engine.metrics import compute_metrics, metrics_numpy
from engine.model import Control, Integrator, Model, SolverConfig, State
from engine.pack import pack_worlds
from engine.rollout import Stepper, Trace, rollout

from engine.spec import Body, GroundPlane, Joint, JointDrive, JointType, MechanismSpec, Shape, ShapeType, TrackedPoint
from engine.step import StageTimer, step

__all__ = [
    "Body", "Control", "GroundPlane", "Health", "Integrator", "Joint", "JointDrive", "JointType", "MechanismSpec", "Model",
    "Shape", "ShapeType", "SolverConfig", "StageTimer", "State", "Stepper", "Trace", "TrackedPoint", "compute_metrics",
    "metrics_numpy", "pack_worlds", "rollout", "step",
]
