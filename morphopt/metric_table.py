"""A generation's metrics as arrays: what a cluster worker sends back and what the coordinator scores
and stores, without one Python dict a design on the way (a dict is made only for a design someone
reads by index, e.g. a notebook's plot).

A MetricTable is a read-mostly sequence of per-design metric dicts backed by a float64 matrix of the
scalar metrics (with a mask of which design has which), tracked-point paths end to end, and per-design
dicts of whatever else (bools, strings; usually none).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

PATHS = "paths"  # the metric holding a design's tracked-point paths: {point: (T, 2) array}


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


class MetricTable(Sequence):
    """names (M,); values (N, M) float64; present (N, M) bool (a design has that metric); paths
    {point: (data (total, 2) float64, begin (N,), end (N,))}: design i's path of the point is
    data[begin[i]:end[i]] (begin -1: it has none; paths differ in length between designs);
    path_rows (N,) bool: which designs have paths; extra: None or per design a dict of its other
    metrics."""

    def __init__(self, names, values, present, paths=None, path_rows=None, extra=None):
        self.names = [str(n) for n in names]
        self.values = np.asarray(values, dtype=np.float64).reshape(-1, len(self.names))
        self.present = np.asarray(present, dtype=bool).reshape(self.values.shape)
        self.paths = dict(paths or {})
        n = len(self.values)
        self.path_rows = np.zeros(n, bool) if path_rows is None else np.asarray(path_rows, bool)
        self.extra = extra
        self._rows: dict[int, dict] = {}  # dicts made on request (kept, so edits to them persist)
        self._where = {name: j for j, name in enumerate(self.names)}

    @classmethod
    def from_dicts(cls, dicts: list) -> MetricTable:
        """The table of per-design metric dicts (None: no metrics)."""
        dicts = [d or {} for d in dicts]
        n = len(dicts)
        groups: dict[tuple, list] = {}
        for i, d in enumerate(dicts):
            groups.setdefault(tuple(d), []).append(i)
        names, kinds = [], {}
        for keys, rows in groups.items():
            first = dicts[rows[0]]
            for k in keys:
                value = first[k]
                kind = "path" if k == PATHS and isinstance(value, dict) else (
                    "number" if value is None or _is_number(value) else "other")
                kinds.setdefault(k, kind)
                if kinds[k] == "number" and k not in names:
                    names.append(k)
        where = {name: j for j, name in enumerate(names)}
        values = np.full((n, len(names)), np.nan)
        present = np.zeros((n, len(names)), bool)
        extra = None
        paths: dict[str, list] = {}
        path_rows = np.zeros(n, bool)
        for keys, rows in groups.items():
            numeric = [k for k in keys if kinds[k] == "number"]
            cols = [where[k] for k in numeric]
            for i in rows:
                d = dicts[i]
                for k, j in zip(numeric, cols):
                    v = d[k]
                    if v is None or _is_number(v):
                        values[i, j] = math.nan if v is None else float(v)
                        present[i, j] = True
                    else:  # a later design has something else than a number under the key
                        extra = extra or [{} for _ in range(n)]
                        extra[i][k] = v
                for k in keys:
                    if kinds[k] != "number" and not (k == PATHS and isinstance(d[k], dict)):
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
        """(N,) the metric ``name``, NaN where a design does not have it."""
        j = self._where.get(name)
        if j is None:
            return np.full(len(self), np.nan)
        return np.where(self.present[:, j], self.values[:, j], np.nan)

    def set_column(self, name: str, values, rows=None) -> None:
        """Set metric ``name`` to ``values`` for the designs in the boolean mask ``rows`` (all: None)."""
        rows = np.ones(len(self), bool) if rows is None else np.asarray(rows, bool)
        j = self._where.get(name)
        if j is None:
            j = self._where[name] = len(self.names)
            self.names.append(name)
            self.values = np.concatenate([self.values, np.full((len(self), 1), np.nan)], axis=1)
            self.present = np.concatenate([self.present, np.zeros((len(self), 1), bool)], axis=1)
        values = np.broadcast_to(np.asarray(values, dtype=np.float64), (len(self),))
        self.values[rows, j] = values[rows]
        self.present[rows, j] = True
        for i, row in self._rows.items():
            if rows[i]:
                row[name] = float(values[i])

    def scalars(self) -> tuple[list, np.ndarray]:
        """(names, (N, M) float64) of the stored scalar metrics: NaN where absent or not finite (what
        morphopt.storage.encode_metrics makes of the same dicts). Metrics set on a design's dict after
        it was read by index are included."""
        values = np.where(self.present, self.values, np.nan)
        names = list(self.names)
        for i, row in self._rows.items():  # edits made through dicts handed out
            for name, v in row.items():
                if name == PATHS or not (v is None or _is_number(v)):
                    continue
                if name not in self._where:
                    self.set_column(name, np.nan, np.zeros(len(self), bool))
                    values = np.concatenate([values, np.full((len(self), 1), np.nan)], axis=1)
                    names = list(self.names)
                values[i, self._where[name]] = math.nan if v is None else float(v)
        values[~np.isfinite(values)] = np.nan
        keep = [j for j, name in enumerate(names) if np.any(self.present[:, j]) or np.any(np.isfinite(values[:, j]))]
        return [names[j] for j in keep], values[:, keep]
