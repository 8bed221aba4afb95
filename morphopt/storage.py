"""Study storage: every evaluated design in an SQL database (SQLite file by default, any
SQLAlchemy URL), written in bulk once per generation together with the optimizer checkpoint, read
back as a pandas DataFrame."""

from __future__ import annotations

import json
import math

import pandas as pd
import sqlalchemy as sa

__all__ = ["StudyStorage", "export_to_optuna"]

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
                         state: bytes, seconds: float) -> None:
        """Append one generation and replace the checkpoint, in one transaction."""
        rows = [{"study": self.name, "generation": generation, "member": k, "value": _finite_or_none(v),
                 "failure": failure, "params": p, "metrics": m}
                for k, (v, p, m, failure) in enumerate(zip(values, json_rows(params), json_rows(metrics), failures))]
        with self.engine.begin() as connection:
            connection.execute(DESIGNS.insert(), rows)
            connection.execute(CHECKPOINTS.delete().where(CHECKPOINTS.c.study == self.name))
            connection.execute(CHECKPOINTS.insert(), [{"study": self.name, "generation": generation, "state": state,
                                                       "seconds": seconds}])

    def checkpoint(self):
        """(last completed generation, optimizer state, seconds so far) or None."""
        with self.engine.connect() as connection:
            row = connection.execute(sa.select(CHECKPOINTS).where(CHECKPOINTS.c.study == self.name)).first()
        return None if row is None else (row.generation, row.state, row.seconds)

    def clear(self) -> None:
        """Remove this study's designs and checkpoint (a fresh run)."""
        with self.engine.begin() as connection:
            connection.execute(DESIGNS.delete().where(DESIGNS.c.study == self.name))
            connection.execute(CHECKPOINTS.delete().where(CHECKPOINTS.c.study == self.name))

    def designs(self) -> pd.DataFrame:
        """All designs: generation, member, value, failure, one column per parameter and metric."""
        with self.engine.connect() as connection:
            frame = pd.read_sql(sa.select(DESIGNS).where(DESIGNS.c.study == self.name)
                                .order_by(DESIGNS.c.generation, DESIGNS.c.member), connection)
        if frame.empty:
            return frame
        params = pd.DataFrame([json.loads(p) for p in frame.pop("params")])
        metrics = pd.DataFrame([json.loads(m) for m in frame.pop("metrics")]).add_prefix("metric_")
        return pd.concat([frame.drop(columns="study"), params, metrics], axis=1)


def export_to_optuna(frame: pd.DataFrame, *, study_name: str, space, direction: str, storage: str) -> int:
    """Copy a study's designs into an Optuna storage (e.g. for optuna-dashboard); returns trials written.

    Failed designs become FAIL trials. Written in one bulk call (add_trials) per study.
    """
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name=study_name, storage=storage, direction=direction, load_if_exists=True)
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
