"""Dynamics of whole steps against analytic solutions and conservation laws."""

import math

import numpy as np
import pytest
import warp as wp

from engine import Body, MechanismSpec, SolverConfig, Tuning, compute_metrics, metrics_numpy, pack_worlds, rollout, step
from engine.scenes import GRAVITY, chain, fourbar, pendulum, sixbar


def run(model, steps, dt, control=None, top_speed=None):
    """The state after ``steps`` steps; top_speed: a list that gets each world's largest body speed
    [m/s] over the run."""
    state, other = model.state(), model.state()
    control = control or model.control()
    fastest = np.zeros(model.num_worlds)
    for _ in range(steps):
        step(model, state, other, control, dt)
        state, other = other, state
        if top_speed is not None:
            fastest = np.maximum(fastest, np.linalg.norm(state.body_qd.numpy()[:, :, :3], axis=2).max(axis=1))
    if top_speed is not None:
        top_speed.extend(fastest.tolist())
    return state


@pytest.mark.parametrize("integrator", ["euler", "moreau"])
def test_pendulum_small_angle_period(integrator, device):
    """A bar pendulum released at 5 degrees swings with the small-angle period
    2 pi sqrt(I_pivot / (m g L/2)) within 0.5 %."""
    length, thickness = 0.5, 0.01
    scene = pendulum(length=length, angle=math.radians(5.0))
    model = pack_worlds([scene.spec], device=device, config=SolverConfig(integrator=integrator))
    dt = 1e-3
    trace, _ = rollout(model, model.state(), model.control(), 5000, dt=dt)
    x = trace.points[:, 0, 0, 0].astype(np.float64)  # tip x changes sign at the bottom of every swing
    crossings = [k + x[k] / (x[k] - x[k + 1]) for k in range(len(x) - 1) if x[k] * x[k + 1] < 0 or x[k + 1] == 0]
    period = 2 * (crossings[-1] - crossings[0]) / (len(crossings) - 1) * dt
    mass = length
    inertia_pivot = mass * (length**2 + thickness**2) / 12 + mass * (length / 2) ** 2
    expected = 2 * math.pi * math.sqrt(inertia_pivot / (mass * GRAVITY * length / 2))
    assert len(crossings) >= 7
    assert abs(period - expected) / expected < 5e-3


def test_dzhanibekov_flip_conserves_angular_momentum(device):
    """A free body spun about its intermediate axis flips over, and its world angular momentum
    stays within 0.5 % of the initial one."""
    inertia = np.diag([0.01, 0.02, 0.03])
    omega_body = np.array([1e-3, 5.0, 1e-3])
    spec = MechanismSpec([Body("tee", 1.0, inertia, angular_velocity=omega_body)], gravity=(0, 0, 0))
    model = pack_worlds([spec], device=device)
    state, other, control = model.state(), model.state(), model.control()
    momentum0 = inertia @ omega_body
    omega_y, worst = [], 0.0
    for _ in range(6000):
        step(model, state, other, control, 1e-3)
        state, other = other, state
        q = state.body_q.numpy()[0, 0, 3:]
        w = state.body_qd.numpy()[0, 0, 3:].astype(np.float64)
        x, y, z, s = q
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * s), 2 * (x * z + y * s)],
                        [2 * (x * y + z * s), 1 - 2 * (x * x + z * z), 2 * (y * z - x * s)],
                        [2 * (x * z - y * s), 2 * (y * z + x * s), 1 - 2 * (x * x + y * y)]])
        momentum = rot @ inertia @ rot.T @ w
        worst = max(worst, np.linalg.norm(momentum - momentum0) / np.linalg.norm(momentum0))
        omega_y.append((rot.T @ w)[1])
    assert min(omega_y) < -0.9 * omega_body[1], "the body never flipped"
    assert worst < 5e-3
    assert np.linalg.norm(state.body_q.numpy()[0, 0, :3]) < 1e-6  # centre of mass stays put


