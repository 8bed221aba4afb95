"""engine.reduced.chains (closed chains in reduced coordinates) against independent oracles: finite
differences of the kinematics for the mass matrix and the loop rows, the compound pendulum's ODE,
MuJoCo C (float64, RK4) and the maximal-coordinate engine for trajectories, the maximal engine's
joint residuals for the loops, energy conservation and static equilibrium."""

import dataclasses
import math

import numpy as np
import pytest

import engine
from engine import SolverConfig, compute_metrics, pack_worlds
from engine.reduced.chain_layout import MAX_COORDS, MAX_SHAPES, chain_layout
from engine.rollout import Stepper
from engine.scenes import chain, fourbar, pendulum, sixbar
from engine.spec import Body, GroundPlane, Joint, JointDrive, MechanismSpec, Shape


def pack_tree(specs, device=None, *, dt=1e-3, config=None, contact_capacity=None):
    """engine.pack with the TREE plan forced: its ChainModel (``.inner``: the layouts, arrays, work
    and step these tests inspect)."""
    return engine.pack(specs, device, dt=dt, config=config, contact_capacity=contact_capacity,
                       coordinates="tree").inner


def _rotation(axis, angle):
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _quat(R):
    w = math.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    return (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w


def spatial_loop(seed: int = 7, origin=(0.0, 0.0, 0.0), prefix: str = "") -> MechanismSpec:
    """A spatial 7R loop: six bodies hinged one to the next from the world about axes in different
    directions, the last hinged back to the world; one degree of freedom, started assembled."""
    rng = np.random.default_rng(seed)
    bodies, joints = [], []
    R, p = np.eye(3), np.asarray(origin, dtype=float)
    parent = None
    for k in range(6):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = R @ _rotation(rng.normal(size=3), 0.6)
        offset = np.array([0.12, 0.02 * (k % 2), -0.03])
        pivot = p
        p = p + R @ offset
        name = f"{prefix}link{k}"
        bodies.append(Body(name, 0.2 + 0.05 * k, [2e-4 + 1e-5 * k, 3e-4, 1e-4 + 2e-5 * k], com=(0.03, 0.01, 0.0),
                           position=p, orientation=_quat(R)))
        # the hinge at pivot (world frame): parent anchor in the parent frame, child anchor in the child's
        parent_R = np.eye(3) if parent is None else parent[0]
        parent_p = np.zeros(3) if parent is None else parent[1]
        joints.append(Joint(f"{prefix}j{k}", "revolute", None if parent is None else f"{prefix}link{k - 1}", name,
                            parent_position=parent_R.T @ (pivot - parent_p), child_position=R.T @ (pivot - p),
                            parent_orientation=_quat(parent_R.T @ R), axis=R.T @ axis))
        parent = (R, p)
    end = p + R @ np.array([0.1, 0.0, 0.02])
    axis = R @ np.array([0.3, 0.8, 0.5])
    joints.append(Joint(f"{prefix}close", "revolute", None, f"{prefix}link5", parent_position=end,
                        parent_orientation=_quat(R), child_position=R.T @ (end - p), axis=R.T @ axis))
    return MechanismSpec(bodies, joints, name=f"{prefix}spatial_loop")


def gimbal() -> MechanismSpec:
    """A frame turning about the vertical carrying a rotor that spins fast about a horizontal hinge,
    its centre of mass off the hinge and its inertia unequal: the gyroscopic torques matter."""
    pivot = np.array([0.1, 0.0, 0.05])
    com = pivot + np.array([0.0, 0.02, 0.01])
    yaw, spin = np.array([0.0, 0.0, 2.0]), np.array([20.0, 0.0, 0.0])
    frame = Body("frame", 0.5, [0.004, 0.003, 0.002], com=(0.05, 0.0, 0.02), angular_velocity=yaw,
                 velocity=np.cross(yaw, [0.05, 0.0, 0.02]))
    rotor = Body("rotor", 0.3, [0.001, 0.003, 0.0038], com=com, angular_velocity=yaw + spin,
                 velocity=np.cross(yaw, pivot) + np.cross(yaw + spin, com - pivot))
    joints = [Joint("yaw", "revolute", None, "frame", axis=(0, 0, 1)),
              Joint("spin", "revolute", "frame", "rotor", parent_position=pivot, child_position=pivot, axis=(1, 0, 0))]
    return MechanismSpec([frame, rotor], joints, name="gimbal")


def welded() -> MechanismSpec:
    """A base welded to the world at a turned, offset pose, a two-bar chain hinged on it, the first
    bar's hinge written child to parent (the tree runs it the other way), with initial rates."""
    R = _rotation([0.3, 1.0, 0.2], 0.7)
    base_p = np.array([0.1, -0.2, 0.4])
    bodies = [Body("base", 1.0, [0.01, 0.01, 0.01], position=base_p, orientation=_quat(R)),
              Body("bar1", 0.3, [1e-4, 8e-4, 8e-4], com=(0.1, 0.0, 0.0), position=base_p + R @ [0.05, 0, 0],
                   orientation=_quat(R), angular_velocity=R @ [0, 2.0, 0],
                   velocity=np.cross(R @ [0, 2.0, 0], R @ [0.1, 0, 0])),
              Body("bar2", 0.2, [1e-4, 5e-4, 5e-4], com=(0.08, 0.0, 0.0), position=base_p + R @ [0.25, 0, 0],
                   orientation=_quat(R), angular_velocity=R @ [0, 2.0, 0],
                   velocity=np.cross(R @ [0, 2.0, 0], R @ [0.28, 0, 0]))]
    joints = [Joint("weld", "fixed", None, "base", parent_position=base_p, parent_orientation=_quat(R)),
              Joint("hinge1", "revolute", "bar1", "base", parent_position=(0, 0, 0), child_position=(0.05, 0, 0),
                    axis=(0, -1, 0)),
              Joint("hinge2", "revolute", "bar1", "bar2", parent_position=(0.2, 0, 0), axis=(0, 1, 0))]
    return MechanismSpec(bodies, joints, name="welded")


def random_mechanism(seed: int) -> MechanismSpec:
    """4 to 7 bodies at random poses, each hinged at a random point about a random axis to the world,
    to an earlier body or to a base welded to the world (half the time), half the hinges between
    bodies written child to parent, anchor frames turned at random; and one more hinge between two
    random bodies, assembled at the start (a loop, which may lock a joint or leave a chain mobile)."""
    rng = np.random.default_rng(seed)
    count = int(rng.integers(4, 8))
    bodies, joints, poses = [], [], []
    if rng.random() < 0.5:
        R, p = _rotation(rng.normal(size=3), rng.uniform(0, 3)), rng.normal(size=3) * 0.1
        bodies.append(Body("base", 1.0, [0.01, 0.01, 0.01], position=p, orientation=_quat(R)))
        joints.append(Joint("weld", "fixed", None, "base", parent_position=p, parent_orientation=_quat(R)))
        poses.append((R, p))
    first = len(bodies)
    for k in range(count):
        R = _rotation(rng.normal(size=3), rng.uniform(0, 3))
        parent = int(rng.integers(-1, len(bodies)))
        Rp, pp = (np.eye(3), np.zeros(3)) if parent < 0 else poses[parent]
        pivot = pp + rng.normal(size=3) * 0.08
        p = pivot + rng.normal(size=3) * 0.08
        bodies.append(Body(f"b{k}", float(rng.uniform(0.1, 1.0)), rng.uniform(5e-4, 1e-3, size=3),
                           com=rng.normal(size=3) * 0.02, position=p, orientation=_quat(R)))
        poses.append((R, p))
        A = _rotation(rng.normal(size=3), rng.uniform(0, 3))
        axis = rng.normal(size=3)
        near = (None if parent < 0 else bodies[parent].name, pivot if parent < 0 else Rp.T @ (pivot - pp),
                _quat(A if parent < 0 else Rp.T @ A))
        far = (f"b{k}", R.T @ (pivot - p), _quat(R.T @ A))
        if near[0] is not None and rng.random() < 0.5:
            near, far = far, near
        joints.append(Joint(f"j{k}", "revolute", near[0], far[0], parent_position=near[1], parent_orientation=near[2],
                            child_position=far[1], child_orientation=far[2], axis=A.T @ axis))
    a, b = rng.choice(np.arange(first, len(bodies)), size=2, replace=False)
    (Ra, pa), (Rb, pb) = poses[a], poses[b]
    pivot = 0.5 * (pa + pb)
    A = _rotation(rng.normal(size=3), rng.uniform(0, 3))
    axis = rng.normal(size=3)
    joints.append(Joint("loop", "revolute", bodies[a].name, bodies[b].name, parent_position=Ra.T @ (pivot - pa),
                        parent_orientation=_quat(Ra.T @ A), child_position=Rb.T @ (pivot - pb),
                        child_orientation=_quat(Rb.T @ A), axis=A.T @ axis))
    return MechanismSpec(bodies, joints, name=f"random{seed}")


def _reference_matrices(layout, q, h=1e-6):
    """M = sum_b J_b^T diag(m, I) J_b and the loop rows' Jacobian d phi / d q, from central
    differences of the layout's NumPy kinematics (float64)."""
    n = layout.n

    def poses(qq):
        R, p, _, _ = layout.kinematics(qq)
        com = np.array([p[k] + R[k] @ layout.spec.bodies[layout.tree_body[k]].com for k in range(n)])
        return R, com

    R0, _ = poses(q)
    bodies = [k for k in range(n) if layout.kind[k] in (0, 3)]  # a floating root's massless entries left out
    Jv = np.zeros((n, 3, n))
    Jw = np.zeros((n, 3, n))
    dphi = np.zeros((5 * len(layout.loops), n))
    for j in range(n):
        dq = np.zeros(n)
        dq[j] = h
        Rp, cp = poses(q + dq)
        Rm, cm = poses(q - dq)
        Jv[:, :, j] = (cp - cm) / (2 * h)
        for k in range(n):
            W = (Rp[k] - Rm[k]) / (2 * h) @ R0[k].T
            Jw[k, :, j] = (W[2, 1], W[0, 2], W[1, 0])
        dphi[:, j] = (layout.loop_rows(q + dq)[1] - layout.loop_rows(q - dq)[1]) / (2 * h)
    M = np.zeros((n, n))
    for k in bodies:
        body = layout.spec.bodies[layout.tree_body[k]]
        Iw = R0[k] @ body.inertia @ R0[k].T
        M += body.mass * Jv[k].T @ Jv[k] + Jw[k].T @ Iw @ Jw[k]
    return M, dphi


def floating(spec: MechanismSpec, velocity=(0.0, 0.0, 0.0), spin=(0.0, 0.0, 0.0)) -> MechanismSpec:
    """The mechanism with its world joints moved onto a new free body 'frame' (at the origin,
    unturned: the anchors keep their coordinates), which starts at the given centre-of-mass
    velocity and angular velocity (the other bodies keep theirs relative to it)."""
    frame = Body("frame", 2.0, [0.01, 0.02, 0.015], com=(0.05, 0.0, 0.02), velocity=velocity, angular_velocity=spin)
    joints = [dataclasses.replace(j, parent="frame") if j.parent is None else j for j in spec.joints]
    bodies = []
    for b in spec.bodies:
        R = np.array(_quat_matrix(b.orientation))
        centre = np.asarray(b.position) + R @ np.asarray(b.com)
        bodies.append(dataclasses.replace(b, velocity=np.asarray(b.velocity) + np.asarray(velocity)
                                          + np.cross(spin, centre - np.array([0.05, 0.0, 0.02])),
                                          angular_velocity=np.asarray(b.angular_velocity) + np.asarray(spin)))
    return dataclasses.replace(spec, bodies=[frame] + bodies, joints=joints, name=f"floating_{spec.name}")


def _quat_matrix(q):
    x, y, z, w = q
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]


