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

Guarantees: nothing read from a database runs code (checkpoints are JSON and float64 arrays,
morphopt.checkpoint); one writer per study (a lease row in ``studies``, taken before the first
generation, checked and renewed in every generation's transaction, renewed by a heartbeat while
the writer lives, taken over only when stale or on request); a generation is stored whole or not
at all; results are never deleted (a fresh run moves the earlier ones aside under a new name);
the schema is created race-free by any number of processes at once. Driver errors (read-only,
locked, damaged, full) are ValueErrors of one line naming the study and its storage.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import os
import pathlib
import re
import socket
import struct
import threading
import time
import uuid
from datetime import datetime, timezone

import numpy as np
import pandas as pd
import sqlalchemy as sa

from morphopt.metric_table import MetricTable

__all__ = ["LEASE_SECONDS", "StudyStorage", "export_to_optuna", "read_designs", "read_workers", "storage_exists"]

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
STUDIES = sa.Table(  # one row per study: its effective settings and its writer's lease
    "studies", METADATA,
    sa.Column("name", sa.String(255), primary_key=True), sa.Column("settings", sa.Text),
    sa.Column("created", sa.Float), sa.Column("owner", sa.String(64), nullable=True),
    sa.Column("host", sa.String(255), nullable=True), sa.Column("pid", sa.Integer, nullable=True),
    sa.Column("since", sa.Float, nullable=True), sa.Column("heartbeat", sa.Float, nullable=True),
    sa.Column("node", sa.String(255), nullable=True),
)
OPTIMIZER_LOG = sa.Table(  # per generation: what the optimizer asked for (a digest) and was told (float64)
    "optimizer_log", METADATA,
    sa.Column("study", sa.String(255), primary_key=True), sa.Column("generation", sa.Integer, primary_key=True),
    sa.Column("asked", sa.String(64)), sa.Column("width", sa.Integer), sa.Column("told", sa.LargeBinary),
)
WORKERS = sa.Table(  # per generation of a study on a cluster (morphopt.cluster): what each worker did
    "workers", METADATA,
    sa.Column("study", sa.String(255), index=True), sa.Column("generation", sa.Integer),
    sa.Column("worker", sa.Integer), sa.Column("designs", sa.Integer), sa.Column("seconds", sa.Float),
    sa.Column("failures", sa.Integer), sa.Column("replaced", sa.Integer),
)
LEASE_SECONDS = 120.0  # a lease whose heartbeat is older than this is stale (the heartbeat runs every 15 s)
HEARTBEAT_SECONDS = 15.0
SQLITE_TIMEOUT = 30.0  # seconds a writer waits for another connection's lock before giving up
MAX_GENERATIONS = 10**6  # a stored generation number beyond this is damage


