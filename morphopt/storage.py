"""Study storage: every evaluated design in an SQL database (SQLite file by default, any
SQLAlchemy URL), written in bulk once per generation together with the optimizer checkpoint, read
back as a pandas DataFrame.

One row per design: study, generation, member, objective value and failure reason as SQL
columns; its numeric parameters and its scalar metrics as little-endian float64 byte strings
(formatting 25 metrics per design as text cost more than the rest of a generation's recording),
whose names and kinds are stored once per generation (table ``design_columns``): float, int or
bool parameters as numbers, string parameters (categorical choices) as indices into a label
list, parameters with the same value in every design as that value, anything else as JSON in the
row's ``extras``. Non-finite metrics read back as NaN. Databases written by earlier versions
(parameters and metrics as JSON text) are read as they are and extended in the new layout.

The optimizer checkpoint is a pickle, read only from the study's own row of its own storage and
only through ``load_checkpoint``: an unpickler that builds the optimizers' own classes and NumPy,
pycma and Optuna objects (restoring their state, without running their constructors) and calls
no function outside a short list of NumPy and standard-library constructors, so a damaged or
foreign checkpoint fails with a ValueError naming the storage instead of running code.
"""

from __future__ import annotations

import enum
import io
import itertools
import json
import math
import operator
import pathlib
import pickle
import types
from typing import ClassVar

import numpy as np
import pandas as pd
import sqlalchemy as sa

__all__ = ["StudyStorage", "dump_checkpoint", "export_to_optuna", "load_checkpoint", "read_designs", "storage_exists"]

METADATA = sa.MetaData()
DESIGNS = sa.Table(
    "designs", METADATA,
    sa.Column("study", sa.String(200), index=True), sa.Column("generation", sa.Integer, index=True),
    sa.Column("member", sa.Integer), sa.Column("value", sa.Float, nullable=True),
    sa.Column("failure", sa.Text), sa.Column("params", sa.LargeBinary), sa.Column("metrics", sa.LargeBinary),
    sa.Column("extras", sa.Text, nullable=True),
)
COLUMNS = sa.Table(  # per generation: what the byte strings of its designs hold
    "design_columns", METADATA,
    sa.Column("study", sa.String(200), index=True), sa.Column("generation", sa.Integer),
    sa.Column("layout", sa.Text),
)
CHECKPOINTS = sa.Table(
    "checkpoints", METADATA,
    sa.Column("study", sa.String(200), primary_key=True), sa.Column("generation", sa.Integer),
    sa.Column("state", sa.LargeBinary), sa.Column("seconds", sa.Float),
)


CHECKPOINT_MODULES = ("morphopt.design_space", "morphopt.optimizers", "cma", "optuna", "numpy", "datetime")
CHECKPOINT_BUILTINS = ("set", "frozenset", "complex", "slice", "range", "bytearray", "getattr")
CHECKPOINT_CALLS = {  # the only callables a checkpoint may call while it is read (besides enum lookups)
    ("numpy", "dtype"), ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"), ("numpy.core.multiarray", "scalar"),
    ("numpy.random._pickle", "__bit_generator_ctor"), ("numpy.random._pickle", "__generator_ctor"),
    ("numpy.random._pickle", "__randomstate_ctor"), ("numpy.random.bit_generator", "__pyx_unpickle_SeedSequence"),
    ("datetime", "datetime"), ("datetime", "date"), ("datetime", "timedelta"), ("datetime", "timezone"),
    ("builtins", "set"), ("builtins", "frozenset"), ("builtins", "complex"), ("builtins", "slice"),
    ("builtins", "range"), ("builtins", "bytearray"), ("builtins", "getattr"),
}


def _allowed_module(module) -> bool:
    return isinstance(module, str) and any(module == m or module.startswith(m + ".") for m in CHECKPOINT_MODULES)


def _checkpoint_getattr(obj, name):
    """getattr as a checkpoint may use it: public methods of NumPy random generators (pycma keeps
    ``RandomState.randn`` as its sampler), nothing else."""
    import numpy as np

    if not isinstance(name, str) or name.startswith("_") or not isinstance(obj, (np.random.RandomState,
                                                                                  np.random.Generator)):
        raise pickle.UnpicklingError(f"attribute {name!r} of a {type(obj).__name__} is not allowed in a checkpoint")
    return getattr(obj, name)


