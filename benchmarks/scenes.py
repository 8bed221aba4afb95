"""The benchmark scenes, declared as data: how to build each batch, how long to simulate it, which
batch sizes to time and which solver settings to sweep for the work-precision curves.

Every scene builder returns a BenchScene: the distinct mechanisms (a batch of N worlds cycles
through them), the potential energy of each one's static equilibrium (for the energy drift of
passive scenes; None where drives, limits or contacts put energy in or take it out) and a note.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
from dataclasses import dataclass, field

import numpy as np

from engine import GroundPlane, Joint, MechanismSpec
from engine.scenes import SCENES, make_scene

__all__ = ["SCENES_DECLARED", "BenchScene", "dr_legs_path"]


@dataclass
class BenchScene:
    specs: list[MechanismSpec]
    potential_min: np.ndarray | None
    note: str
    usd: pathlib.Path | None = None  # the file the scene was read from (peers through Newton load it too)
    standing: bool = False


def _engine_scenes(names) -> BenchScene:
    scenes = [make_scene(n) for n in names]
    return BenchScene([s.spec for s in scenes], np.array([s.potential_min for s in scenes]),
                      "engine.scenes " + ", ".join(names))


def dr_legs_path(assets: str | None = None) -> pathlib.Path | None:
    """The DR Legs USD file: --assets, $MORPHOPT_ASSETS, or shared/assets beside the checkout."""
    roots = [assets, os.environ.get("MORPHOPT_ASSETS"),
             pathlib.Path(__file__).resolve().parents[2] / "shared" / "assets"]
    for root in roots:
        if root:
            path = pathlib.Path(root) / "disneyresearch/dr_legs/usd/dr_legs_with_boxes.usda"
            if path.is_file():
                return path
    return None


# Newton's DR Legs example (examples/kamino/example_kamino_robot_dr_legs.py): PD gains 10 N m/rad and
# 2 N m s/rad on the 12 drives, armature 0.011 kg m^2 and damping 0.044 N m s/rad on every joint
NEWTON_EXAMPLE_JOINTS = dict(stiffness=10.0, drive_damping=2.0, armature=0.011, damping=0.044)


def dr_legs(standing: bool, assets: str | None = None, joints: dict | None = None) -> BenchScene:
    """DR Legs from its USD file through morphopt's import: standing on its PD drives on the
    ground, or hanging passively from a welded pelvis (no drives, no contacts). ``joints`` replaces
    the file's drive gains and gives every joint an armature and damping (NEWTON_EXAMPLE_JOINTS)."""
    from morphopt.formats.usd import read_usd

    path = dr_legs_path(assets)
    if path is None:
        raise FileNotFoundError("the DR Legs asset was not found (pass --assets or set MORPHOPT_ASSETS)")
    if standing:
        spec = read_usd(path, origin=(0.0, 0.0, 0.265))
        # its boxes touch the ground only, as both Newton peers run it (enable_self_collisions=False)
        spec = ground_contacts_only(dataclasses.replace(spec, ground=GroundPlane()))
        note = "DR Legs standing on its 12 PD drives (file gains), ground contact"
        if joints is not None:
            spec = dataclasses.replace(spec, joints=[dataclasses.replace(
                j, armature=joints["armature"], damping=joints["damping"],
                drive=None if j.drive is None else dataclasses.replace(
                    j.drive, stiffness=joints["stiffness"], damping=joints["drive_damping"]))
                for j in spec.joints])
            note = ("DR Legs standing as in Newton's example: PD gains {stiffness} / {drive_damping}, armature "
                    "{armature} and damping {damping} on every joint, ground contact").format(**joints)
        return BenchScene([spec], None, note, usd=path, standing=True)
    spec = read_usd(path, origin=(0.0, 0.0, 0.5))
    pelvis = spec.bodies[spec.body_index["pelvis"]]
    joints = [dataclasses.replace(j, drive=None) for j in spec.joints]
    joints.append(Joint("weld", "fixed", None, "pelvis", parent_position=pelvis.position,
                        parent_orientation=pelvis.orientation))
    spec = dataclasses.replace(spec, joints=joints, shapes=[])
    return BenchScene([spec], None, "DR Legs hanging passively from a welded pelvis (36 revolute joints, 6 loops)",
                      usd=path)


