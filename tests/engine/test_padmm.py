"""PADMM against dense NumPy references: random bilateral problems and a saturated drive."""

import math

import numpy as np
import pytest
import warp as wp

from engine import Body, Joint, JointDrive, MechanismSpec, SolverConfig, Tuning, pack_worlds, rollout
from engine.config import MAXIMAL_RHO
from engine.model import UNBOUNDED
from engine.padmm import padmm_decide, solve_padmm


def random_problem(rng, rows, bodies, redundant):
    """J (rows x 6 bodies), block-diagonal M, free velocity; a redundant problem repeats rows."""
    J = rng.normal(size=(rows, 6 * bodies))
    if redundant:
        J[-2:] = J[:2] * np.array([[1.0], [-2.0]])  # consistent duplicates: rank rows - 2
    M = np.zeros((6 * bodies, 6 * bodies))
    for b in range(bodies):
        A = rng.normal(size=(3, 3))
        M[6 * b:6 * b + 3, 6 * b:6 * b + 3] = np.eye(3) * rng.uniform(0.5, 2.0)
        M[6 * b + 3:6 * b + 6, 6 * b + 3:6 * b + 6] = A @ A.T + 0.1 * np.eye(3)
    return J, M, rng.normal(size=6 * bodies)


@pytest.mark.parametrize("redundant", [False, True], ids=["full_rank", "redundant"])
def test_padmm_matches_dense_kkt(redundant, device):
    """The impulses of PADMM on random bilateral problems give the post-step velocities of the
    dense KKT system [[M, J^T], [J, 0]] to 1e-4 relative (and the multipliers, when unique)."""
    rng = np.random.default_rng(7 if redundant else 3)
    # 4 bodies welded to the world give a model with room for 24 rows per world
    spec = MechanismSpec([Body(f"b{k}", 1.0, (1, 1, 1)) for k in range(4)],
                         [Joint(f"j{k}", "fixed", None, f"b{k}") for k in range(4)])
    num_worlds = 3
    model = pack_worlds([spec] * num_worlds, device=device, config=SolverConfig(tolerance=1e-7, relative_tolerance=0.0,
                                                                                 max_iterations=300))
    R = model.max_rows
    problems = [random_problem(rng, rows, 3, redundant) for rows in (8, 12, 16)]
    delassus = np.tile(np.eye(R, dtype=np.float32), (num_worlds, 1, 1))
    precond, v_f = np.ones((num_worlds, R), np.float32), np.zeros((num_worlds, R), np.float32)
    lo, hi = np.zeros((num_worlds, R), np.float32), np.zeros((num_worlds, R), np.float32)
    counts = np.zeros(num_worlds, np.int32)
    for w, (J, M, u_free) in enumerate(problems):
        n = J.shape[0]
        D = J @ np.linalg.solve(M, J.T)
        P = 1.0 / np.sqrt(np.diag(D))
        delassus[w, :n, :n] = P[:, None] * D * P[None, :]
        precond[w, :n], v_f[w, :n] = P, P * (J @ u_free)
        lo[w, :n], hi[w, :n] = -UNBOUNDED, UNBOUNDED
        counts[w] = n
    work = model.work
    model.row_count.assign(counts)
    work.delassus.assign(delassus)
    work.row_precond.assign(precond)
    work.v_f.assign(v_f)
    work.lo.assign(lo)
    work.hi.assign(hi)
    lambda_out = wp.zeros((num_worlds, R), dtype=float, device=device)
    solve_padmm(model, wp.zeros((num_worlds, R), dtype=float, device=device), lambda_out)
    impulses = lambda_out.numpy().astype(np.float64)
    assert work.converged.numpy().all()
    for w, (J, M, u_free) in enumerate(problems):
        n = J.shape[0]
        kkt = np.block([[M, J.T], [J, np.zeros((n, n))]])
        solution = np.linalg.lstsq(kkt, np.concatenate([M @ u_free, np.zeros(n)]), rcond=None)[0]
        u_ref, lam_ref = solution[:M.shape[0]], -solution[M.shape[0]:]
        u = u_free + np.linalg.solve(M, J.T @ impulses[w, :n])
        assert np.linalg.norm(u - u_ref) < 1e-4 * np.linalg.norm(u_ref)
        assert np.abs(J @ u).max() < 1e-4 * np.abs(J @ u_free).max()
        if not redundant:
            assert np.linalg.norm(impulses[w, :n] - lam_ref) < 1e-4 * np.linalg.norm(lam_ref)