class _CheckpointUnpickler(pickle._Unpickler):  # the Python unpickler, whose calls (REDUCE) can be vetted
    """Builds the classes of CHECKPOINT_MODULES (without running their constructors) and calls
    only CHECKPOINT_CALLS, with no callable arguments but classes of those modules."""

    dispatch: ClassVar[dict] = dict(pickle._Unpickler.dispatch)

    def __init__(self, data: bytes):
        super().__init__(io.BytesIO(data))
        self.callables = {}  # id -> object, of the globals that may be called

    def find_class(self, module, name):
        if "." in name:  # no walking from an allowed module to whatever it imported
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a checkpoint")
        if module == "builtins" and name in CHECKPOINT_BUILTINS:
            obj = _checkpoint_getattr if name == "getattr" else super().find_class(module, name)
        elif _allowed_module(module):
            obj = super().find_class(module, name)
            foreign = callable(obj) and not _allowed_module(getattr(obj, "__module__", None))  # imported from elsewhere
            if isinstance(obj, types.ModuleType) or foreign:
                raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a checkpoint (it comes from "
                                             f"{getattr(obj, '__module__', None) or obj.__name__})")
        else:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a checkpoint")
        if (module, name) in CHECKPOINT_CALLS:
            self.callables[id(obj)] = obj
        return obj

    def _reduce(self):
        func, args = self.stack[-2], self.stack[-1]
        lookup = isinstance(func, enum.EnumMeta) and len(args) == 1  # Enum(value): a member lookup
        if not (lookup or self.callables.get(id(func)) is func):
            raise pickle.UnpicklingError(f"calling {getattr(func, '__qualname__', type(func).__name__)} is not "
                                         f"allowed in a checkpoint")
        for arg in args if isinstance(args, tuple) else ():  # numpy's helpers call callables they are given
            if callable(arg) and not (self.callables.get(id(arg)) is arg
                                      or (isinstance(arg, type) and _allowed_module(arg.__module__))):
                raise pickle.UnpicklingError(f"passing {getattr(arg, '__qualname__', type(arg).__name__)} to "
                                             f"{func.__qualname__} is not allowed in a checkpoint")
        self.load_reduce()

    def _refuse(self):
        raise pickle.UnpicklingError("protocol 0/1 instance opcodes are not allowed in a checkpoint")

    dispatch[pickle.REDUCE[0]] = _reduce
    dispatch[pickle.INST[0]] = _refuse
    dispatch[pickle.OBJ[0]] = _refuse


def dump_checkpoint(optimizer) -> bytes:
    """The optimizer's state as stored in the checkpoint row."""
    return pickle.dumps(optimizer, protocol=4)


def load_checkpoint(state: bytes, where: str):
    """The optimizer stored by dump_checkpoint; ValueError naming ``where`` (the study and its
    storage) when the bytes are damaged or would load anything but an optimizer's state."""
    if not isinstance(state, (bytes, bytearray, memoryview)):
        raise ValueError(f"{where}: the optimizer checkpoint is not a byte string")
    try:
        return _CheckpointUnpickler(bytes(state)).load()
    except Exception as exc:  # whatever the damage, one clear message
        raise ValueError(f"{where}: the optimizer checkpoint cannot be read ({type(exc).__name__}: {exc}); "
                         f"start the study afresh with 'study run'") from exc


def storage_exists(url: str) -> bool:
    """False only for an SQLite file that is not there (reading it would create it)."""
    prefix = "sqlite:///"
    return not url.startswith(prefix) or pathlib.Path(url[len(prefix):].split("?")[0]).exists()


def _finite_or_none(value):
    return float(value) if value is not None and math.isfinite(value) else None


_MISSING = object()  # a key some designs of a generation lack


def _plain(value):
    """json.dumps's fallback for the values a design may carry besides JSON's own."""
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    return str(value)


def _kind(types_: set) -> str | None:
    """The binary kind of a parameter column whose values have these types, or None."""
    if types_ <= {bool, np.bool_}:
        return "bool"
    if all(issubclass(t, (int, np.integer)) and t is not bool for t in types_):
        return "int"
    if all(issubclass(t, (int, float, np.integer, np.floating)) and t is not bool for t in types_):
        return "float"
    return "choice" if types_ == {str} else None


