"""The walker benchmarks run end to end at tiny sizes and report what they promise."""

import json
import pathlib

import numpy as np
import pytest

from benchmarks import spec_build, walker_precision, walker_steps, walker_study


def test_walker_steps_reports_a_finite_batch_of_three_leg_walkers(tmp_path, capsys):
    assert walker_steps.main(["--device", "cpu", "--worlds", "2", "--warmup", "10", "--steps", "10",
                              "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "walker_steps_cpu.json").read_text())
    assert result == json.loads(capsys.readouterr().out)
    assert result["worlds"] == 2 and result["legs_per_side"] == 3 and result["linear_solver"] == "sparse"
    assert result["rows"] > 128 and result["nan_worlds"] == 0
    assert result["ms_per_step"] > 0 and result["padmm_iterations_mean"] >= 1
    assert set(result["stage_ms"]) == {"kinematics", "collision", "dual_problem", "padmm", "integrate", "projection"}


def test_walker_precision_takes_final_poses_at_the_nominal_duration():
    """A step size that does not divide the duration (dt 3 ms, records every 21 ms, last at 1.008 s)
    is compared at 1.0 s: points on a straight line at 0.3 m/s land on the line's point at 1.0 s."""
    time = np.arange(49) * 0.021
    path = np.stack([np.stack([0.3 * time, np.zeros_like(time), 0.5 + 0 * time], axis=1)] * 2, axis=1)  # (T, 2, 3)
    final = walker_precision.pose_at(time, path, 1.0)
    np.testing.assert_allclose(final, [[0.3, 0.0, 0.5]] * 2, atol=1e-12)
    np.testing.assert_allclose(walker_precision.pose_at(time, path, time[-1]), path[-1], atol=1e-12)


def test_walker_precision_compares_settings_with_the_reference(tmp_path):
    assert walker_precision.main(["--device", "cpu", "--worlds", "2", "--duration", "0.04", "--only", "default",
                                  "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "walker_precision_cpu.json").read_text())
    rows = {r["setting"]: r for r in report["settings"]}
    assert set(rows) == {"reference", "default"}
    assert rows["reference"]["speed_error_median"] == 0.0  # the reference against itself
    assert np.isfinite(rows["default"]["speed_error_median"]) and rows["default"]["diverged"] == 0
    assert rows["default"]["joint_separation_max"] < 1e-3
    assert (tmp_path / "walker_precision_cpu.png").stat().st_size > 1000


def test_benchmark_runner_quick_fourbar_writes_results_with_a_float64_reference(tmp_path):
    """python -m benchmarks.run --quick on the CPU: throughput and work-precision rows with the
    promised fields (throughput "default": engine.pack's plan, the tree for the four-bar, with
    "maximal" beside it; the sweep in maximal coordinates); the default setting's trajectory stays
    within 1e-5 m of MuJoCo's float64 RK4 reference (an independent simulator), a 4x larger step is
    measurably worse, and the files exist."""
    import json

    from benchmarks.run import main

    assert main(["--device", "cpu", "--quick", "--only", "fourbar", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "fourbar.json").read_text())
    assert result["reference"]["engine"].startswith("mujoco C")
    assert {r["num_worlds"] for r in result["throughput"]} == {1, 8}
    plans = [(r["label"], r["num_worlds"], r["coordinates"]) for r in result["throughput"]]
    assert plans[:4] == [("default", 1, "grounded"), ("maximal", 1, "maximal"), ("default", 8, "grounded"),
                         ("maximal", 8, "maximal")]
    assert all(r["coordinates"] == "maximal" for r in result["precision"]
               if "reduced" not in r["label"] and "grounded" not in r["label"])
    for row in result["throughput"] + result["precision"]:
        assert row["world_steps_per_s"] > 0 and row["diverged_worlds"] == 0
        assert row["loop_error_m"] < 1e-5 and row["energy_drift_rel"] < 1e-2
    rows = {r["label"]: r for r in result["precision"]}
    assert rows["default"]["step_kernel"] == "fused" and rows["staged kernels"]["step_kernel"] == "staged"
    assert rows["default"]["trajectory_error_m"] < 1e-5
    assert rows["dt x4"]["trajectory_error_m"] > 10 * rows["default"]["trajectory_error_m"]
    for ext in ("csv", "png"):
        assert (tmp_path / f"fourbar.{ext}").stat().st_size > 0
    # memory: the engine's arrays grow with the batch (the CPU has no memory pool to read)
    for label in ("default", "maximal"):
        memory = {r["num_worlds"]: r["engine_arrays_mb"] for r in result["throughput"] if r["label"] == label}
        assert 0 < memory[1] < memory[8]
    assert all(r["device_memory_mb"] is None for r in result["throughput"])


def test_benchmark_runner_times_a_scenes_variants_at_its_largest_batch(tmp_path, monkeypatch):
    """A declared variant (other solver settings, maximal coordinates unless it names others) gets
    its own throughput row at the largest batch, labelled, with its settings and its measured loop
    error: without the projection (Baumgarte feedback instead) the four-bar's loops open by more
    than with it (the "maximal" row: the default settings in maximal coordinates)."""
    import dataclasses
    import json

    from benchmarks import run, scenes

    variant = dict(label="no projection", config=dict(position_iterations=0, baumgarte=0.01,
                                                      tuning=dict(projection_velocity_update=False)))
    declared = dataclasses.replace(scenes.SCENES_DECLARED["fourbar"], duration=0.0, variants=[variant])
    monkeypatch.setitem(run.SCENES_DECLARED, "fourbar", declared)
    assert run.main(["--device", "cpu", "--quick", "--only", "fourbar", "--parts", "throughput",
                     "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "fourbar.json").read_text())["throughput"]
    assert [(r["label"], r["num_worlds"]) for r in rows] == [("default", 1), ("maximal", 1), ("default", 8),
                                                             ("maximal", 8), ("no projection", 8)]
    assert rows[4]["settings"] == variant["config"] and rows[4]["world_steps_per_s"] > 0
    assert rows[4]["coordinates"] == rows[3]["coordinates"] == "maximal"
    assert rows[4]["loop_error_m"] > 10 * rows[3]["loop_error_m"]
    assert (tmp_path / "fourbar.png").stat().st_size > 0


def test_mujoco_warp_capacities_cover_a_host_rollout():
    """The MuJoCo Warp peer's per-world contact and constraint capacities come from a MuJoCo C
    rollout of one world: a box settling on the ground needs its 4 corner contacts and their
    constraint rows, and the capacities cover twice what the rollout saw."""
    import mujoco

    from benchmarks.peers import contact_capacity
    from engine.scenes_contact import CONTACT_SCENES
    from morphopt.formats.mjcf import mjcf_string

    spec = CONTACT_SCENES["box_on_plane"]().spec
    model = mujoco.MjModel.from_xml_string(mjcf_string(spec, timestep=2e-3, integrator="Euler"))
    data = mujoco.MjData(model)
    capacity = contact_capacity(model, data.qpos.copy(), data.qvel.copy(), steps=300)
    ncon = nefc = 0
    for _ in range(300):
        mujoco.mj_step(model, data)
        ncon, nefc = max(ncon, data.ncon), max(nefc, data.nefc)
    assert ncon >= 4 and nefc >= 4 * ncon  # the box rests on its corners (pyramidal cones: 4 rows each)
    assert capacity["nconmax"] >= 2 * ncon and capacity["njmax"] >= 2 * nefc


def test_padmm_bandwidth_counts_at_least_the_arrays_every_iteration_must_touch(tmp_path, capsys):
    from benchmarks import padmm_bandwidth

    assert padmm_bandwidth.main(["--device", "cpu", "--scene", "fourbar", "--worlds", "4", "--warmup", "3",
                                 "--steps", "2", "--out", str(tmp_path)]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    W, R = 4, result["rows"]
    # every iteration reads the factor (W R R floats) and the iterate, its previous value and the rhs
    assert result["linear_solver"] == "dense"
    assert result["bytes_per_iteration"] >= 4 * (W * R * R + 3 * W * R)
    assert result["loop_trips_per_step"] >= 1
    assert 0.0 < result["fraction_of_bandwidth"] < 1.0
    assert result["floor_ms"] == pytest.approx(result["bytes_per_iteration"] / (1e6 * result["bandwidth_GBps"]))
    assert (tmp_path / "padmm_bandwidth_cpu.csv").stat().st_size > 0


def test_spec_build_benchmark_compares_the_pool_with_building_here(tmp_path, capsys):
    assert spec_build.main(["--designs", "6", "--repeats", "1", "--workers", "2", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "spec_build.json").read_text())
    assert report == json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["identical"] is True and report["workers"] == 2 and report["built"] >= 1
    assert report["here_s"] > 0 and report["pool_s"] > 0 and report["here_ms_per_design"] > 0


def test_walker_study_writes_its_time_by_stage(tmp_path):
    stages = {"ask": 0.5, "build": 3.0, "simulate": 12.0, "storage": 0.25}
    walker_study.write_stages(stages, 16.0, "cpu", tmp_path / "walker_study_cpu")
    lines = (tmp_path / "walker_study_cpu_stages.csv").read_text().splitlines()
    assert lines[0] == "stage,seconds,share"
    rows = [line.split(",") for line in lines[1:]]
    assert [r[0] for r in rows] == ["simulate", "build", "ask", "storage"]  # largest first
    assert [float(r[2]) for r in rows] == [0.75, 0.1875, 0.03125, 0.015625]
    assert (tmp_path / "walker_study_cpu_stages.png").stat().st_size > 5000


def test_legged_precision_compares_the_study_and_settings_with_the_reference(tmp_path):
    import pandas as pd

    from benchmarks import legged_precision

    assert legged_precision.main(["--device", "cpu", "--designs", "3", "--duration", "0.1", "--quick",
                                  "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "legged_precision_cpu.json").read_text())
    assert report["designs"] == 3 and report["duration"] == 0.1
    assert [r["setting"] for r in report["results"]] == ["study (dt 5 ms, its [solver])", "dt 2 ms, rho 1",
                                                         "dt 5 ms, loose, cap 30", "dt 10 ms, loose"]
    study, _, same_settings, _ = report["results"]
    for key in ("same_outcome", "walk_in_both", "speed_error_median"):  # the study runs dt 5 ms, loose, cap 30
        assert study[key] == same_settings[key]
    assert all(0.0 <= r["same_outcome"] <= 1.0 for r in report["results"])
    rows = pd.read_csv(tmp_path / "legged_precision_cpu.csv.gz")
    assert len(rows) == 4 * 3 and set(rows["design"]) == {0, 1, 2}
    assert (tmp_path / "legged_precision_cpu.png").stat().st_size > 1000


def test_newton_peer_quaternion_helpers_match_rotation_matrices():
    """The Newton peer's error metric rotates anchors and multiplies quaternions (x, y, z, w) in
    NumPy: checked against rotation matrices built from the axis-angle formula."""
    from benchmarks.peers_newton import _multiply, _rotate

    rng = np.random.default_rng(3)

    def matrix(q):
        x, y, z, w = q
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    p = rng.normal(size=(5, 4))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    v = rng.normal(size=(5, 3))
    products = _multiply(q, p)
    for k in range(5):
        assert np.allclose(matrix(products[k]), matrix(q[k]) @ matrix(p[k]), atol=1e-12)
    assert np.allclose(_rotate(q, v), np.stack([matrix(q[k]) @ v[k] for k in range(5)]), atol=1e-12)


def test_newton_peer_takes_the_joint_settings_of_our_spec_and_names_a_spec_it_cannot_take():
    from benchmarks.peers_newton import joint_parameters
    from engine import JointDrive
    from engine.scenes import make_scene
    import dataclasses

    spec = make_scene("fourbar").spec
    drive = JointDrive(stiffness=10.0, damping=2.0, effort_limit=5.0)
    joints = [dataclasses.replace(j, armature=0.01, damping=0.04, drive=drive if k == 0 else None)
              for k, j in enumerate(spec.joints)]
    params = joint_parameters(dataclasses.replace(spec, joints=joints))
    assert params == {"stiffness": 10.0, "damping": 2.0, "effort_limit": 5.0, "armature": 0.01,
                      "joint_damping": 0.04, "driven": True}
    assert joint_parameters(spec)["driven"] is False
    joints[1] = dataclasses.replace(joints[1], armature=0.02)
    with pytest.raises(ValueError, match=spec.name):
        joint_parameters(dataclasses.replace(spec, joints=joints))


def test_step_variants_times_every_variant_and_restores_the_inverse_choice(tmp_path, capsys):
    """benchmarks.step_variants on the CPU: one timing per variant and scene, finite and positive,
    the variants' settings as named (the CPU never solves through L^-1 nor splits joints by
    itself), the module's threshold restored after the runs, and an unknown scene refused."""
    from benchmarks import step_variants
    from engine import fused

    before = fused.INVERSE_MAX_ROWS
    out = tmp_path / "variants.json"
    assert step_variants.main(["--device", "cpu", "--worlds", "2", "--repeats", "1", "--scenes", "fourbar",
                               "pendulum", "--out", str(out)]) == 0
    assert fused.INVERSE_MAX_ROWS == before
    rows = json.loads(out.read_text())["measurements"]
    assert len(rows) == 2 * len(step_variants.VARIANTS)
    assert all(r["step_ms"] > 0 and np.isfinite(r["step_ms"]) for r in rows)
    by_variant = {r["variant"]: r for r in rows if r["scene"] == "fourbar"}
    assert by_variant["skip_off"]["projection_skip_floor"] == 0.0 < by_variant["default"]["projection_skip_floor"]
    assert not any(r["inverse"] for r in rows)
    assert {r["sharing"] for r in rows if r["variant"] in ("default", "sharing_off")} == {0}
    # asked for on the CPU, the joints split (one thread runs the parts in turn); the body sums'
    # groups need whole warps and are left out
    assert by_variant["groups_off"]["sharing"] == 1 and by_variant["split_off"]["sharing"] == 0
    assert len(capsys.readouterr().out.strip().splitlines()) == len(rows)
    with pytest.raises(SystemExit):
        step_variants.main(["--device", "cpu", "--scenes", "pentagon"])


def test_kernel_times_account_for_every_launch_of_a_staged_step(tmp_path, capsys):
    """benchmarks.kernel_times on the CPU (the default walker: staged, contacts): one row per
    scene, every kernel with a positive time and whole launches per step, the stages' kernels
    present (joint rows, PADMM, the projection), the per-kernel times summing to the total, the
    library's launch functions restored; an unknown scene is refused."""
    import warp as wp

    from benchmarks import kernel_times

    launch, launch_tiled = wp.launch, wp.launch_tiled
    out = tmp_path / "kernels.json"
    assert kernel_times.main(["--device", "cpu", "--scenes", "walker_default", "--worlds", "2", "--steps", "2",
                              "--out", str(out)]) == 0
    assert (wp.launch, wp.launch_tiled) == (launch, launch_tiled)
    (row,) = json.loads(out.read_text())["results"]
    assert row["step_kernel"] == "staged"
    kernels = row["kernels"]
    assert {"joint_rows", "padmm_start", "padmm_update", "apply_impulses", "projection_pass",
            "apply_projection"} <= set(kernels)
    assert all(ms > 0 and count >= 0.5 for ms, count in kernels.values())
    # per step: once; two passes each step and two output passes on the chunk's last step (of 2)
    assert kernels["joint_rows"][1] == 1.0 and kernels["projection_pass"][1] == 3.0
    assert sum(count for _, count in kernels.values()) == row["launches_per_step"]
    assert sum(ms for ms, _ in kernels.values()) == pytest.approx(row["total_ms_per_step"], rel=1e-3)
    assert len(capsys.readouterr().out.strip().splitlines()) == 1
    with pytest.raises(SystemExit):
        kernel_times.main(["--device", "cpu", "--scenes", "pentagon"])
    with pytest.raises(SystemExit):  # CUDA events need a CUDA device
        kernel_times.main(["--device", "cpu", "--clock", "device"])


def test_chains_stages_reports_every_stage_of_the_reduced_step(tmp_path, capsys):
    """benchmarks.chains_stages on the CPU: the four-bar in reduced coordinates (no contacts: the
    contact stages absent) has one row with positive cycles for each stage it ran, summing to the
    step's; the CSV has a row per stage, the PNG is written; a scene without that variant is refused."""
    import csv

    from benchmarks import chains_stages
    from engine.reduced.chain_stages import STAGES

    out = tmp_path / "stages" / "fourbar.json"
    assert chains_stages.main(["--device", "cpu", "--scenes", "fourbar", "--worlds", "2", "--steps", "2",
                               "--warmup", "1", "--out", str(out)]) == 0
    (row,) = json.loads(out.read_text())["results"]
    stages = row["stages"]
    assert "contact factor and PADMM" not in stages and {"tree factor", "X = M~^-1 G^T", "output"} <= set(stages)
    assert set(stages) <= set(STAGES) and all(c > 0 for c in stages.values())
    assert row["step_cycles"] == pytest.approx(sum(stages.values()))
    with open(out.with_suffix(".csv")) as f:
        assert len(list(csv.DictReader(f))) == len(stages)
    assert out.with_suffix(".png").stat().st_size > 0
    assert len(capsys.readouterr().out.strip().splitlines()) == 1
    with pytest.raises(SystemExit):
        chains_stages.main(["--device", "cpu", "--scenes", "walker", "--worlds", "1"])


def test_heterogeneity_times_both_batches_at_each_cap(tmp_path, capsys):
    """benchmarks.heterogeneity on the CPU: random walkers (two topologies) and copies of the
    default walker at each iteration cap, finite times, the largest world's iterations within the
    cap, the ratio of the two times recorded on the random batch's row."""
    from benchmarks import heterogeneity

    out = tmp_path / "hetero.json"
    assert heterogeneity.main(["--device", "cpu", "--worlds", "4", "--caps", "20", "--warmup", "1",
                               "--free-rhos", "5e-4", "--orderings", "shallow", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["results"]
    assert [r["batch"] for r in rows] == ["random", "default"]
    assert all(r["free_rho"] == 5e-4 and r["free_rho_used"] == pytest.approx(5e-4) for r in rows)
    assert all(r["sparse_ordering"] == "shallow" for r in rows)
    random_walkers, default = rows
    assert random_walkers["patterns"] == 2 and default["patterns"] == 1
    assert all(r["step_ms"] > 0 and max(r["iterations_largest_world"]) <= 20 for r in rows)
    assert "ratio_to_default" in random_walkers and "ratio_to_default" not in default
    assert random_walkers["iterations_mean"] > 0 and default["iterations_mean"] > 0
    assert len(capsys.readouterr().out.strip().splitlines()) == 2


def test_heterogeneity_runs_the_reduced_walkers(tmp_path):
    """benchmarks.heterogeneity --model reduced: the same random designs and the default walker in
    the coordinates engine.pack plans for them (tabulated), with the walker study's dt; the largest
    world's iterations within the cap, finite times and the ratio on the random batch's row;
    spread_phases turns each world's cranks by an angle of its own."""
    import engine
    from benchmarks import heterogeneity
    from benchmarks.scenes import walker_default

    out = tmp_path / "hetero_reduced.json"
    assert heterogeneity.main(["--device", "cpu", "--worlds", "4", "--caps", "12", "--warmup", "1",
                               "--model", "reduced", "--registers", "64", "0", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["results"]
    batches = [("random", "reduced"), ("default", "reduced"), ("default, phases spread", "reduced")]
    assert [(r["batch"], r["model"]) for r in rows] == batches * 2
    assert all(r["coordinates"] == "tabulated" for r in rows)
    assert [r["max_registers"] for r in rows] == [64] * 3 + [None] * 3
    assert all(r["step_ms"] > 0 and 0 < max(r["iterations_largest_world"]) <= 12 for r in rows)
    assert all(r["diverged"] == 0 for r in rows)
    for first in (0, 3):
        random_walkers, default, spread = rows[first:first + 3]
        assert "ratio_to_default" not in default
        assert random_walkers["ratio_to_default"] == pytest.approx(random_walkers["step_ms"] / default["step_ms"])
        assert spread["ratio_to_default"] == pytest.approx(spread["step_ms"] / default["step_ms"])
    with pytest.raises(SystemExit):
        heterogeneity.main(["--device", "cpu", "--registers", "64"])  # maximal model: no register cap
    spec = walker_default().specs[0]
    model = engine.pack([spec] * 3, "cpu", coordinates="tabulated")
    model.state()
    before = model.inner.coord.numpy().copy()
    heterogeneity.spread_phases(model)
    turn = np.mod(model.inner.coord.numpy() - before, 2 * np.pi)
    legs = len(model.inner.layouts[0].groups)
    assert legs == 6 and np.allclose(turn[:, :legs], turn[:, :1], atol=1e-5)  # one turn per world, phases kept
    assert np.ptp(turn[:, 0]) > 0.1  # and the worlds turned apart
    assert not turn[:, legs:].any()  # the padding left alone
    from morphopt.study_spec import load_study_spec

    study = load_study_spec(pathlib.Path(heterogeneity.__file__).resolve().parents[1] / "studies" / "walker.toml")
    assert all(r["dt"] == study.dt for r in rows)


def test_newton_peer_matches_our_bodies_by_name_in_world_zero():
    """The Newton peer's trajectory error compares its bodies with ours by name: the last part of
    Newton's body labels (USD prim paths), world 0 only; a body it lacks is named in the error."""
    import types

    import warp as wp

    from benchmarks.peers_newton import _body_indices

    labels = ["/robot/RigidBodies/pelvis", "/robot/RigidBodies/foot_l", "/robot/RigidBodies/foot_r",
              "/robot/RigidBodies/pelvis", "/robot/RigidBodies/foot_l", "/robot/RigidBodies/foot_r"]
    model = types.SimpleNamespace(body_label=labels,
                                  body_world=wp.array([0, 0, 0, 1, 1, 1], dtype=wp.int32, device="cpu"))
    assert _body_indices(model, ["foot_r", "pelvis", "foot_l"]).tolist() == [2, 0, 1]
    with pytest.raises(ValueError, match="knee"):
        _body_indices(model, ["pelvis", "knee"])


def test_newton_peers_work_precision_rows_measure_trajectory_error_against_the_reference(monkeypatch):
    """benchmarks.run's Newton peer sweep on a USD scene: each peer at each declared step size, the
    same records as ours, its trajectory error the largest body distance from the reference at the
    common records; a peer that fails or diverges is a row with its reason, not a crash."""
    import dataclasses
    import types

    from benchmarks import peers_newton, run, scenes

    reference = np.zeros((6, 1, 3, 3))
    reference[:, 0, :, 0] = np.arange(6)[:, None]  # bodies move along x
    calls = []

    def fake_run(path, *, standing, solver, worlds, dt, steps, record_every, device, joints, record_bodies):
        calls.append((solver, dt, steps, record_every, tuple(record_bodies)))
        if solver == "kamino" and dt > 0.015:
            raise RuntimeError("peer failed")
        positions = reference.copy()
        positions[3, 0, 1, 2] += 0.25 * dt  # one body off by dt / 4 at one record
        return {"engine": "kamino" if solver == "kamino" else "mujoco_warp", "num_worlds": worlds, "dt": dt,
                "wall_s_per_simulated_s": 1.0, "loop_error_m": 1e-4, "finite": True, "positions": positions}

    monkeypatch.setattr(peers_newton, "available", lambda: None)
    monkeypatch.setattr(peers_newton, "newton_drlegs_run", fake_run)
    monkeypatch.setattr(peers_newton, "joint_parameters", lambda spec: {})
    spec = types.SimpleNamespace(bodies=[types.SimpleNamespace(name=n) for n in ("a", "b", "c")],
                                 joints=[])
    scene = scenes.BenchScene([spec], None, "test", usd="robot.usda")
    declared = dataclasses.replace(scenes.SCENES_DECLARED["drlegs_hanging"],
                                   peer_dt_scales={"mujoco": [0.5, 1.0], "kamino": [1.0, 2.0]})
    args = types.SimpleNamespace(device="cpu", peer_solvers=["mujoco", "kamino"])
    rows = run.newton_precision(scene, 4, 0.01, 0.2, 0.04, reference, declared, args)
    assert [r["label"] for r in rows] == ["MuJoCo Warp, dt x0.5", "MuJoCo Warp, dt x1", "Kamino, dt x1",
                                          "Kamino, dt x2"]
    assert [c[1:4] for c in calls] == [(0.005, 40, 8), (0.01, 20, 4), (0.01, 20, 4), (0.02, 10, 2)]
    assert all(c[4] == ("a", "b", "c") for c in calls)
    for row in rows[:3]:
        assert row["kind"] == "precision" and "positions" not in row
        assert row["trajectory_error_m"] == pytest.approx(0.25 * row["dt"])
    assert "peer failed" in rows[3]["error"] and rows[3]["engine"] == "kamino"
    calls.clear()  # --peer-solvers mujoco: Kamino is not run
    rows = run.newton_precision(scene, 4, 0.01, 0.2, 0.04, reference, declared,
                                types.SimpleNamespace(device="cpu", peer_solvers=["mujoco"]))
    assert [r["label"] for r in rows] == ["MuJoCo Warp, dt x0.5", "MuJoCo Warp, dt x1"]
    assert [c[0] for c in calls] == ["mujoco", "mujoco"]


def test_records_fall_on_steps_of_every_sweep_point_and_peer():
    """A record interval that is not a whole number of steps is refused (rounding it took records
    every 48 ms against a reference every 50 ms); every declared scene's records, full and quick,
    fall on steps of each of its sweep's step sizes and of its peers'."""
    from benchmarks.run import MUJOCO_WARP_POINTS, record_interval
    from benchmarks.scenes import SCENES_DECLARED, steps_per_record

    assert steps_per_record(0.04, 0.004) == 10 and steps_per_record(0.04, 5e-5) == 800
    with pytest.raises(ValueError, match="0.05 s do not fall on steps of 0.004 s"):
        steps_per_record(0.05, 0.004)
    hanging = SCENES_DECLARED["drlegs_hanging"]  # DR Legs: our sweep and both Newton peers, at 4096 worlds
    assert hanging.duration > 0 and hanging.precision_worlds == 4096 and "mujoco" in hanging.peer_dt_scales
    checked = 0
    for name, declared in SCENES_DECLARED.items():
        if declared.duration <= 0:
            continue
        scales = [x["dt_scale"] for x in declared.sweep] + [0.05, 0.1]  # the references: dt / 20, dt / 10
        scales += [scale for values in declared.peer_dt_scales.values() for scale in values]
        if declared.peers and not declared.peer_dt_scales:
            scales += [scale for _, scale in MUJOCO_WARP_POINTS]
        for record_dt, duration in ((record_interval(declared, False), declared.duration),
                                    (record_interval(declared, True), 0.2)):
            assert steps_per_record(duration, record_dt) >= 1, name
            for scale in scales:
                assert steps_per_record(record_dt, declared.dt * scale) >= 1
                checked += 1
    assert checked > 40


def test_graph_overhead_times_steps_and_every_synthetic_graph(tmp_path, capsys):
    """benchmarks.graph_overhead on the CPU (no graphs: the script's path, not the costs): a row per
    scene and batch size with its windows, kernels and launches, the gap per launch derived from
    them, and a row per synthetic variant with its launches counted (the loops' flag launches
    included) and positive times; bad arguments are refused."""
    from benchmarks import graph_overhead

    out = tmp_path / "overhead.json"
    assert graph_overhead.main(["--device", "cpu", "--scenes", "fourbar", "--worlds", "2", "--launches", "4",
                                "--windows", "2", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["results"]
    assert len(capsys.readouterr().out.strip().splitlines()) == len(rows) == 1 + len(graph_overhead.VARIANTS)
    (step_row,) = [r for r in rows if r["kind"] == "step"]
    assert step_row["scene"] == "fourbar" and step_row["num_worlds"] == 2 and len(step_row["graph_ms_windows"]) == 2
    assert step_row["graph_ms_per_step_least"] <= step_row["graph_ms_per_step"]
    assert step_row["kernels_ms_per_step"] > 0 and step_row["launches_per_step"] >= 1
    gap = 1e3 * (step_row["graph_ms_per_step"] - step_row["kernels_ms_per_step"]) / step_row["launches_per_step"]
    assert step_row["between_kernels_us_per_launch"] == pytest.approx(gap, abs=0.01)
    synthetic = {r["variant"]: r for r in rows if r["kind"] == "synthetic"}
    assert set(synthetic) == set(graph_overhead.VARIANTS)
    assert synthetic["plain"]["launches"] == 4 and synthetic["conditional"]["launches"] == 6
    assert synthetic["empty_loop"]["launches"] == 5
    assert all(0 < r["us_per_launch_least"] <= r["us_per_launch"] for r in synthetic.values())
    for bad in (["--launches", "1"], ["--worlds", "0"], ["--scenes", "pentagon"]):
        with pytest.raises(SystemExit):
            graph_overhead.main(["--device", "cpu", *bad])


def test_variant_flag_times_a_declared_variant_with_its_settings(tmp_path, capsys):
    """--variant of benchmarks.kernel_times and benchmarks.graph_overhead on the CPU: the row names
    the variant and carries its declared settings, which reach the packed batch (the four-bar's
    'staged kernels' point runs the staged step, whose projection kernels are timed, where the
    default four-bar runs the fused one), a sweep point's dt factor sets the step, and a label the
    scene does not declare is refused with the scene's labels."""
    from benchmarks import graph_overhead, kernel_times
    from benchmarks.scenes import SCENES_DECLARED

    fourbar = SCENES_DECLARED["fourbar"]
    declared = {s["label"]: s for s in [*fourbar.variants, *fourbar.sweep]}
    without = next(label for label, s in declared.items() if s.get("config", {}).get("position_iterations") == 0)
    rows = {}
    for variant in ("default", "staged kernels", without):
        out = tmp_path / f"kernels{len(rows)}.json"
        assert kernel_times.main(["--device", "cpu", "--scenes", "fourbar", "--worlds", "2", "--steps", "2",
                                  "--variant", variant, "--out", str(out)]) == 0
        rows[variant] = json.loads(out.read_text())["results"][0]
    assert all(row["variant"] == variant for variant, row in rows.items())
    assert rows["default"]["settings"] == {} and rows[without]["settings"] == declared[without]["config"]
    assert rows["default"]["step_kernel"] == "fused" and rows["staged kernels"]["step_kernel"] == "staged"
    assert {"projection_pass", "apply_projection"} <= set(rows["staged kernels"]["kernels"])
    dt_point = next(s for s in fourbar.sweep if s.get("dt_scale", 1.0) != 1.0 and not s.get("config"))
    out = tmp_path / "dt.json"
    assert kernel_times.main(["--device", "cpu", "--scenes", "fourbar", "--worlds", "1", "--steps", "1",
                              "--variant", dt_point["label"], "--out", str(out)]) == 0
    assert json.loads(out.read_text())["results"][0]["dt"] == pytest.approx(fourbar.dt * dt_point["dt_scale"])
    overhead = tmp_path / "overhead.json"
    assert graph_overhead.main(["--device", "cpu", "--scenes", "fourbar", "--worlds", "2", "--launches", "2",
                                "--windows", "1", "--variant", "staged kernels", "--out", str(overhead)]) == 0
    (step_row,) = [r for r in json.loads(overhead.read_text())["results"] if r["kind"] == "step"]
    assert step_row["variant"] == "staged kernels" and step_row["step_kernel"] == "staged"
    assert step_row["dt"] == pytest.approx(fourbar.dt)
    capsys.readouterr()
    for module in (kernel_times, graph_overhead):
        with pytest.raises(SystemExit):
            module.main(["--device", "cpu", "--scenes", "fourbar", "--variant", "no such setting"])
        assert "staged kernels" in capsys.readouterr().err  # the error lists the scene's labels


def test_runner_measures_reduced_coordinates_settings_against_the_reference(tmp_path):
    """--settings picks declared points by label: the four-bar in reduced coordinates (engine.pack's
    TREE plan, forced) runs as its own rows, its loops measured by the maximal engine's joint residuals
    (below 1e-6 m),
    its trajectory within 5e-5 m of MuJoCo C's float64 reference at dt 1 ms and measurably further at
    dt 4 ms; a label no scene declares is refused, naming it."""
    import json

    from benchmarks.run import main

    assert main(["--device", "cpu", "--quick", "--only", "fourbar", "--settings", "reduced coordinates",
                 "reduced coordinates, dt x4", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "fourbar.json").read_text())
    variants = [r for r in result["throughput"] if r["label"] not in ("default", "maximal")]
    assert [(r["label"], r["step_kernel"]) for r in variants] == [("reduced coordinates", "tree")]
    rows = {r["label"]: r for r in result["precision"]}
    assert sorted(rows) == ["reduced coordinates", "reduced coordinates, dt x4"]
    for row in list(rows.values()) + variants:
        assert row["step_kernel"] == row["coordinates"] == "tree"
        assert row["diverged_worlds"] == 0 and row["world_steps_per_s"] > 0
        assert 0 < row["loop_error_m"] < 1e-6
    assert rows["reduced coordinates"]["trajectory_error_m"] < 5e-5
    coarse, fine = rows["reduced coordinates, dt x4"], rows["reduced coordinates"]
    assert coarse["trajectory_error_m"] > 2 * fine["trajectory_error_m"]
    with pytest.raises(SystemExit):
        main(["--device", "cpu", "--quick", "--only", "fourbar", "--settings", "no such setting"])


def test_runner_takes_the_batch_sizes_asked_for(tmp_path, capsys):
    """--worlds replaces the scene's throughput batch sizes: the default settings run at each (in
    engine.pack's plan and in maximal coordinates), the variants at the largest; a size below 1, or
    --worlds without its own --out folder, is refused."""
    import json

    from benchmarks.run import main

    assert main(["--device", "cpu", "--parts", "throughput", "--only", "fourbar", "--worlds", "5", "3",
                 "--settings", "reduced coordinates", "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "fourbar.json").read_text())["throughput"]
    assert [(r["label"], r["num_worlds"]) for r in rows] == [("default", 3), ("maximal", 3), ("default", 5),
                                                             ("maximal", 5), ("reduced coordinates", 5)]
    assert all(r["world_steps_per_s"] > 0 and r["diverged_worlds"] == 0 for r in rows)
    for argv, message in ((["--worlds", "0", "--out", str(tmp_path)], "at least 1"),
                          (["--worlds", "4"], "own --out")):
        with pytest.raises(SystemExit):
            main(["--device", "cpu", "--only", "fourbar", *argv])
        assert message in capsys.readouterr().err


def test_walker_agreement_compares_the_same_walkers_in_both_plans(tmp_path, capsys):
    from benchmarks import walker_agreement

    result = walker_agreement.main(["--designs", "3", "--device", "cpu", "--out", str(tmp_path)])
    assert result == json.loads((tmp_path / "walker_agreement_cpu.json").read_text())
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == result
    assert result["feasible_both"] + result["failed_tabulated_only"] + result["failed_maximal_only"] <= 3
    if result["feasible_both"]:
        assert 0.0 <= result["speed_diff_median_m_s"] <= result["speed_diff_p90_m_s"] < 1.0
    assert result["seconds"]["tabulated"] > 0.0 and result["seconds"]["maximal"] > 0.0


def test_work_precision_points_are_grouped_into_step_size_sweeps():
    from benchmarks.run import _series
    assert [_series(label) for label in ("default", "dt x0.5", "dt x2", "reduced coordinates",
                                         "reduced coordinates, dt x4", "MuJoCo Warp RK4, dt x2", "staged, dt x2")] == \
        ["maximal", "maximal", "maximal", "reduced coordinates", "reduced coordinates", "MuJoCo Warp RK4", "staged"]


def test_tabulated_launch_times_both_kernels_at_each_batch_and_plots(tmp_path, capsys):
    """Both of the tabulated plan's kernels at every batch size asked for (on the CPU the tiled one
    is a block of one thread), one JSON line each, and the files."""
    from benchmarks.tabulated_launch import main

    main(["--device", "cpu", "--designs", "3", "--worlds", "4", "6", "--steps", "2", "--out", str(tmp_path)])
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [(r["worlds"], r["tiled"]) for r in rows] == [(4, True), (4, False), (6, True), (6, False)]
    assert all(r["ms_per_step"] > 0.0 for r in rows)
    saved = json.loads((tmp_path / "tabulated_launch_cpu.json").read_text())
    assert saved["tiled_max_worlds"] == 0 and saved["designs"] == 3 and len(saved["rows"]) == 4
    assert (tmp_path / "tabulated_launch_cpu.png").stat().st_size > 0
    assert (tmp_path / "tabulated_launch_cpu.csv").read_text().count("\n") == 5