def ground_contacts_only(spec: MechanismSpec) -> MechanismSpec:
    """``spec`` with every shape in one collision group: its shapes touch the ground, never each
    other, which is what the tree plan models (engine.plan refuses a TREE world whose shapes may
    touch each other). DR Legs' pelvis and feet boxes are such a pair in maximal coordinates (they
    do not meet while it stands); its reduced-coordinate settings run it this way, as
    engine.reduced.chains ran them before the plan checked (it kept ground contacts only)."""
    if not spec.shapes:
        return spec
    return dataclasses.replace(spec, shapes=[dataclasses.replace(s, collision_group=1) for s in spec.shapes])


def walker_params(count: int = 64, seed: int = 1) -> list[dict]:
    """Validated parameters of random walker designs (Jansen and Klann legs, 3 per side); samples
    the design space refuses are left out."""
    from morphopt.families import load_family

    family = load_family("walker")
    out = []
    for params in family.space.sample(np.random.default_rng(seed), count):
        try:
            out.append(family.space.validate({**params, "legs_per_side": 3}))
        except ValueError:
            continue
    return out


def walkers(count: int = 64, seed: int = 1) -> BenchScene:
    """Random designs of the walker family (Jansen and Klann legs, 3 per side): heterogeneous."""
    from morphopt.families import load_family

    family = load_family("walker")
    specs = []
    for params in walker_params(count, seed):
        try:
            specs.append(family.build_spec(params))
        except ValueError:
            continue
    return BenchScene(specs, None, f"{len(specs)} random walker designs (Jansen/Klann legs, 3 per side) cycled")


def walker_default_params() -> dict:
    """Validated parameters of the walker family's default design with 3 legs per side."""
    from morphopt.families import load_family

    family = load_family("walker")
    return family.space.validate({**family.space.default(), "legs_per_side": 3})


def walker_default() -> BenchScene:
    """The walker family's default design replicated (homogeneous batch of the largest member kind)."""
    from morphopt.families import load_family

    spec = load_family("walker").build_spec(walker_default_params())
    return BenchScene([spec], None, "the default walker design (3 Jansen legs per side)")


@dataclass
class Declared:
    """One scene of the benchmark: builder, step size, simulated time of the precision runs,
    batch sizes for throughput, worlds of the precision runs, reference settings and the sweep."""

    build: object
    dt: float
    duration: float
    throughput_worlds: list[int]
    precision_worlds: int
    sweep: list[dict] = field(default_factory=list)
    reference: dict | None = field(default_factory=dict)  # None: no trajectory reference (loop error only)
    throughput_steps: int = 300
    # records compared with the reference: every step size of the sweep and of the peers must divide
    # it (steps_per_record), or a record would be taken a fraction of a step off the reference's time
    record_dt: float = 0.04
    peers: bool = False  # MuJoCo Warp from the MJCF export, or both Newton peers where the scene has a USD file
    quick_worlds: list[int] = field(default_factory=lambda: [1, 8])
    # throughput of other settings at the largest batch: label, SolverConfig overrides (scenes
    # without a work-precision sweep: what a setting buys in time and costs in loop error)
    variants: list[dict] = field(default_factory=list)
    # Newton peers' work-precision points on USD scenes: solver ("mujoco", "kamino") -> multipliers of dt
    peer_dt_scales: dict = field(default_factory=dict)


def steps_per_record(record_dt: float, step_dt: float) -> int:
    """Steps between two records: record_dt / step_dt, which must be a whole number. (Rounding it
    took the four-bar's dt x4 records every 48 ms against a reference every 50 ms: a trajectory
    error of 3.8e-2 m that was the records' time offset, 400 times the step's own 9.6e-5 m.)"""
    steps = round(record_dt / step_dt)
    if steps < 1 or abs(steps * step_dt - record_dt) > 1e-9 * max(record_dt, 1.0):
        raise ValueError(f"records every {record_dt:g} s do not fall on steps of {step_dt:g} s: "
                         f"choose a record interval that is a multiple of every step size")
    return steps


