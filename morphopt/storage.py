"""Study storage: every evaluated design in an SQL database (SQLite file by default, any
SQLAlchemy URL), written in bulk once per generation together with the optimizer checkpoint, read
back as a pandas DataFrame.

The optimizer checkpoint is a pickle, read only from the study's own row of its own storage and
only through ``load_checkpoint``: an unpickler that builds the optimizers' own classes and NumPy,
pycma and Optuna objects (restoring their state, without running their constructors) and calls
no function outside a short list of NumPy and standard-library constructors, so a damaged or
foreign checkpoint fails with a ValueError naming the storage instead of running code.
"""

from __future__ import annotations

import enum
import io
import json
import math
import pathlib
import pickle
import types
from typing import ClassVar

import pandas as pd
import sqlalchemy as sa

__all__ = ["StudyStorage", "dump_checkpoint", "export_to_optuna", "load_checkpoint", "read_designs", "storage_exists"]

METADATA = sa.MetaData()
DESIGNS = sa.Table(
    "designs", METADATA,
    sa.Column("study", sa.String(200), index=True), sa.Column("generation", sa.Integer, index=True),
    sa.Column("member", sa.Integer), sa.Column("value", sa.Float, nullable=True),
    sa.Column("failure", sa.Text), sa.Column("params", sa.Text), sa.Column("metrics", sa.Text),
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


def _json_value(value) -> str:
    if type(value) is float and math.isfinite(value):
        return repr(value)  # what json.dumps writes for a finite float, without its dispatch
    return json.dumps(value)


def json_rows(dicts: list[dict]) -> list[str]:
    """json.dumps of every dict, the same text, several times faster for a generation of designs:
    the dicts of a generation share their keys, so the key text is built once per key set and each
    row only formats its values."""
    templates = {}
    out = []
    for d in dicts:
        keys = tuple(d)
        template = templates.get(keys)
        if template is None:
            if not all(type(k) is str for k in keys):
                out.append(json.dumps(d))
                continue
            template = templates[keys] = "{" + ", ".join(json.dumps(k).replace("%", "%%") + ": %s" for k in keys) + "}"
        out.append(template % tuple(map(_json_value, d.values())))
    return out


class StudyStorage:
    """Designs and checkpoints of one study (``name``) in the database at ``url``."""

    def __init__(self, url: str, name: str):
        self.url, self.name = url, name
        try:
            self.engine = sa.create_engine(url)
            METADATA.create_all(self.engine)
        except Exception as exc:  # noqa: BLE001  (any driver error becomes a clear message)
            raise ValueError(f"cannot open study storage '{url}': {exc}") from exc

    def write_generation(self, generation: int, params: list, values, metrics: list, failures: list,
                         state: bytes, seconds: float, *, replace: bool = False) -> None:
        """Append one generation and replace the checkpoint, in one transaction; ``replace`` first
        removes the study's earlier designs (the first generation of a fresh run), in the same
        transaction, so that a run which fails before its first generation is stored leaves the
        earlier results as they were."""
        rows = [{"study": self.name, "generation": generation, "member": k, "value": _finite_or_none(v),
                 "failure": failure, "params": p, "metrics": m}
                for k, (v, p, m, failure) in enumerate(zip(values, json_rows(params), json_rows(metrics), failures))]
        with self.engine.begin() as connection:
            if replace:
                connection.execute(DESIGNS.delete().where(DESIGNS.c.study == self.name))
            connection.execute(DESIGNS.insert(), rows)
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
            connection.execute(CHECKPOINTS.delete().where(CHECKPOINTS.c.study == self.name))

    def designs(self) -> pd.DataFrame:
        """All designs: generation, member, value, failure, one column per parameter and metric."""
        try:
            with self.engine.connect() as connection:
                frame = pd.read_sql(sa.select(DESIGNS).where(DESIGNS.c.study == self.name)
                                    .order_by(DESIGNS.c.generation, DESIGNS.c.member), connection)
        except sa.exc.SQLAlchemyError as exc:
            raise ValueError(f"{self.where}: cannot read the designs ({exc.__class__.__name__}: {exc})") from exc
        if frame.empty:
            return frame
        try:
            params = pd.DataFrame([json.loads(p) for p in frame.pop("params")])
            metrics = pd.DataFrame([json.loads(m) for m in frame.pop("metrics")]).add_prefix("metric_")
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self.where}: a stored design is not valid JSON ({exc})") from exc
        return pd.concat([frame.drop(columns="study"), params, metrics], axis=1)


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
