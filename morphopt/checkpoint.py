"""Optimizer checkpoints without pickle: a declarative blob, and the optimizer rebuilt by replay.

A study never stores an optimizer object. Every generation it stores what the optimizer was told
(one row of ``optimizer_log``: a digest of the designs it asked for and the values it was told,
float64) and a small checkpoint blob:

    b"morphopt-checkpoint\\n" | header length (uint64, little-endian) | header (UTF-8 JSON) | float64 data

The header holds the format version, the optimizer's name, the generation, the design space, and
the names, offsets and shapes of float64 arrays that summarize the optimizer's state after that
generation (CMA-ES's mean and step size, the random generators' states, the best design). The
reader builds nothing but dicts, lists, strings, numbers and float64 arrays: a checkpoint from a
foreign database can be wrong, never run code.

Resume rebuilds the optimizer from the study's settings (a fresh, seeded instance) and replays
every stored generation: ask, check that the designs asked for hash to the stored digest, tell the
stored values. The summary of the rebuilt optimizer must then equal the checkpoint's bit for bit,
so a resumed study continues exactly as an uninterrupted one (pycma, Optuna's samplers and the
random search are deterministic given their seed and what they were told). A study stored by an
earlier morphopt as a pickle is never unpickled: ``rebuild`` can replay its stored designs instead.
"""

from __future__ import annotations

import hashlib
import json
import math
import struct

import numpy as np

from morphopt.design_space import Choice, DesignSpace, Int

__all__ = ["MAGIC", "CheckpointError", "check_summary", "decode", "designs_digest", "encode", "is_legacy_pickle",
           "replay", "restore_random_states", "space_description", "summary"]

MAGIC = b"morphopt-checkpoint\n"
VERSION = 1
MAX_HEADER = 1 << 20  # bytes; a header is a few kilobytes


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or does not match its study (the message says why)."""


def is_legacy_pickle(blob: bytes) -> bool:
    """True for a checkpoint stored by an earlier morphopt (a pickle, protocol 2 or later)."""
    return bytes(blob[:1]) == b"\x80"


def designs_digest(designs) -> str:
    """SHA-256 of a batch of designs (parameter dicts), exact: a column of floats by its float64
    bytes, of integers by their int64 bytes, anything else by its JSON text (a column at a time:
    hashing 4096 designs costs about a millisecond)."""
    digest = hashlib.sha256()
    keys = sorted({key for design in designs for key in design})
    digest.update(json.dumps([len(designs), keys]).encode())
    for key in keys:
        column = [design.get(key) for design in designs]
        if all(isinstance(v, (float, np.floating)) for v in column):
            digest.update(b"f" + np.asarray(column, dtype="<f8").tobytes())
        elif all(isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) for v in column):
            digest.update(b"i" + np.asarray(column, dtype="<i8").tobytes())
        else:
            digest.update(b"j" + json.dumps([_plain(v) for v in column]).encode())
    return digest.hexdigest()


def _plain(value):
    """A design value as JSON data (NumPy scalars as Python ones; anything else by its text)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return value if value is None or isinstance(value, str) else str(value)


def space_description(space: DesignSpace) -> list:
    """The design space as JSON data (names, kinds, bounds, choices): a checkpoint is only valid for it."""
    out = []
    for name, p in space.parameters.items():
        if isinstance(p, Choice):
            out.append([name, "choice", [str(o) for o in p.options]])
        else:
            out.append([name, "int" if isinstance(p, Int) else "float", [repr(float(p.low)), repr(float(p.high)),
                                                                         bool(getattr(p, "log", False))]])
    return out


def _rng_arrays(prefix: str, rng) -> dict:
    """A NumPy random state as float64 arrays (exact: every word is below 2**53)."""
    if isinstance(rng, np.random.RandomState):
        _, key, pos, has_gauss, gauss = rng.get_state()
        return {f"{prefix}.mt19937": np.asarray(key, dtype=np.float64),
                f"{prefix}.position": np.array([pos, has_gauss, gauss], dtype=np.float64)}
    state = rng.bit_generator.state["state"]  # PCG64: two 128-bit words, split into 32-bit pieces
    words = [(state[k] >> (32 * i)) & 0xFFFFFFFF for k in ("state", "inc") for i in range(4)]
    return {f"{prefix}.pcg64": np.array(words, dtype=np.float64)}


def summary(optimizer) -> dict:
    """Named float64 arrays that pin down the optimizer's state (what a replay must reproduce)."""
    from morphopt.optimizers import CMAES, OptunaSampler

    best = optimizer.best_value if math.isfinite(optimizer.best_value) else math.inf
    arrays = {"evaluations": np.array([optimizer.evaluations], dtype=np.float64),
              "best.value": np.array([best]),
              **_rng_arrays("rng", optimizer.rng)}
    if optimizer.best_params is not None:
        arrays["best.unit"] = optimizer.space.to_unit(optimizer.best_params).astype(np.float64)
    if isinstance(optimizer, CMAES):
        es = optimizer.es
        arrays["cma.mean"] = np.asarray(es.mean, dtype=np.float64)
        arrays["cma.sigma"] = np.array([es.sigma], dtype=np.float64)
        arrays["cma.iterations"] = np.array([es.countiter, optimizer.restarts_done], dtype=np.float64)
        arrays.update(_rng_arrays("cma.randn", optimizer.randn_state))
    elif isinstance(optimizer, OptunaSampler):
        arrays["optuna.trials"] = np.array([len(optimizer.study.get_trials(deepcopy=False))], dtype=np.float64)
        for k, rng in enumerate(optimizer.sampler_states()):
            arrays.update(_rng_arrays(f"optuna.rng{k}", rng))
    return arrays