def test_saturated_velocity_drive_applies_its_effort_limit(device):
    """A wheel driven towards 100 rad/s with a 0.2 N m effort limit accelerates at exactly
    limit / (I + armature) (the box-bounded drive row is clamped at its bound)."""
    inertia_axis, armature, limit = 0.05, 0.01, 0.2
    wheel = Body("wheel", 1.0, (0.05, 0.05, inertia_axis))
    motor = Joint("motor", "revolute", None, "wheel", axis=(0, 0, 1), armature=armature,
                  drive=JointDrive(damping=50.0, target_velocity=100.0, effort_limit=limit))
    model = pack_worlds([MechanismSpec([wheel], [motor], gravity=(0, 0, 0))], device=device)
    dt, steps = 1e-3, 500
    _, state = rollout(model, model.state(), model.control(), steps, dt=dt, record_every=steps)
    omega = state.body_qd.numpy()[0, 0, 5]
    expected = limit / (inertia_axis + armature) * dt * steps
    assert abs(omega - expected) < 1e-3 * expected


def test_stiff_position_drive_holds_target(device):
    """An implicit PD drive (stiffness 1e4) holds a pendulum at its 30 degree target against
    gravity: the static torque balance k (target - q) = m g (L/2) sin q is met."""
    length = 0.4
    mass = length
    rod = Body("rod", mass, np.diag([1e-5, mass * length**2 / 12, mass * length**2 / 12]), com=(0, 0, -length / 2))
    target = math.radians(30.0)
    stiffness = 1.0e4
    joint = Joint("hip", "revolute", None, "rod", axis=(0, 1, 0),
                  drive=JointDrive(stiffness=stiffness, damping=20.0, target_position=target))
    model = pack_worlds([MechanismSpec([rod], [joint])], device=device)
    _, state = rollout(model, model.state(), model.control(), 3000, dt=1e-3, record_every=3000)
    com = state.body_q.numpy()[0, 0, :3]
    q = math.atan2(-com[0], -com[2])  # rotation about +y moves the hanging COM towards -x
    residual = stiffness * (target - q) - mass * 9.81 * length / 2 * math.sin(q)
    assert abs(residual) < 1e-3 * stiffness * 1e-2
    assert abs(q - target) < 1e-3


