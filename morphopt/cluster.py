"""A study's evaluations spread over a Ray cluster (``pip install "morphopt[cluster]"``).

The coordinator (run_study) keeps the optimizer and the storage; ClusterEvaluator keeps one
long-lived Ray actor per worker (a GPU each on a CUDA study, or a share of one: a worker's host
side, building and packing, takes longer than its GPU time, so two workers can keep one GPU
busier; else a group of CPU cores), so every
worker compiles its kernels once and keeps them warm between generations. A generation is split
into one shard per worker, designs grouped by their categorical parameters (their topology) so
each shard's padded batch stays tight; shards come back as arrays (morphopt.metric_table), in order, so the study is the same
whatever the number of workers. A worker that dies (its process killed, its node lost) or that
does not answer within the shard timeout is replaced and its shard runs again on a live worker,
said in the log; a generation is stored only once all its shards are in.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from morphopt.evaluate import Evaluation
from morphopt.metric_table import MetricTable
from morphopt.study_spec import MAX_WORKERS

__all__ = ["ClusterEvaluator", "WorkerStats", "shards"]

SHARD_TIMEOUT_MIN = 60.0  # [s] the least a shard is waited for (compiling kernels takes tens of seconds)
SHARD_TIMEOUT_FACTOR = 10.0  # a shard slower than this many times the generation's median is re-run elsewhere
SHARD_ATTEMPTS = 3  # a shard whose worker died or stalled this many times stops the study (a design that kills it)


def _ray():
    try:
        import ray
    except ImportError as exc:
        raise ValueError("a study on a cluster needs Ray: pip install \"morphopt[cluster]\"") from exc
    return ray


def shards(params: list, count: int, categorical: list) -> list:
    """Indices of ``params`` in ``count`` contiguous shards of near-equal size, after a stable sort by
    the categorical parameters' values (designs of one topology together)."""
    key = [tuple(str(p.get(name)) for name in categorical) for p in params]
    order = sorted(range(len(params)), key=lambda i: key[i])
    return [list(part) for part in np.array_split(np.asarray(order, dtype=int), max(1, min(count, len(params))))]


class _Worker:
    """A Ray actor's body: the study's family and evaluation settings, loaded once."""

    def __init__(self, family: str, mode: str, kwargs: dict):
        from morphopt.families import load_family
        from morphopt.warp_setup import quiet_warp

        quiet_warp()
        self.family, self.mode, self.kwargs = load_family(family), mode, kwargs

    def pid(self) -> int:
        return os.getpid()

    def stall(self, seconds: float) -> None:
        """Tests: keep this worker busy (a hung GPU, a swapping node)."""
        time.sleep(seconds)

    def evaluate(self, params: list, scenarios: list | None = None):
        """(MetricTable, failure codes (n,) int32, reasons (code -> text, 0: ""), timings, plan text)
        of one shard, arrays rather than a dict a design (what Ray moves back); scenarios: per design
        a robust study's scenario (morphopt.robust) or None."""
        from morphopt.evaluate import evaluate_dynamic, evaluate_kinematic
        from morphopt.robust import scenario_hooks

        if self.mode == "kinematic":
            result = evaluate_kinematic(self.family, params, **self.kwargs)
        else:
            hook = scenario_hooks(params, scenarios) if scenarios is not None else None
            result = evaluate_dynamic(self.family, params, spec_hook=hook, **self.kwargs)
        reasons = [""] + sorted({f for f in result.failures if f})
        code = {reason: k for k, reason in enumerate(reasons)}
        codes = np.fromiter((code[f] for f in result.failures), np.int32, len(result.failures))
        return (MetricTable.from_dicts(result.metrics), codes, reasons, result.timings,
                None if result.plan is None else str(result.plan))


@dataclass
class WorkerStats:
    """What one worker slot did over the study: designs evaluated, seconds spent, failed designs,
    and how often it was replaced (died or timed out)."""

    designs: int = 0
    seconds: float = 0.0
    failures: int = 0
    replaced: int = 0
    history: list = field(default_factory=list)

    @property
    def rate(self) -> float:
        """Designs a second over the seconds its shards took."""
        return self.designs / self.seconds if self.seconds > 0 else 0.0