def encode(header: dict, arrays: dict) -> bytes:
    """The blob of a header (JSON data) and named float64 arrays."""
    entries, offset, chunks = [], 0, []
    for name, array in arrays.items():
        data = np.ascontiguousarray(array, dtype="<f8")
        entries.append([name, offset, list(data.shape)])
        offset += data.size
        chunks.append(data.tobytes())
    text = json.dumps({**header, "version": VERSION, "arrays": entries}, allow_nan=False).encode()
    return MAGIC + struct.pack("<Q", len(text)) + text + b"".join(chunks)


def decode(blob, where: str) -> tuple[dict, dict]:
    """(header, arrays) of a blob written by ``encode``; CheckpointError naming ``where`` otherwise."""
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise CheckpointError(f"{where}: the optimizer checkpoint is not a byte string")
    blob = bytes(blob)
    if is_legacy_pickle(blob):
        raise CheckpointError(f"{where}: the optimizer checkpoint is a pickle written by an earlier morphopt, which "
                              f"this version never unpickles (a pickle can run code); 'study resume --trust-checkpoint' "
                              f"rebuilds the optimizer from the stored designs instead, or start over with "
                              f"'study run --fresh'")
    start = len(MAGIC) + 8
    if not blob.startswith(MAGIC) or len(blob) < start:
        raise CheckpointError(f"{where}: the optimizer checkpoint is not in morphopt's checkpoint format")
    (length,) = struct.unpack("<Q", blob[len(MAGIC):start])
    if length > min(MAX_HEADER, len(blob) - start):
        raise CheckpointError(f"{where}: the optimizer checkpoint is truncated or damaged (header of {length} bytes)")
    try:
        header = json.loads(blob[start:start + length].decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise CheckpointError(f"{where}: the optimizer checkpoint's header is not JSON ({exc})") from exc
    if not isinstance(header, dict) or header.get("version") != VERSION:
        version = header.get("version") if isinstance(header, dict) else None
        raise CheckpointError(f"{where}: the optimizer checkpoint has format version {version!r}; this morphopt "
                              f"reads version {VERSION}")
    data = blob[start + length:]
    if len(data) % 8:
        raise CheckpointError(f"{where}: the optimizer checkpoint is truncated ({len(data)} bytes of arrays)")
    values = np.frombuffer(data, dtype="<f8")
    arrays = {}
    try:
        for name, offset, shape in header["arrays"]:
            size = math.prod(shape)
            if not (isinstance(name, str) and all(isinstance(n, int) and n >= 0 for n in (offset, size, *shape))
                    and offset + size <= values.size):
                raise ValueError(f"array {name!r} out of bounds")
            arrays[name] = values[offset:offset + size].reshape(shape)
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{where}: the optimizer checkpoint's arrays are damaged ({exc})") from exc
    return header, arrays


def replay(optimizer, log, where: str, designs=None) -> None:
    """Bring a freshly built optimizer to the state after the logged generations: ``log`` yields
    (generation, digest of the designs asked for, told (designs, 1 + objectives) float64). The
    second column on holds the objective vectors of a Pareto study. ``designs`` (per generation,
    the stored designs): an optimizer that ``takes_stored_designs`` (Optuna's TPE and random) gets
    them through ``ask_stored`` instead of sampling, and its random states must then be restored
    from the checkpoint (``restore_random_states``)."""
    for k, (generation, digest, told) in enumerate(log):
        if designs is not None and getattr(optimizer, "takes_stored_designs", False):
            asked = optimizer.ask_stored(designs[k])
        else:
            asked = optimizer.ask(len(told))
        if designs_digest(asked) != digest:
            raise CheckpointError(f"{where}: the optimizer rebuilt from the stored study asks for other designs in "
                                  f"generation {generation} than the stored ones (another version of pycma or "
                                  f"Optuna, or a changed design space?); start over with 'study run --fresh'")
        values = told[:, 0].tolist()
        if told.shape[1] > 1:
            optimizer.tell(asked, values, told[:, 1:])
        else:
            optimizer.tell(asked, values)


def restore_random_states(optimizer, arrays: dict, where: str) -> None:
    """Set the random states of an Optuna sampler to the checkpoint's (after a replay of stored designs)."""
    states = optimizer.sampler_states()
    for k, rng in enumerate(states):
        key, position = arrays.get(f"optuna.rng{k}.mt19937"), arrays.get(f"optuna.rng{k}.position")
        if key is None or position is None or key.shape != (624,) or position.shape != (3,):
            raise CheckpointError(f"{where}: the checkpoint lacks the state of the sampler's random generator {k}")
        words_ok = bool(np.all((key >= 0) & (key < 2.0**32) & (key == np.floor(key))))
        pos, has_gauss, gauss = (float(v) for v in position)
        if not (words_ok and pos in range(625) and has_gauss in (0.0, 1.0) and math.isfinite(gauss)):
            raise CheckpointError(f"{where}: the checkpoint's state of the sampler's random generator {k} is damaged")
        rng.set_state(("MT19937", key.astype(np.uint32), int(pos), int(has_gauss), gauss))


def check_summary(optimizer, arrays: dict, where: str) -> None:
    """CheckpointError unless the rebuilt optimizer's summary equals the checkpoint's, bit for bit."""
    rebuilt = summary(optimizer)
    for name in sorted(set(rebuilt) | set(arrays)):
        a, b = rebuilt.get(name), arrays.get(name)
        if a is None or b is None or a.shape != b.shape or a.astype("<f8").tobytes() != b.astype("<f8").tobytes():
            raise CheckpointError(f"{where}: the optimizer rebuilt from the stored generations differs from its "
                                  f"checkpoint ({name}); start over with 'study run --fresh'")
