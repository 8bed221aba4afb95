"""Designs to MechanismSpecs, in this process or spread over a pool of worker processes.

Building a walker's spec is Python and small NumPy operations (assembly, bars' mass and inertia,
validation of every body and joint): about 1 ms per walker on one core of the 2-core CPU when the
family builds a batch at once (a family's optional build_specs: the walker assembles every leg of
a generation in one solve). ``build_specs`` hands large batches to worker processes (one per core
but one), which load the family from its file and send the specs back pickled (a MechanismSpec
pickles as columns); the specs are the same to the last bit as the ones built here.

``build_prepared`` also has the workers make engine.prepare of their specs (the per-spec part of
engine.pack's analysis), so that the process that packs and simulates, the one that holds the GPU,
only receives it.

Workers start through a fork server that preloads this module (never by forking a process that may
hold a CUDA context); as with any spawned process, a worker imports the user's main script first
(as ``__mp_main__``), so a script's work belongs under ``if __name__ == "__main__":``. A pool that
breaks (a worker killed, or a script without that guard) is dropped with a warning and the batch
is built here. The pool is made on first use and kept for the next generations.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import gc
import multiprocessing
import os
import warnings
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from morphopt.families import load_family
from morphopt.linkage import to_spec

__all__ = ["LINKAGE_CRANK_SPEED", "PARALLEL_MIN_DESIGNS", "build_prepared", "build_spec", "build_specs",
           "crank_speed_of", "default_workers", "no_collection"]

LINKAGE_CRANK_SPEED = 2.0 * np.pi  # [rad/s] a linkage family's drive when the study sets no crank_speed
PARALLEL_MIN_DESIGNS = 256  # smaller batches build faster here than a pool sends them back
# engine.prepare costs a worker about as much as it saves the packing process (0.3 ms a walker, 2-core CPU):
# worth it from this many workers on (benchmarks/results/README.md, "The build workers prepare the pack")
PREPARE_MIN_WORKERS = 3
_pools: dict[int, ProcessPoolExecutor] = {}


def crank_speed_of(family, crank_speed: float | None) -> float | None:
    """The crank speed [rad/s] build_spec drives a design at: crank_speed, else LINKAGE_CRANK_SPEED
    for a linkage family, else None (a whole-world family's own default)."""
    if crank_speed is not None or hasattr(family, "build_spec"):
        return crank_speed
    return LINKAGE_CRANK_SPEED


def build_spec(family, params: dict, crank_speed: float | None):
    """One design's engine.MechanismSpec: a whole-world family's build_spec, or a linkage family's
    generate then to_spec (driven at crank_speed, LINKAGE_CRANK_SPEED when None). ValueError when
    the design cannot be built."""
    if hasattr(family, "build_spec"):
        return family.build_spec(family.space.validate(params), crank_speed=crank_speed)
    return to_spec(family.generate(family.space.validate(params), crank_speed=crank_speed_of(family, crank_speed)))


def default_workers() -> int:
    """Worker processes for a large batch: the cores this process may use, but one (at most 32)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores - 1, 32))


def _build_each(family, params: Sequence[dict], crank_speed) -> list:
    """Spec or failure reason (str) per design, in order. A whole-world family that also defines
    build_specs(designs, crank_speed=...) (per design its spec or ValueError, as build_spec
    would give or raise it) builds the validated designs in one call."""
    if hasattr(family, "build_spec") and hasattr(family, "build_specs") and len(params) > 1:
        out, valid = [], []
        for p in params:
            try:
                valid.append(family.space.validate(p))
                out.append(None)
            except ValueError as exc:
                out.append(f"cannot be built: {exc}")
        made = iter(family.build_specs(valid, crank_speed=crank_speed))
        return [f"cannot be built: {spec}" if isinstance(spec, ValueError) else spec
                for spec in (reason if reason is not None else next(made) for reason in out)]
    out = []
    for p in params:
        try:
            out.append(build_spec(family, p, crank_speed))
        except ValueError as exc:
            out.append(f"cannot be built: {exc}")
    return out


@functools.lru_cache(maxsize=8)
def _family_at(path: str, stamp: float):
    """The family module of a file, loaded once per worker and file version."""
    return load_family(path)


def _build_chunk(path: str, stamp: float, params: list, crank_speed, prepare: bool = False):
    """Worker side: the family from its file, then _build_each; with ``prepare``, the built list
    and engine.prepare of its specs (None for a design that failed)."""
    built = _build_each(_family_at(path, stamp), params, crank_speed)
    if not prepare:
        return built
    from engine import prepare as engine_prepare

    specs = [spec for spec in built if not isinstance(spec, str)]
    try:
        made = iter(engine_prepare(specs))
    except Exception:  # noqa: BLE001 - only a head start: the packing process analyses these specs itself
        return built, [None] * len(built)
    return built, [None if isinstance(spec, str) else next(made) for spec in built]


def _pool(workers: int) -> ProcessPoolExecutor:
    pool = _pools.get(workers)
    if pool is None:
        methods = multiprocessing.get_all_start_methods()
        context = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
        if "forkserver" in methods:
            context.set_forkserver_preload(["morphopt.build"])  # instead of the default, the user's __main__
        pool = _pools[workers] = ProcessPoolExecutor(workers, mp_context=context)
    return pool


@atexit.register
def _close_pools() -> None:
    for pool in _pools.values():
        pool.shutdown(wait=False, cancel_futures=True)
    _pools.clear()


def _family_file(family) -> str | None:
    """The .py file a family module was loaded from (morphopt.families.load_family), else None."""
    path = getattr(family, "__file__", None)
    return path if path and os.path.isfile(path) and path.endswith(".py") else None


def build_specs(family, params: Sequence[dict], *, crank_speed: float | None = None,
                workers: int | None = None, share: bool = False) -> list:
    """Spec or failure reason ("cannot be built: ...") per design, in the order of ``params``.

    workers: None picks default_workers() for batches of PARALLEL_MIN_DESIGNS or more and builds
    smaller ones here; 1 builds here; more uses that many worker processes for any batch. A family
    that was not loaded from a file (load_family) is always built here. If the pool breaks (a
    worker killed), the batch is built here instead. share: designs of equal parameters (a robust
    study's scenario worlds of one design) are built once and share one spec object, which the
    caller must then not change in place.
    """
    return build_prepared(family, params, crank_speed=crank_speed, workers=workers, share=share, prepare=False)[0]


def build_prepared(family, params: Sequence[dict], *, crank_speed: float | None = None,
                   workers: int | None = None, share: bool = False, prepare: bool = True) -> tuple[list, list | None]:
    """build_specs' list, and per design engine.prepare of its spec where PREPARE_MIN_WORKERS or
    more worker processes built it (None for a design that failed; the whole list None where the
    batch was built here or by fewer workers, which leaves the analysis to engine.pack). For
    ``engine.pack(specs, prepared=...)`` while the specs stay as built (a spec_hook that changes
    them must not pass it on)."""
    params = list(params)
    if share:
        first, unique, where = {}, [], []  # per design its index among the distinct designs
        for p in params:
            k = first.setdefault(_design_key(p), len(unique))
            if k == len(unique):
                unique.append(p)
            where.append(k)
        if len(unique) < len(params):
            built, prepared = build_prepared(family, unique, crank_speed=crank_speed, workers=workers,
                                             prepare=prepare)
            return [built[k] for k in where], None if prepared is None else [prepared[k] for k in where]
    path = _family_file(family)
    if workers is None:
        workers = default_workers() if len(params) >= PARALLEL_MIN_DESIGNS else 1
    if not isinstance(workers, (int, np.integer)) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"build_specs: workers must be a positive integer or None, got {workers!r}")
    # Making (or unpickling) thousands of small objects sets off the cyclic garbage collector again
    # and again (2/3 of the time of receiving a generation's specs, a fifth of building them here):
    # none of them is garbage yet.
    with no_collection():
        if workers == 1 or path is None or len(params) < 2:
            return _build_each(family, params, crank_speed), None
        stamp = os.path.getmtime(path)
        prepare = prepare and workers >= PREPARE_MIN_WORKERS
        chunks = [list(c) for c in np.array_split(np.arange(len(params)), min(len(params), 4 * workers)) if len(c)]
        pool = _pool(int(workers))
        try:
            futures = [pool.submit(_build_chunk, path, stamp, [params[i] for i in c], crank_speed, prepare)
                       for c in chunks]
            results = [future.result() for future in futures]
        except BrokenProcessPool as exc:
            _pools.pop(int(workers), None)
            warnings.warn(f"morphopt.build: the build processes broke ({exc}); building this batch here. A script "
                          f"that builds designs needs its work under if __name__ == '__main__':",
                          RuntimeWarning, stacklevel=2)
            return _build_each(family, params, crank_speed), None
        if not prepare:
            return [spec for built in results for spec in built], None
        return [spec for built, _ in results for spec in built], [p for _, made in results for p in made]


def _design_key(params: dict) -> tuple:
    """Equal for designs of equal parameter values (names and exact reprs, arrays by their bytes, in
    any key order)."""
    return tuple(sorted((name, type(value).__name__,
                         (value.dtype.str, value.shape, value.tobytes()) if isinstance(value, np.ndarray)
                         else repr(value)) for name, value in params.items()))


@contextlib.contextmanager
def no_collection():
    """A block without the cyclic garbage collector (as it was before: on or off) afterwards."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if collecting:
            gc.enable()
