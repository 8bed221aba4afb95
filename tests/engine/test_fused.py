"""The fused step (engine.fused: a whole step per world in one warp) against the staged step
(engine.step: one kernel per stage, tile Cholesky, captured PADMM loop): two implementations of the
same method must give the same trajectories, for every feature the fused path accepts."""

import dataclasses

import numpy as np
import pytest

import warp as wp

from engine import SolverConfig, Tuning, pack_worlds, step
from engine.fused import INVERSE_MAX_ROWS, SHARE_JOINT_PARTS, fused_block, fused_inverse
from engine.linalg.dense import cholesky_lanes, cholesky_solve_lanes, inverse_solve_lanes, triangular_inverse_lanes
from engine.linalg.lanes import block_sync
from engine.model import ROW_LIMIT, ROW_LINEAR
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


# The projection's velocity update (SHAKE) divides each position correction by dt, so float32
# rounding of the poses reaches the twists as noise of ~1e-7 m / dt: two implementations whose
# substitutions sum in different orders agree to rounding with it off, and to that noise with it on.
STRICT = SolverConfig(tuning=Tuning(projection_velocity_update=False))


def trajectory(specs, kind, steps, config=None, control_fn=None, device="cpu", inverse=None, sharing=None):
    config = (config or STRICT).tuned(step_kernel=kind, fused_inverse=inverse, fused_sharing=sharing)
    model = pack_worlds(specs, device=device, config=config, dt=1e-3)
    assert model.step_kernel == kind and (model.fused_inverse, model.fused_sharing) == (inverse, sharing)
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


# fused step variants the CPU would not choose by itself: (solve through L^-1, a joint's rows split
# over the lanes one part each; engine.fused.SHARE_JOINT_PARTS); on a GPU both are on for small
# batches (and each body's row sums shared by a group of lanes, which needs a warp: covered by the
# device test below)
VARIANTS = {"substitution": (False, 0), "inverse": (True, 0), "split_joints": (False, int(SHARE_JOINT_PARTS))}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("integrator", ["euler", "moreau"])
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_fused_step_matches_staged_step(case, integrator, variant):
    """Same poses, twists, impulses and PADMM iterations over 200 steps (both run on the CPU; the
    lanes' substitutions or products with L^-1 and the tile Cholesky solve may differ in rounding
    only: poses within 2e-6, about 16 float32 ulps of 1, after 200 steps of a contact scene). The
    rows computed a part of a joint at a time are the same rows (drives, limits, armature rows and
    every joint type of the cases included)."""
    specs = CASES[case]()
    config = dataclasses.replace(STRICT, integrator=integrator)
    inverse, sharing = VARIANTS[variant]
    staged_model, staged = trajectory(specs, "staged", 200, config)
    fused_model, fused = trajectory(specs, "fused", 200, config, inverse=inverse, sharing=sharing)
    for name, tolerance in (("body_q", 2e-6), ("body_qd", 1e-5), ("row_lambda", 1e-5)):
        a, b = getattr(staged, name).numpy(), getattr(fused, name).numpy()
        assert np.all(np.isfinite(b)), name
        assert np.abs(a - b).max() <= tolerance * max(1.0, np.abs(a).max()), (case, name, np.abs(a - b).max())
    np.testing.assert_array_equal(staged_model.iterations_seen, fused_model.iterations_seen)


def test_fused_projection_factor_takes_the_free_rows_penalty():
    """With drive rows the projection refactors its bilateral block, shifted by eta + free_rho in
    both step kernels (engine.integrate.projection_penalty). At a large free_rho (5e-2: heavily
    damped Gauss-Newton steps) the fused and staged Jansen legs keep the same poses to 1e-6 over
    200 steps (1.2e-7 here); a fused factor shifted by eta + rho_init instead parts them by 3e-6."""
    specs = CASES["jansen_drive"]()
    config = STRICT.tuned(free_rho=5e-2)
    staged_model, staged = trajectory(specs, "staged", 200, config)
    fused_model, fused = trajectory(specs, "fused", 200, config)
    assert np.abs(staged.body_q.numpy() - fused.body_q.numpy()).max() < 1e-6
    np.testing.assert_array_equal(staged_model.iterations_seen, fused_model.iterations_seen)