# work-precision settings: label, dt multiplier of the scene's dt, SolverConfig overrides (their knobs under
# "tuning": engine.Tuning's), and the coordinates engine.pack is forced into: a sweep point or variant runs in
# maximal coordinates unless it names others (TREE below: "tree", with ground_only, the specs through
# ground_contacts_only; pack: engine.pack's other options). Only the throughput rows labelled "default" take
# engine.pack's automatic plan; where that is not maximal, rows labelled "maximal" (default settings, maximal
# coordinates) beside them keep the measurements comparable with earlier runs, whose "default" was maximal.
TREE = dict(coordinates="tree", ground_only=True)  # reduced coordinates on the spanning tree: engine.reduced.chains
LINKAGE_SWEEP = [
    dict(label="default", dt_scale=1.0),
    dict(label="dt x0.5", dt_scale=0.5),
    dict(label="dt x2", dt_scale=2.0),
    dict(label="dt x4", dt_scale=4.0),
    dict(label="staged kernels", dt_scale=1.0, config=dict(tuning=dict(step_kernel="staged"))),
    dict(label="staged, dt x2", dt_scale=2.0, config=dict(tuning=dict(step_kernel="staged"))),
    dict(label="tolerance 1e-4", dt_scale=1.0, config=dict(tolerance=1e-4, relative_tolerance=1e-2)),
    dict(label="no projection (Baumgarte 0.01)", dt_scale=1.0,
         config=dict(position_iterations=0, baumgarte=0.01, tuning=dict(projection_velocity_update=False))),
    dict(label="semi-implicit Euler", dt_scale=1.0, config=dict(integrator="euler")),
    dict(label="float32 state", dt_scale=1.0, config=dict(tuning=dict(compensated_state=False))),
    dict(label="dt x8", dt_scale=8.0),
    # the same linkages in reduced coordinates (engine.pack's TREE plan: engine.reduced.chains)
    dict(label="reduced coordinates, dt x0.5", dt_scale=0.5, **TREE),
    dict(label="reduced coordinates", dt_scale=1.0, **TREE),
    dict(label="reduced coordinates, dt x2", dt_scale=2.0, **TREE),
    dict(label="reduced coordinates, dt x4", dt_scale=4.0, **TREE),
    # in their one coordinate (engine.pack's GROUNDED plan, the four-bar's automatic one: engine.reduced.grounded)
    dict(label="grounded coordinates", dt_scale=1.0, coordinates="grounded"),
    dict(label="grounded coordinates, dt x2", dt_scale=2.0, coordinates="grounded"),
    dict(label="grounded coordinates, dt x4", dt_scale=4.0, coordinates="grounded"),
    dict(label="grounded coordinates, dt x8", dt_scale=8.0, coordinates="grounded"),
]
LINKAGE_VARIANTS = [dict(label="reduced coordinates", config={}, **TREE)]
TIGHT = dict(tolerance=1e-9, relative_tolerance=0.0, max_iterations=300, position_iterations=4)
# one Gauss-Newton iteration for the dynamics' configuration and one for the output instead of two each;
# no projection at all, the loops held by the velocity-level Baumgarte term alone: on the CPU (one world,
# 2 s, dt 10 ms) its largest loop opening is 1.2e-4 m hanging and 2.9e-6 m standing at 0.5 (0.1: 4.3e-4 and
# 1.9e-5 m; 1.0: 5.7e-5 and 8.3e-5 m), below MuJoCo Warp's 4e-4 to 6e-4 m, but 1.0e-4 and 1.4e-3 rad in
# angle (its: 8e-5 to 1.2e-4 rad); the step skips the projection's solves (standing: also the projection's
# own matrix and factor)
NO_PROJECTION = dict(position_iterations=0, baumgarte=0.5, tuning=dict(projection_velocity_update=False))
# and the sparse factor in the elimination order of the shortest estimated schedule
# (engine.linalg.sparse_analysis.shallowest)
DRLEGS_VARIANTS = [dict(label="1 projection iteration", config=dict(position_iterations=1)),
                   dict(label="no projection (Baumgarte 0.5)", config=NO_PROJECTION),
                   dict(label="shallow elimination order", config=dict(tuning=dict(sparse_ordering="shallow")))]
# standing (drive, armature and contact rows beside the joints'): the projection's factor on the PADMM's
# pattern with the other rows made identity, or on a pattern of the bilateral rows alone, whichever
# Tuning.sparse_projection_pattern="auto" did not choose
DRLEGS_STANDING_VARIANTS = DRLEGS_VARIANTS + [
    dict(label="projection on the PADMM pattern", config=dict(tuning=dict(sparse_projection_pattern="never"))),
    dict(label="projection on its own pattern", config=dict(tuning=dict(sparse_projection_pattern="always")))]