def encode_params(dicts: list[dict]) -> tuple[list, np.ndarray, list]:
    """(layout, (designs, columns) float64, per-design extras JSON or None) of a generation's
    parameter dicts; decode_params inverts it."""
    keys = list(dict.fromkeys(k for keyset in dict.fromkeys(map(tuple, dicts)) for k in keyset))
    layout, columns, extras = [], [], {}
    for key in keys:
        column = [d.get(key, _MISSING) for d in dicts]
        kind = _kind(set(map(type, column)))
        if kind == "int" and not all(-2**53 <= v <= 2**53 for v in column):
            kind = None  # beyond float64's integers
        if kind == "choice":
            labels = list(dict.fromkeys(column))
            index = {label: i for i, label in enumerate(labels)}
            layout.append({"name": key, "kind": kind, "labels": labels})
            columns.append(np.fromiter(map(index.__getitem__, column), np.float64, len(column)))
        elif kind is not None:
            layout.append({"name": key, "kind": kind})
            columns.append(np.array(column, dtype=np.float64))
        elif column[0] is not _MISSING and type(key) is str and all(v is column[0] for v in column):
            layout.append({"name": key, "kind": "constant", "value": json.loads(json.dumps(column[0], default=_plain))})
        else:
            layout.append({"name": key, "kind": "json"})
            extras[key] = column
    matrix = np.column_stack(columns) if columns else np.zeros((len(dicts), 0))
    rows = [None] * len(dicts)
    for i in range(len(dicts)) if extras else ():
        row = {key: column[i] for key, column in extras.items() if column[i] is not _MISSING}
        rows[i] = json.dumps(row, default=_plain)
    return layout, matrix, rows


def decode_params(layout: list, matrix: np.ndarray, extras: list) -> pd.DataFrame:
    """The parameter columns of one generation (encode_params's input as a DataFrame)."""
    columns, k = {}, 0
    extra = [json.loads(text) if text else {} for text in extras] if any(extras) else None
    for entry in layout:
        name, kind = entry["name"], entry["kind"]
        if kind == "constant":
            columns[name] = [entry["value"]] * len(matrix)
            continue
        if kind == "json":
            columns[name] = [row.get(name, math.nan) for row in extra] if extra else [math.nan] * len(matrix)
            continue
        values = matrix[:, k]
        k += 1
        if kind == "choice":
            columns[name] = np.asarray(entry["labels"], dtype=object)[values.astype(np.int64)]
        else:
            columns[name] = values.astype({"bool": bool, "int": np.int64, "float": np.float64}[kind])
    return pd.DataFrame(columns)


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _scalar_or_nan(value) -> float:
    return float(value) if _is_number(value) else math.nan


def encode_metrics(dicts: list[dict]) -> tuple[list, np.ndarray]:
    """(names, (designs, names) float64) of the scalar metrics (numbers, not bools) of a
    generation's metric dicts; a design without a metric, or with a non-finite one, has NaN."""
    if dicts and all(map(dicts[0].keys().__eq__, map(dict.keys, dicts))):  # the common case: one key set
        groups = {tuple(dicts[0]): range(len(dicts))}
    else:
        groups = {}
        for i, d in enumerate(dicts):
            groups.setdefault(tuple(d), []).append(i)
    selected = {}
    for keyset, rows in groups.items():
        first = dicts[rows[0]]
        selected[keyset] = [k for k in keyset if first[k] is None or _is_number(first[k])]
    names = list(dict.fromkeys(k for keys in selected.values() for k in keys))
    where = {name: j for j, name in enumerate(names)}
    matrix = np.full((len(dicts), len(names)), np.nan)
    for keyset, rows in groups.items():
        keys = selected[keyset]
        if not keys:
            continue
        getter = operator.itemgetter(*keys)
        values = [getter(dicts[i]) for i in rows] if len(keys) > 1 else [(dicts[i][keys[0]],) for i in rows]
        try:  # the values as one flat sequence of numbers
            block = np.fromiter(itertools.chain.from_iterable(values), np.float64, len(values) * len(keys))
            block = block.reshape(len(values), len(keys))
        except (TypeError, ValueError):
            try:  # None among them (a non-finite metric): NaN
                block = np.array(values, dtype=np.float64)
            except (TypeError, ValueError):  # a later design has something else than a number under a key
                block = np.array([[_scalar_or_nan(v) for v in row] for row in values], dtype=np.float64)
        matrix[np.asarray(rows)[:, None], [where[k] for k in keys]] = block
    matrix[~np.isfinite(matrix)] = np.nan
    return [str(name) for name in names], matrix


def _row_bytes(matrix: np.ndarray) -> list[bytes]:
    data = np.ascontiguousarray(matrix, dtype="<f8")
    return [row.tobytes() for row in data]


