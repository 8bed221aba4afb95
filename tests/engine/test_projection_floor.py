"""The projection's velocity update (SHAKE) at small dt: a rounding-level pose correction divided by
a small dt must not turn into noise in the twists. Oracles: conservation of energy of the passive
four-bar (no friction, no drive), and of a parallelogram through its flat (singular) position."""

import math

import numpy as np
import pytest

from benchmarks.stress import n_fourbar
from engine import SolverConfig, Tuning, pack_worlds, rollout
from engine.scenes import fourbar
from engine.testspeed import run


@pytest.mark.parametrize("kernel", ["fused", "staged"])
def test_energy_holds_at_small_dt_with_or_without_floor(kernel):
    """Four-bar, dt 0.1 ms, 0.3 s: the energy drift stays below 2e-4 with the rounding floor and
    without it (the dynamics run on projected midpoints, so rounding is not fed back; with the end
    of the step projected instead, the drift was 3.3 % without the floor), loops closed."""
    for floor in (0.0, Tuning.projection_velocity_floor):
        config = SolverConfig(tuning=Tuning(projection_velocity_floor=floor, step_kernel=kernel))
        result = run("fourbar", 1, 3000, 1e-4, "cpu", chunk=100, stages=False, config=config)
        assert result["max_constraint_violation_m"] < 1e-6
        assert result["diverged_worlds"] == 0
        assert result["energy_drift_rel"] < 2e-4, (floor, result["energy_drift_rel"])


@pytest.mark.parametrize("kernel", ["fused", "staged"])
def test_parallelogram_keeps_its_energy_through_flat_passes(kernel):
    """A parallelogram (cranks 1 m, 1 kg) turning over at dt 0.25 ms passes its flat position,
    where the joint Jacobian loses rank, four times in 2.5 s: its energy stays within 0.05 % and
    the two cranks' centres of mass move together (no period-two oscillation between steps).
    Projecting the end of each step instead lost 3.8 % (fused) and 0.45 % (staged) of the energy
    here, and the cranks' speeds differed by up to 0.2 m/s, alternating sign from step to step."""
    dt = 0.25e-3
    model = pack_worlds([n_fourbar(1, -0.5 * math.pi, 1.0)], device="cpu", dt=dt,
                        config=SolverConfig(tuning=Tuning(step_kernel=kernel)))
    trace, final = rollout(model, model.state(), model.control(), round(2.5 / dt), record_every=40)
    energy = trace.energy[:, 0]
    assert np.isfinite(energy).all()
    assert np.abs(energy - energy[0]).max() < 5e-4 * energy[0], np.abs(energy - energy[0]).max()
    twists = final.body_qd.numpy()[0]
    assert np.linalg.norm(twists[0, :3] - twists[1, :3]) < 1e-2 * np.linalg.norm(twists[0, :3])
    assert trace.violation_linear.max() < 1e-6


def test_velocity_floor_is_validated():
    with pytest.raises(ValueError, match="projection_velocity_floor"):
        SolverConfig(tuning=Tuning(projection_velocity_floor=-1.0))


@pytest.mark.parametrize("kernel", ["fused", "staged"])
def test_projection_skips_iterations_whose_correction_is_rounding(kernel):
    """The second Gauss-Newton iteration of a projection starts from a joint error at float32
    rounding: with projection_skip_floor it is skipped (the worlds' projection mask ends at 0),
    without either floor it runs (mask 1). The motion is the same to rounding: four-bar, 300 steps of 1 ms,
    poses within 1e-5 m of each other, energies within 1e-5 relative, loops closed to 2e-7 m in both."""
    results = {}
    for skip in (0.0, Tuning.projection_skip_floor):
        config = SolverConfig(tuning=Tuning(step_kernel=kernel, projection_skip_floor=skip,
                                            projection_skip_floor_angular=skip))
        model = pack_worlds([fourbar().spec] * 2, device="cpu", dt=1e-3, config=config)
        trace, final = rollout(model, model.state(), model.control(), 300, record_every=30)
        assert trace.violation_linear.max() < 2e-7, (skip, trace.violation_linear.max())
        np.testing.assert_array_equal(model.work.projection_mask.numpy(), [int(skip == 0.0)] * 2)
        results[skip] = (final.body_q.numpy(), trace.energy[:, 0])
    (q0, e0), (q1, e1) = results.values()
    assert np.abs(q0 - q1).max() < 1e-5
    assert np.abs(e0 - e1).max() < 1e-5 * np.abs(e0).max()


