"""The fused step (engine.fused: a whole step per world in one thread) against the staged step
(engine.step: one kernel per stage, tile Cholesky, captured PADMM loop): two implementations of the
same method must give the same trajectories, for every feature the fused path accepts."""

import dataclasses

import numpy as np
import pytest

from engine import SolverConfig, pack_worlds, step
from engine.scenes import chain, fourbar, pendulum, sixbar
from engine.scenes_contact import CONTACT_SCENES
from engine.testspeed import ALL_SCENES
from morphopt.families import load_family
from morphopt.linkage.to_spec import to_spec


def jansen_spec():
    """Jansen's leg with its crank drive (velocity drive with an effort limit), inline loop closures."""
    family = load_family("jansen_leg")
    return to_spec(family.generate(family.space.default()))


def armature_fourbar():
    """The four-bar with rotor inertia and viscous damping on its crank (a dynamics row)."""
    spec = fourbar().spec
    joints = list(spec.joints)
    joints[0] = dataclasses.replace(joints[0], armature=0.01, damping=0.05)
    return dataclasses.replace(spec, joints=joints)


CASES = {
    "fourbar": lambda: [fourbar().spec] * 3,
    "mixed": lambda: [pendulum().spec, fourbar().spec, sixbar().spec],  # 40 rows padded (a 10-link chain has 56)
    "limits": lambda: [ALL_SCENES["fourbar_limits"]().spec] * 2,
    "jansen_drive": lambda: [jansen_spec()] * 2,
    "armature": lambda: [armature_fourbar()] * 2,
}


def trajectory(specs, kind, steps, config=None, control_fn=None):
    config = dataclasses.replace(config or SolverConfig(), step_kernel=kind)
    model = pack_worlds(specs, device="cpu", config=config, dt=1e-3)
    assert model.step_kernel == kind
    state, other, control = model.state(), model.state(), model.control()
    if control_fn is not None:
        control_fn(model, control)
    model.iterations_seen, model.rho_seen = [], []
    for _ in range(steps):
        step(model, state, other, control)
        state, other = other, state
        model.iterations_seen.append(model.work.iterations.numpy().copy())
        model.rho_seen.append(model.work.rho.numpy().copy())
    return model, state


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("integrator", ["euler", "moreau"])
def test_fused_step_matches_staged_step(case, integrator):
    """Same poses, twists, impulses and PADMM iterations over 200 steps (both run on the CPU; the
    serial Cholesky and the tile Cholesky may differ in rounding only)."""
    specs = CASES[case]()
    config = SolverConfig(integrator=integrator)
    staged_model, staged = trajectory(specs, "staged", 200, config)
    fused_model, fused = trajectory(specs, "fused", 200, config)
    for name in ("body_q", "body_qd", "row_lambda"):
        a, b = getattr(staged, name).numpy(), getattr(fused, name).numpy()
        assert np.all(np.isfinite(b)), name
        assert np.abs(a - b).max() <= 1e-6 * max(1.0, np.abs(a).max()), (case, name, np.abs(a - b).max())
    np.testing.assert_array_equal(staged_model.iterations_seen, fused_model.iterations_seen)


def test_fused_penalty_updates_refactor_like_the_staged_path():
    """With a penalty update every iteration and a tight tolerance (many refactorizations per
    step, joint limits active) both paths still agree and use the same iterations."""
    config = SolverConfig(rho_update_interval=1, tolerance=1e-9, relative_tolerance=0.0, max_iterations=40)
    specs = CASES["limits"]() + CASES["jansen_drive"]()[:1]
    staged_model, staged = trajectory(specs, "staged", 100, config)
    fused_model, fused = trajectory(specs, "fused", 100, config)
    assert len(np.unique(staged_model.rho_seen)) > 2  # the penalty changed (and the matrix was refactored)
    np.testing.assert_array_equal(staged_model.rho_seen, fused_model.rho_seen)
    assert np.abs(staged.body_q.numpy() - fused.body_q.numpy()).max() < 1e-6
    np.testing.assert_array_equal(staged_model.iterations_seen, fused_model.iterations_seen)


def test_fused_guard_freezes_a_diverged_world_and_leaves_the_others_bit_identical():
    """A world pushed to overflow is flagged and frozen in the fused step; its neighbours give
    bit-identical results to a batch without the push."""
    specs = [fourbar().spec] * 3

    def push(model, control):
        forces = np.zeros((3, model.max_bodies, 6), np.float32)
        forces[1, 0, 0] = 3.0e38
        control.body_f.assign(forces)

    reference_model, reference = trajectory(specs, "fused", 100)
    model, state = trajectory(specs, "fused", 100, control_fn=push)
    assert model.work.diverged.numpy().tolist() == [0, 1, 0]
    assert np.array_equal(state.body_q.numpy()[[0, 2]], reference.body_q.numpy()[[0, 2]])
    assert np.all(np.isfinite(state.body_q.numpy()[1]))


def test_auto_choice_and_errors():
    """'auto' fuses small batches without contacts and stages the others; forcing the fused step
    on a batch it cannot take names the reason; an unknown choice is refused."""
    assert pack_worlds([fourbar().spec], device="cpu").step_kernel == "fused"
    assert pack_worlds([fourbar().spec, chain().spec], device="cpu").step_kernel == "staged"  # 56 rows > 48
    walker = CONTACT_SCENES["walker"]().spec
    assert pack_worlds([walker], device="cpu").step_kernel == "staged"
    with pytest.raises(ValueError, match="step_kernel='fused'.*contacts"):
        pack_worlds([walker], device="cpu", config=SolverConfig(step_kernel="fused"))
    with pytest.raises(ValueError, match="step_kernel"):
        SolverConfig(step_kernel="megakernel")