# DR Legs hanging: step sizes from 2.5 to 40 ms, the projection iterations, the float32 state (its dual
# problem is linear: one PADMM iteration at any tolerance). Records every 40 ms fall on a step of each.
DRLEGS_SWEEP = [
    dict(label="default", dt_scale=1.0),
    dict(label="dt x0.25", dt_scale=0.25),
    dict(label="dt x0.5", dt_scale=0.5),
    dict(label="dt x2", dt_scale=2.0),
    dict(label="dt x4", dt_scale=4.0),
    dict(label="1 projection iteration", dt_scale=1.0, config=dict(position_iterations=1)),
    dict(label="1 projection iteration, dt x2", dt_scale=2.0, config=dict(position_iterations=1)),
    dict(label="float32 state", dt_scale=1.0, config=dict(tuning=dict(compensated_state=False))),
    dict(label="no projection (Baumgarte 0.5)", dt_scale=1.0, config=NO_PROJECTION),
    dict(label="no projection (Baumgarte 0.5), dt x2", dt_scale=2.0, config=NO_PROJECTION),
    # CPU, one world, 2 s: loops within 9.0e-4 m hanging and 7.6e-4 m standing, no world diverged
    dict(label="no projection (Baumgarte 0.5), dt x4", dt_scale=4.0, config=NO_PROJECTION),
]
DRLEGS_PEER_DT_SCALES = {"mujoco": [0.25, 0.5, 1.0, 2.0, 4.0], "kamino": [1.0, 2.0]}
# DR Legs hanging in reduced coordinates (the TREE plan, engine.reduced.chains: 30 joint angles, 18 independent
# loop rows, one fused launch per step): the loops' velocity constraint solved exactly, then 2 (or 1, or no)
# Gauss-Newton projections of the angles onto the loops; no projection: the velocity-level Baumgarte term alone
REDUCED = dict(position_iterations=2)
REDUCED_ONE = dict(position_iterations=1)
REDUCED_NO_PROJECTION = dict(position_iterations=0, baumgarte=0.5)
DRLEGS_REDUCED_VARIANTS = [
    dict(label="reduced coordinates", **TREE, config=REDUCED),
    dict(label="reduced coordinates, 1 projection", **TREE, config=REDUCED_ONE),
    dict(label="reduced coordinates, no projection (Baumgarte 0.5)", **TREE, config=REDUCED_NO_PROJECTION)]
DRLEGS_REDUCED_SWEEP = [
    dict(label="reduced coordinates", dt_scale=1.0, **TREE, config=REDUCED),
    dict(label="reduced coordinates, dt x0.5", dt_scale=0.5, **TREE, config=REDUCED),
    dict(label="reduced coordinates, dt x2", dt_scale=2.0, **TREE, config=REDUCED),
    dict(label="reduced coordinates, dt x4", dt_scale=4.0, **TREE, config=REDUCED),
    dict(label="reduced coordinates, 1 projection, dt x2", dt_scale=2.0, **TREE, config=REDUCED_ONE),
    dict(label="reduced coordinates, 1 projection, dt x4", dt_scale=4.0, **TREE, config=REDUCED_ONE)]
# DR Legs standing: the same steps and settings; no trajectory reference (MuJoCo C on our MJCF export
# of the standing robot is not a reference: its contacts and soft loops differ from the hard model)
DRLEGS_STANDING_SWEEP = [s for s in DRLEGS_SWEEP if s["label"] != "float32 state"] + [
    s for s in DRLEGS_REDUCED_SWEEP if "1 projection" not in s["label"]]
# DR Legs standing in reduced coordinates: 36 coordinates (the pelvis floating: 6), 18 loop rows and 6
# soft rows (the loop joints' armature and damping), up to 12 contacts (3 boxes' 4 deepest corners each);
# the feet alone have 8: the "8 contacts" variant keeps no more (contacts_dropped_max counts any loss)
FEET = dict(contact_capacity=8)
# the projections skipped up to 3x the default floors (Tuning.projection_skip_floor, _angular)
REDUCED_SKIP_3X = dict(REDUCED, tuning=dict(projection_skip_floor=3e-7, projection_skip_floor_angular=3e-6))
DRLEGS_STANDING_REDUCED_VARIANTS = DRLEGS_REDUCED_VARIANTS + [
    dict(label="reduced coordinates, 8 contacts", **TREE, config=REDUCED, pack=FEET),
    dict(label="reduced coordinates, 8 contacts, 1 projection", **TREE, config=REDUCED_ONE, pack=FEET),
    dict(label="reduced coordinates, 8 contacts, no projection (Baumgarte 0.5)", **TREE,
         config=REDUCED_NO_PROJECTION, pack=FEET),
    # the projections skipped up to 3x the default floors (float32 rounding of the loops on a GPU is
    # about the default floors: DR Legs standing projected 0.6 times a step with them, none with these)
    dict(label="reduced coordinates, 8 contacts, skip floors 3e-7 m, 3e-6 rad", **TREE,
         config=REDUCED_SKIP_3X, pack=FEET)]
