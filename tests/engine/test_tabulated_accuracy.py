"""The tabulated plan's Moreau-Jean step (issue 51): second order on a free walker whose cranks turn
at their drives' speed, against semi-implicit Euler; the tiled and per-thread forms step alike."""

import dataclasses

import numpy as np
import pytest

from engine import Integrator, SolverConfig
from engine.reduced.tabulated import pack_tabulated
from morphopt.families import load_family

WALKER = load_family("walker")


def free_walker():
    """The default walker without ground and gravity (only internal forces act: its linear momentum
    is conserved)."""
    spec = WALKER.build_spec({**WALKER.space.default(), "leg_family": "jansen_leg"})
    return dataclasses.replace(spec, ground=None, shapes=[], gravity=(0.0, 0.0, 0.0))


def momentum(model, spec):
    """The total linear momentum [kg m/s] of world 0 (every body's mass times its centre's velocity)."""
    _, body_qd = model.body_poses()
    masses = np.array([b.mass for b in spec.bodies])
    return (masses[:, None] * body_qd[0, :, :3]).sum(axis=0)


def momentum_drift(integrator, dt, samples=512, tiled=False, duration=1.0):
    """The largest |P(t) - P(0)| [kg m/s] over ``duration`` (read every tenth of it) of the free
    walker moving (0.3, 0, 0.1) m/s, spinning (0, 0.5, 0.2) rad/s, its cranks turning at their
    drives' 5 rad/s from the start (so the drives act smoothly); and the model."""
    spec = free_walker()
    config = SolverConfig(integrator=integrator).tuned(tabulated_tiled=tiled)
    model = pack_tabulated([spec], dt=dt, config=config, samples=samples)
    model.velocity.assign(np.array([[0.3, 0.0, 0.1]], np.float32))
    model.angular_velocity.assign(np.array([[0.0, 0.5, 0.2]], np.float32))
    rates = model.coord_rate.numpy()
    rates[0, :len(model.layouts[0].groups)] = 5.0
    model.coord_rate.assign(rates)
    start = momentum(model, spec)
    steps = int(round(duration / dt))
    worst = 0.0
    for _ in range(10):
        model.step(steps // 10)
        worst = max(worst, float(np.abs(momentum(model, spec) - start).max()))
    assert model.failure_reasons() == [""]
    return worst, model


def test_moreau_jean_conserves_momentum_to_second_order():
    """Free walker, 1 s: Euler's momentum drift halves with dt (first order); Moreau-Jean's shrinks
    ~4x per halving of dt (measured 3.97 from 5 to 2.5 ms with 2048-sample tables; with the default
    512 samples the tables' interpolation floors it near 2e-5 kg m/s below 5 ms) and stays far below
    Euler's (CPU: 2.0e-3 vs 3.8e-5 kg m/s at 5 ms, 1.0e-3 vs 2.0e-5 at 2.5 ms; momentum ~0.68)."""
    euler = [momentum_drift(Integrator.SEMI_IMPLICIT_EULER, dt)[0] for dt in (5e-3, 2.5e-3)]
    moreau = [momentum_drift(Integrator.MOREAU_JEAN, dt)[0] for dt in (5e-3, 2.5e-3)]
    assert 1.8 < euler[0] / euler[1] < 2.2, euler
    assert moreau[0] < euler[0] / 20 and moreau[1] < euler[1] / 20, (euler, moreau)
    fine = [momentum_drift(Integrator.MOREAU_JEAN, dt, samples=2048)[0] for dt in (1e-2, 5e-3, 2.5e-3)]
    assert fine[0] / fine[1] > 3.5 and fine[1] / fine[2] > 3.5, fine


@pytest.mark.parametrize("integrator", list(Integrator))
def test_tiled_and_per_thread_forms_step_alike(integrator):
    """Both kernel forms compute the same step with either integrator (the free walker, 0.5 s at
    5 ms): the same momentum drift and the same state (bit for bit on the CPU, where a block is one lane)."""
    tiled, plain = (momentum_drift(integrator, 5e-3, tiled=t, duration=0.5) for t in (True, False))
    assert tiled[1].tiled and not plain[1].tiled
    assert tiled[0] == plain[0]
    for name in ("position", "orientation", "velocity", "angular_velocity", "coord", "coord_rate"):
        np.testing.assert_array_equal(getattr(tiled[1], name).numpy(), getattr(plain[1], name).numpy())


def test_reset_between_steps_restarts_without_extrapolation():
    """The state set between steps (reset to the start, warm start included) steps as a fresh
    trajectory does: the step does not extrapolate the rates from a step that did not lead there."""
    spec = free_walker()
    fresh, reused = (pack_tabulated([spec], dt=5e-3) for _ in range(2))
    names = ("position", "orientation", "velocity", "angular_velocity", "coord", "coord_rate", "impulse")
    start = {name: getattr(reused, name).numpy().copy() for name in names}
    reused.step(20)
    for name in names:
        getattr(reused, name).assign(start[name])
    fresh.step(20)
    reused.step(20)
    for name in names:
        np.testing.assert_array_equal(getattr(fresh, name).numpy(), getattr(reused, name).numpy())


def test_plan_names_the_integrator():
    """The plan's description says which integrator the tabulated step runs."""
    spec = free_walker()
    assert pack_tabulated([spec]).midpoint
    assert not pack_tabulated([spec], config=SolverConfig(integrator=Integrator.SEMI_IMPLICIT_EULER)).midpoint
    import engine

    for integrator, words in ((Integrator.MOREAU_JEAN, "Moreau-Jean"),
                              (Integrator.SEMI_IMPLICIT_EULER, "semi-implicit Euler")):
        model = engine.pack([spec], device="cpu", coordinates="tabulated", config=SolverConfig(integrator=integrator))
        assert words in model.plan.integrator, model.plan.integrator