def _mixed_problem_batch(device, cap_joint_penalty: bool, seed: int = 11):
    """Three worlds of random problems mixing bilateral joint rows (unbounded) with box-bounded
    drive rows, some of which end at their bounds; every world starts from rho = 1 (as after
    contact steps: the penalty persists between steps). Returns the model, the dense preconditioned
    problems and the preconditioned solution PADMM returns."""
    from engine.model import ROW_DYNAMICS, ROW_LINEAR

    rng = np.random.default_rng(seed)
    spec = MechanismSpec([Body(f"b{k}", 1.0, (1, 1, 1)) for k in range(4)],
                         [Joint(f"j{k}", "fixed", None, f"b{k}") for k in range(4)])
    num_worlds = 3
    model = pack_worlds([spec] * num_worlds, device=device,
                        config=SolverConfig(tolerance=1e-6, relative_tolerance=0.0, max_iterations=2000,
                                            tuning=Tuning(cap_joint_penalty=cap_joint_penalty, stall_ratio=0.0)))
    R = model.max_rows
    delassus = np.tile(np.eye(R, dtype=np.float32), (num_worlds, 1, 1))
    v_f = np.zeros((num_worlds, R), np.float32)
    lo, hi = np.zeros((num_worlds, R), np.float32), np.zeros((num_worlds, R), np.float32)
    kinds = np.full((num_worlds, R), ROW_LINEAR, np.int32)
    counts = np.zeros(num_worlds, np.int32)
    problems = []
    for w, rows in enumerate((10, 14, 18)):
        J, M, u_free = random_problem(rng, rows, 3, False)
        D = J @ np.linalg.solve(M, J.T)
        P = 1.0 / np.sqrt(np.diag(D))
        A = P[:, None] * D * P[None, :]
        # soft directions, as long loops of light links give: scale two eigenvalues down
        values, vectors = np.linalg.eigh(A)
        values[:2] *= 1e-3
        A = (vectors * values) @ vectors.T
        b = (P * (J @ u_free)).astype(np.float64)
        box = np.arange(rows) % 3 == 0  # every third row a drive bounded by +-0.3 (preconditioned)
        delassus[w, :rows, :rows] = A
        v_f[w, :rows] = b
        lo[w, :rows] = np.where(box, -0.3, -UNBOUNDED)
        hi[w, :rows] = np.where(box, 0.3, UNBOUNDED)
        kinds[w, :rows] = np.where(box, ROW_DYNAMICS, ROW_LINEAR)
        counts[w] = rows
        problems.append((A.astype(np.float32).astype(np.float64), b.astype(np.float32).astype(np.float64), box))
    work = model.work
    model.row_count.assign(counts)
    model.row_kind.assign(kinds)
    model.has_unilateral_or_drive_rows = True  # the batch's flag, as pack_worlds sets it for drive rows
    work.delassus.assign(delassus)
    work.row_precond.assign(np.ones((num_worlds, R), np.float32))
    work.v_f.assign(v_f)
    work.lo.assign(lo)
    work.hi.assign(hi)
    work.rho.assign(np.ones(num_worlds, np.float32))
    lambda_out = wp.zeros((num_worlds, R), dtype=float, device=device)
    solve_padmm(model, wp.zeros((num_worlds, R), dtype=float, device=device), lambda_out)
    return model, problems, lambda_out.numpy().astype(np.float64)


def test_capped_joint_penalty_solves_mixed_problems_in_fewer_iterations(device):
    """Joint rows with their own penalty (Tuning.cap_joint_penalty, free_rho):
    the same solution of the box-constrained QP min 1/2 x^T A x + b^T x (its KKT conditions
    checked in NumPy: zero gradient on the joint rows and on drive rows inside their box, the
    gradient's sign at a bound) as with one rho for all rows, in far fewer PADMM iterations."""
    iterations = {}
    for cap in (True, False):
        model, problems, x = _mixed_problem_batch(device, cap)
        assert model.work.converged.numpy().all(), cap
        iterations[cap] = model.work.iterations.numpy()
        at_bound = 0
        for w, (A, b, box) in enumerate(problems):
            n = len(b)
            xw = x[w, :n]
            gradient = A @ xw + b
            scale = np.abs(b).max()
            low, high = box & (xw <= -0.3 + 1e-5), box & (xw >= 0.3 - 1e-5)
            inside = ~(low | high)
            at_bound += int(np.sum(low | high))
            assert np.abs(gradient[inside]).max() < 1e-3 * scale, (cap, w)
            assert (gradient[low] > -1e-3 * scale).all() and (gradient[high] < 1e-3 * scale).all(), (cap, w)
            assert np.all(np.abs(xw[box]) <= 0.3 + 1e-6)
        assert at_bound > 0  # the boxes bind: a mixed problem, not a linear one
    assert np.all(iterations[True] * 2 <= iterations[False]), iterations  # here 12, 24, 25 against 49, 50, 76