def test_skip_floor_is_validated():
    with pytest.raises(ValueError, match="projection_skip_floor"):
        SolverConfig(tuning=Tuning(projection_skip_floor=-1.0))


def test_projection_gate_weighs_linear_and_angular_errors_by_their_own_floors():
    """engine.integrate.projection_gates (projection_pass's test): a world's iteration is skipped
    (mask 0) only when its largest linear joint error is within projection_skip_floor and its
    largest angular one within projection_skip_floor_angular; rows other than bilateral joint rows
    do not count; a world not projected keeps mask 0; the velocity gate opens above its floor on
    either kind."""
    import warp as wp

    from engine.integrate import projection_gates
    from engine.model import ROW_ANGULAR, ROW_DYNAMICS, ROW_LINEAR, ModelArrays, WorkArrays

    @wp.kernel
    def gates(m: ModelArrays, w: WorkArrays, floor: float, skip_floor: float, skip_floor_angular: float,
              gate: wp.array(dtype=wp.int32), mask: wp.array(dtype=wp.int32)):
        world, lane = wp.tid()
        opened, move = projection_gates(world, lane, wp.block_dim(), m, w, floor, skip_floor, skip_floor_angular)
        if lane == 0:
            gate[world] = opened
            mask[world] = move

    residual = np.array([[5e-8, 5e-7, 1.0],  # both within their floors (the drive row's 1.0 does not count)
                         [2e-7, 0.0, 0.0],  # linear above
                         [0.0, 2e-6, 0.0],  # angular above
                         [1.0, 1.0, 0.0],  # not projected
                         [5e-8, 5e-8, 0.0]], np.float32)  # within the velocity floor too
    W = len(residual)
    kind = np.tile(np.array([ROW_LINEAR, ROW_ANGULAR, ROW_DYNAMICS], np.int32), (W, 1))
    cpu = "cpu"
    project = wp.array([1, 1, 1, 0, 1], dtype=wp.int32, device=cpu)
    gate, mask = wp.zeros(W, dtype=wp.int32, device=cpu), wp.zeros(W, dtype=wp.int32, device=cpu)
    m, w = ModelArrays(), WorkArrays()  # only the arrays projection_gates reads
    m.row_kind = wp.array(kind, dtype=wp.int32, device=cpu)
    w.row_count, w.project = wp.full(W, 3, dtype=wp.int32, device=cpu), project
    w.row_residual = wp.array(residual, dtype=float, device=cpu)
    wp.launch_tiled(gates, dim=[W], block_dim=1, device=cpu, inputs=[m, w, 1e-7, 1e-7, 1e-6], outputs=[gate, mask])
    assert mask.numpy().tolist() == [0, 1, 1, 0, 0]
    assert gate.numpy().tolist() == [1, 1, 1, 1, 0]


@pytest.mark.parametrize("kernel", ["fused", "staged"])
def test_angular_skip_floor_alone_decides_for_angular_errors(kernel):
    """With the linear floor out of reach (1 m), the angular floor alone keeps a Bricard linkage's
    projection iterations running (0 rad: the angular rows of its skew joint axes always carry some
    rounding) or skips them all (1 rad), in the fused and the staged step alike."""
    from benchmarks.stress import bricard

    for angular, expected in ((0.0, 1), (1.0, 0)):
        config = SolverConfig(tuning=Tuning(step_kernel=kernel, projection_skip_floor=1.0,
                                            projection_skip_floor_angular=angular))
        model = pack_worlds([bricard()] * 2, device="cpu", dt=1e-3, config=config)
        trace, _ = rollout(model, model.state(), model.control(), 20, record_every=10)
        np.testing.assert_array_equal(model.work.projection_mask.numpy(), [expected] * 2)
    with pytest.raises(ValueError, match="projection_skip_floor_angular"):
        SolverConfig(tuning=Tuning(projection_skip_floor_angular=-1.0))