def _matrix(blobs, count: int) -> np.ndarray:
    return np.frombuffer(b"".join(blobs), dtype="<f8").reshape(len(blobs), count)


def _insert_many(connection, table: sa.Table, rows: list[tuple]) -> None:
    """table.insert() of ``rows`` (tuples in the table's column order) through the driver's
    executemany: SQLAlchemy's own per-row parameter handling took as long as the rest of
    recording a generation."""
    compiled = table.insert().compile(dialect=connection.dialect)
    names = [column.name for column in table.c]
    if compiled.positional:
        order = [names.index(name) for name in compiled.positiontup]
        data = rows if order == list(range(len(names))) else [tuple(row[i] for i in order) for row in rows]
    else:
        data = [dict(zip(names, row)) for row in rows]
    connection.exec_driver_sql(str(compiled), data)


class StudyStorage:
    """Designs and checkpoints of one study (``name``) in the database at ``url``."""

    def __init__(self, url: str, name: str):
        self.url, self.name = url, name
        try:
            self.engine = sa.create_engine(url)
            METADATA.create_all(self.engine)
            columns = {c["name"] for c in sa.inspect(self.engine).get_columns("designs")}
        except Exception as exc:  # noqa: BLE001  (any driver error becomes a clear message)
            raise ValueError(f"cannot open study storage '{url}': {exc}") from exc
        self.legacy = "extras" not in columns  # written by an earlier version: JSON text, no extras column

    def _upgrade(self, connection) -> None:
        """Let a database of the earlier layout take designs of the current one (SQLite stores
        byte strings in its text columns); its earlier designs stay as they are."""
        if self.engine.dialect.name != "sqlite":
            raise ValueError(f"{self.where}: the database holds designs in the layout of an earlier morphopt "
                             f"(JSON text), which this version reads but extends only on SQLite; run the study "
                             f"into a new database")
        connection.exec_driver_sql("ALTER TABLE designs ADD COLUMN extras TEXT")
        self.legacy = False

    def write_generation(self, generation: int, params: list, values, metrics: list, failures: list,
                         state: bytes, seconds: float, *, replace: bool = False) -> None:
        """Append one generation and replace the checkpoint, in one transaction; ``replace`` first
        removes the study's earlier designs (the first generation of a fresh run), in the same
        transaction, so that a run which fails before its first generation is stored leaves the
        earlier results as they were. ``metrics``: dicts whose scalar values are stored (others,
        such as paths, are not)."""
        param_layout, param_matrix, extras = encode_params(params)
        metric_names, metric_matrix = encode_metrics(metrics)
        layout = json.dumps({"params": param_layout, "metrics": metric_names}, default=_plain)
        rows = [(self.name, generation, k, _finite_or_none(v), failure, p, m, e)  # in DESIGNS's column order
                for k, (v, p, m, e, failure) in enumerate(zip(values, _row_bytes(param_matrix),
                                                              _row_bytes(metric_matrix), extras, failures))]
        with self.engine.begin() as connection:
            if self.legacy:
                self._upgrade(connection)
            if replace:
                connection.execute(DESIGNS.delete().where(DESIGNS.c.study == self.name))
                connection.execute(COLUMNS.delete().where(COLUMNS.c.study == self.name))
            connection.execute(COLUMNS.delete().where((COLUMNS.c.study == self.name)
                                                      & (COLUMNS.c.generation == generation)))
            connection.execute(COLUMNS.insert(), [{"study": self.name, "generation": generation, "layout": layout}])
            _insert_many(connection, DESIGNS, rows)
            connection.execute(CHECKPOINTS.delete().where(CHECKPOINTS.c.study == self.name))
            connection.execute(CHECKPOINTS.insert(), [{"study": self.name, "generation": generation, "state": state,
                                                       "seconds": seconds}])

    @property
    def where(self) -> str:
        """The study and its storage, for messages."""
        return f"study '{self.name}' in {self.url}"

    def checkpoint(self):
        """(last completed generation, optimizer state (bytes), seconds so far) or None."""
        try:
            with self.engine.connect() as connection:
                row = connection.execute(sa.select(CHECKPOINTS).where(CHECKPOINTS.c.study == self.name)).first()
        except sa.exc.SQLAlchemyError as exc:
            raise ValueError(f"{self.where}: cannot read the checkpoint ({exc.__class__.__name__}: {exc})") from exc
        return None if row is None else (row.generation, row.state, row.seconds)

    def clear(self) -> None:
        """Remove this study's designs and checkpoint (a fresh run)."""
        with self.engine.begin() as connection:
            connection.execute(DESIGNS.delete().where(DESIGNS.c.study == self.name))
            connection.execute(COLUMNS.delete().where(COLUMNS.c.study == self.name))
            connection.execute(CHECKPOINTS.delete().where(CHECKPOINTS.c.study == self.name))

    def designs(self) -> pd.DataFrame:
        """All designs: generation, member, value, failure, one column per parameter and one
        ``metric_<name>`` column per scalar metric."""
        wanted = [c for c in DESIGNS.c if c.name != "study" and not (self.legacy and c.name == "extras")]
        try:
            with self.engine.connect() as connection:
                rows = connection.execute(sa.select(*wanted).where(DESIGNS.c.study == self.name)
                                          .order_by(DESIGNS.c.generation, DESIGNS.c.member)).all()
                layouts = dict(connection.execute(sa.select(COLUMNS.c.generation, COLUMNS.c.layout)
                                                  .where(COLUMNS.c.study == self.name)).all())
        except sa.exc.SQLAlchemyError as exc:
            raise ValueError(f"{self.where}: cannot read the designs ({exc.__class__.__name__}: {exc})") from exc
        if not rows:
            return pd.DataFrame(columns=["generation", "member", "value", "failure"])
        base = pd.DataFrame({"generation": [r.generation for r in rows], "member": [r.member for r in rows],
                             "value": [math.nan if r.value is None else r.value for r in rows],
                             "failure": [r.failure for r in rows]})
        parts, start = [], 0
        while start < len(rows):
            generation = rows[start].generation
            stop = start
            while stop < len(rows) and rows[stop].generation == generation:
                stop += 1
            try:
                parts.append(self._decode(rows[start:stop], layouts.get(generation)))
            except (TypeError, ValueError, KeyError, IndexError) as exc:
                raise ValueError(f"{self.where}: the designs of generation {generation} cannot be read "
                                 f"({exc.__class__.__name__}: {exc})") from exc
            start = stop
        return pd.concat([base, pd.concat(parts, ignore_index=True)], axis=1)

    @staticmethod
    def _decode(rows, layout) -> pd.DataFrame:
        """Parameters and metric_ columns of one generation's rows."""
        if layout is None:  # the earlier layout: JSON text
            params = pd.DataFrame([json.loads(r.params) for r in rows])
            metrics = pd.DataFrame([json.loads(r.metrics) for r in rows])
        else:
            layout = json.loads(layout)
            numeric = sum(entry["kind"] not in ("constant", "json") for entry in layout["params"])
            params = decode_params(layout["params"], _matrix([r.params for r in rows], numeric),
                                   [r.extras for r in rows])
            metrics = pd.DataFrame(_matrix([r.metrics for r in rows], len(layout["metrics"])),
                                   columns=layout["metrics"])
        return pd.concat([params, metrics.add_prefix("metric_")], axis=1)