def fixed_and_floating() -> MechanismSpec:
    """A pendulum on the world, a free-floating six-bar and a free-floating spatial loop in one
    mechanism: a fixed tree and two floating roots, independent of each other."""
    parts = [chain(links=2).spec, floating(sixbar().spec), floating(spatial_loop(3, prefix="s_"))]
    parts[2] = dataclasses.replace(parts[2], bodies=[dataclasses.replace(parts[2].bodies[0], name="frame2")]
                                   + parts[2].bodies[1:],
                                   joints=[dataclasses.replace(j, parent="frame2") if j.parent == "frame" else j
                                           for j in parts[2].joints])
    return MechanismSpec([b for p in parts for b in p.bodies], [j for p in parts for j in p.joints],
                         name="fixed_and_floating")


@pytest.mark.parametrize("make", [lambda: sixbar().spec, spatial_loop, lambda: chain(links=5).spec,
                                  lambda: floating(sixbar().spec), lambda: floating(spatial_loop()),
                                  fixed_and_floating])
def test_mass_matrix_and_loop_rows_match_finite_differences(make, device):
    """The step's mass matrix (composite rigid bodies about the origin) equals sum J^T diag(m, I) J
    with the Jacobians from differences of the kinematics, and its kept loop rows equal the loop
    errors' derivatives (the loops start closed), to float32 rounding; with a floating root its six
    coordinates are differences of its centre of mass's position and of a rotation vector."""
    spec = make()
    model = pack_tree([spec], device=device, dt=1e-3, config=SolverConfig(integrator="euler"))  # at q0
    layout = model.layouts[0]
    state = model.state()
    model.step(state, record=True)
    M_ref, dphi = _reference_matrices(layout, layout.q0)
    n, R = layout.n, len(layout.rows)
    M = model.work.matrix.numpy()[0, :n, :n]
    assert np.abs(M - M_ref).max() < 2e-5 * np.abs(M_ref).max()
    if R:
        G = model.work.rows.numpy()[0, :R, :n]
        G_ref = dphi[5 * layout.rows[:, 0] + layout.rows[:, 1]]
        assert np.abs(G - G_ref).max() < 1e-4 * np.abs(G_ref).max()
        # the kept rows span every loop row (nothing left unenforced), the dropped ones add nothing
        assert np.linalg.matrix_rank(G_ref, 1e-6) == R == np.linalg.matrix_rank(dphi, 1e-6 * np.abs(dphi).max())


def test_spatial_loop_keeps_five_rows_and_the_planar_loops_two_each():
    """Row selection: a generic spatial loop keeps all five rows; a planar loop (parallel axes) only
    its two in-plane position rows, its other three being implied by the hinges."""
    assert len(chain_layout(spatial_loop()).rows) == 5
    for spec, loops in ((fourbar().spec, 1), (sixbar().spec, 2)):
        layout = chain_layout(spec)
        assert len(layout.loops) == loops and len(layout.rows) == 2 * loops
        assert set(layout.rows[:, 1].tolist()) <= {0, 1, 2}


def _rk4(f, x: float, duration: float, h: float = 1e-5) -> float:
    """x(duration) of x'' = f(x, x')[1], from rest at x, by classical RK4 with step h (float64)."""
    v = 0.0
    for _ in range(round(duration / h)):
        k1 = f(x, v)
        k2 = f(x + h / 2 * k1[0], v + h / 2 * k1[1])
        k3 = f(x + h / 2 * k2[0], v + h / 2 * k2[1])
        k4 = f(x + h * k3[0], v + h * k3[1])
        x += h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        v += h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    return x


def test_pendulum_follows_the_compound_pendulum_ode(device):
    """A bar released at 30 degrees: its angle follows theta'' = -(m g d / I_pivot) sin theta
    (integrated with RK4 at 1e-5 s) over 1 s: the default Moreau-Jean midpoint step within 2e-5 rad
    at dt 1 ms (float32 rounding is its floor), semi-implicit Euler within 2e-3 rad and first order
    (4x less at dt 0.25 ms)."""
    scene = pendulum()
    body = scene.spec.bodies[0]
    d = float(np.linalg.norm(body.com))
    inertia = body.inertia[1, 1] + body.mass * d * d
    k = body.mass * 9.81 * d / inertia

    def f(x, v):
        return v, -k * math.sin(x)

    th = _rk4(f, math.radians(30.0), 1.0)

    def error(dt, integrator):
        model = pack_tree([scene.spec], device=device, dt=dt, config=SolverConfig(integrator=integrator))
        state = model.state()
        for _ in range(round(1.0 / dt)):
            model.step(state)
        com = state.body_q.numpy()[0, 0, :3]
        return abs(math.atan2(com[0], -com[2]) - th)  # from the downward vertical

    assert error(1e-3, "moreau") < 2e-5
    euler = [error(dt, "euler") for dt in (1e-3, 2.5e-4)]
    assert 2e-4 < euler[0] < 2e-3 and 3.5 < euler[0] / euler[1] < 4.5