@wp.kernel
def _decide_until_stop(residuals: wp.array(dtype=float), stall_ratio: float, out: wp.array(dtype=wp.int32),
                       rho: wp.array(dtype=float), active: wp.array(dtype=wp.int32),
                       converged: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32),
                       momentum: wp.array(dtype=float), momentum_beta: wp.array(dtype=float),
                       merit: wp.array(dtype=float), needs_factor: wp.array(dtype=wp.int32),
                       residual_primal: wp.array(dtype=float), residual_dual: wp.array(dtype=float),
                       residual_complementarity: wp.array(dtype=float), demote: wp.array(dtype=wp.int32),
                       tolerance: wp.array(dtype=float), stall_reference: wp.array(dtype=float)):
    for k in range(residuals.shape[0]):
        r = residuals[k]
        if padmm_decide(0, r, r, 0.0, r, 1.0, 1.0, residuals.shape[0], 0.0, 4, 0, 0, tolerance, rho, active, converged,
                        iterations, momentum, momentum_beta, merit, needs_factor, residual_primal, residual_dual,
                        residual_complementarity, demote, stall_ratio, stall_reference) != 0:
            out[0] = iterations[0]
            out[1] = converged[0]
            return


@pytest.mark.parametrize("decay, stall_ratio, stops_at", [(0.95, 0.5, 20), (0.95, 0.6, 200), (0.9, 0.5, 200),
                                                        (0.95, 0.0, 200)])
def test_stall_ratio_stops_a_world_whose_residual_falls_too_slowly(decay, stall_ratio, stops_at):
    """Tuning.stall_ratio: residuals falling by ``decay`` per iteration fall by decay^10 over
    a window of 10 (0.95: 0.60; 0.9: 0.35). A world stops, unconverged, at the first check from
    iteration 20 on where they did not fall below stall_ratio times the last check's value; else it
    runs to the cap (200 here, tolerance 0: never converged); 0 turns the rule off."""
    from engine.padmm import STALL_WINDOW

    assert STALL_WINDOW == 10
    residuals = wp.array((decay ** np.arange(200)).astype(np.float32), dtype=float, device="cpu")
    out = wp.zeros(2, dtype=wp.int32, device="cpu")

    def one(value, dtype=float):
        return wp.array([value], dtype=dtype, device="cpu")

    arrays = [one(1e-3), one(1, wp.int32), one(0, wp.int32), one(0, wp.int32), one(1.0), one(0.0), one(1e30),
              one(0, wp.int32), one(0.0), one(0.0), one(0.0), one(0, wp.int32), one(0.0), one(0.0)]
    wp.launch(_decide_until_stop, dim=1, device="cpu", inputs=[residuals, stall_ratio, out, *arrays])
    assert out.numpy().tolist() == [stops_at, 0]


def test_stall_ratio_cuts_the_tail_of_random_walkers():
    """Eight random walkers (two topologies, contacts), 60 steps at dt 2 ms: with stall_ratio 0.5
    the largest world's iterations per step fall (no step needs more than the rule allows it to
    stall at), no world diverges; off, the same batch runs longer tails."""
    from benchmarks.scenes import walkers

    specs = walkers(8).specs
    largest = {}
    for ratio in (0.0, 0.5):
        model = pack_worlds(specs, device="cpu", dt=2e-3, config=SolverConfig(tuning=Tuning(stall_ratio=ratio)))
        trace, final = rollout(model, model.state(), model.control(), 60, record_every=1)
        assert np.isfinite(final.body_q.numpy()).all() and model.work.diverged.numpy().sum() == 0
        largest[ratio] = trace.iterations.max(axis=1)
    assert largest[0.5].sum() < largest[0.0].sum(), (largest[0.5].sum(), largest[0.0].sum())


def test_stall_ratio_is_validated():
    with pytest.raises(ValueError, match="stall_ratio"):
        SolverConfig(tuning=Tuning(stall_ratio=1.0))