@pytest.mark.parametrize("stabilization", ["shake", "projection"])
def test_fourbar_ten_seconds_closed_and_conservative(stabilization, device):
    """The passive four-bar over 10 s at dt = 1 ms: loop closure < 1e-5 m and energy drift < 1 %
    of the energy above equilibrium (the projection-only variant must keep the loop closed too)."""
    scene = fourbar()
    config = SolverConfig(tuning=Tuning(projection_velocity_update=stabilization == "shake"))
    model = pack_worlds([scene.spec], device=device, config=config)
    trace, _ = rollout(model, model.state(), model.control(), 10000, dt=1e-3, record_every=20)
    assert trace.violation_linear.max() < 1e-5
    assert trace.violation_angular.max() < 1e-5
    if stabilization == "shake":
        drift = np.abs(trace.energy[:, 0] - trace.energy[0, 0]) / (trace.energy[0, 0] - scene.potential_min)
        assert drift.max() < 1e-2
    assert not trace.diverged.any()


def test_baumgarte_only_drifts_more_than_projection(device):
    """Without position projection, velocity-level Baumgarte feedback leaves more loop drift: the
    position correction is doing the work (both measured on the four-bar over 2 s)."""
    results = {}
    for name, config in {"baumgarte": SolverConfig(position_iterations=0, baumgarte=0.01,
                                                   tuning=Tuning(projection_velocity_update=False)),
                         "shake": SolverConfig()}.items():
        model = pack_worlds([fourbar().spec], device=device, config=config)
        trace, _ = rollout(model, model.state(), model.control(), 2000, dt=1e-3, record_every=50)
        results[name] = trace.violation_linear.max()
    assert results["shake"] < 1e-5
    assert results["baumgarte"] > 3 * results["shake"]


def test_heterogeneous_batch_matches_worlds_alone(device):
    """Pendulum, four-bar, six-bar and 10-link chain in one padded batch follow the same
    trajectories as each world simulated alone (to 1e-6)."""
    scenes = [pendulum(), fourbar(), sixbar(), chain()]
    batch = pack_worlds([s.spec for s in scenes], device=device)
    together = run(batch, 300, 1e-3).body_q.numpy()
    for w, scene in enumerate(scenes):
        alone = run(pack_worlds([scene.spec], device=device), 300, 1e-3).body_q.numpy()[0]
        n = len(scene.spec.bodies)
        assert np.abs(together[w, :n] - alone[:n]).max() < 1e-6, scene.spec.name


def test_diverged_world_is_frozen_and_isolated(device):
    """A world pushed to a non-finite state is flagged diverged and frozen at its last finite
    state; the other worlds give bit-identical results to a batch without the push."""
    specs = [fourbar().spec] * 3
    reference = pack_worlds(specs, device=device)
    poisoned = pack_worlds(specs, device=device)
    control = poisoned.control()
    forces = np.zeros((3, poisoned.max_bodies, 6), np.float32)
    forces[1, 0, 0] = 3.0e38  # overflows to inf in the first velocity update
    control.body_f.assign(forces)
    state_ref = run(reference, 200, 1e-3)
    state_bad = run(poisoned, 200, 1e-3, control)
    assert poisoned.work.diverged.numpy().tolist() == [0, 1, 0]
    q_bad, q_ref = state_bad.body_q.numpy(), state_ref.body_q.numpy()
    assert np.array_equal(q_bad[[0, 2]], q_ref[[0, 2]])
    assert np.array_equal(state_bad.body_qd.numpy()[[0, 2]], state_ref.body_qd.numpy()[[0, 2]])
    assert np.all(np.isfinite(q_bad[1]))
    np.testing.assert_array_equal(q_bad[1], poisoned.state().body_q.numpy()[1])  # frozen at the start