def _maximal_reference(spec, duration, dt=1e-4):
    model = pack_worlds([spec], device="cpu", dt=dt)
    stepper = Stepper(model, model.state(), model.control(), chunk=round(duration / dt))
    stepper.advance()
    return stepper.state.body_q.numpy()[0, :, :3]


def _chains_positions(spec, duration, dt, device, config=None):
    model = pack_tree([spec], device=device, dt=dt, config=config)
    state = model.state()
    for _ in range(round(duration / dt)):
        model.step(state)
    return state.body_q.numpy()[0, :, :3], model, state


def test_fourbar_matches_mujoco_and_converges_at_second_order(device):
    """The four-bar's bodies follow MuJoCo C's float64 RK4 trajectory (an independent simulator;
    MJCF export) within 3e-5 m after 0.5 s at dt 4 ms, and 3.5x closer at dt 2 ms (measured 6.3e-6,
    1.6e-6 m; at 1 ms 4.3e-7, near float32's floor)."""
    pytest.importorskip("mujoco")
    from benchmarks.peers import mujoco_reference

    spec = fourbar().spec
    reference = mujoco_reference([spec], duration=0.5, record_dt=0.5, dt=5e-5)[-1, 0]
    errors = [np.linalg.norm(_chains_positions(spec, 0.5, dt, device)[0] - reference, axis=1).max()
              for dt in (4e-3, 2e-3)]
    assert errors[0] < 3e-5 and errors[1] < errors[0] / 3.5


@pytest.mark.parametrize("make", [lambda: sixbar().spec, spatial_loop, gimbal, welded])
def test_closed_chains_match_the_maximal_engine_and_stay_closed(make, device):
    """The six-bar, the spatial loop, the gimbal and a chain on a welded base (a joint written child
    to parent, initial rates): starting where the maximal engine starts (every body's pose and
    velocity within 1e-6), within 1e-3 m of the maximal-coordinate engine
    at dt 0.1 ms after 0.3 s at dt 0.5 ms (a different formulation: every body's pose, PADMM), and 2x
    closer at dt 0.125 ms unless within 2e-5 m already (the reference's own error: the second-order
    step meets it at 0.5 ms; the gimbal without its gyroscopic torques: 2.5e-3 m at both); the maximal
    engine's own joint residuals of our poses stay below 1e-6 m and 1e-5 rad with two projections."""
    spec = make()
    start = pack_worlds([spec], device=device).state()
    initial = pack_tree([spec], device=device).state()
    assert np.abs(initial.body_q.numpy() - start.body_q.numpy()).max() < 1e-6
    assert np.abs(initial.body_qd.numpy() - start.body_qd.numpy()).max() < 1e-6
    reference = _maximal_reference(spec, 0.3)
    errors = []
    for dt in (5e-4, 1.25e-4):
        positions, model, state = _chains_positions(spec, 0.3, dt, device)
        errors.append(np.linalg.norm(positions - reference, axis=1).max())
    moved = np.linalg.norm(reference - np.array([b.position for b in spec.bodies]), axis=1).max()
    assert moved > 1e-2  # the mechanism moves
    assert errors[0] < 1e-3 and errors[1] < max(errors[0] / 2, 2e-5)
    gauge = pack_worlds([spec], device=device)
    compute_metrics(gauge, state)
    assert gauge.work.violation_linear.numpy()[0] < 1e-6 and gauge.work.violation_angular.numpy()[0] < 1e-5


def test_random_mechanisms_converge_to_the_maximal_engine():
    """Ten random mechanisms (random_mechanism: welds, reversed hinges, turned anchor frames, a loop
    that may lock a joint; seed 1 locks a hinge with a second one whose first position row only
    grazes the constraint): after 0.2 s, at dt 1 ms, our bodies are within 5e-3 m of the
    maximal-coordinate engine at dt 0.1 ms, and 2.5x closer at dt 0.25 ms (first order) unless
    already within 3e-5 m (the reference's own error); nearly all of them move. Rows chosen in row
    order without pivoting kept seed 1's grazing row and let its locked hinge drift: 9.5e-2 m."""
    moved = 0
    for seed in range(10):
        spec = random_mechanism(seed)
        reference = _maximal_reference(spec, 0.2)
        errors = [np.linalg.norm(_chains_positions(spec, 0.2, dt, "cpu")[0] - reference, axis=1).max()
                  for dt in (1e-3, 2.5e-4)]
        assert errors[0] < 5e-3, (seed, errors)
        assert errors[1] < max(errors[0] / 2.5, 3e-5), (seed, errors)
        moved += np.linalg.norm(reference - np.array([b.position for b in spec.bodies]), axis=1).max() > 0.05
    assert moved >= 8


def test_projection_closes_what_the_velocity_constraint_lets_drift(device):
    """Without projection or Baumgarte feedback the six-bar's loops drift open under semi-implicit
    Euler (the velocity constraint holds at the step's start, the positions' error accumulates); the
    projections close them 100x tighter. (Moreau-Jean's rates, tangent where the step ends, let
    them drift to 3e-7 m only.)"""
    spec = sixbar().spec
    gaps = []
    for config in (SolverConfig(position_iterations=0, baumgarte=0.0, integrator="euler"),
                   SolverConfig(position_iterations=2, integrator="euler")):
        _, _, state = _chains_positions(spec, 0.5, 2e-3, device, config)
        gauge = pack_worlds([spec], device=device)
        compute_metrics(gauge, state)
        gaps.append(gauge.work.violation_linear.numpy()[0])
    assert gaps[0] > 100 * gaps[1] and gaps[1] < 1e-6


def test_projection_stops_at_the_rounding_floors(device):
    """The projections stop once every loop row's error is within SolverConfig's skip floors: floors
    every error passes (1e9) step the swinging six-bar bit for bit as no projection at all (the
    check's poses are the final ones) and apply no correction; floors of 0 apply every one. With the
    default floors (1e-7 m, 1e-6 rad) its loops stay as closed as with floors of 0 (within 1e-6 m)
    and tighter than without projection (3x: Moreau-Jean's own drift is 3e-7 m), and a four-bar at
    rest without gravity applies none."""
    spec = sixbar().spec
    runs = {}
    for name, config in (("none", SolverConfig(position_iterations=0)),
                         ("always", SolverConfig().tuned(projection_skip_floor=1e9, projection_skip_floor_angular=1e9)),
                         ("never", SolverConfig().tuned(projection_skip_floor=0.0, projection_skip_floor_angular=0.0)),
                         ("default", SolverConfig())):
        _, model, state = _chains_positions(spec, 0.5, 2e-3, device, config)
        gauge = pack_worlds([spec], device=device)
        compute_metrics(gauge, state)
        runs[name] = (state.q.numpy(), state.body_q.numpy(), gauge.work.violation_linear.numpy()[0],
                      int(model.work.projections.numpy()[0]))
    assert np.array_equal(runs["always"][0], runs["none"][0]) and np.array_equal(runs["always"][1], runs["none"][1])
    assert runs["always"][3] == runs["none"][3] == 0 and runs["never"][3] == 2
    assert runs["default"][2] < 1e-6 and runs["never"][2] < 1e-6
    assert runs["none"][2] > 2 * max(runs["default"][2], runs["never"][2])
    still = dataclasses.replace(fourbar(crank_speed=0.0).spec, gravity=(0.0, 0.0, 0.0))  # at rest, closed
    _, model, _ = _chains_positions(still, 0.1, 2e-3, device, SolverConfig())
    assert int(model.work.projections.numpy()[0]) == 0


def _energy_error(scene, model, device, chunks: int, steps: int):
    """Step world 0 of ``model`` chunks x steps times from its initial state: (the state, the
    largest |E(t) - E(0)| at the chunks' ends, E(0) - E_min), energies from engine.metrics."""
    gauge = pack_worlds([scene.spec], device=device)
    state = model.state()
    compute_metrics(gauge, state)
    e0 = gauge.work.energy.numpy()[0]
    worst = 0.0
    for _ in range(chunks):
        for _ in range(steps):
            model.step(state)
        compute_metrics(gauge, state)
        worst = max(worst, abs(gauge.work.energy.numpy()[0] - e0))
    return state, worst, e0 - scene.potential_min