def test_free_rho_is_validated():
    with pytest.raises(ValueError, match="free_rho"):
        SolverConfig(tuning=Tuning(free_rho=0.0))


@pytest.mark.parametrize("free_rho", [2e-4, 5e-3])
def test_projection_factor_of_a_driven_linkage_takes_the_free_rows_penalty(free_rho):
    """A batch with drive rows refactors for the position projection (its drive rows taken out):
    every row of that factor is shifted by eta + Tuning.free_rho, the penalty the joint rows
    had in the PADMM factor; with cap_joint_penalty off, by eta + the initial rho."""
    from morphopt.families import load_family
    from morphopt.linkage.to_spec import to_spec

    family = load_family("jansen_leg")
    spec = to_spec(family.generate(family.space.default()))
    assert any(j.drive is not None for j in spec.joints)
    for cap in (True, False):
        config = SolverConfig(tuning=Tuning(step_kernel="staged", free_rho=free_rho, cap_joint_penalty=cap))
        model = pack_worlds([spec] * 2, device="cpu", dt=1e-3, config=config)
        rollout(model, model.state(), model.control(), 3)
        n = int(model.row_count.numpy()[0])
        expected = config.tuning.eta + (free_rho if cap else MAXIMAL_RHO)  # the maximal plan's starting rho
        assert np.allclose(model.work.row_shift.numpy()[:, :n], expected, rtol=1e-6), cap


@pytest.mark.parametrize("kernel", ["fused", "staged"])
@pytest.mark.parametrize("start_rho", ["initial", "minimum"])
def test_a_redundant_linkage_at_tight_tolerance_keeps_its_joint_rows_penalty(kernel, start_rho):
    """A double parallelogram (one redundant crank: a singular Delassus matrix) at tolerance 1e-9,
    which float32 cannot reach, so PADMM runs to its cap. Its rows are all free joint rows, which
    keep their own penalty (Tuning.free_rho, engine.padmm.row_penalty) and do not take part in the penalty update
    (their primal residual is zero): the world's rho stays where it is, the factor keeps its shift
    eta + free_rho, and the crank follows scipy's motion as closely as at the default tolerance
    (6.5e-6 m over 0.5 s). Also from a world whose rho was driven to RHO_MIN before (as contacts or
    limits can). Before, the update drove the joint rows' penalty to RHO_MIN and the crank drifted
    1.9e-4 m (fused) and 9e-4 m (staged) in 0.5 s."""
    from benchmarks.stress import crank_reference, double_parallelogram, parallel_linkage_constants
    from engine.padmm import RHO_MIN

    theta0, speed = -1.2, 2.0
    spec = double_parallelogram(theta0, speed)
    config = SolverConfig(tolerance=1e-9, relative_tolerance=0.0, max_iterations=300).tuned(step_kernel=kernel)
    model = pack_worlds([spec], device="cpu", dt=1e-3, config=config)
    rho0 = MAXIMAL_RHO if start_rho == "initial" else float(RHO_MIN)
    model.work.rho.fill_(rho0)
    trace, _ = rollout(model, model.state(), model.control(), 500, record_every=10)
    reference = crank_reference(theta0, speed, trace.time, *parallel_linkage_constants(spec))
    expected = np.stack([np.cos(reference), np.zeros_like(reference), -np.sin(reference)], axis=1)
    error = np.linalg.norm(trace.points[:, 0, 0] - expected, axis=1).max()
    assert model.work.rho.numpy()[0] == pytest.approx(rho0)
    assert error < 2e-5, error
    if kernel == "staged":  # every row of this linkage is a free joint row: shift eta + free_rho
        n = int(model.row_count.numpy()[0])
        assert np.allclose(model.work.row_shift.numpy()[0, :n], config.tuning.eta + config.tuning.free_rho, rtol=1e-6)
