"""The walker family: a torso on Jansen or Klann legs that actually walks, in heterogeneous batches."""

import re

import numpy as np

from engine.pack import MAX_DENSE_ROWS, dense_rows_needed
from morphopt.evaluate import evaluate_dynamic
from morphopt.families import load_family


def test_walkers_of_different_topologies_walk_in_one_batch():
    """Jansen walkers with three and one legs per side and a Klann walker with two legs per side
    run in one batch (loops closed, motors working); the default (three Jansen legs per side)
    walks straight at > 0.1 m/s with its feet lifting. The large worlds exceed the dense tile, so
    the batch runs on the sparse solver."""
    family = load_family("walker")
    base = family.space.default()
    assert base["legs_per_side"] == 3 and base["leg_family"] == "jansen_leg"
    params = [base, {**base, "legs_per_side": 1},
              {**base, "leg_family": "klann_leg", "legs_per_side": 2}]
    specs = [family.build_spec(p) for p in params]
    assert [sum(1 for j in s.joints if j.drive is not None) for s in specs] == [6, 2, 4]  # one motor per leg
    assert dense_rows_needed(specs[0]) > MAX_DENSE_ROWS
    # the fall rules off: walkers with one or two legs per side rest on one foot per side at times and
    # pitch onto the torso's nose (a fall by the default rule); here they show the mixed batch works
    evaluation = evaluate_dynamic(family, params, duration=1.5, dt=2e-3, record_every=5, fall_tilt=np.pi,
                                  fall_height=0.0)
    assert evaluation.feasible.all(), evaluation.failures
    for metrics in evaluation.metrics:
        assert metrics["loop_violation_max"] < 1e-4
        assert metrics["torque_peak"] > 0.0 and np.isfinite(metrics["walking_speed"])
    walker = evaluation.metrics[0]
    assert walker["walking_speed"] > 0.1, walker["walking_speed"]
    # straight, no sideways fall: the sideways offset of a 1.5 s walk follows the contacts' rounding
    # (0.01 to 0.12 of the distance, measured across dt 1-2 ms and projection variants); a fall
    # sideways or a turn gives more than 1
    assert walker["heading_drift"] < 0.2
    assert walker["left0_foot_step_height"] > 0.01 and 0.0 < walker["energy_per_distance"] < 100.0
    assert walker["torso_tilt_max"] < np.radians(15.0) and walker["torso_height_min"] > 0.8  # it stays up
    assert all(m["torso_tilt_max"] > np.radians(30.0) for m in evaluation.metrics[1:])  # they pitch over


def test_a_walker_without_feet_falls_and_fails_with_the_reason():
    """Without its foot shapes the walker's legs pass through the ground and the torso drops onto it:
    a failed design ("fell", the height reached in the reason); its twin with feet stands."""
    import dataclasses

    family = load_family("walker")
    params = [family.space.default()] * 2

    def hook(spec, p):
        if hook.calls == 0:
            spec = dataclasses.replace(spec, shapes=[s for s in spec.shapes if not s.name.endswith("foot")])
        hook.calls += 1
        return spec

    hook.calls = 0
    evaluation = evaluate_dynamic(family, params, duration=0.4, dt=2e-3, record_every=5, spec_hook=hook)
    assert re.match(r"fell after 0\.\d\d s: the torso sank to 0\.\d\d of its starting height \(less than 0\.5\)$",
                    evaluation.failures[0]), evaluation.failures[0]
    assert evaluation.failures[1] == "", evaluation.failures[1]
    assert evaluation.metrics[1]["torso_height_min"] > 0.8


def test_walker_legs_copied_at_their_phase_equal_generated_legs():
    """_placements generates a walker's first leg and copies it at the other crank phases: every
    leg equals its family's generate at its phase (the same numbers and graph)."""
    walker = load_family("walker")
    designs = [walker.space.default(), {**walker.space.default(), "leg_family": "klann_leg", "side_phase": 1.3}]
    for params in designs + walker.space.sample(np.random.default_rng(5), 6):
        lay = walker._sizes(params, None)
        family = walker.LEG_FAMILIES[lay["p"]["leg_family"]]
        leg = {k: v * lay["scale"] for k, v in family.space.default().items()}
        placed = walker._placements(lay)
        assert len(placed) == len(lay["places"])
        for (prefix, x, y, linkage), (name, px, py, phase) in zip(placed, lay["places"]):
            expected = family.generate(leg, crank_speed=lay["speed"], phase=phase)
            assert (prefix, x, y) == (f"{name}_", px, py)
            assert linkage == expected and type(linkage.crank.phase) is type(expected.crank.phase)
