"""A generation's metrics as arrays: what a cluster worker sends back and what the coordinator scores
and stores, without one Python dict a design on the way (a dict is made only for a design someone
reads by index, e.g. a notebook's plot).

A MetricTable is a read-mostly sequence of per-design metric dicts backed by a float64 matrix of the
scalar metrics (with a mask of which design has which), tracked-point paths end to end, and per-design
dicts of whatever else (bools, strings; usually none).
"""

from __future__ import annotations

import itertools
import math
import operator
from collections.abc import Sequence

import numpy as np

PATHS = "paths"  # the metric holding a design's tracked-point paths: {point: (T, 2) array}


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _number_block(dicts: list, rows: list, keys: list):
    """(len(rows), len(keys)) float64 of those designs' values under those keys when all are
    numbers (a bool among them reads as 0 or 1), else None (a None or anything else among them)."""
    if not keys:
        return None
    getter = operator.itemgetter(*keys)
    picked = [getter(dicts[i]) for i in rows] if len(keys) > 1 else [(dicts[i][keys[0]],) for i in rows]
    try:
        block = np.fromiter(itertools.chain.from_iterable(picked), np.float64, len(rows) * len(keys))
    except (TypeError, ValueError):
        return None
    return block.reshape(len(rows), len(keys))


class MetricTable(Sequence):
    """names (M,); values (N, M) float64; present (N, M) bool (a design has that metric); paths
    {point: (data (total, 2) float64, begin (N,), end (N,))}: design i's path of the point is
    data[begin[i]:end[i]] (begin -1: it has none; paths differ in length between designs);
    path_rows (N,) bool: which designs have paths; extra: None or per design a dict of its other
    metrics."""

    def __init__(self, names, values, present, paths=None, path_rows=None, extra=None):
        self.names = [str(n) for n in names]
        # writable copies where the arrays came read-only (unpickled from Ray's object store)
        self.values = np.require(np.asarray(values, dtype=np.float64), requirements=["W"])
        self.present = np.require(np.asarray(present, dtype=bool), requirements=["W"])
        if self.values.ndim != 2 or self.values.shape[1] != len(self.names) or self.present.shape != self.values.shape:
            raise ValueError(f"MetricTable: values {self.values.shape} and present {self.present.shape} must be "
                             f"(designs, {len(self.names)})")
        self.paths = dict(paths or {})
        n = len(self.values)
        self.path_rows = np.zeros(n, bool) if path_rows is None else np.asarray(path_rows, bool)
        self.extra = extra
        self._rows: dict[int, dict] = {}  # dicts made on request (kept, so edits to them persist)
        self._where = {name: j for j, name in enumerate(self.names)}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.values = np.require(self.values, requirements=["W"])  # Ray may hand back read-only buffers
        self.present = np.require(self.present, requirements=["W"])

    @classmethod
    def from_dicts(cls, dicts: list) -> MetricTable:
        """The table of per-design metric dicts (None: no metrics)."""
        dicts = [d or {} for d in dicts]
        n = len(dicts)
        groups: dict[tuple, list] = {}
        for i, d in enumerate(dicts):
            groups.setdefault(tuple(d), []).append(i)
        kinds = {}  # a key is a column where any group's first design has a number (or None) under it
        for keys, rows in groups.items():
            first = dicts[rows[0]]
            for k in keys:
                value = first[k]
                if value is None or _is_number(value):
                    kinds[k] = "number"
                else:
                    kinds.setdefault(k, "path" if k == PATHS and isinstance(value, dict) else "other")
        for keys, rows in groups.items():  # (rare) a key whose first value is not a number: any later one?
            for k in keys:
                if kinds[k] == "other" and any(dicts[i][k] is None or _is_number(dicts[i][k]) for i in rows):
                    kinds[k] = "number"
        names = [k for k, kind in kinds.items() if kind == "number"]
        where = {name: j for j, name in enumerate(names)}
        values = np.full((n, len(names)), np.nan)
        present = np.zeros((n, len(names)), bool)
        extra = None
        paths: dict[str, list] = {}
        path_rows = np.zeros(n, bool)
        for keys, rows in groups.items():
            numeric = [k for k in keys if kinds[k] == "number"]
            cols = [where[k] for k in numeric]
            block = _number_block(dicts, rows, numeric)
            if block is not None:  # the common case: numbers only, one array for the group
                values[np.asarray(rows)[:, None], cols] = block
                present[np.asarray(rows)[:, None], cols] = True
            others = [k for k in keys if kinds[k] != "number"]
            for i in (rows if block is None or others else ()):
                d = dicts[i]
                for k, j in zip(numeric if block is None else (), cols):
                    v = d[k]
                    if v is None or _is_number(v):
                        values[i, j] = math.nan if v is None else float(v)
                        present[i, j] = True
                    else:  # a later design has something else than a number under the key
                        extra = extra or [{} for _ in range(n)]
                        extra[i][k] = v
                for k in others:
                    if not (k == PATHS and isinstance(d[k], dict)):
                        extra = extra or [{} for _ in range(n)]
                        extra[i][k] = d[k]
                if isinstance(d.get(PATHS), dict):
                    path_rows[i] = True
                    for point, path in d[PATHS].items():
                        paths.setdefault(point, []).append((i, np.asarray(path, dtype=np.float64)))
        ragged = {}
        for point, entries in paths.items():
            trailing = {path.shape[1:] for _, path in entries}
            if len(trailing) != 1:
                raise ValueError(f"MetricTable: the paths of point '{point}' differ in their point size between "
                                 f"designs ({sorted(trailing)})")
            lengths = np.array([len(path) for _, path in entries], dtype=np.int64)
            begin, end = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
            rows_of = np.array([i for i, _ in entries], dtype=np.int64)
            begin[rows_of] = np.cumsum(lengths) - lengths
            end[rows_of] = np.cumsum(lengths)
            ragged[point] = (np.concatenate([path for _, path in entries]), begin, end)
        return cls(names, values, present, ragged, path_rows, extra)

    @classmethod
    def gather(cls, count: int, parts: list) -> MetricTable:
        """One table of ``count`` designs from shards: (indices, MetricTable) pairs, each shard's
        rows scattered to its indices."""
        names = list(dict.fromkeys(n for _, t in parts for n in t.names))
        where = {name: j for j, name in enumerate(names)}
        values = np.full((count, len(names)), np.nan)
        present = np.zeros((count, len(names)), bool)
        path_rows = np.zeros(count, bool)
        pieces: dict[str, list] = {}  # point -> [(data, begin, end, index)] of the shards
        extra = None
        for index, table in parts:
            index = np.asarray(index, dtype=np.int64)
            cols = np.array([where[n] for n in table.names], dtype=np.int64)
            values[index[:, None], cols] = table.values
            present[index[:, None], cols] = table.present
            path_rows[index] = table.path_rows
            for point, (data, begin, end) in table.paths.items():
                pieces.setdefault(point, []).append((data, begin, end, index))
            if table.extra is not None:
                extra = extra or [{} for _ in range(count)]
                for i, d in zip(index.tolist(), table.extra):
                    extra[i] = d
        paths = {}
        for point, shard_paths in pieces.items():  # the shards' data end to end, the bounds shifted
            if len({data.shape[1:] for data, *_ in shard_paths}) != 1:
                raise ValueError(f"MetricTable.gather: the paths of point '{point}' differ in their point size "
                                 f"between shards")
            begin, end = np.full(count, -1, np.int64), np.full(count, -1, np.int64)
            offset = 0
            for data, b, e, index in shard_paths:
                has = b >= 0
                begin[index[has]], end[index[has]] = b[has] + offset, e[has] + offset
                offset += len(data)
            paths[point] = (np.concatenate([data for data, *_ in shard_paths]), begin, end)
        return cls(names, values, present, paths, path_rows, extra)

    def __len__(self) -> int:
        return len(self.values)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        i = range(len(self))[i]
        row = self._rows.get(i)
        if row is None:
            row = {name: float(v) for name, v, p in zip(self.names, self.values[i].tolist(), self.present[i]) if p}
            if self.path_rows[i]:
                row[PATHS] = {point: data[begin[i]:end[i]] for point, (data, begin, end) in self.paths.items()
                              if begin[i] >= 0}
            if self.extra is not None:
                row.update(self.extra[i])
            self._rows[i] = row
        return row

    def column(self, name: str) -> np.ndarray:
        """(N,) the metric ``name`` as floats, NaN where a design does not have it (a bool counts as
        0 or 1, as it does in arithmetic on the dicts)."""
        self._sync()
        j = self._where.get(name)
        out = np.full(len(self), np.nan) if j is None else np.where(self.present[:, j], self.values[:, j], np.nan)
        if self.extra is not None:
            for i, d in enumerate(self.extra):
                v = d.get(name)
                if isinstance(v, (bool, np.bool_)) or (v is not None and _is_number(v)):
                    out[i] = float(v)
        return out

    def _add_column(self, name: str) -> int:
        j = self._where[name] = len(self.names)
        self.names.append(name)
        self.values = np.concatenate([self.values, np.full((len(self), 1), np.nan)], axis=1)
        self.present = np.concatenate([self.present, np.zeros((len(self), 1), bool)], axis=1)
        return j

    def _sync(self) -> None:
        """Take in the edits made through the dicts handed out by index (set, changed, deleted)."""
        for i, row in self._rows.items():
            for name, v in row.items():
                if name != PATHS and (v is None or _is_number(v)) and name not in self._where:
                    self._add_column(name)
            for j, name in enumerate(self.names):
                v = row.get(name, row)  # the row itself: absent
                number = v is not row and (v is None or _is_number(v))
                self.present[i, j] = number
                self.values[i, j] = float(v) if number and v is not None else math.nan
            other = {k: v for k, v in row.items() if k != PATHS and not (v is None or _is_number(v))}
            if other or self.extra is not None:
                self.extra = self.extra or [{} for _ in range(len(self))]
                self.extra[i] = other

    def set_column(self, name: str, values, rows=None) -> None:
        """Set metric ``name`` to ``values`` for the designs in the boolean mask ``rows`` (all: None)."""
        self._sync()
        rows = np.ones(len(self), bool) if rows is None else np.asarray(rows, bool)
        j = self._where.get(name)
        if j is None:
            j = self._add_column(name)
        values = np.broadcast_to(np.asarray(values, dtype=np.float64), (len(self),))
        self.values[rows, j] = values[rows]
        self.present[rows, j] = True
        for i, row in self._rows.items():
            if rows[i]:
                row[name] = float(values[i])

    def scalars(self) -> tuple[list, np.ndarray]:
        """(names, (N, M) float64) of the stored scalar metrics, the metrics some design has as a
        number or None (not bools): NaN where absent or not finite (what
        morphopt.storage.encode_metrics makes of the same dicts), edits made through the dicts
        handed out by index included."""
        self._sync()
        values = np.where(self.present, self.values, np.nan)
        values[~np.isfinite(values)] = np.nan
        keep = np.flatnonzero(self.present.any(axis=0))
        return [self.names[j] for j in keep], values[:, keep]