def read_designs(url: str, name: str) -> pd.DataFrame:
    """Study ``name``'s stored designs (StudyStorage.designs); empty when ``url`` holds no
    database yet (reading creates none)."""
    return StudyStorage(url, name).designs() if storage_exists(url) else pd.DataFrame()


def export_to_optuna(frame: pd.DataFrame, *, study_name: str, space, direction: str, storage: str) -> int:
    """Copy a study's designs into an Optuna storage (e.g. for optuna-dashboard); returns trials written.

    Failed designs become FAIL trials. Written in one bulk call (add_trials) per study.
    """
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        study = optuna.create_study(study_name=study_name, storage=storage, direction=direction, load_if_exists=True)
    except Exception as exc:  # any storage or driver error becomes a clear message
        raise ValueError(f"cannot open the Optuna storage '{storage}': {exc.__class__.__name__}: {exc}") from exc
    distributions = space.optuna_distributions()
    trials = []
    for row in frame.itertuples(index=False):
        params = {name: getattr(row, name) for name in distributions}
        params = {k: (v.item() if hasattr(v, "item") else v) for k, v in params.items()}
        failed = bool(row.failure) or row.value is None or not math.isfinite(row.value)
        trials.append(optuna.trial.create_trial(
            params=params, distributions=distributions, value=None if failed else float(row.value),
            state=optuna.trial.TrialState.FAIL if failed else optuna.trial.TrialState.COMPLETE,
            user_attrs={"generation": int(row.generation), "failure": row.failure}))
    study.add_trials(trials)
    return len(trials)