def test_passive_fourbar_conserves_energy(device):
    """No damping, no drives: kinetic plus potential energy (engine.metrics on our poses) stays
    within 0.5 % of what the four-bar can lose (E0 - E_min) over 1 s at dt 0.25 ms."""
    scene = fourbar()
    model = pack_tree([scene.spec], device=device, dt=2.5e-4)
    _, worst, available = _energy_error(scene, model, device, 20, 200)
    assert worst < 5e-3 * available


def test_pd_drive_settles_at_the_static_equilibrium(device):
    """A pendulum on an implicit PD drive comes to rest where the drive's torque about the pin's
    axis balances gravity's: kp (target - q) (a . y) + m g r_x = 0 (pin at the origin, axis a along
    +y, r the centre of mass)."""
    spec = pendulum().spec
    kp, kd, target = 2.0, 0.2, 0.5
    spec = dataclasses.replace(spec, joints=[dataclasses.replace(
        spec.joints[0], drive=JointDrive(stiffness=kp, damping=kd, target_position=target))])
    model = pack_tree([spec], device=device, dt=2e-3)
    state = model.state()
    for _ in range(3000):
        model.step(state)
    layout = model.layouts[0]
    q = float(state.q.numpy()[0, 0])
    axis = layout.parent_R[0] @ layout.axis[0]
    com = state.body_q.numpy()[0, 0, :3]
    drive = kp * (target - q) * float(axis @ np.array([0.0, 1.0, 0.0]))
    gravity = spec.bodies[0].mass * 9.81 * float(com[0])
    assert abs(float(state.u.numpy()[0, 0])) < 1e-4
    assert abs(drive) > 0.05 and abs(drive + gravity) < 1e-4 * abs(drive)


def test_damped_pd_drive_with_armature_follows_its_linear_ode(device):
    """No gravity: a bar on a PD drive with joint damping and armature obeys
    (I + armature) q'' = kp (target - q) + kd (0 - q') - damping q' (all implicit in the step);
    its angle follows the ODE's RK4 solution within 5e-3 rad over 1 s at dt 1 ms, and 3x closer at
    dt 0.25 ms, with either integrator (the drive's terms are backward Euler in both, for stiff
    drives' sake: first order, measured 2.5e-3 and 3.0e-3 rad at dt 1 ms)."""
    spec = pendulum().spec
    kp, kd, damping, armature, target = 3.0, 0.05, 0.02, 0.004, 0.4
    spec = dataclasses.replace(spec, gravity=(0.0, 0.0, 0.0), joints=[dataclasses.replace(
        spec.joints[0], drive=JointDrive(stiffness=kp, damping=kd, target_position=target), damping=damping,
        armature=armature)])
    body = spec.bodies[0]
    inertia = body.inertia[1, 1] + body.mass * float(body.com @ body.com) + armature
    q0 = chain_layout(spec).q0[0]

    def f(x, v):
        return v, (kp * (target - x) - (kd + damping) * v) / inertia

    th = _rk4(f, q0, 1.0)
    assert abs(th - q0) > 0.1  # the drive moves it

    def error(integrator, dt):
        model = pack_tree([spec], device=device, dt=dt, config=SolverConfig(integrator=integrator))
        state = model.state()
        for _ in range(round(1.0 / dt)):
            model.step(state)
        return abs(float(state.q.numpy()[0, 0]) - th)

    for integrator in ("moreau", "euler"):
        coarse, fine = error(integrator, 1e-3), error(integrator, 2.5e-4)
        assert coarse < 5e-3 and fine < coarse / 3, integrator


def test_a_batch_of_different_mechanisms_steps_each_as_alone(device):
    """Heterogeneous batch (padded): each world's angles after 100 steps equal those of the same
    mechanism stepped alone."""
    specs = [fourbar().spec, sixbar().spec, pendulum().spec, chain(links=4).spec, spatial_loop(), welded()]
    specs = specs + specs[:2]  # repeated mechanisms share one layout
    model = pack_tree(specs, device=device, dt=1e-3)
    state = model.state()
    for _ in range(100):
        model.step(state)
    for w, spec in enumerate(specs):
        alone = pack_tree([spec], device=device, dt=1e-3)
        s = alone.state()
        for _ in range(100):
            alone.step(s)
        n = alone.layouts[0].n
        assert np.allclose(state.q.numpy()[w, :n], s.q.numpy()[0, :n], atol=1e-6, rtol=0)


def test_cuda_steps_a_large_tree_as_the_cpu_does():
    """Five spatial 7R loops on the world in one mechanism (30 coordinates, 25 kept rows: the lanes
    of a warp share every stage, and some stages take more items than lanes): CUDA's 32 lanes per
    world give the CPU's single-thread result to float32 rounding after 50 steps (a race between
    lanes would not)."""
    import warp as wp

    if not wp.is_cuda_available():
        pytest.skip("no CUDA device on this machine")
    parts = [spatial_loop(seed, origin=(0.5 * seed, 0.0, 0.0), prefix=f"m{seed}_") for seed in range(5)]
    spec = MechanismSpec([b for m in parts for b in m.bodies], [j for m in parts for j in m.joints], name="five_loops")
    layout = chain_layout(spec)
    assert layout.n == 30 and len(layout.rows) == 25
    results = []
    for device in ("cpu", "cuda"):
        model = pack_tree([spec, spec], device=device, dt=1e-3)
        state = model.state()
        for _ in range(50):
            model.step(state)
        results.append(state.q.numpy()[:, :30])
    moved = np.abs(results[0] - layout.q0).max()
    assert moved > 1e-3 and np.abs(results[1] - results[0]).max() < 1e-4 * max(1.0, moved)


def test_cuda_steps_floating_mechanisms_on_the_ground_as_the_cpu_does():
    """Floating worlds with contacts on both devices: the six-bar on a box (two loops, 4 contacts), a
    floating spatial loop landing on a box and a sphere, a sliding box and five spatial loops on
    one floating frame landing on a box (36 coordinates: more than a warp's lanes); CUDA's lanes give the CPU's
    single-thread result to float32 and PADMM-tolerance rounding after 100 steps (a race between
    lanes would not)."""
    import warp as wp

    if not wp.is_cuda_available():
        pytest.skip("no CUDA device on this machine")
    loop = floating(spatial_loop(), velocity=(0.2, 0.0, 0.0), spin=(0.0, 0.0, 1.0))
    loop = dataclasses.replace(loop, ground=GroundPlane(offset=-0.03), shapes=[
        Shape("pad", "box", "frame", size=(0.1, 0.1, 0.02)), Shape("tip", "sphere", "link5", size=(0.03,))])
    parts = [spatial_loop(seed, origin=(0.5 * seed, 0.0, 0.0), prefix=f"m{seed}_") for seed in range(5)]
    big = floating(MechanismSpec([b for m in parts for b in m.bodies], [j for m in parts for j in m.joints],
                                 name="five_loops"))
    big = dataclasses.replace(big, ground=GroundPlane(offset=-0.06), shapes=[
        Shape("pad", "box", "frame", size=(0.2, 0.2, 0.05))])
    specs = [_sixbar_on_a_box(), loop, _box(velocity=(1.0, 0.0, 0.0)), big]
    assert chain_layout(big).n > 32
    results = []
    for device in ("cpu", "cuda"):
        model = pack_tree(specs, device=device, dt=1e-3)
        state = model.state()
        for _ in range(100):
            model.step(state)
        assert not model.diverged.any()
        results.append(state.body_q.numpy()[..., :3])
    moved = max(np.abs(results[0][w, :len(s.bodies)] - [b.position for b in s.bodies]).max()
                for w, s in enumerate(specs))
    assert moved > 1e-2
    assert np.abs(results[1] - results[0]).max() < 1e-4