@pytest.mark.parametrize("inverse", [False, True])
def test_fused_penalty_updates_refactor_like_the_staged_path(inverse):
    """With a penalty update every iteration and a tight tolerance (many refactorizations per
    step, joint limits active; with ``inverse`` L^-1 formed again after each) both paths still
    agree and use the same iterations. One penalty for all rows (cap_joint_penalty off): the joint
    rows' zero primal residual then drives it down; with their own penalty they do not move it."""
    config = dataclasses.replace(STRICT, tolerance=1e-9, relative_tolerance=0.0, max_iterations=40).tuned(
        rho_update_interval=1, cap_joint_penalty=False)
    specs = CASES["limits"]() + CASES["jansen_drive"]()[:1]
    staged_model, staged = trajectory(specs, "staged", 100, config)
    fused_model, fused = trajectory(specs, "fused", 100, config, inverse=inverse)
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
    assert pack_worlds([fourbar().spec, chain().spec], device="cpu").step_kernel == "fused"  # 56 rows
    assert pack_worlds([fourbar().spec, chain(links=13).spec], device="cpu").step_kernel == "staged"  # 72 > 64
    walker = CONTACT_SCENES["walker"]().spec
    assert pack_worlds([walker], device="cpu").step_kernel == "staged"
    with pytest.raises(ValueError, match="step_kernel='fused'.*contacts"):
        pack_worlds([walker], device="cpu", config=SolverConfig(tuning=Tuning(step_kernel="fused")))
    with pytest.raises(ValueError, match="step_kernel"):
        SolverConfig(tuning=Tuning(step_kernel="megakernel"))


@wp.kernel(enable_backward=False)
def factor_and_solve(n: wp.array(dtype=wp.int32), sigma: float, sigma_free: float, bilateral_only: int,
                     row_kind: wp.array2d(dtype=wp.int32), row_free: wp.array2d(dtype=wp.int32),
                     matrix: wp.array3d(dtype=float),
                     rhs: wp.array2d(dtype=float), x: wp.array2d(dtype=float), x_inverse: wp.array2d(dtype=float)):
    world, lane = wp.tid()
    a = wp.tile_load(matrix[world], shape=(48, 48), storage="shared")
    lower = wp.tile_zeros(shape=(48, 48), dtype=float, storage="shared")
    acc = wp.tile_zeros(shape=48, dtype=float, storage="shared")
    sol = wp.tile_zeros(shape=48, dtype=float, storage="shared")
    block_sync()
    cholesky_lanes(world, lane, wp.block_dim(), n[world], sigma, sigma_free, bilateral_only, row_kind, row_free, a,
                   lower)
    cholesky_solve_lanes(world, lane, wp.block_dim(), n[world], lower, rhs, x, acc, sol)
    inverse = wp.tile_zeros(shape=(48, 48), dtype=float, storage="shared")
    block_sync()
    triangular_inverse_lanes(lane, wp.block_dim(), n[world], lower, inverse)
    inverse_solve_lanes(world, lane, wp.block_dim(), n[world], inverse, rhs, x_inverse, acc, sol)


@pytest.mark.parametrize("bilateral_only", [0, 1])
def test_lane_factor_and_solve_match_numpy(device, bilateral_only):
    """The fused step's factor, its substitutions and its solve through G = L^-1 (lanes sharing
    columns; one lane on the CPU, a warp on a GPU) against NumPy on random SPD systems of several
    sizes, with the bilateral-only masking of the projection (non-bilateral rows and columns
    replaced by the identity) and the PADMM factor's shifts (sigma_free on the rows flagged free,
    sigma on the others)."""
    rng = np.random.default_rng(3)
    sizes, R, sigma, sigma_free = [1, 7, 24, 33, 48], 48, 0.05, 0.02
    free = (rng.uniform(size=(len(sizes), R)) < 0.5).astype(np.int32)
    matrices = np.zeros((len(sizes), R, R), np.float32)
    kinds = np.full((len(sizes), R), ROW_LINEAR, np.int32)
    rhs = np.zeros((len(sizes), R), np.float32)
    expected = []
    for w, n in enumerate(sizes):
        a = rng.normal(size=(n, n))
        spd = a @ a.T / n + 0.1 * np.eye(n)
        matrices[w, :n, :n] = spd
        kinds[w, : n : 3] = ROW_LIMIT
        rhs[w, :n] = rng.normal(size=n)
        used = spd.copy()
        if bilateral_only:
            keep = kinds[w, :n] == ROW_LINEAR
            used = np.where(np.outer(keep, keep), spd, np.eye(n))
        shift = np.where(free[w, :n] != 0, sigma_free, sigma)
        expected.append(np.linalg.solve(used + np.diag(shift), rhs[w, :n].astype(np.float64)))
    arrays = [wp.array(sizes, dtype=wp.int32, device=device), wp.array(kinds, device=device),
              wp.array(matrices, device=device), wp.array(rhs, device=device),
              wp.zeros((len(sizes), R), dtype=float, device=device),
              wp.zeros((len(sizes), R), dtype=float, device=device)]
    lanes = 64 if wp.get_device(device).is_cuda else 1  # two warps: the lanes' strides cross a warp
    wp.launch_tiled(factor_and_solve, dim=[len(sizes)], block_dim=lanes, device=device,
                    inputs=[arrays[0], sigma, sigma_free, bilateral_only, arrays[1], wp.array(free, device=device),
                            arrays[2], arrays[3], arrays[4], arrays[5]])
    for x in (arrays[4].numpy(), arrays[5].numpy()):
        for w, n in enumerate(sizes):
            np.testing.assert_allclose(x[w, :n], expected[w], rtol=2e-4, atol=2e-4 * np.abs(expected[w]).max())