class ClusterEvaluator:
    """Evaluates a study's generations on ``workers`` Ray actors. address: "local" (a Ray instance
    started here, ended by close()), "auto" (the running cluster this machine belongs to) or a Ray
    address; gpus_per_worker: a CUDA study's share of a GPU per worker, 0.0001 to 1 (0.5: two workers
    on each GPU); shard_timeout [s]: 0 chooses max(SHARD_TIMEOUT_MIN, SHARD_TIMEOUT_FACTOR x the
    generation's median shard time)."""

    def __init__(self, spec, space, *, address: str, workers: int = 0, gpus_per_worker: float = 1.0,
                 shard_timeout: float = 0.0, log=None):
        ray = _ray()
        self.ray, self.spec, self.log = ray, spec, log or (lambda line: print(line, file=sys.stderr))
        cuda = spec.device.startswith("cuda")
        self._started = False
        try:
            self._start(ray, spec, space, address, workers, gpus_per_worker if cuda else 0.0, shard_timeout, cuda)
        except BaseException:
            if self._started:  # a Ray instance this evaluator started does not outlive its failure
                ray.shutdown()
            raise

    def _start(self, ray, spec, space, address, workers, share, shard_timeout, cuda) -> None:
        if not ray.is_initialized():
            if address == "local":
                cpus = max(1, workers or os.cpu_count() or 1)
                ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False, configure_logging=False)
                self._started = True
            else:
                ray.init(address=address, log_to_driver=False, configure_logging=False)
        resources = ray.cluster_resources()
        gpus = int(resources.get("GPU", 0))
        if cuda and gpus <= 0:
            raise ValueError(f"{spec.path}: 'study.device' is {spec.device!r} but the Ray cluster at {address!r} "
                             f"has no GPU")
        # workers that fit: each GPU holds whole shares (the float's rounding forgiven), else CPU cores
        have = gpus * int(1.0 / share + 1e-9) if cuda else int(resources.get("CPU", 0))
        if have <= 0:
            raise ValueError(f"{spec.path}: the Ray cluster at {address!r} has no whole CPU for a worker")
        if workers <= 0:
            workers = min(have, MAX_WORKERS)  # as many as fit
        if workers > have:  # an actor that can never be placed would time out and be replaced forever
            raise ValueError(f"{spec.path}: {workers} workers asked for, the Ray cluster at {address!r} has "
                             + (f"{gpus} GPUs, room for {have} workers at {share:g} GPU each" if cuda
                                else f"{have} CPUs"))
        self.workers = workers
        self.cpus = 0 if cuda else max(1, have // workers)
        if spec.mode == "kinematic":  # (an actor sees its one GPU as cuda:0)
            kwargs = dict(samples=spec.samples, device="cuda" if cuda else spec.device,
                          keep_paths=any(o.metric == "path_error" for o in spec.objectives))
        else:
            kwargs = dict(duration=spec.duration, dt=spec.dt, device="cuda" if cuda else spec.device,
                          crank_speed=spec.crank_speed, config=spec.solver_config())
        self._args = (spec.family, spec.mode, kwargs)
        self._actor_class = ray.remote(num_cpus=self.cpus, num_gpus=share if cuda else 0)(_Worker)
        self.actors = [self._new_actor() for _ in range(workers)]
        self.stats = [WorkerStats() for _ in range(workers)]
        self.shard_timeout = float(shard_timeout)
        self.generation = 0
        self.kill_hook = _test_hook("MORPHOPT_TEST_KILL_WORKER")
        # the actors' process ids, read while they are idle (tests: the kill hook kills mid-shard)
        self._pids = ray.get([a.pid.remote() for a in self.actors]) if self.kill_hook else []
        self.last = None  # the last generation's per-worker rows (worker, designs, seconds, failures, replaced)
        self._fresh = set(range(workers))  # slots whose actor has not returned a shard yet (compiling)
        self.categorical = [n for n, p in space.parameters.items() if not _numeric(p)]

    def _new_actor(self):
        return self._actor_class.remote(*self._args)

    def _replace(self, slot: int, why: str) -> None:
        self.log(f"{self.spec.name}: worker {slot} {why}; its shard runs again on a new worker")
        try:
            self.ray.kill(self.actors[slot])
        except Exception:  # noqa: BLE001 - already gone
            pass
        self.actors[slot] = self._new_actor()
        self.stats[slot].replaced += 1
        self._fresh.add(slot)

    def evaluate(self, params: list, scenarios: list | None = None) -> Evaluation:
        """Every design of ``params`` evaluated on the workers, results in the order of ``params``;
        scenarios: per design a robust study's scenario or None (morphopt.robust)."""
        ray = self.ray
        parts = shards(params, self.workers, self.categorical)
        pending = {}  # future -> (shard, slot, started)
        stall = _test_hook("MORPHOPT_TEST_STALL_WORKER")
        if stall and stall[0] == self.generation:  # tests: a worker that hangs before its shard
            self.actors[stall[1] % self.workers].stall.remote(3600.0)
        for k, part in enumerate(parts):
            slot = k % self.workers
            pending[self._submit(part, params, scenarios, slot)] = (k, slot, time.perf_counter())
        if self.kill_hook and self.kill_hook[0] == self.generation:  # tests: a worker's process killed mid-shard
            victim = self.kill_hook[1] % self.workers
            os.kill(self._pids[victim], signal.SIGKILL)
        done, durations = {}, []
        attempts = [1] * len(parts)
        before = [(s.designs, s.seconds, s.failures, s.replaced) for s in self.stats]
        while pending:
            warm = self._timeout(durations)
            limits = {f: (10 * SHARD_TIMEOUT_MIN if slot in self._fresh and self.shard_timeout <= 0 else warm)
                      for f, (_, slot, _) in pending.items()}  # a fresh worker compiles first
            now = time.perf_counter()
            wait = max(0.0, min(started + limits[f] - now for f, (_, _, started) in pending.items()))
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=wait)
            if not ready:  # the shards past their time: re-run elsewhere, their workers replaced
                now = time.perf_counter()
                for future, (k, slot, started) in list(pending.items()):
                    if now - started >= limits[future]:
                        del pending[future]
                        self._again(k, attempts, f"did not return shard {k} within {limits[future]:.0f} s")
                        self._replace(slot, f"did not return shard {k} within {limits[future]:.0f} s")
                        pending[self._submit(parts[k], params, scenarios, slot)] = (k, slot, time.perf_counter())
                continue
            future = ready[0]
            k, slot, started = pending.pop(future)
            try:
                done[k] = ray.get(future)
            except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as exc:
                self._again(k, attempts, f"died during shard {k} ({type(exc).__name__})")
                self._replace(slot, f"died during shard {k} ({type(exc).__name__})")
                pending[self._submit(parts[k], params, scenarios, slot)] = (k, slot, time.perf_counter())
                continue
            spent = time.perf_counter() - started
            if slot not in self._fresh:
                durations.append(spent)  # (a fresh worker's shard includes its compilation)
            self._fresh.discard(slot)
            stats = self.stats[slot]
            stats.designs += len(parts[k])
            stats.seconds += spent
            stats.failures += int(np.count_nonzero(done[k][1]))
        self.generation += 1
        self.last = [(k, s.designs - b[0], s.seconds - b[1], s.failures - b[2], s.replaced - b[3])
                     for k, (s, b) in enumerate(zip(self.stats, before))]  # this generation's, per worker
        return _gathered(params, parts, done)

    def _again(self, k: int, attempts: list, why: str) -> None:
        """Count another attempt of shard k; ValueError once it has had SHARD_ATTEMPTS."""
        if attempts[k] >= SHARD_ATTEMPTS:
            raise ValueError(f"{self.spec.name}: shard {k} failed {attempts[k]} times on fresh workers (last: {why}); "
                             f"a design in it may crash its worker: run the generation in one process to see which")
        attempts[k] += 1

    def _submit(self, part, params, scenarios, slot):
        """Shard ``part`` (indices of params) to the actor in ``slot``."""
        return self.actors[slot].evaluate.remote([params[i] for i in part],
                                                 None if scenarios is None else [scenarios[i] for i in part])

    def _timeout(self, durations: list) -> float:
        if self.shard_timeout > 0:
            return self.shard_timeout
        if not durations:
            return 10 * SHARD_TIMEOUT_MIN  # no warm shard measured yet
        return max(SHARD_TIMEOUT_MIN, SHARD_TIMEOUT_FACTOR * float(np.median(durations)))

    def report(self) -> str:
        """One line per worker: designs, designs/s, failed designs, replacements."""
        return "; ".join(f"worker {k}: {s.designs} designs, {s.rate:,.1f} designs/s, {s.failures} failed"
                         + (f", replaced {s.replaced}x" if s.replaced else "") for k, s in enumerate(self.stats))

    def close(self) -> None:
        """End the workers, and the Ray instance where this evaluator started it."""
        for actor in self.actors:
            try:
                self.ray.kill(actor)
            except Exception:  # noqa: BLE001
                pass
        if self._started:
            self.ray.shutdown()