@pytest.mark.parametrize("kick", [1e4, float("nan")])
def test_a_diverging_world_is_frozen_and_flagged_while_the_others_go_on(kick, device):
    """A world whose bodies move faster than max_speed, or turn non-finite, is flagged diverged and
    frozen at the start of the step that failed (finite angles, its bodies as the last good step
    left them); the other world of the batch steps exactly as alone. The stepper replays chunks."""
    spec = fourbar().spec
    packed = engine.pack([spec, spec], device, dt=1e-3, config=SolverConfig(max_speed=50.0), coordinates="tree")
    model = packed.inner
    stepper = engine.Stepper(packed, packed.state(), chunk=10)
    state = stepper.state.inner
    stepper.advance()
    good_bodies = state.body_q.numpy()[1].copy()
    good_q = state.q.numpy()[1].copy()
    u = state.u.numpy()
    u[1, :3] = kick
    state.u.assign(u)
    stepper.advance()
    stepper.advance()
    assert model.diverged.tolist() == [False, True]
    assert np.array_equal(state.body_q.numpy()[1], good_bodies)
    assert np.array_equal(state.q.numpy()[1], good_q)
    alone = pack_tree([spec], device=device, dt=1e-3)
    s = alone.state()
    for _ in range(30):
        alone.step(s)
    assert np.allclose(state.q.numpy()[0], s.q.numpy()[0], atol=1e-6, rtol=0)


def test_what_the_path_cannot_model_is_named():
    """Limits, shapes without a ground plane or with restitution, non-revolute joints, a loop whose
    every joint is driven, and too many coordinates: a ValueError naming the
    joint, shape or body (and the world in a batch)."""
    spec = fourbar().spec
    cases = [
        (dataclasses.replace(spec, joints=[dataclasses.replace(spec.joints[0], limit_lower=-1.0)] + spec.joints[1:]),
         "joint 'ground_crank' has limits"),
        (dataclasses.replace(spec, shapes=[Shape("pad", "sphere", "crank", size=(0.01,))]),
         "shape 'pad': shapes collide with the ground plane only"),
        (dataclasses.replace(spec, shapes=[Shape("pad", "sphere", "crank", size=(0.01,), restitution=0.5)],
                             ground=GroundPlane()), "shape 'pad': restitution"),
        (dataclasses.replace(spec, joints=[dataclasses.replace(j, drive=JointDrive(stiffness=1.0))
                                           for j in spec.joints]), "joint '.*' closes a loop of driven joints"),
        (dataclasses.replace(spec, joints=[dataclasses.replace(spec.joints[0], type="spherical")] + spec.joints[1:]),
         "joint 'ground_crank' is spherical"),
        (chain(links=MAX_COORDS + 1).spec, f"{MAX_COORDS + 1} tree coordinates"),
        (dataclasses.replace(spec, joints=spec.joints + [Joint("glue", "fixed", "crank", "coupler")]),
         "joint 'glue': only welds to the world"),
        (dataclasses.replace(welded(), joints=welded().joints + [Joint("pin", "revolute", None, "base")]),
         "joint 'pin' joins two fixed bodies"),
    ]
    for bad, words in cases:
        with pytest.raises(ValueError, match=words):
            chain_layout(bad)
    with pytest.raises(ValueError, match=r"^engine.pack: coordinates 'tree' do not fit world 1 \(fourbar\): "
                                         r"engine.reduced.chains: joint 'ground_crank' has limits; limits are not "
                                         r"modelled$"):
        pack_tree([spec, cases[0][0]], device="cpu")


def _momentum(spec, state):
    """Linear and angular (about the origin) momentum of world 0's bodies from the state's COM poses
    and velocities."""
    q, qd = state.body_q.numpy()[0], state.body_qd.numpy()[0]
    linear, angular = np.zeros(3), np.zeros(3)
    for b, body in enumerate(spec.bodies):
        R = np.array(_quat_matrix(q[b, 3:]))
        v, w = qd[b, :3], qd[b, 3:]
        linear += body.mass * v
        angular += np.cross(q[b, :3], body.mass * v) + R @ body.inertia @ R.T @ w
    return linear, angular


@pytest.mark.parametrize("make", [lambda: sixbar().spec, spatial_loop])
def test_free_floating_chain_conserves_momentum_in_the_limit(make, device):
    """Without gravity a free-floating closed chain (its world joints moved onto a free body that
    starts moving and spinning) has constant linear and angular momentum: the loops' and joints'
    forces are internal. The momenta drift at second order (module docstring of
    engine.reduced.chain_kernel): after the first step (which projects the initial rates onto the
    loops), over 0.5 s, within 1e-4 of their size at dt 4 ms (measured 1.4e-5 to 4.2e-5) and 3x
    less at dt 2 ms, while the bodies turn and travel."""
    spec = dataclasses.replace(floating(make(), velocity=(0.3, -0.2, 0.1), spin=(1.0, 2.0, -1.5)),
                               gravity=(0.0, 0.0, 0.0))
    drifts = []
    for dt in (4e-3, 2e-3):
        model = pack_tree([spec], device=device, dt=dt)
        state = model.state()
        model.step(state)
        p0, l0 = _momentum(spec, state)
        start = state.body_q.numpy()[0].copy()
        for _ in range(round(0.5 / dt)):
            model.step(state)
        p1, l1 = _momentum(spec, state)
        assert np.linalg.norm(p0) > 0.1 and np.linalg.norm(l0) > 1e-3
        drifts.append((np.linalg.norm(p1 - p0) / np.linalg.norm(p0), np.linalg.norm(l1 - l0) / np.linalg.norm(l0)))
        assert np.abs(state.body_q.numpy()[0, :, :3] - start[:, :3]).max() > 0.05
        assert not model.diverged.any()
    (p_coarse, l_coarse), (p_fine, l_fine) = drifts
    assert max(p_coarse, l_coarse) < 1e-4, drifts
    assert p_fine < p_coarse / 3 and l_fine < l_coarse / 3, drifts


def test_free_fall_moves_the_centre_of_mass_as_a_point_mass(device):
    """A free-floating six-bar thrown under gravity: its centre of mass follows c0 + v0 t + g t^2 / 2
    (the midpoint step integrates a constant acceleration exactly, and the projections move no
    centre of mass: the loops' rows have no part along a floating root's translations) to float32
    rounding, while the mechanism flails."""
    spec = floating(sixbar().spec, velocity=(0.5, 0.0, 2.0), spin=(0.0, 3.0, 0.0))
    model = pack_tree([spec], device=device, dt=1e-3)
    state = model.state()
    masses = np.array([b.mass for b in spec.bodies])

    def centre():
        return masses @ state.body_q.numpy()[0, :, :3] / masses.sum()

    model.step(state)  # the initial rates projected onto the loops: the momentum to follow
    c0 = centre()
    v0 = masses @ state.body_qd.numpy()[0, :, :3] / masses.sum()
    for _ in range(400):
        model.step(state)
    t = 0.4
    expected = c0 + v0 * t + 0.5 * np.array(spec.gravity) * t * t
    assert np.linalg.norm(centre() - expected) < 5e-5  # 400 float32 steps of a position 0.3 m out
    assert np.linalg.norm(centre() - c0) > 0.15


def _box(velocity=(0.0, 0.0, 0.0), friction=0.5, height=0.05, size=(0.1, 0.08, 0.05)):
    body = Body("box", 2.0, [0.01, 0.012, 0.015], position=(0.0, 0.0, height), velocity=velocity)
    return MechanismSpec([body], [], shapes=[Shape("block", "box", "box", size=size, friction=friction)],
                         ground=GroundPlane(friction=friction), name="box")


def test_a_box_rests_on_the_ground_with_its_weight_on_four_corners(device):
    """A free box set on the ground stays there: after 0.5 s its height is within 1e-4 m of its
    half-height and it is still; its four bottom corners carry its weight (normal impulses per step
    sum to m g dt within 1 %)."""
    spec = _box()
    dt = 1e-3
    model = pack_tree([spec], device=device, dt=dt)
    state = model.state()
    for _ in range(500):
        model.step(state)
    z = state.body_q.numpy()[0, 0, 2]
    assert abs(z - 0.05) < 1e-4
    assert np.abs(state.body_qd.numpy()[0, 0]).max() < 1e-3
    assert model.work.contact_count.numpy()[0] == 4
    impulses = model.work.contact_impulse.numpy()[0]
    weight = spec.bodies[0].mass * 9.81 * dt
    assert abs(impulses[:, 0].sum() - weight) < 0.01 * weight