def test_runaway_world_is_flagged_before_it_overflows(device):
    """A world driven to ever higher speed (finite numbers all along) is flagged diverged and
    frozen once a body moves faster than SolverConfig.max_speed; the others run on unchanged.
    With a higher max_speed the same world is not flagged: the bound is what decides."""
    specs = [fourbar().spec] * 3
    forces = np.zeros((3, 3, 6), np.float32)
    forces[1, 0, 2] = 1.0e6  # [N] on the crank: over a thousand m/s within the run, far from overflow

    def pushed(config, top_speed=None):
        model = pack_worlds(specs, device=device, config=config)
        control = model.control()
        padded = np.zeros((3, model.max_bodies, 6), np.float32)
        padded[:, :3] = forces
        control.body_f.assign(padded)
        state = run(model, 100, 1e-3, control, top_speed)
        return model, state

    model, state = pushed(SolverConfig())
    assert model.work.diverged.numpy().tolist() == [0, 1, 0]
    speeds = np.linalg.norm(state.body_qd.numpy()[1, :3, :3], axis=1)
    assert np.all(np.isfinite(state.body_q.numpy()[1])) and speeds.max() <= 1.0e3
    reference = run(pack_worlds(specs, device=device), 100, 1e-3)
    assert np.array_equal(state.body_q.numpy()[[0, 2]], reference.body_q.numpy()[[0, 2]])
    top_speed = []
    model, state = pushed(SolverConfig(max_speed=1.0e9), top_speed)
    assert model.work.diverged.numpy().tolist() == [0, 0, 0]
    assert top_speed[1] > 1.0e3 and max(top_speed[0], top_speed[2]) < 10.0  # the pushed world's crank swings
    assert np.all(np.isfinite(state.body_qd.numpy()[1]))


def test_energy_metric_matches_numpy(device):
    """The energy metric equals kinetic + gravitational energy computed in NumPy from the state."""
    scene = sixbar()
    model = pack_worlds([scene.spec], device=device)
    state = run(model, 50, 1e-3)
    compute_metrics(model, state)
    energy = metrics_numpy(model)["energy"][0]
    expected = 0.0
    for b, body in enumerate(scene.spec.bodies):
        pose, twist = state.body_q.numpy()[0, b].astype(float), state.body_qd.numpy()[0, b].astype(float)
        x, y, z, s = pose[3:]
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * s), 2 * (x * z + y * s)],
                        [2 * (x * y + z * s), 1 - 2 * (x * x + z * z), 2 * (y * z - x * s)],
                        [2 * (x * z - y * s), 2 * (y * z + x * s), 1 - 2 * (x * x + y * y)]])
        w = rot.T @ twist[3:]
        expected += 0.5 * body.mass * twist[:3] @ twist[:3] + 0.5 * w @ body.inertia @ w + body.mass * GRAVITY * pose[2]
    assert abs(energy - expected) < 1e-5 * max(1.0, abs(expected))


def test_cuda_graph_replay_matches_eager():
    """A captured chunk of steps replayed on CUDA gives the eager trajectory."""
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device on this machine")
    from engine import Stepper

    model = pack_worlds([fourbar().spec] * 4, device="cuda")
    eager = run(model, 40, 1e-3).body_q.numpy()
    model2 = pack_worlds([fourbar().spec] * 4, device="cuda")
    stepper = Stepper(model2, model2.state(), model2.control(), chunk=10, capture=True)
    for _ in range(4):
        stepper.advance()
    assert np.abs(stepper.state.body_q.numpy() - eager).max() < 1e-6


def test_rollout_halt_freezes_the_marked_world_and_leaves_the_others_bit_identical():
    """A world marked by rollout's halt keeps its last state from that record on, does no solver
    work and is not flagged as diverged; the other world of the batch runs exactly as it does
    without the halt (CPU: each world's arithmetic is its own)."""
    specs = [fourbar().spec, fourbar(crank=0.12).spec]
    calls = []

    def halt(points, start):
        calls.append(points.shape)
        assert points.shape == start.shape == (2, model.max_points, 3)
        return np.array([len(calls) >= 3, False])

    model = pack_worlds(specs, device="cpu", dt=1e-3)
    trace, _ = rollout(model, model.state(), model.control(), 100, record_every=10, halt=halt)
    free = pack_worlds(specs, device="cpu", dt=1e-3)
    reference, _ = rollout(free, free.state(), free.control(), 100, record_every=10)
    assert len(calls) == 10
    assert trace.halted_at[0] == pytest.approx(0.03) and trace.halted_at[1] == -1.0
    assert not trace.diverged.any()
    assert np.array_equal(trace.points[:, 1], reference.points[:, 1])
    assert np.array_equal(trace.points[:4, 0], reference.points[:4, 0])  # up to the halt: the same run
    assert np.all(trace.points[3:, 0] == trace.points[3, 0])  # then frozen
    assert not np.array_equal(reference.points[3:, 0], np.broadcast_to(reference.points[3, 0], reference.points[3:, 0].shape))
    assert np.all(trace.iterations[4:, 0] == 0) and np.all(trace.iterations[4:, 1] > 0)
