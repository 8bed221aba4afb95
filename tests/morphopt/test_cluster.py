"""Studies on a Ray cluster (morphopt.cluster) against the single-process study with the same seed:
the same stored designs from a local cluster of two workers (kinematic and dynamic), after a worker
killed mid-generation, after a coordinator killed between generations and resumed; on PostgreSQL a
second coordinator refused while the first completes, and readers during a run seeing whole
generations only."""

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("ray")

from morphopt.cluster import shards  # noqa: E402
from morphopt.storage import StudyStorage, read_designs, read_workers  # noqa: E402
from morphopt.study import run_study  # noqa: E402
from morphopt.study_spec import load_study_spec  # noqa: E402
from tests.morphopt.postgres import postgres_url  # noqa: E402,F401

pytestmark = pytest.mark.slow
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

KINEMATIC = """
[study]
name = "{name}"
family = "jansen_leg"
mode = "kinematic"
seed = 3
generations = {generations}
worlds = 48
device = "cpu"
{storage}
[objective]
metric = "foot_stride"
direction = "maximize"

[constraints]
foot_step_height = [0.02, 1.0]

[simulation]
samples = 90

[fixed]
m = 0.015
"""

DYNAMIC = """
[study]
name = "{name}"
family = "walker"
mode = "dynamic"
seed = 1
generations = {generations}
worlds = 12
device = "cpu"
{storage}
[objective]
metric = "walking_speed"
direction = "maximize"

[simulation]
duration = 1.3
dt = 0.005

[fixed]
legs_per_side = 3
"""


def study(tmp_path, text, name, generations=3, storage="", **overrides):
    path = tmp_path / f"{name}.toml"
    path.write_text(text.format(name=name, generations=generations,
                                storage=f'storage = "{storage}"\n' if storage else ""))
    return load_study_spec(path).with_overrides(**overrides)


def stored(spec):
    frame = read_designs(spec.storage_url, spec.name)
    return frame.drop(columns=[c for c in frame.columns if c in ("seconds",)])


def assert_same_study(a, b):
    x, y = stored(a), stored(b)
    assert len(x) == a.generations * a.worlds and len(y) == len(x)
    np.testing.assert_array_equal(x["value"].to_numpy(), y["value"].to_numpy())
    for column in x.columns:
        left, right = x[column].to_numpy(), y[column].to_numpy()
        if left.dtype.kind == "f":
            np.testing.assert_array_equal(left, right, err_msg=column)
        else:
            assert list(left) == list(right), column


def test_shards_group_topologies_and_cover_every_design():
    params = [{"leg_family": f, "x": i} for i, f in enumerate("abab" * 5)]
    parts = shards(params, 3, ["leg_family"])
    assert sorted(i for part in parts for i in part) == list(range(20))
    families = [[params[i]["leg_family"] for i in part] for part in parts]
    assert families[0] == ["a"] * 7 and families[2] == ["b"] * 6  # one topology per shard where sizes allow
    assert len(shards(params[:1], 4, [])) == 1


@pytest.mark.parametrize("text", [KINEMATIC, DYNAMIC], ids=["kinematic", "dynamic"])
def test_two_workers_store_the_single_process_study(tmp_path, text, capfd):
    alone = study(tmp_path, text, "alone")
    run_study(alone, progress=False)
    spread = study(tmp_path, text, "spread", cluster="local", workers=2)
    result = run_study(spread, progress=False)
    assert result.evaluations == spread.generations * spread.worlds
    assert_same_study(alone, spread)
    assert "worker 1:" in capfd.readouterr().err


def test_a_robust_dynamic_study_on_two_workers_stores_the_single_process_study(tmp_path):
    """Scenarios travel to the workers as data (morphopt.robust.scenario_hooks there): the same
    aggregates and failures as in one process."""
    robust = DYNAMIC + """[robustness]
samples = 2
aggregate = "worst"
max_failure_share = 0.5
slope = {{ uniform = [-5.0, 5.0] }}
payload = {{ uniform = [0.0, 0.3] }}
"""
    alone = study(tmp_path, robust, "alone", generations=2)
    run_study(alone, progress=False)
    spread = study(tmp_path, robust, "spread", generations=2, cluster="local", workers=2)
    run_study(spread, progress=False)
    assert_same_study(alone, spread)
    assert "metric_walking_speed_worst" in stored(spread).columns


def test_a_worker_killed_mid_generation_leaves_the_study_complete_and_identical(tmp_path, monkeypatch, capfd):
    alone = study(tmp_path, KINEMATIC, "alone")
    run_study(alone, progress=False)
    monkeypatch.setenv("MORPHOPT_TEST_KILL_WORKER", "1:0")
    spread = study(tmp_path, KINEMATIC, "spread", cluster="local", workers=2)
    run_study(spread, progress=False)
    assert_same_study(alone, spread)
    err = capfd.readouterr().err
    assert "worker 0 died during shard" in err and "replaced 1x" in err
    workers = read_workers(spread.storage_url, spread.name)  # what study show reports per worker
    assert len(workers) == 2 * spread.generations and workers.designs.sum() == spread.generations * spread.worlds
    assert workers.replaced.sum() == 1 and workers[workers.replaced == 1].worker.tolist() == [0]
    from morphopt.cli import main
    assert main(["study", "show", str(spread.path)]) == 0
    assert "worker 0: 72 designs in 3 generations" in capfd.readouterr().out


def test_a_stalled_worker_is_replaced_after_the_shard_timeout(tmp_path, monkeypatch, capfd):
    alone = study(tmp_path, KINEMATIC, "alone")
    run_study(alone, progress=False)
    monkeypatch.setenv("MORPHOPT_TEST_STALL_WORKER", "1:1")
    spread = study(tmp_path, KINEMATIC, "spread", cluster="local", workers=2, shard_timeout=4.0)
    run_study(spread, progress=False)
    assert_same_study(alone, spread)
    err = capfd.readouterr().err
    assert "worker 1 did not return shard 1 within 4 s" in err and "replaced 1x" in err


