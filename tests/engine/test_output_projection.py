"""The output projection of Moreau-Jean's step runs only where the state is read (engine.step's
project_output, engine.rollout.Stepper): the motion must not depend on it, and poses set by hand
must still take effect."""

import numpy as np
import pytest

from engine import SolverConfig, Tuning, compute_metrics, pack_worlds, step
from engine.rollout import Stepper
from engine.scenes import make_scene


def _records(model, chunk: int, steps: int, every: int = 10) -> np.ndarray:
    stepper = Stepper(model, model.state(), model.control(), chunk=chunk)
    out = []
    while stepper.steps_done < steps:
        stepper.advance()
        if stepper.steps_done % every == 0:
            out.append(np.concatenate([stepper.state.body_q.numpy(), stepper.state.body_qd.numpy()], axis=-1))
    return np.array(out)


@pytest.mark.parametrize("kernel", ["fused", "staged"])
def test_skipping_the_output_projection_leaves_the_motion_bit_identical(kernel):
    """A 10-link chain (its output projection moves the poses: above the rounding floor), 1000
    steps at dt 1 ms: chunks of 10 steps (9 of 10 outputs not projected) give the same bits at
    every 10th step as projecting every step. The next step continues from the midpoint the last
    one left (State.body_q_next + body_q_low) whether or not its end was projected; rebuilding it
    from the output instead left the two runs 6e-6 m apart."""
    spec = make_scene("chain").spec
    runs = [_records(pack_worlds([spec], device="cpu", dt=1e-3, config=SolverConfig().tuned(step_kernel=kernel)), chunk, 1000)
            for chunk in (1, 10)]
    np.testing.assert_array_equal(runs[0], runs[1])


@pytest.mark.parametrize("kernel", ["fused", "staged"])
def test_an_unprojected_end_of_step_is_left_open_and_a_projected_one_closed(kernel):
    """project_output=False leaves the end of the step where the pose step put it (the joints open
    by the drift of half a step: 5e-6 m for the 10-link chain at dt 10 ms), project_output=True
    closes them to the usual 1e-7 m."""
    spec = make_scene("chain").spec
    errors = {}
    for project in (False, True):
        model = pack_worlds([spec], device="cpu", dt=1e-2, config=SolverConfig(tuning=Tuning(step_kernel=kernel)))
        a, b = model.state(), model.state()
        for k in range(20):
            step(model, a, b, model.control(), project_output=project or k < 19)
            a, b = b, a
        compute_metrics(model, a)
        errors[project] = float(model.work.violation_linear.numpy().max())
    assert errors[True] < 2e-7 < 10 * errors[True] < errors[False], errors


@pytest.mark.parametrize("kernel", ["fused", "staged"])
def test_poses_set_by_hand_take_effect(kernel):
    """Setting a state back to the initial poses and twists by hand (zeroing body_q_offset, as
    State asks; its low parts and body_q_next left stale) restarts the motion: the next 300 steps
    follow a fresh run from the initial state to within 1e-5 m, although the stale midpoint of
    the earlier motion lies centimetres away."""
    spec = make_scene("fourbar").spec
    model = pack_worlds([spec], device="cpu", dt=1e-3, config=SolverConfig(tuning=Tuning(step_kernel=kernel)))
    stepper = Stepper(model, model.state(), model.control(), chunk=10)
    for _ in range(20):
        stepper.advance()
    fresh = model.state()
    state = stepper.state
    moved = np.abs(state.body_q.numpy() - fresh.body_q.numpy())[..., :3].max()
    state.body_q.assign(fresh.body_q.numpy())
    state.body_qd.assign(fresh.body_qd.numpy())
    state.body_q_offset.zero_()
    for _ in range(30):
        stepper.advance()
    reference = pack_worlds([spec], device="cpu", dt=1e-3, config=SolverConfig(tuning=Tuning(step_kernel=kernel)))
    again = Stepper(reference, reference.state(), reference.control(), chunk=10)
    for _ in range(30):
        again.advance()
    gap = np.abs(stepper.state.body_q.numpy() - again.state.body_q.numpy())[..., :3].max()
    assert moved > 1e-2 and gap < 1e-5, (moved, gap)
