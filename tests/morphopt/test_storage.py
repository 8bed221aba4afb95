"""Study storage: what a generation's designs read back as, checked against a DataFrame built
directly from the same dicts; exact float64 round trips; databases of the earlier JSON layout."""

import json
import math
import sqlite3

import numpy as np
import pandas as pd
import pytest

from morphopt.storage import StudyStorage


def expected_frame(generation, params, values, metrics, failures):
    """The documented reading, written out with pandas alone: one column per parameter (NaN where
    a design lacks it), one metric_ column per metric that is a number (not a bool) in some design,
    NaN where a design lacks it or has no finite number there."""
    names = list(dict.fromkeys(k for m in metrics for k, v in m.items()
                               if v is None or (isinstance(v, (int, float, np.number)) and not isinstance(v, bool))))

    def number(v):
        ok = isinstance(v, (int, float, np.number)) and not isinstance(v, (bool, np.bool_))
        return float(v) if ok and math.isfinite(v) else math.nan

    frame = pd.DataFrame({"generation": generation, "member": range(len(params)),
                          "value": [v if math.isfinite(v) else math.nan for v in values], "failure": failures})
    table = pd.DataFrame([{k: (v.item() if isinstance(v, np.generic) else v) for k, v in p.items()} for p in params])
    scores = pd.DataFrame({f"metric_{n}": [number(m.get(n)) for m in metrics] for n in names}, index=frame.index)
    return pd.concat([frame, table, scores], axis=1)


def generation_data(rng, count=64):
    families = ["jansen_leg", "klann_leg", 'quote " and 100 %']
    params, metrics = [], []
    for k in range(count):
        p = {"scale": float(rng.uniform(1, 5)), "legs": int(rng.integers(1, 5)), "mirror": bool(k % 3 == 0),
             "family": families[k % 3], "phases": [0.0, 0.5], "speed": np.float32(rng.uniform(-1, 1)),
             "count": np.int64(k), "tag": {"k": k} if k % 2 else [k]}
        if k % 5 == 0:
            p["only_some"] = 2.5 * k
        params.append(p)
        m = {"walking_speed": float(rng.normal()), "stride": rng.normal(), "paths": {"foot": np.zeros((3, 2))},
             "jammed": bool(k % 2), "torque_peak": int(k)}
        if k % 7 == 0:  # a failed design: fewer metrics, some of them not finite
            m = {"walking_speed": math.nan, "stride": math.inf if k % 2 else -math.inf, "torque_peak": None}
        if k == 5:
            m["stride"] = "not a number"  # a non-number under a numeric key
        metrics.append(m)
    values = [float(v) for v in rng.normal(size=count)]
    values[3] = math.inf
    failures = ["" if k % 7 else f"jammed at {k}" for k in range(count)]
    return params, values, metrics, failures


def test_a_generation_reads_back_as_the_dicts_it_was_written_from(tmp_path):
    rng = np.random.default_rng(3)
    storage = StudyStorage(f"sqlite:///{tmp_path / 's.db'}", "walk")
    storage.acquire({})
    first = generation_data(rng)
    second = generation_data(rng, 17)
    second[2][0]["new_metric"] = 1.25  # a metric only the second generation has
    storage.write_generation(0, *first, b"state0", 1.0)
    storage.write_generation(1, *second, b"state1", 2.0)
    frame = storage.designs()
    expected = pd.concat([expected_frame(0, *first), expected_frame(1, *second)], ignore_index=True)
    expected = expected[frame.columns]  # the same columns, in the stored order
    assert sorted(frame.columns) == sorted(expected.columns)
    pd.testing.assert_frame_equal(frame, expected, check_exact=True, check_dtype=False)
    assert frame["legs"].dtype == np.int64 and frame["mirror"].dtype == bool and frame["scale"].dtype == np.float64
    assert frame["metric_stride"].iloc[5] != frame["metric_stride"].iloc[5]  # the string became NaN
    assert "metric_jammed" not in frame and "metric_paths" not in frame  # bools and paths are not stored
    assert storage.checkpoint() == (1, b"state1", 2.0)
    # a generation is stored once: writing it again changes nothing
    with pytest.raises(ValueError, match=r"generation 0 is stored already; nothing was written"):
        storage.write_generation(0, *second, b"again", 0.5)
    pd.testing.assert_frame_equal(storage.designs(), frame, check_exact=True)
    assert storage.checkpoint() == (1, b"state1", 2.0)