def test_a_sliding_box_stops_where_coulomb_friction_says(device):
    """A box sliding at 1 m/s on the ground (friction 0.5 with the ground, 0.5 combined) decelerates
    at mu g: it stops after v / (mu g) = 0.204 s, v^2 / (2 mu g) = 0.102 m on, within 2 %."""
    spec = _box(velocity=(1.0, 0.0, 0.0))
    model = pack_tree([spec], device=device, dt=1e-3)
    state = model.state()
    stopped = None
    for k in range(400):
        model.step(state)
        if stopped is None and state.body_qd.numpy()[0, 0, 0] < 1e-3:
            stopped = (k + 1) * 1e-3
    x = state.body_q.numpy()[0, 0, 0]
    assert abs(x - 1.0 / (2 * 0.5 * 9.81)) < 0.02 * 0.102
    assert stopped is not None and abs(stopped - 1.0 / (0.5 * 9.81)) < 0.02 * 0.204
    assert abs(state.body_q.numpy()[0, 0, 2] - 0.05) < 1e-4


def test_a_dropped_sphere_lands_without_bouncing_or_sinking(device):
    """A sphere dropped from 0.3 m lands and stays on the ground (no restitution): once down, its
    centre stays within 1 mm of its radius above the plane and it never rises again."""
    body = Body("ball", 0.5, [2e-4, 2e-4, 2e-4], position=(0.0, 0.0, 0.3))
    spec = MechanismSpec([body], [], shapes=[Shape("ball", "sphere", "ball", size=(0.04,))], ground=GroundPlane(),
                         name="ball")
    model = pack_tree([spec], device=device, dt=1e-3)
    state = model.state()
    heights = []
    for _ in range(600):
        model.step(state)
        heights.append(state.body_q.numpy()[0, 0, 2])
    heights = np.array(heights)
    landed = int(np.argmax(heights < 0.041))
    assert 200 < landed < 260  # free fall of 0.26 m: 0.230 s
    after = heights[landed:]
    assert after.min() > 0.039 and after.max() < 0.041
    assert np.abs(np.diff(after)).max() < 1e-3


def _sixbar_on_a_box() -> MechanismSpec:
    """The six-bar carried on top of a heavy box (its world joints moved onto the box) standing on
    the ground."""
    base = floating(sixbar().spec)
    frame = dataclasses.replace(base.bodies[0], mass=8.0, inertia=[0.05, 0.05, 0.05], com=(0.0, 0.0, 0.0),
                                position=(0.0, 0.0, 0.0))
    lift = 0.6
    bodies = [frame] + [dataclasses.replace(b, position=np.asarray(b.position) + [0, 0, lift])
                        for b in base.bodies[1:]]
    joints = [dataclasses.replace(j, parent_position=np.asarray(j.parent_position) + [0, 0, lift])
              if j.parent == "frame" else j for j in base.joints]
    frame = dataclasses.replace(frame, position=(0.0, 0.0, 0.1))
    joints = [dataclasses.replace(j, parent_position=np.asarray(j.parent_position) - [0, 0, 0.1])
              if j.parent == "frame" else j for j in joints]
    return dataclasses.replace(base, bodies=[frame] + bodies[1:], joints=joints, ground=GroundPlane(friction=1.0),
                               shapes=[Shape("foot", "box", "frame", size=(0.3, 0.2, 0.1), friction=1.0)],
                               name="sixbar_on_a_box")


def test_the_solves_take_a_floating_roots_chain_unrolled(device):
    """A floating root's six entries start every entry's ancestry: the solves take them unrolled
    (ChainArrays.prefix) instead of walking the parents, in the same order, so the six-bar on a box
    steps bit for bit as with the walk alone (prefix 0) and as with a kernel compiled without the
    unrolled code (unroll 0, which a batch without floating roots gets); the prefix counts a leading
    chain only while it is every other entry's (at most MAX_PREFIX)."""
    from engine.reduced.chain_layout import MAX_PREFIX, _prefix

    assert _prefix(np.array([0, 1, 2, 3, 4, 5, 6, 6, 7])) == 6 and _prefix(np.arange(MAX_COORDS)) == MAX_PREFIX
    assert _prefix(np.array([0, 0, 1, 1])) == 0 and _prefix(np.array([0, 1, 2, 2, 3])) == 2
    assert pack_tree([sixbar().spec], device=device, dt=2e-3).unroll == 0  # a fixed base: no prefix code
    spec = _sixbar_on_a_box()
    models = [pack_tree([spec], device=device, dt=2e-3) for _ in range(3)]
    assert int(models[0].arrays.prefix.numpy()[0]) == 6 and models[0].unroll == MAX_PREFIX
    models[1].arrays.prefix.zero_()
    models[2].unroll = 0  # the prefix (still 6 in its arrays) read as 0
    states = [model.state() for model in models]
    for _ in range(50):
        for model, state in zip(models, states):
            model.step(state)
    assert models[0].work.contact_count.numpy()[0] > 0
    for other in states[1:]:
        assert np.array_equal(states[0].q.numpy(), other.q.numpy())
        assert np.array_equal(states[0].u.numpy(), other.u.numpy())


def test_a_mechanism_on_the_ground_follows_the_maximal_engine(device):
    """A heavy box on the ground carrying the six-bar on its top (world joints moved onto the box):
    the bodies follow the maximal-coordinate engine (stepped at dt 0.1 ms) within 2e-3 m after
    0.3 s at dt 1 ms, and closer at dt 0.25 ms, with the box's corners on the ground throughout."""
    spec = _sixbar_on_a_box()
    reference = _maximal_reference(spec, 0.3)
    errors = []
    for dt in (1e-3, 2.5e-4):
        positions, model, state = _chains_positions(spec, 0.3, dt, device)
        errors.append(np.linalg.norm(positions - reference, axis=1).max())
        assert model.work.contact_count.numpy()[0] == 4 and not model.diverged.any()
    moved = np.linalg.norm(reference - np.array([b.position for b in spec.bodies]), axis=1).max()
    assert moved > 0.05
    assert errors[0] < 2e-3 and errors[1] < errors[0], errors


def test_a_drive_past_its_effort_limit_stops_its_world_with_the_reason(device):
    """Effort limits are checked, not enforced: a pendulum whose PD drive needs more torque than its
    limit to hold it stops with the reason 'effort limit' (frozen), while the same pendulum with an
    ample limit in the same batch runs on."""
    spec = pendulum().spec

    def driven(limit):
        return dataclasses.replace(spec, joints=[dataclasses.replace(spec.joints[0], drive=JointDrive(
            stiffness=5.0, damping=0.5, target_position=1.5, effort_limit=limit))])

    model = pack_tree([driven(1e-3), driven(100.0)], device=device, dt=1e-3)
    state = model.state()
    for _ in range(50):
        model.step(state)
    assert model.failure_reasons() == ["effort limit", None]
    frozen = state.q.numpy()[0, 0]
    for _ in range(50):
        model.step(state)
    assert state.q.numpy()[0, 0] == frozen and abs(state.q.numpy()[1, 0] - frozen) > 1e-3


def test_capped_contact_iterations_stay_physical(device):
    """Three PADMM iterations a step (SolverConfig.max_iterations) instead of convergence: the box
    at rest and the six-bar on its box stay on the ground (within 1 mm of their converged heights
    after 0.1 s), the sliding box stays on the ground and stops, within 1.5x Coulomb's distance
    (measured 0.130 m instead of 0.102: the friction under-resolved): a cap costs accuracy, not
    stability."""
    capped = SolverConfig(max_iterations=3)
    for spec, index in ((_box(), 0), (_sixbar_on_a_box(), 0)):
        heights = []
        for config in (SolverConfig(), capped):
            model = pack_tree([spec], device=device, dt=1e-3, config=config)
            state = model.state()
            for _ in range(100):
                model.step(state)
            assert not model.diverged.any()
            heights.append(state.body_q.numpy()[0, index, 2])
        assert abs(heights[1] - heights[0]) < 1e-3, (spec.name, heights)
    model = pack_tree([_box(velocity=(1.0, 0.0, 0.0))], device=device, dt=1e-3, config=capped)
    state = model.state()
    for _ in range(400):
        model.step(state)
    coulomb = 1.0 / (2 * 0.5 * 9.81)
    assert 0.95 * coulomb < state.body_q.numpy()[0, 0, 0] < 1.5 * coulomb
    assert abs(state.body_q.numpy()[0, 0, 2] - 0.05) < 1e-3 and np.abs(state.body_qd.numpy()[0, 0]).max() < 1e-3
    assert model.work.iterations.numpy().max() <= 3