@pytest.mark.parametrize("batch", ["mixed", "small"])
def test_fused_step_on_the_device_matches_the_staged_step(device, batch):
    """On a GPU the fused step's lanes share a world (barriers between stages): it must still give
    the staged step's trajectories (rounding apart) on a batch of mixed linkages and drives (48
    rows: substitutions), and on one of at most 32 rows (on a GPU: solves through L^-1, formed
    again after every penalty update and projection refactor; the projection's rounding skip)."""
    if batch == "mixed":
        specs, config = CASES["mixed"]() + CASES["jansen_drive"]()[:1] + CASES["limits"]()[:1], STRICT
    else:
        specs = CASES["limits"]()[:1] + CASES["armature"]()[:1] + CASES["fourbar"]()[:1]
        config = STRICT.tuned(rho_update_interval=1)
    staged_model, staged = trajectory(specs, "staged", 100, config, device=device)
    fused_model, fused = trajectory(specs, "fused", 100, config, device=device)
    assert fused_model.fused_block == fused_block(device) == (32 if wp.get_device(device).is_cuda else 1)
    small = fused_model.max_rows <= INVERSE_MAX_ROWS
    assert small == (batch == "small")
    assert fused_inverse(device, fused_model.max_rows) == (small and wp.get_device(device).is_cuda)
    scale = np.abs(staged.body_q.numpy()).max()
    assert np.abs(staged.body_q.numpy() - fused.body_q.numpy()).max() < 1e-5 * scale
    a, b = staged.row_lambda.numpy(), fused.row_lambda.numpy()
    assert np.abs(a - b).max() < 1e-4 * np.abs(a).max()
    mean_staged = np.mean(staged_model.iterations_seen)
    assert abs(np.mean(fused_model.iterations_seen) - mean_staged) <= 0.05 * mean_staged


def test_default_projection_velocity_update_keeps_the_paths_within_its_noise():
    """With the SHAKE velocity update on every projection, poses agree to 1e-4 m and twists to 1 %
    over 200 steps: the update turns pose rounding into twist noise, but neither path drifts from
    the other. (The default rounding floor of that update, a threshold, is off here: the two paths
    may fall on either side of it; tests/engine/test_projection_floor.py covers it on both.)"""
    for case in ("fourbar", "jansen_drive", "armature"):
        for integrator in ("euler", "moreau"):
            config = SolverConfig(integrator=integrator, tuning=Tuning(projection_velocity_floor=0.0))
            _, staged = trajectory(CASES[case](), "staged", 200, config)
            _, fused = trajectory(CASES[case](), "fused", 200, config)
            assert np.abs(staged.body_q.numpy() - fused.body_q.numpy()).max() < 1e-4, (case, integrator)
            a, b = staged.body_qd.numpy(), fused.body_qd.numpy()
            assert np.abs(a - b).max() < 1e-2 * np.abs(a).max(), (case, integrator)


def test_body_sum_groups_only_with_whole_warps():
    """The body sums' lane groups shuffle within warps: engine.fused.sharing_used drops them on
    the CPU and for blocks that are not whole warps, keeps what else was asked."""
    from types import SimpleNamespace

    from engine.fused import SHARE_BODY_SUMS, sharing_used

    both = int(SHARE_JOINT_PARTS) | int(SHARE_BODY_SUMS)
    gpu = SimpleNamespace(is_cuda=True)
    assert sharing_used(SimpleNamespace(device=gpu, fused_sharing=both, fused_block=32)) == both
    assert sharing_used(SimpleNamespace(device=gpu, fused_sharing=both, fused_block=64)) == both
    assert sharing_used(SimpleNamespace(device=gpu, fused_sharing=both, fused_block=48)) == int(SHARE_JOINT_PARTS)
    model = pack_worlds([fourbar().spec], device="cpu", config=SolverConfig().tuned(fused_sharing=both))
    assert sharing_used(model) == int(SHARE_JOINT_PARTS)
    assert sharing_used(pack_worlds([fourbar().spec], device="cpu")) == 0


def test_shuffled_reductions_only_for_one_warps_first_lanes():
    """engine.fused.warp_lanes: the fused step's sums and maxima over a world's rows take warp
    shuffles only for blocks of 2 to 32 threads that are powers of two (one warp's first lanes);
    one thread (the CPU) needs no reduction, and other blocks keep the tile reductions."""
    from engine.fused import warp_lanes

    assert [warp_lanes(b) for b in (1, 2, 4, 8, 16, 32)] == [False, True, True, True, True, True]
    assert not any(warp_lanes(b) for b in (3, 12, 48, 64))