DRLEGS_STANDING_SWEEP += [
    dict(label="reduced coordinates, 8 contacts, dt x0.5", dt_scale=0.5, **TREE, config=REDUCED, pack=FEET),
    dict(label="reduced coordinates, 8 contacts", dt_scale=1.0, **TREE, config=REDUCED, pack=FEET),
    dict(label="reduced coordinates, 8 contacts, dt x2", dt_scale=2.0, **TREE, config=REDUCED, pack=FEET),
    dict(label="reduced coordinates, 8 contacts, dt x4", dt_scale=4.0, **TREE, config=REDUCED, pack=FEET),
    dict(label="reduced coordinates, 8 contacts, skip floors 3e-7 m, 3e-6 rad, dt x4", dt_scale=4.0, **TREE,
         config=REDUCED_SKIP_3X, pack=FEET)]

SCENES_DECLARED = {
    "fourbar": Declared(lambda assets: _engine_scenes(["fourbar"]), dt=1e-3, duration=2.0,
                        throughput_worlds=[1, 64, 1024, 4096, 16384], precision_worlds=4096, sweep=LINKAGE_SWEEP,
                        reference=dict(dt=1e-4, config=TIGHT), peers=True, variants=LINKAGE_VARIANTS),
    "mixed": Declared(lambda assets: _engine_scenes(list(SCENES)), dt=1e-3, duration=1.0,
                      throughput_worlds=[4, 1024, 4096, 16384], precision_worlds=4096, sweep=LINKAGE_SWEEP,
                      reference=dict(dt=1e-4, config=TIGHT), quick_worlds=[4, 8], variants=LINKAGE_VARIANTS),
    "walker": Declared(lambda assets: walkers(), dt=2e-3, duration=0.0, throughput_worlds=[64, 1024, 4096],
                       precision_worlds=0, throughput_steps=30, quick_worlds=[2]),
    "walker_default": Declared(lambda assets: walker_default(), dt=2e-3, duration=0.0, throughput_worlds=[4096],
                               precision_worlds=0, throughput_steps=30, quick_worlds=[2]),
    "drlegs_hanging": Declared(lambda assets: dr_legs(False, assets), dt=1e-2, duration=2.0,
                               throughput_worlds=[1, 1024, 4096], precision_worlds=4096, throughput_steps=50,
                               peers=True, quick_worlds=[1], variants=DRLEGS_VARIANTS + DRLEGS_REDUCED_VARIANTS,
                               sweep=DRLEGS_SWEEP + DRLEGS_REDUCED_SWEEP,
                               reference=dict(config=TIGHT), peer_dt_scales=DRLEGS_PEER_DT_SCALES),
    "drlegs_standing": Declared(lambda assets: dr_legs(True, assets), dt=1e-2, duration=0.0,
                                throughput_worlds=[1, 1024, 4096], precision_worlds=0, throughput_steps=50,
                                peers=True, quick_worlds=[1], variants=DRLEGS_STANDING_VARIANTS),
    "drlegs_standing_newton": Declared(lambda assets: dr_legs(True, assets, NEWTON_EXAMPLE_JOINTS), dt=1e-2,
                                       duration=1.0, throughput_worlds=[1, 1024, 4096], precision_worlds=4096,
                                       throughput_steps=50, peers=True, quick_worlds=[1],
                                       variants=DRLEGS_STANDING_VARIANTS + DRLEGS_STANDING_REDUCED_VARIANTS,
                                       sweep=DRLEGS_STANDING_SWEEP, reference=None,
                                       peer_dt_scales=DRLEGS_PEER_DT_SCALES),
}