def test_a_box_that_leaves_the_ground_lands_from_a_fresh_penalty(device):
    """Each step's contact penalty starts where the world's last step left it, but not for contacts
    that carry no impulse over: a box at rest (its penalty settled below CONTACT_RHO), tossed up at
    1 m/s with three PADMM iterations a step from then on (too few for the penalty to adapt), is off
    the ground for 0.2 s (the carried penalty cleared), lands from CONTACT_RHO, and 0.4 s after the
    toss rests on the ground and is still, having risen to its toss's apex (5.1 cm) and no higher."""
    from engine.reduced.chains import CONTACT_RHO

    model = pack_tree([_box()], device=device, dt=1e-3)
    state = model.state()
    for _ in range(100):
        model.step(state)
    assert 0.0 < model.work.contact_rho.numpy()[0] < CONTACT_RHO
    model.config = dataclasses.replace(model.config, max_iterations=3)
    u = state.u.numpy()
    u[0, 2] = 1.0  # the root's centre-of-mass velocity, up
    state.u.assign(u)
    heights, flying, landed = [], 0, None
    for _ in range(400):
        model.step(state)
        heights.append(state.body_q.numpy()[0, 0, 2])
        contacts, rho = model.work.contact_count.numpy()[0], model.work.contact_rho.numpy()[0]
        if contacts == 0:
            flying += 1
            assert rho == 0.0
        elif flying and landed is None:
            landed = rho
    assert flying > 150 and landed == CONTACT_RHO
    assert abs(max(heights) - (0.05 + 1.0 / (2 * 9.81))) < 2e-3
    assert abs(heights[-1] - 0.05) < 1e-3 and np.abs(state.body_qd.numpy()[0, 0]).max() < 1e-2
    assert not model.diverged.any()


def test_independent_parts_of_one_world_move_as_if_alone(device):
    """A world of a fixed two-link pendulum, a free ball resting on the ground and a free ball
    falling (the balls in one collision group: the tree plan takes ground contacts only): each moves
    as it would alone (the pendulum's angles as the pendulum alone's, the resting ball still, the
    falling ball at z0 - g t^2 / 2), and the mass matrix couples none of them (its blocks between
    parts are zero)."""
    pend = chain(links=2).spec
    rest = Body("rest", 1.0, [1e-3] * 3, position=(2.0, 0.0, 0.04))
    fall = Body("fall", 0.5, [2e-4] * 3, position=(-2.0, 0.0, 0.5))
    spec = MechanismSpec(list(pend.bodies) + [rest, fall], list(pend.joints), ground=GroundPlane(),
                         shapes=[Shape("r", "sphere", "rest", size=(0.04,), collision_group=1),
                                 Shape("f", "sphere", "fall", size=(0.04,), collision_group=1)],
                         name="three_parts")
    model = pack_tree([spec, pend], device=device, dt=1e-3)
    state = model.state()
    model.step(state, record=True)
    M = model.work.matrix.numpy()[0]
    layout = model.layouts[0]
    part = [int(layout.sub_of[k]) if layout.kind[k] else -1 for k in range(layout.n)]  # -1: the fixed tree
    for a in range(layout.n):
        for b in range(layout.n):
            if part[a] != part[b]:
                assert M[a, b] == 0.0, (a, b)
    for _ in range(199):
        model.step(state)
    q, qd = state.body_q.numpy()[0], state.body_qd.numpy()[0]
    assert np.allclose(state.q.numpy()[0, :2], state.q.numpy()[1, :2], atol=1e-6, rtol=0)
    assert abs(q[2, 2] - 0.04) < 1e-4 and np.abs(qd[2]).max() < 1e-4 and abs(q[2, 0] - 2.0) < 1e-6
    assert abs(q[3, 2] - (0.5 - 0.5 * 9.81 * 0.2 ** 2)) < 1e-4 and abs(qd[3, 2] + 9.81 * 0.2) < 1e-4


def test_a_loop_joints_armature_and_damping_act_as_on_a_tree_joint(device):
    """Armature and damping on the joint that closes the four-bar's loop (a soft row on its rate)
    move it as the same joint does when it is a tree joint (a drive of zero gains puts it in the
    tree, where armature and damping enter the mass matrix): two first-order discretizations of
    the same motion, within 1e-4 m after 0.5 s at dt 1 ms (measured 1.2e-7) and 3x closer at dt
    0.25 ms unless within 2e-7 m already, while the motion without armature and damping is more
    than 1e-3 m away."""
    spec = fourbar().spec
    closing = chain_layout(spec).loops[0]
    heavy = dataclasses.replace(spec.joints[closing], armature=0.002, damping=0.01)
    soft = dataclasses.replace(spec, joints=[heavy if k == closing else j for k, j in enumerate(spec.joints)])
    tree = dataclasses.replace(soft, joints=[dataclasses.replace(heavy, drive=JointDrive(stiffness=0.0, damping=0.0))
                                             if k == closing else j for k, j in enumerate(spec.joints)])
    assert closing in chain_layout(soft).loops and closing not in chain_layout(tree).loops
    assert len(chain_layout(soft).soft) == 1
    gaps = []
    for dt in (1e-3, 2.5e-4):
        runs = [_chains_positions(s, 0.5, dt, device)[0] for s in (soft, tree, spec)]
        gaps.append(np.linalg.norm(runs[0] - runs[1], axis=1).max())
        assert np.linalg.norm(runs[0] - runs[2], axis=1).max() > 1e-3
    assert gaps[0] < 1e-4 and gaps[1] < max(gaps[0] / 3, 2e-7), gaps


def test_contacts_past_the_capacity_are_counted_and_shapes_limited(device):
    """A box on the ground with room for 2 contacts keeps 2 of its 4 corners and counts the other 2
    as dropped; more shapes on moving bodies than MAX_SHAPES are refused with a shape named."""
    model = pack_tree([_box()], device=device, dt=1e-3, contact_capacity=2)
    state = model.state()
    model.step(state)
    assert model.work.contact_count.numpy()[0] == 2 and model.work.contact_dropped.numpy()[0] == 2
    with pytest.raises(ValueError, match="contact_capacity must be a non-negative integer, got -1$"):
        pack_tree([_box()], device=device, contact_capacity=-1)
    body = Body("b", 1.0, [1e-3] * 3)
    many = MechanismSpec([body], [], ground=GroundPlane(), name="many",
                         shapes=[Shape(f"s{k}", "sphere", "b", size=(0.01,)) for k in range(MAX_SHAPES + 1)])
    with pytest.raises(ValueError, match=f"{MAX_SHAPES + 1} shapes on moving bodies .*at most {MAX_SHAPES}"):
        chain_layout(many)


