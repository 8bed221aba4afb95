"""Peers on the same mechanisms, same device, same run: MuJoCo Warp (`pip install '.[bench]'`).

The mechanism reaches MuJoCo Warp through morphopt's MJCF export (loops as equality constraints,
drives as actuators, the initial keyframe), so both engines simulate the same spec. One model for
all worlds (MuJoCo Warp cannot batch different mechanisms), every world starting from the same
keyframe; steps replayed from a CUDA graph of `record_every` steps. Accuracy is measured with
MuJoCo C on the host for a few worlds: loop-closure error = largest |efc_pos| of the equality
rows [m], energy = MuJoCo's potential + kinetic energy, body positions for the trajectory error.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

__all__ = ["available", "contact_capacity", "mujoco_warp_run"]


def available() -> str | None:
    """None when MuJoCo Warp can run here, else why not."""
    try:
        import mujoco  # noqa: F401
        import mujoco_warp  # noqa: F401
    except ImportError as exc:
        return f"MuJoCo Warp is not installed ({exc}); pip install '.[bench]'"
    return None


def contact_capacity(host_model, qpos, qvel, steps: int, margin: float = 2.0) -> dict:
    """MuJoCo Warp's per-world contact and constraint capacities (nconmax, njmax) sized from a
    rollout of one world in MuJoCo C: the largest counts seen, times ``margin``, plus 8. MuJoCo Warp
    allocates these up front and drops what does not fit (its default njmax is too small for a
    legged robot standing on its feet, whose run then loses its contacts and goes non-finite)."""
    import mujoco

    probe = mujoco.MjData(host_model)
    probe.qpos[:], probe.qvel[:] = qpos, qvel
    ncon = nefc = 0
    for _ in range(min(steps, 1000)):
        mujoco.mj_step(host_model, probe)
        if probe.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0:
            break  # the host run went unstable (MuJoCo resets it): keep the counts seen so far
        ncon, nefc = max(ncon, int(probe.ncon)), max(nefc, int(probe.nefc))
    return {"nconmax": int(margin * ncon) + 8, "njmax": int(margin * nefc) + 8}


def mujoco_warp_run(spec, *, worlds: int, dt: float, steps: int, record_every: int, integrator: str, device: str,
                    body_names: list[str], sample_worlds: int = 8) -> dict:
    """Time ``steps`` steps of ``worlds`` copies of ``spec``; sample accuracy every ``record_every`` steps."""
    import mujoco
    import mujoco_warp as mjw

    from morphopt.formats.mjcf import mjcf_string

    xml = mjcf_string(spec, timestep=dt, integrator=integrator)
    host_model = mujoco.MjModel.from_xml_string(xml)
    host_model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    host = mujoco.MjData(host_model)
    if host_model.nkey > 0:
        mujoco.mj_resetDataKeyframe(host_model, host, 0)
    q0, v0 = host.qpos.copy(), host.qvel.copy()
    device_model = mujoco.MjModel.from_xml_string(xml)
    body_ids = [mujoco.mj_name2id(host_model, mujoco.mjtObj.mjOBJ_BODY, n) for n in body_names]
    has_contacts = bool(spec.shapes)
    from benchmarks.run import mempool_megabytes

    pool_before = mempool_megabytes(device)
    with wp.ScopedDevice(device):
        t0 = time.perf_counter()
        model = mjw.put_model(device_model)
        kwargs = dict(nworld=worlds)
        if not has_contacts:
            kwargs.update(nconmax=0, njmax=max(8, 2 * int(host_model.neq) * 6 + 8))
        else:
            kwargs.update(contact_capacity(host_model, q0, v0, steps))
        data = mjw.make_data(device_model, **kwargs)

        def reset():
            data.qpos.assign(np.tile(q0, (worlds, 1)).astype(np.float32))
            data.qvel.assign(np.tile(v0, (worlds, 1)).astype(np.float32))
            data.time.zero_()

        reset()
        mjw.step(model, data)  # compiles
        wp.synchronize_device()
        compile_s = time.perf_counter() - t0
        graph = None
        if wp.get_device().is_cuda:
            with wp.ScopedCapture() as capture:
                for _ in range(record_every):
                    mjw.step(model, data)
            graph = capture.graph
        reset()
        wp.synchronize_device()
        sample = np.unique(np.linspace(0, worlds - 1, min(sample_worlds, worlds)).round().astype(int))
        loop_error, energies, positions, chunk_times = [], [], [], []

        def measure():
            qpos, qvel = data.qpos.numpy()[sample], data.qvel.numpy()[sample]
            errors, energy, pos = [], [], []
            for q, v in zip(qpos, qvel):
                host.qpos[:] = q
                host.qvel[:] = v
                mujoco.mj_forward(host_model, host)
                rows = host.efc_type[: host.nefc] == int(mujoco.mjtConstraint.mjCNSTR_EQUALITY)
                errors.append(float(np.abs(host.efc_pos[: host.nefc][rows]).max()) if rows.any() else 0.0)
                energy.append(float(host.energy.sum()))
                pos.append(host.xipos[body_ids].copy())  # centres of mass, as engine body_q
            loop_error.append(max(errors))
            energies.append(energy)
            positions.append(pos)

        measure()
        done = 0
        while done < steps:
            wp.synchronize_device()
            t = time.perf_counter()
            if graph is not None:
                wp.capture_launch(graph)
            else:
                for _ in range(record_every):
                    mjw.step(model, data)
            wp.synchronize_device()
            chunk_times.append((time.perf_counter() - t) / record_every)
            done += record_every
            measure()
        finite = bool(np.all(np.isfinite(data.qpos.numpy())))
        memory = None if pool_before is None else mempool_megabytes(device) - pool_before
    energies = np.array(energies)
    return {
        "engine": f"mujoco_warp {mjw.__version__}", "integrator": integrator, "num_worlds": worlds, "dt": dt,
        "steps": done, "compile_s": compile_s, "step_ms_median": float(np.median(chunk_times) * 1e3),
        "world_steps_per_s": worlds / float(np.median(chunk_times)), "loop_error_m": float(max(loop_error)),
        "energy": energies, "positions": np.array(positions), "finite": finite, "device_memory_mb": memory,
        "versions": {"mujoco": mujoco.__version__, "mujoco_warp": mjw.__version__},
        "solver": {"solver": int(device_model.opt.solver), "iterations": int(device_model.opt.iterations),
                   "tolerance": float(device_model.opt.tolerance), "cone": int(device_model.opt.cone),
                   "loops": "equality constraints (connect), MJCF export defaults"},
    }


def mujoco_reference(specs, *, duration: float, record_dt: float, dt: float) -> np.ndarray:
    """Reference trajectories from MuJoCo C (float64, RK4 at ``dt``, the MJCF export's near-hard loop
    closures, time constant 2 dt): body positions (records, len(specs), max bodies, 3) [m] every
    ``record_dt`` from t = 0, the same records engine runs take."""
    import mujoco

    from morphopt.formats.mjcf import mjcf_string

    from benchmarks.scenes import steps_per_record

    records = round(duration / record_dt) + 1
    every = steps_per_record(record_dt, dt)
    out = np.zeros((records, len(specs), max(len(s.bodies) for s in specs), 3))
    for k, spec in enumerate(specs):
        model = mujoco.MjModel.from_xml_string(mjcf_string(spec, timestep=dt, integrator="RK4"))
        data = mujoco.MjData(model)
        if model.nkey > 0:
            mujoco.mj_resetDataKeyframe(model, data, 0)
        mujoco.mj_forward(model, data)
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b.name) for b in spec.bodies]
        for r in range(records):
            if r > 0:
                for _ in range(every):
                    mujoco.mj_step(model, data)
            out[r, k, : len(ids)] = data.xipos[ids]  # centres of mass, as engine body_q
    return out