def _numeric(parameter) -> bool:
    from morphopt.design_space import Float, Int

    return isinstance(parameter, (Float, Int))


def _gathered(params: list, parts: list, done: dict) -> Evaluation:
    """The shards' results in the order of ``params``: one MetricTable and the failures scattered
    by index, the stages' seconds summed over the shards (worker-seconds, more than the
    generation's wall time when the workers run at once), the first shard's plan."""
    failures = np.full(len(params), "", dtype=object)
    timings = {}
    plan = None
    for k, part in enumerate(parts):
        _, codes, reasons, shard_timings, shard_plan = done[k]
        failures[np.asarray(part, dtype=np.int64)] = np.asarray(reasons, dtype=object)[codes]
        for stage, spent in shard_timings.items():
            timings[stage] = timings.get(stage, 0.0) + spent
        plan = plan or shard_plan
    metrics = MetricTable.gather(len(params), [(part, done[k][0]) for k, part in enumerate(parts)])
    return Evaluation(list(params), metrics, failures.tolist(), timings, plan)


def _test_hook(name: str):
    """(G, K) of a test hook "G:K": MORPHOPT_TEST_KILL_WORKER kills worker K's process during
    generation G, MORPHOPT_TEST_STALL_WORKER keeps it busy then; None when not set."""
    value = os.environ.get(name, "")
    if not value:
        return None
    generation, worker = value.split(":")
    return int(generation), int(worker)