def test_steps_with_more_contacts_than_the_tiles_hold_go_to_the_full_kernel(device):
    """The step kernel's contact tiles hold Tuning.tree_contact_working contacts, by default the most any world
    has at its initial pose (a box resting on the ground: its 4 corners; one dropped from 3 cm: none,
    so the least, 1); a step that finds more, within the capacity, is stepped again from its start
    by a second kernel with tiles for the full capacity. In one batch with tiles for 1 contact, a
    resting box (handed over every step), a dropped box and the six-bar dropped on its box (handed
    over from their landing on; the six-bar's angles move) and a four-bar without shapes (never)
    step bit for bit as with tiles for the full capacity throughout; a tree_contact_working below 1
    is refused."""
    assert pack_tree([_box()], device=device, dt=1e-3).contact_working == 4
    assert pack_tree([_box(height=0.08)], device=device, dt=1e-3).contact_working == 1
    sixbar_box = _sixbar_on_a_box()
    lifted = dataclasses.replace(sixbar_box.bodies[0], position=(0.0, 0.0, 0.13))
    batch = [_box(), _box(height=0.08), dataclasses.replace(sixbar_box, bodies=[lifted] + list(sixbar_box.bodies[1:])),
             fourbar().spec]
    models = [pack_tree(batch, device=device, dt=1e-3, config=SolverConfig().tuned(tree_contact_working=w))
              for w in (1, 4)]
    assert models[0].contact_working == 1 and models[0].tile_working < models[0].tile_contacts
    assert models[1].tile_working == models[1].tile_contacts  # one kernel
    states = [model.state() for model in models]
    steps = 150
    for _ in range(steps):
        for model, state in zip(models, states):
            model.step(state)
    redone = models[0].work.contact_redone.numpy()
    assert redone[0] == steps and 0 < redone[1] < steps and 0 < redone[2] < steps and redone[3] == 0
    assert not models[1].work.contact_redone.numpy().any()
    assert list(models[0].work.contact_count.numpy()) == [4, 4, 4, 0]
    angles = states[0].q.numpy()[2]
    assert np.abs(angles - models[0]._init["q"][2]).max() > 1e-3  # the six-bar's joints moved
    for name in ("q", "u", "root", "body_q", "body_qd"):
        assert np.array_equal(getattr(states[0], name).numpy(), getattr(states[1], name).numpy()), name
    assert np.array_equal(models[0].work.contact_impulse.numpy(), models[1].work.contact_impulse.numpy())
    assert abs(states[0].body_q.numpy()[1, 0, 2] - 0.05) < 1e-3  # the dropped box landed on its corners
    with pytest.raises(ValueError, match="Tuning.tree_contact_working"):
        SolverConfig().tuned(tree_contact_working=0)


def test_dr_legs_standing_matches_the_maximal_engine_converged_tightly():
    """DR Legs standing as in Newton's example (a floating pelvis, 12 PD drives, armature and
    damping on every joint, its feet's boxes on the ground): after 1 s at dt 10 ms our bodies are
    within 1e-4 m of the maximal-coordinate engine's at the same step size with its PADMM converged
    to 1e-9 (measured 1.9e-5 m, while the robot settles by 2.6 mm; at the maximal engine's default
    tolerances its pelvis creeps 1.3 cm in that second), loops closed within 1e-6 m. Its boxes in one
    collision group for both (the tree plan takes ground contacts only; with the pairs between its
    boxes, which never meet standing, the reference moves by 2.4e-5 m and the gap was 3.2e-5 m)."""
    from benchmarks.scenes import NEWTON_EXAMPLE_JOINTS, dr_legs, dr_legs_path, ground_contacts_only

    if dr_legs_path() is None:
        pytest.skip("the DR Legs asset is not on this machine; it is benchmark data kept outside the project")
    spec = ground_contacts_only(dr_legs(True, None, NEWTON_EXAMPLE_JOINTS).specs[0])
    tight = SolverConfig(tolerance=1e-9, relative_tolerance=1e-9, max_iterations=500)
    model = pack_worlds([spec], device="cpu", dt=1e-2, config=tight)
    stepper = Stepper(model, model.state(), model.control(), chunk=100)
    stepper.advance()
    reference = stepper.state.body_q.numpy()[0, :, :3]
    positions, chains, state = _chains_positions(spec, 1.0, 1e-2, "cpu")
    start = np.array([b.position for b in spec.bodies])
    assert np.linalg.norm(reference - start, axis=1).max() > 1e-3
    assert np.linalg.norm(positions - reference, axis=1).max() < 1e-4
    assert chains.work.contact_count.numpy()[0] == 8 and not chains.diverged.any()
    gauge = pack_worlds([spec], device="cpu")
    compute_metrics(gauge, state)
    assert gauge.work.violation_linear.numpy()[0] < 1e-6


def test_capsules_and_cylinders_rest_on_the_ground(device):
    """A capsule lying down (its two ends), a cylinder lying down (its caps' lowest rim points) and
    a cylinder standing up (its bottom cap's 4 rim points) set on the ground stay there: after
    0.3 s each body is within 1e-4 m of its resting height and still, on the contacts
    engine.collide.plane_point gives it within the margin (2, 2 and 4)."""
    turn = (0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5))  # the shape's axis (local z) along x
    cases = [("capsule", (0.03, 0.1), turn, 0.03, 2), ("cylinder", (0.05, 0.1), turn, 0.05, 2),
             ("cylinder", (0.05, 0.1), (0.0, 0.0, 0.0, 1.0), 0.1, 4)]
    specs = [MechanismSpec([Body("b", 1.0, [2e-3] * 3, position=(0.0, 0.0, h), orientation=q)], [],
                           shapes=[Shape("s", kind, "b", size=size)], ground=GroundPlane(), name=f"{kind}{k}")
             for k, (kind, size, q, h, _) in enumerate(cases)]
    model = pack_tree(specs, device=device, dt=1e-3)
    state = model.state()
    for _ in range(300):
        model.step(state)
    for w, (_, _, _, height, contacts) in enumerate(cases):
        assert abs(state.body_q.numpy()[w, 0, 2] - height) < 1e-4
        assert np.abs(state.body_qd.numpy()[w, 0]).max() < 1e-3
        assert model.work.contact_count.numpy()[w] == contacts


def test_the_packed_mass_matrix_holds_the_deepest_tree(device):
    """A hanging chain of MAX_COORDS links, each entry's ancestors all the ones before it: the packed
    mass matrix (row k: its k ancestors and itself) needs MAX_COORDS (MAX_COORDS + 1) / 2 entries,
    and its tile holds them; released from 30 degrees without damping, the chain keeps its kinetic
    plus potential energy (engine.metrics) within 1e-4 of what it can lose over 0.1 s at dt 0.1 ms
    (1.2e-5 on the CPU; the factor's off-diagonal entries 1 % off give 7e-4)."""
    from engine.reduced.chain_layout import _packed_rows

    scene = chain(links=MAX_COORDS)
    model = pack_tree([scene.spec], device=device, dt=1e-4)
    layout = model.layouts[0]
    level, starts = _packed_rows(layout.parent)
    assert layout.n == MAX_COORDS and list(level) == list(range(MAX_COORDS))
    assert starts[-1] == MAX_COORDS * (MAX_COORDS + 1) // 2
    assert model.packed_size >= starts[-1]
    assert np.array_equal(model.arrays.ancestor.numpy()[0, starts[-2]:starts[-1]], np.arange(MAX_COORDS))
    state, worst, available = _energy_error(scene, model, device, 10, 100)
    assert np.abs(state.q.numpy()[0, :MAX_COORDS] - layout.q0).max() > 1e-2  # it swung
    assert worst < 1e-4 * available


def test_stage_clocks_leave_the_step_unchanged(device):
    """ChainModel.step(stages=True) compiles clock readings into the step and nothing else: a box
    on the ground and a six-bar (contacts in one world, none in the other) stepped 20 times with
    and without them end bit for bit alike; the readings rise stage by stage, every stage has its
    cycles (the contact stages only from the box's world), and before any such step stage_cycles
    says so."""
    from engine.reduced.chain_stages import STAGES

    specs = [_box(), sixbar().spec]
    plain, timed = (pack_tree(specs, device=device, dt=1e-3) for _ in range(2))
    with pytest.raises(RuntimeError, match="stages=True"):
        timed.stage_cycles()
    states = [plain.state(), timed.state()]
    for _ in range(20):
        plain.step(states[0])
        timed.step(states[1], stages=True)
    for name in ("q", "u", "root", "body_q", "body_qd"):
        assert np.array_equal(getattr(states[0], name).numpy(), getattr(states[1], name).numpy()), name
    clock = timed.work.stage_clock.numpy()
    assert clock.shape == (2, len(STAGES) + 1)
    box_clock = clock[0]
    assert (box_clock > 0).all() and (np.diff(box_clock) >= 0).all()
    ran = clock[1] > 0
    contact_stages = [STAGES.index(s) + 1 for s in ("Y = M~^-1 J^T", "contact factor and PADMM")]
    assert not ran[contact_stages].any() and ran[[0, 1, len(STAGES)]].all()
    assert (np.diff(clock[1][ran]) >= 0).all()
    cycles = timed.stage_cycles()
    assert list(cycles) == list(STAGES) and all(c >= 0.0 for c in cycles.values())