def test_floats_round_trip_bit_for_bit(tmp_path):
    rng = np.random.default_rng(11)
    raw = np.concatenate([rng.normal(size=200) * 10.0 ** rng.integers(-300, 300, 200), [5e-324, -0.0, 1.7e308]])
    params = [{"x": float(v)} for v in raw]
    metrics = [{"m": float(v), "n": float(-v)} for v in raw]
    storage = StudyStorage(f"sqlite:///{tmp_path / 's.db'}", "exact")
    storage.acquire({})
    storage.write_generation(0, params, list(raw), metrics, [""] * len(raw), b"", 0.0)
    frame = storage.designs()
    for column, want in (("x", raw), ("metric_m", raw), ("metric_n", -raw)):
        assert frame[column].to_numpy().tobytes() == want.tobytes(), column
    assert np.array_equal(frame["value"], raw)  # an SQL REAL column: equal values (SQLite keeps no -0.0)


def test_a_database_of_the_earlier_json_layout_is_read_and_extended(tmp_path):
    path = tmp_path / "old.db"
    with sqlite3.connect(path) as db:  # the layout of earlier versions, written as they wrote it
        db.execute("CREATE TABLE designs (study VARCHAR(200), generation INTEGER, member INTEGER, value FLOAT, "
                   "failure TEXT, params TEXT, metrics TEXT)")
        db.execute("CREATE TABLE checkpoints (study VARCHAR(200) PRIMARY KEY, generation INTEGER, state BLOB, "
                   "seconds FLOAT)")
        old = [({"scale": 1.5, "family": "jansen_leg"}, {"walking_speed": 0.25, "stride": None}),
               ({"scale": 2.0, "family": "klann_leg"}, {"walking_speed": 0.5, "stride": 0.1})]
        for k, (p, m) in enumerate(old):
            db.execute("INSERT INTO designs VALUES (?, ?, ?, ?, ?, ?, ?)",
                       ("walk", 0, k, -m["walking_speed"], "", json.dumps(p), json.dumps(m)))
        db.execute("INSERT INTO checkpoints VALUES ('walk', 0, x'00', 1.0)")
    storage = StudyStorage(f"sqlite:///{path}", "walk")
    frame = storage.designs()
    assert list(frame["family"]) == ["jansen_leg", "klann_leg"] and list(frame["scale"]) == [1.5, 2.0]
    assert list(frame["metric_walking_speed"]) == [0.25, 0.5] and math.isnan(frame["metric_stride"][0])
    storage.acquire({})
    new_params = [{"scale": 3.0, "family": "jansen_leg"}]
    storage.write_generation(1, new_params, [-0.75], [{"walking_speed": 0.75, "stride": 0.2}], [""], b"s", 2.0)
    frame = storage.designs()
    assert list(frame["generation"]) == [0, 0, 1] and list(frame["scale"]) == [1.5, 2.0, 3.0]
    assert list(frame["metric_walking_speed"]) == [0.25, 0.5, 0.75]
    assert StudyStorage(f"sqlite:///{path}", "walk").designs().equals(frame)  # reopened: the same


def test_damaged_designs_are_a_clear_error(tmp_path):
    path = tmp_path / "s.db"
    storage = StudyStorage(f"sqlite:///{path}", "walk")
    storage.acquire({})
    storage.write_generation(0, [{"x": 1.0}], [1.0], [{"m": 2.0}], [""], b"", 0.0)
    with sqlite3.connect(path) as db:
        db.execute("UPDATE designs SET metrics = x'0102'")
    with pytest.raises(ValueError, match=r"study 'walk' in sqlite.*generation 0 cannot be read"):
        storage.designs()