def _driver_reason(exc: BaseException) -> str:
    """The first line of a driver error, with what it means for a study database."""
    text = str(getattr(exc, "orig", None) or exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    low = text.lower()
    hints = (("readonly", "the database or its folder is read-only"),
             ("read-only", "the database or its folder is read-only"),
             ("locked", f"another connection held a lock on it for more than {SQLITE_TIMEOUT:g} s"),
             ("malformed", "the file is damaged; restore it from a copy"),
             ("not a database", "the file is damaged or not an SQLite database"),
             ("disk is full", "the disk is full; free space, then resume"),
             ("no space", "the disk is full; free space, then resume"),
             ("unable to open", "the file or its folder cannot be opened"))
    hint = next((h for key, h in hints if key in low), None)
    return f"{text} ({hint})" if hint else text


def _node() -> str:
    """This machine and PID namespace (pids mean something only within one): the kernel's boot id
    and the namespace's inode on Linux, else the host name."""
    try:
        boot = pathlib.Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        return f"{boot}:{os.stat('/proc/self/ns/pid').st_ino}"
    except OSError:
        return socket.gethostname()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _read_guard(action: str):
    """A reading method whose failures on damaged or hostile data become one ValueError naming the
    study and its storage (a database can be anyone's file: it may hold any value in any column)."""
    def wrap(method):
        @functools.wraps(method)
        def guarded(self, *args, **kwargs):
            try:
                return method(self, *args, **kwargs)
            except ValueError:
                raise
            except sa.exc.SQLAlchemyError as exc:
                raise self._error(action, exc) from exc
            except (TypeError, KeyError, IndexError, AttributeError, RecursionError, OverflowError, MemoryError,
                    UnicodeError, struct.error) as exc:
                raise ValueError(f"{self.where}: cannot {action}: the stored data is damaged "
                                 f"({type(exc).__name__}: {str(exc)[:200]})") from exc
        return guarded
    return wrap


def _generation(value, where: str) -> int:
    """A stored generation number, checked (0 <= g < MAX_GENERATIONS)."""
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < MAX_GENERATIONS:
        raise ValueError(f"{where}: the stored generation {str(value)[:40]!r} is damaged")
    return value


def _printable(text) -> str:
    """Stored text without control characters (a database may hold terminal escapes)."""
    return re.sub(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]", "?", text) if isinstance(text, str) else text


def _utc(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def storage_exists(url: str) -> bool:
    """False only for an SQLite file that is not there (reading it would create it)."""
    if not url.startswith("sqlite") or "://" not in url:
        return True
    path = url.split("://", 1)[1]
    if not path.startswith("/"):
        return True  # in memory: refused by the study's checks
    path = path[1:].split("?")[0]
    return pathlib.Path(path[len("file:"):] if path.startswith("file:") else path).exists()


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


def encode_metrics(dicts) -> tuple[list, np.ndarray]:
    """(names, (designs, names) float64) of the scalar metrics (numbers, not bools) of a
    generation's metric dicts or MetricTable (morphopt.metric_table: a key is a column where any
    design has a number under it); a design without a metric, or with a non-finite one, has NaN."""
    table = dicts if isinstance(dicts, MetricTable) else MetricTable.from_dicts(dicts)
    return table.scalars()


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
    """Designs, optimizer log, checkpoint, settings and writer's lease of one study (``name``) in
    the database at ``url``. Opening reads nothing and creates nothing; ``acquire`` (a writer)
    creates the schema, takes the lease and thereby probes that the database can be written."""

    def __init__(self, url: str, name: str):
        self.url, self.name = url, name
        self.owner: str | None = None  # this writer's lease token, while it holds the lease
        self._heartbeat: threading.Thread | None = None
        self._stop = threading.Event()
        self.lease_lost = False
        self._current_layout = False  # set once this writer stored a generation: the table has extras
        try:
            sqlite = url.startswith("sqlite") and "timeout=" not in url  # a URL may set its own
            connect_args = {"timeout": SQLITE_TIMEOUT} if sqlite else {}
            self.engine = sa.create_engine(url, connect_args=connect_args)
        except Exception as exc:  # noqa: BLE001  (a bad URL or a missing driver: one clear line)
            raise ValueError(f"cannot open study storage '{url}': {_driver_reason(exc)}") from exc

    @property
    def where(self) -> str:
        """The study and its storage, for messages."""
        return f"study '{self.name}' in {self.url}"

    def _error(self, action: str, exc: BaseException) -> ValueError:
        return ValueError(f"{self.where}: cannot {action}: {_driver_reason(exc)}")

    def _tables(self) -> set:
        try:
            return set(sa.inspect(self.engine).get_table_names())
        except Exception as exc:  # noqa: BLE001
            raise self._error("read the database", exc) from exc

    @property
    def legacy(self) -> bool:
        """True for a designs table of the earlier layout (JSON text, no extras column)."""
        if "designs" not in self._tables():
            return False
        return "extras" not in {c["name"] for c in sa.inspect(self.engine).get_columns("designs")}

    def create_schema(self) -> None:
        """Create the missing tables and indexes; safe when several processes do it at once."""
        for attempt in range(8):
            try:
                missing = [t for t in METADATA.sorted_tables if t.name not in self._tables()]
                with self.engine.begin() as connection:
                    for table in missing:
                        connection.execute(sa.schema.CreateTable(table, if_not_exists=True))
                        for index in table.indexes:
                            connection.execute(sa.schema.CreateIndex(index, if_not_exists=True))
                return
            except sa.exc.SQLAlchemyError as exc:  # another process created the same object in between
                if attempt == 7:
                    raise self._error("create the study tables", exc) from exc
                time.sleep(0.05 * (attempt + 1))

    # ---- the lease -------------------------------------------------------------------------------

    @_read_guard('read the study')
    def info(self) -> dict:
        """What the database holds for this study: stored generations and designs, the settings
        it was run with (dict or None) and its lease row (or None). Reads only."""
        tables = self._tables()
        out = {"generations": 0, "designs": 0, "checkpoint": False, "settings": None, "lease": None}
        try:
            with self.engine.connect() as connection:
                if "designs" in tables:
                    count, last = connection.execute(sa.select(sa.func.count(), sa.func.max(DESIGNS.c.generation))
                                                     .where(DESIGNS.c.study == self.name)).one()
                    out["designs"], out["generations"] = count, (last + 1 if last is not None else 0)
                if "checkpoints" in tables:
                    out["checkpoint"] = connection.execute(sa.select(CHECKPOINTS.c.generation)
                                                           .where(CHECKPOINTS.c.study == self.name)).first() is not None
                if "studies" in tables:
                    row = connection.execute(sa.select(STUDIES).where(STUDIES.c.name == self.name)).first()
                    if row is not None:
                        out["settings"] = json.loads(row.settings) if row.settings else None
                        out["lease"] = row
                        if out["settings"] is not None and not isinstance(out["settings"], dict):
                            raise ValueError(f"{self.where}: the stored settings are damaged (not a table)")
        except (sa.exc.SQLAlchemyError, ValueError) as exc:
            raise self._error("read the study", exc) from exc
        return out

    @staticmethod
    def _lease(row) -> dict:
        """The lease columns of a studies row with the types they must have (a damaged row reads as
        a lease without heartbeat, which is stale)."""
        def number(value, kind):
            return kind(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and \
                math.isfinite(value) else None
        return {"owner": row.owner if isinstance(row.owner, str) else None, "pid": number(row.pid, int),
                "host": str(row.host)[:255] if row.host is not None else "?", "since": number(row.since, float),
                "heartbeat": number(row.heartbeat, float),
                "node": row.node if isinstance(getattr(row, "node", None), str) else None}

    def _holder(self, row) -> str:
        lease = self._lease(row)
        beat = f", last heartbeat {time.time() - lease['heartbeat']:.0f} s ago" if lease["heartbeat"] else ""
        since = _utc(lease["since"]) if lease["since"] and 0 < lease["since"] < 1e11 else "?"
        return f"pid {lease['pid']} on host {lease['host']} since {since}{beat}"

    def _stale(self, row) -> bool:
        """A lease whose process is gone: its heartbeat (renewed every HEARTBEAT_SECONDS while the
        writer lives) older than LEASE_SECONDS, or its pid dead in this same PID namespace."""
        lease = self._lease(row)
        if time.time() - (lease["heartbeat"] or 0.0) > LEASE_SECONDS:
            return True
        return lease["node"] == _node() and lease["pid"] is not None and not _pid_alive(lease["pid"])

    def acquire(self, settings: dict, *, steal: bool = False) -> None:
        """Take the study's lease (creating the schema and the study's row when needed): a write
        probe before any work. ValueError when another live writer holds it (unless ``steal``),
        or when the database cannot be written."""
        self.create_schema()
        token = uuid.uuid4().hex
        me = {"owner": token, "host": socket.gethostname(), "pid": os.getpid(), "node": _node()}
        for attempt in range(50):
            now = time.time()
            started = time.perf_counter()
            try:
                with self.engine.connect() as connection:
                    row = connection.execute(sa.select(STUDIES).where(STUDIES.c.name == self.name)).first()
                if row is not None and row.owner and not steal and not self._stale(row):
                    raise ValueError(f"study '{self.name}' is being written by {self._holder(row)} (storage "
                                     f"{self.url}); wait, or 'morphopt study resume <spec> --steal' if that "
                                     f"process is gone")
                with self.engine.begin() as connection:
                    if row is None:
                        connection.execute(STUDIES.insert().values(name=self.name, settings=json.dumps(settings),
                                                                   created=now, since=now, heartbeat=now, **me))
                        taken = True
                    else:  # compare-and-set: only if nobody changed the row since it was read
                        same = (STUDIES.c.owner.is_(None) if row.owner is None else STUDIES.c.owner == row.owner)
                        taken = connection.execute(STUDIES.update().where((STUDIES.c.name == self.name) & same)
                                                   .values(since=now, heartbeat=now, **me)).rowcount == 1
            except sa.exc.IntegrityError:  # another process inserted the row first: read it again
                taken = False
            except sa.exc.OperationalError as exc:  # retried only when SQLite refused at once (two writers
                waited = time.perf_counter() - started  # upgrading their locks), never after its busy timeout
                if "locked" not in str(exc).lower() or attempt >= 49 or waited > 0.2:
                    raise self._error("take the study's lease (a write probe)", exc) from exc
                taken = False
            except sa.exc.SQLAlchemyError as exc:
                raise self._error("take the study's lease (a write probe)", exc) from exc
            if taken:
                self.owner, self.lease_lost = token, False
                self._start_heartbeat()
                return
            time.sleep(0.02 * (1 + attempt % 5))
        raise ValueError(f"{self.where}: could not take the study's lease (other processes kept changing it)")

    def _start_heartbeat(self) -> None:
        self._stop.clear()

        def beat():
            while not self._stop.wait(HEARTBEAT_SECONDS):
                try:
                    if not self._renew():
                        self.lease_lost = True
                        return
                except sa.exc.SQLAlchemyError:
                    pass  # a busy database: the next beat tries again

        self._heartbeat = threading.Thread(target=beat, name=f"lease {self.name}", daemon=True)
        self._heartbeat.start()

    def _renew(self, connection=None) -> bool:
        statement = (STUDIES.update().where((STUDIES.c.name == self.name) & (STUDIES.c.owner == self.owner))
                     .values(heartbeat=time.time()))
        if connection is not None:
            return connection.execute(statement).rowcount == 1
        with self.engine.begin() as own:
            return own.execute(statement).rowcount == 1

    def release(self) -> None:
        """Give the lease back (the end of a run, or its failure); never raises."""
        self._stop.set()
        if self._heartbeat is not None:
            self._heartbeat.join(timeout=5.0)
            self._heartbeat = None
        if self.owner is None:
            return
        try:
            with self.engine.begin() as connection:
                connection.execute(STUDIES.update().where((STUDIES.c.name == self.name)
                                                          & (STUDIES.c.owner == self.owner))
                                   .values(owner=None, pid=None, heartbeat=time.time()))
        except sa.exc.SQLAlchemyError:
            pass  # the lease goes stale by itself
        self.owner = None

    def _lost(self, connection, generation: int) -> ValueError:
        row = connection.execute(sa.select(STUDIES).where(STUDIES.c.name == self.name)).first()
        if row is None:
            holder = "nobody: the study was removed"
        elif row.owner:
            holder = self._holder(row)
        else:
            holder = "another run (--steal), which has finished since"
        return ValueError(f"{self.where}: this run lost the study's lease to {holder}; it stops without storing "
                          f"generation {generation}")

    def archive_name(self) -> str:
        """A new name for this study's earlier results: '<name>.before-<UTC time>' (unique)."""
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        names = set()
        if "studies" in self._tables():
            with self.engine.connect() as connection:
                names = set(connection.execute(sa.select(STUDIES.c.name)).scalars())
        base = f"{self.name[:170]}.before-{stamp}"  # within the 200 characters of the study columns
        return next(n for n in (base if k == 0 else f"{base}-{k}" for k in itertools.count()) if n not in names)

    # ---- writing ---------------------------------------------------------------------------------

    def write_generation(self, generation: int, params: list, values, metrics: list, failures: list,
                         state: bytes, seconds: float, *, asked: str = "", told=None, settings: dict | None = None,
                         archive: str | None = None, backfill: list | None = None, workers: list | None = None) -> None:
        """Append one generation, its optimizer log row and the new checkpoint in one transaction
        that first checks (and renews) this writer's lease. ``archive``: move the study's earlier
        results (designs, log, checkpoint, settings) to that study name first, in the same
        transaction; ``settings``: store these as the study's settings; ``backfill``: optimizer log
        rows (generation, digest, told) of earlier generations stored without one. ``metrics``: dicts
        whose scalar values are stored (others, such as paths, are not); ``told``: (designs, k) float64;
        ``workers``: a cluster's per-worker rows (worker, designs, seconds, failures, replaced)."""
        if self.owner is None:
            raise ValueError(f"{self.where}: writing needs the study's lease (StudyStorage.acquire)")
        param_layout, param_matrix, extras = encode_params(params)
        metric_names, metric_matrix = encode_metrics(metrics)
        layout = json.dumps({"params": param_layout, "metrics": metric_names}, default=_plain)
        rows = [(self.name, generation, k, _finite_or_none(v), failure, p, m, e)  # in DESIGNS's column order
                for k, (v, p, m, e, failure) in enumerate(zip(values, _row_bytes(param_matrix),
                                                              _row_bytes(metric_matrix), extras, failures))]
        told = np.zeros((len(rows), 0)) if told is None else np.asarray(told, dtype=np.float64).reshape(len(rows), -1)
        legacy = not self._current_layout and self.legacy  # asked of the database once per writer
        try:
            with self.engine.begin() as connection:
                if not self._renew(connection):
                    raise self._lost(connection, generation)
                if legacy:
                    self._upgrade(connection)
                if archive:
                    self._move(connection, archive)
                if settings is not None:
                    connection.execute(STUDIES.update().where(STUDIES.c.name == self.name)
                                       .values(settings=json.dumps(settings)))
                connection.execute(COLUMNS.insert(), [{"study": self.name, "generation": generation,
                                                       "layout": layout}])
                _insert_many(connection, DESIGNS, rows)
                log = [*(backfill or ()), (generation, asked, told)]
                connection.execute(OPTIMIZER_LOG.insert(), [
                    {"study": self.name, "generation": g, "asked": digest, "width": array.shape[1],
                     "told": np.ascontiguousarray(array, "<f8").tobytes()} for g, digest, array in log])
                if workers:
                    connection.execute(WORKERS.insert(), [
                        {"study": self.name, "generation": generation, "worker": w, "designs": d, "seconds": s,
                         "failures": f, "replaced": r} for w, d, s, f, r in workers])
                connection.execute(CHECKPOINTS.delete().where(CHECKPOINTS.c.study == self.name))
                connection.execute(CHECKPOINTS.insert(), [{"study": self.name, "generation": generation,
                                                           "state": state, "seconds": seconds}])
        except sa.exc.IntegrityError as exc:
            if "unique" in str(exc).lower() or "duplicate" in str(exc).lower():
                raise ValueError(f"{self.where}: generation {generation} is stored already; nothing was "
                                 f"written") from exc
            raise self._error(f"store generation {generation} (nothing of it was stored)", exc) from exc
        except sa.exc.SQLAlchemyError as exc:
            raise self._error(f"store generation {generation} (nothing of it was stored)", exc) from exc
        self._current_layout = True

    def _move(self, connection, archive: str) -> None:
        """Rename the study's stored rows to ``archive`` (and copy its settings row there, unleased)."""
        for table in (DESIGNS, COLUMNS, CHECKPOINTS, OPTIMIZER_LOG, WORKERS):
            connection.execute(table.update().where(table.c.study == self.name).values(study=archive))
        row = connection.execute(sa.select(STUDIES).where(STUDIES.c.name == self.name)).first()
        connection.execute(STUDIES.insert().values(name=archive, settings=row.settings, created=row.created,
                                                   owner=None, host=None, pid=None, since=None,
                                                   heartbeat=time.time()))

    def _upgrade(self, connection) -> None:
        """Let a database of the earlier layout take designs of the current one (SQLite stores
        byte strings in its text columns); its earlier designs stay as they are."""
        if self.engine.dialect.name != "sqlite":
            raise ValueError(f"{self.where}: the database holds designs in the layout of an earlier morphopt "
                             f"(JSON text), which this version reads but extends only on SQLite; run the study "
                             f"into a new database")
        try:
            with connection.begin_nested():
                connection.exec_driver_sql("ALTER TABLE designs ADD COLUMN extras TEXT")
        except sa.exc.OperationalError as exc:  # another study's writer added it first
            if "duplicate column" not in str(exc).lower():
                raise

    # ---- reading ---------------------------------------------------------------------------------

    @_read_guard('list the studies')
    def names(self) -> list[str]:
        """Every study of the database (those moved aside by --fresh included), sorted."""
        tables = self._tables()
        found = set()
        try:
            with self.engine.connect() as connection:
                for table, column in ((STUDIES, STUDIES.c.name), (DESIGNS, DESIGNS.c.study)):
                    if table.name in tables:
                        found |= set(connection.execute(sa.select(column).distinct()).scalars())
        except sa.exc.SQLAlchemyError as exc:
            raise self._error("list the studies", exc) from exc
        return sorted(found)

    @_read_guard('read the checkpoint')
    def checkpoint(self):
        """(last completed generation, checkpoint blob (bytes), seconds so far) or None."""
        if "checkpoints" not in self._tables():
            return None
        try:
            with self.engine.connect() as connection:
                row = connection.execute(sa.select(CHECKPOINTS).where(CHECKPOINTS.c.study == self.name)).first()
        except sa.exc.SQLAlchemyError as exc:
            raise self._error("read the checkpoint", exc) from exc
        if row is None:
            return None
        seconds = row.seconds if isinstance(row.seconds, (int, float)) and math.isfinite(row.seconds) else 0.0
        return _generation(row.generation, self.where), row.state, float(seconds)

    @_read_guard('read the optimizer log')
    def optimizer_log(self) -> list:
        """[(generation, digest of the designs asked for, told (designs, k) float64)] in order."""
        if "optimizer_log" not in self._tables():
            return []
        try:
            with self.engine.connect() as connection:
                rows = connection.execute(sa.select(OPTIMIZER_LOG).where(OPTIMIZER_LOG.c.study == self.name)
                                          .order_by(OPTIMIZER_LOG.c.generation)).all()
        except sa.exc.SQLAlchemyError as exc:
            raise self._error("read the optimizer log", exc) from exc
        out = []
        for row in rows:
            told = np.frombuffer(bytes(row.told or b""), dtype="<f8")
            if not isinstance(row.width, int) or row.width <= 0 or told.size % row.width:
                raise ValueError(f"{self.where}: the optimizer log of generation {row.generation} is damaged")
            out.append((_generation(row.generation, self.where), str(row.asked), told.reshape(-1, row.width)))
        return out

    @_read_guard('read the designs')
    def designs(self) -> pd.DataFrame:
        """All designs: generation, member, value, failure, one column per parameter and one
        ``metric_<name>`` column per scalar metric."""
        if "designs" not in self._tables():
            return pd.DataFrame(columns=["generation", "member", "value", "failure"])
        legacy = self.legacy
        wanted = [c for c in DESIGNS.c if c.name != "study" and not (legacy and c.name == "extras")]
        try:
            with self.engine.connect() as connection:
                rows = connection.execute(sa.select(*wanted).where(DESIGNS.c.study == self.name)
                                          .order_by(DESIGNS.c.generation, DESIGNS.c.member)).all()
                layouts = {}
                if "design_columns" in self._tables():
                    layouts = dict(connection.execute(sa.select(COLUMNS.c.generation, COLUMNS.c.layout)
                                                      .where(COLUMNS.c.study == self.name)).all())
        except sa.exc.SQLAlchemyError as exc:
            raise self._error("read the designs", exc) from exc
        if not rows:
            return pd.DataFrame(columns=["generation", "member", "value", "failure"])
        base = pd.DataFrame({"generation": [r.generation for r in rows], "member": [r.member for r in rows],
                             "value": [math.nan if r.value is None else r.value for r in rows],
                             "failure": [_printable(r.failure) for r in rows]})
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


def read_workers(url: str, name: str) -> pd.DataFrame:
    """A cluster study's workers per generation (worker, designs, seconds, failures, replaced), empty
    for a study run in one process or stored before workers were recorded."""
    engine = sa.create_engine(url)
    try:
        if "workers" not in sa.inspect(engine).get_table_names():
            return pd.DataFrame(columns=["generation", "worker", "designs", "seconds", "failures", "replaced"])
        with engine.connect() as connection:
            rows = connection.execute(sa.select(WORKERS).where(WORKERS.c.study == name)
                                      .order_by(WORKERS.c.generation, WORKERS.c.worker)).all()
    finally:
        engine.dispose()
    return pd.DataFrame([tuple(r)[1:] for r in rows],
                        columns=["generation", "worker", "designs", "seconds", "failures", "replaced"])


def read_designs(url: str, name: str) -> pd.DataFrame:
    """Study ``name``'s stored designs (StudyStorage.designs); empty when ``url`` holds no
    database yet (reading creates none)."""
    return StudyStorage(url, name).designs() if storage_exists(url) else pd.DataFrame()


def export_to_optuna(frame: pd.DataFrame, *, study_name: str, space, direction: str, storage: str) -> tuple[int, int]:
    """Copy a study's designs into an Optuna storage (e.g. for optuna-dashboard); returns (trials
    written, designs already there).

    Failed designs become FAIL trials; each trial carries the design's generation, member and
    failure as user attributes. A design already in the Optuna study (the same generation and
    member) is skipped, so exporting again adds only what the study evaluated since. An SQL
    storage gets every new trial in one transaction (Optuna's own RDBStorage writes its rows); any
    other storage gets them by Optuna's add_trials. An Optuna study of that name that optimizes in
    the other direction is refused.
    """
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        study = optuna.create_study(study_name=study_name, storage=storage, direction=direction, load_if_exists=True)
    except Exception as exc:  # any storage or driver error becomes a clear message
        raise ValueError(f"cannot open the Optuna storage '{storage}': {exc.__class__.__name__}: {exc}") from exc
    if study.direction.name.lower() != direction:
        raise ValueError(f"Optuna study '{study_name}' in {storage} is to {study.direction.name.lower()}; this study's "
                         f"value is to {direction}: export to another storage")
    present = {(t.user_attrs.get("generation"), t.user_attrs.get("member")): t.params
               for t in study.get_trials(deepcopy=False)}
    distributions = space.optuna_distributions()
    names = list(distributions)
    trials = []
    for generation, member, value, failure, *params in frame[["generation", "member", "value", "failure",
                                                              *names]].itertuples(index=False, name=None):
        there = present.get((int(generation), int(member)))
        if there is not None:
            mine = {n: (v.item() if hasattr(v, "item") else v) for n, v in zip(names, params)}
            if there != mine:  # another run of the study (one started over with --fresh): never mix them
                raise ValueError(f"Optuna study '{study_name}' in {storage} holds another run of this study "
                                 f"(generation {int(generation)}, member {int(member)} differs); export to another "
                                 f"storage or Optuna study name")
            continue
        failed = bool(failure) or value is None or not math.isfinite(value)
        trials.append(optuna.trial.create_trial(
            params={n: (v.item() if hasattr(v, "item") else v) for n, v in zip(names, params)},
            distributions=distributions, value=None if failed else float(value),
            state=optuna.trial.TrialState.FAIL if failed else optuna.trial.TrialState.COMPLETE,
            user_attrs={"generation": int(generation), "member": int(member), "failure": failure}))
    if trials:
        try:
            _add_trials(study, storage, trials)
        except Exception as exc:  # noqa: BLE001 - a driver error, as one line
            raise ValueError(f"cannot write to the Optuna storage '{storage}': {exc.__class__.__name__}: "
                             f"{' '.join(str(exc).split())[:300]}") from exc
    return len(trials), len(frame) - len(trials)


def _add_trials(study, storage: str, trials: list) -> None:
    """Add COMPLETE or FAIL FrozenTrials (one value, params, user attributes) to an Optuna study:
    for a database URL in one transaction through the ORM models of Optuna's RDBStorage (its
    add_trials commits every trial: benchmarks/results/README.md, "Optuna export"), else, or with
    another Optuna's internals, by add_trials."""
    import optuna

    try:
        from optuna.storages._rdb import models
    except ImportError:
        models = None
    if models is None or not isinstance(storage, str) or "://" not in storage:
        study.add_trials(trials)
        return
    _check_distributions(study, trials[0].distributions)
    rdb = optuna.storages.RDBStorage(storage)
    session = rdb.scoped_session()
    try:
        owner = models.StudyModel.find_or_raise_by_id(rdb.get_study_id_from_name(study.study_name), session,
                                                      for_update=True)
        first = models.TrialModel.count(session, owner)
        rows = [models.TrialModel(study_id=owner.study_id, number=first + k, state=trial.state,
                                  datetime_start=trial.datetime_start, datetime_complete=trial.datetime_complete)
                for k, trial in enumerate(trials)]
        session.add_all(rows)
        session.flush()  # the trials' ids
        json_of = {n: optuna.distributions.distribution_to_json(d) for n, d in trials[0].distributions.items()}
        children = []
        for row, trial in zip(rows, trials):
            children += [models.TrialParamModel(trial_id=row.trial_id, param_name=name, distribution_json=json_of[name],
                                                param_value=trial.distributions[name].to_internal_repr(value))
                         for name, value in trial.params.items()]
            if trial.value is not None:
                value, kind = models.TrialValueModel.value_to_stored_repr(trial.value)
                children.append(models.TrialValueModel(trial_id=row.trial_id, objective=0, value=value, value_type=kind))
            children += [models.TrialUserAttributeModel(trial_id=row.trial_id, key=key, value_json=json.dumps(value))
                         for key, value in trial.user_attrs.items()]
        session.add_all(children)
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()
        rdb.scoped_session.remove()
        rdb.engine.dispose()


def _check_distributions(study, distributions: dict) -> None:
    """ValueError when the Optuna study holds a parameter of these names with another range or kind."""
    import optuna

    for trial in study.get_trials(deepcopy=False):
        for name, earlier in trial.distributions.items():
            if name in distributions:
                try:
                    optuna.distributions.check_distribution_compatibility(earlier, distributions[name])
                except ValueError as exc:
                    raise ValueError(f"Optuna study '{study.study_name}' holds parameter '{name}' as {earlier}, this "
                                     f"study as {distributions[name]} ({exc})") from None
        return  # one trial holds every parameter that the others hold