def _stored_generations(spec) -> int:
    try:
        return StudyStorage(spec.storage_url, spec.name).info()["generations"]
    except Exception:  # noqa: BLE001 - not created yet
        return 0


def test_a_coordinator_killed_between_generations_resumes_to_the_same_study(tmp_path):
    alone = study(tmp_path, KINEMATIC, "alone", generations=4)
    run_study(alone, progress=False)
    spread = study(tmp_path, KINEMATIC, "spread", generations=60)  # long enough to be killed in flight
    command = [sys.executable, "-m", "morphopt.cli", "study", "run", str(spread.path), "--cluster", "local",
               "--workers", "2"]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               start_new_session=True)
    deadline = time.time() + 120
    while _stored_generations(spread) < 2 and time.time() < deadline and process.poll() is None:
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)  # the coordinator and the Ray processes it started
    process.wait()
    done = _stored_generations(spread)
    assert 2 <= done < 60, done
    resumed = spread.with_overrides(generations=4, cluster="local", workers=2)
    if done < 4:
        run_study(resumed, resume=True, progress=False)
    frame = stored(resumed)
    reference = stored(alone)
    first = frame[frame["generation"] < 4]
    np.testing.assert_array_equal(first["value"].to_numpy(), reference["value"].to_numpy())


def test_postgres_refuses_a_second_coordinator_while_the_first_completes(tmp_path, postgres_url):
    first = study(tmp_path, KINEMATIC, "shared", generations=30, storage=postgres_url)
    outcome = {}

    def run():
        outcome["result"] = run_study(first, progress=False)

    thread = threading.Thread(target=run)
    thread.start()
    while _stored_generations(first) < 1:
        time.sleep(0.02)
    (tmp_path / "other").mkdir()
    second = study(tmp_path / "other", KINEMATIC, "shared", generations=30, storage=postgres_url)
    with pytest.raises(ValueError, match="is being written by"):
        run_study(second, resume=True, progress=False)
    # readers during the run see whole generations only
    sizes = set()
    while thread.is_alive():
        sizes.add(len(read_designs(postgres_url, "shared")) % first.worlds)
    thread.join()
    assert outcome["result"].evaluations == 30 * first.worlds
    assert sizes <= {0}, sizes
    assert len(read_designs(postgres_url, "shared")) == 30 * first.worlds


def test_workers_share_a_gpu_by_the_study_s_share(tmp_path):
    """On a Ray instance that declares one GPU, a CUDA study at 0.5 GPU a worker places two actors,
    each holding half the GPU (the multi-GPU path's arithmetic, checked where no GPU is); a third
    worker is refused before any actor starts, naming the room there is."""
    import ray

    from morphopt.cluster import ClusterEvaluator
    from morphopt.families import load_family

    spec = study(tmp_path, KINEMATIC.replace('device = "cpu"', 'device = "cuda"'), "shared",
                 gpus_per_worker=0.5)
    space = spec.design_space(load_family(spec.family))
    ray.init(num_cpus=2, num_gpus=1, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        evaluator = ClusterEvaluator(spec, space, address="auto", gpus_per_worker=0.5)
        try:
            assert evaluator.workers == 2
            assert len({ray.get(actor.pid.remote()) for actor in evaluator.actors}) == 2  # both placed, both alive
            assert ray.available_resources().get("GPU", 0.0) == pytest.approx(0.0)  # the GPU taken by two halves
        finally:
            evaluator.close()
        with pytest.raises(ValueError, match=r"3 workers asked for.*1 GPUs, room for 2 workers at 0\.5 GPU each"):
            ClusterEvaluator(spec, space, address="auto", workers=3, gpus_per_worker=0.5)
        whole = ClusterEvaluator(spec, space, address="auto", gpus_per_worker=1.0)
        assert whole.workers == 1
        whole.close()
    finally:
        ray.shutdown()
    ray.init(num_cpus=0, num_gpus=0, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:  # a head that offers no CPU (its workers not joined yet): said, not a division by zero
        cpu = study(tmp_path, KINEMATIC, "no_cpu")
        with pytest.raises(ValueError, match="has no whole CPU for a worker"):
            ClusterEvaluator(cpu, space, address="auto")
        with pytest.raises(ValueError, match="has no GPU"):
            ClusterEvaluator(spec, space, address="auto", gpus_per_worker=0.5)
    finally:
        ray.shutdown()


def test_the_cluster_benchmark_times_fresh_runs_and_a_killed_worker(tmp_path):
    """benchmarks.cluster end to end on the CPU: one process, one worker and a run whose worker is
    killed mid-study, each in a fresh process, store the same study; the rates, their ratios and
    the plot come out."""
    import json

    done = subprocess.run([sys.executable, "-m", "benchmarks.cluster", "--studies", "kinematic", "--workers", "0", "1",
                           "--generations", "3", "--kinematic-worlds", "24", "--kill", "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    study = json.loads((tmp_path / "cluster_cpu.json").read_text())["studies"]["kinematic"]
    assert study["same_results"] is True
    runs = study["runs"]
    assert [(r["workers"], bool(r.get("killed"))) for r in runs] == [(0, False), (1, False), (1, True)]
    assert all(r["designs_per_s"] > 0.0 for r in runs) and runs[1]["efficiency"] == 1.0
    assert runs[0]["over_single_process"] == 1.0 and "kinematics" in runs[0]["stage_ms_per_design"]
    assert "replaced 1x" in done.stderr
    assert (tmp_path / "cluster_cpu.png").stat().st_size > 0
