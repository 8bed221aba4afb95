"""MetricTable (a cluster's results as arrays) against the per-design dicts it stands for: the same
stored matrix as morphopt.storage.encode_metrics of the dicts, the same objectives and constraint
failures as the dict code of morphopt.study, and shards gathered by index like a list would be."""

import copy
import math
import pickle
from types import SimpleNamespace

import numpy as np
import pytest

from morphopt.evaluate import Evaluation
from morphopt.metric_table import MetricTable
from morphopt.storage import encode_metrics
from morphopt.study import apply_constraints, objective_matrix


def _dicts(n=40, seed=0):
    """Metric dicts as the evaluators make them: most with one key set, failed designs with none,
    a None (non-finite) value, a bool and a string, and (N, 2) paths."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        if i % 7 == 3:
            out.append({})  # a failed design
            continue
        length = int(rng.integers(10, 30))  # a walker's last crank turn: its own number of records
        d = {"speed": float(rng.normal()), "stride": float(rng.uniform()), "steps": int(rng.integers(0, 9)),
             "paths": {"foot": rng.normal(size=(length, 2)), "knee": rng.normal(size=(length + 1, 2))}}
        if i % 5 == 1:
            d["speed"] = None
        if i % 6 == 2:
            d["closed"] = bool(i % 4)
            d["note"] = f"design {i}"
        if i % 9 == 4:
            del d["stride"]
            d["extra_height"] = np.float32(rng.uniform())
        out.append(d)
    return out


def _same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        if k == "paths":
            assert a[k].keys() == b[k].keys()
            for p in a[k]:
                np.testing.assert_array_equal(a[k][p], b[k][p])
        elif a[k] is None or b[k] is None:
            assert (a[k] is None or math.isnan(a[k])) and (b[k] is None or math.isnan(b[k]))
        elif isinstance(a[k], float) or isinstance(b[k], float):
            assert float(a[k]) == float(b[k])
        else:
            assert a[k] == b[k]


def _columns(names, matrix):
    return {n: matrix[:, j] for j, n in enumerate(names)}


def test_rows_read_back_as_the_dicts():
    dicts = _dicts()
    table = MetricTable.from_dicts(dicts)
    assert len(table) == len(dicts)
    for i, d in enumerate(dicts):
        _same(table[i], d)
    assert table[-1] is table[len(dicts) - 1]  # made once, kept (edits persist)


def test_stored_matrix_matches_encode_metrics_of_the_dicts():
    dicts = _dicts()
    expected = _columns(*encode_metrics(copy.deepcopy(dicts)))
    got = _columns(*encode_metrics(MetricTable.from_dicts(dicts)))
    assert got.keys() == expected.keys()
    for name in expected:
        np.testing.assert_array_equal(got[name], expected[name])


def test_shards_gathered_by_index():
    dicts = _dicts(57, seed=3)
    order = np.random.default_rng(1).permutation(len(dicts))
    parts = [order[:20], order[20:21], order[21:]]
    shards = [(part, pickle.loads(pickle.dumps(MetricTable.from_dicts([dicts[i] for i in part]), protocol=5)))
              for part in parts]
    table = MetricTable.gather(len(dicts), shards)
    for i, d in enumerate(dicts):
        _same(table[i], d)
    expected = _columns(*encode_metrics(dicts))
    got = _columns(*table.scalars())
    for name in expected:
        np.testing.assert_array_equal(got[name], expected[name])


def test_paths_of_different_point_sizes_are_refused():
    dicts = [{"paths": {"foot": np.zeros((5, 2))}}, {"paths": {"foot": np.zeros((6, 3))}}]
    with pytest.raises(ValueError, match="foot"):
        MetricTable.from_dicts(dicts)


def _spec(objectives, constraints=None):
    return SimpleNamespace(objectives=objectives, constraints=constraints or {})


def _objective(metric, sign=1.0, **kw):
    return SimpleNamespace(metric=metric, sign=sign, **kw)


def test_objectives_and_constraints_match_the_dict_code():
    dicts = _dicts(60, seed=5)
    failures = ["" if d else "could not assemble" for d in dicts]
    target = np.random.default_rng(2).normal(size=(16, 2))
    spec = _spec([_objective("speed", -1.0), _objective("path_error", 1.0, point="foot", target=target),
                  _objective("path_error", 1.0, point="knee", target=target)],
                 constraints={"stride": (0.2, 0.9), "steps": (1, 8)})
    by_dicts = Evaluation([{}] * len(dicts), copy.deepcopy(dicts), list(failures))
    by_table = Evaluation([{}] * len(dicts), MetricTable.from_dicts(dicts), list(failures))
    apply_constraints(spec, by_dicts)
    apply_constraints(spec, by_table)
    assert by_table.failures == by_dicts.failures
    assert sum(1 for f in by_dicts.failures if f.startswith("constraint")) > 0  # the check bites
    expected = objective_matrix(spec, by_dicts)
    got = objective_matrix(spec, by_table)
    np.testing.assert_array_equal(got, expected)
    assert np.isfinite(got).any() and np.isinf(got).any()
    expected_stored = _columns(*encode_metrics(by_dicts.metrics))
    got_stored = _columns(*encode_metrics(by_table.metrics))
    assert {"path_error", "path_error_2"} <= got_stored.keys()
    assert got_stored.keys() == expected_stored.keys()
    for name in expected_stored:
        np.testing.assert_array_equal(got_stored[name], expected_stored[name])


def test_edits_through_a_dict_are_stored():
    table = MetricTable.from_dicts(_dicts(10))
    table[2]["speed"] = 7.5
    table[4]["new_metric"] = 1.25
    names, matrix = table.scalars()
    columns = _columns(names, matrix)
    assert columns["speed"][2] == 7.5
    assert columns["new_metric"][4] == 1.25 and np.isnan(columns["new_metric"][5])


def test_a_shard_whose_designs_all_failed():
    for dicts in ([], [{}, {}], [{"note": "n/a"}]):
        table = MetricTable.from_dicts(dicts)
        assert len(table) == len(dicts)
        names, matrix = table.scalars()
        assert names == [] and matrix.shape == (len(dicts), 0)
    gathered = MetricTable.gather(3, [([0, 2], MetricTable.from_dicts([{}, {}])), ([1], MetricTable.from_dicts([{"x": 2.0}]))])
    assert gathered[1] == {"x": 2.0} and gathered[0] == {} and np.isnan(gathered.column("x")[[0, 2]]).all()


def test_edits_bools_and_missing_points_agree_with_the_dicts():
    base = [{"x": 1.0, "closed": True, "paths": {"knee": np.zeros((4, 2))}}, {"x": 2.0, "closed": False}]
    dicts, table = copy.deepcopy(base), MetricTable.from_dicts(copy.deepcopy(base))
    for rows in (dicts, table):
        rows[0]["x"] = 5.0  # an edit through the dict handed out
        del rows[1]["x"]
    failures = ["", ""]
    target = np.zeros((4, 2))
    spec = _spec([_objective("x", 1.0), _objective("closed", -1.0),
                  _objective("path_error", 1.0, point="foot", target=target)])
    by_dicts, by_table = Evaluation([{}] * 2, dicts, list(failures)), Evaluation([{}] * 2, table, list(failures))
    apply_constraints(_spec([], {"closed": (1, 1)}), by_dicts)
    apply_constraints(_spec([], {"closed": (1, 1)}), by_table)
    assert by_table.failures == by_dicts.failures == ["", "constraint closed in [1, 1] violated: 0"]
    ok = Evaluation([{}] * 2, table, ["", "failed"])
    matrix = objective_matrix(_spec(spec.objectives[:2]), ok)
    np.testing.assert_array_equal(matrix, [[5.0, -1.0], [np.inf, np.inf]])
    assert np.isinf(objective_matrix(_spec(spec.objectives[2:]), ok)).all()  # no design has the point 'foot'
    assert table.scalars()[0] == ["x"]  # bools are not stored
    np.testing.assert_array_equal(table.scalars()[1][:, 0], [5.0, np.nan])


def test_read_only_buffers_from_the_object_store():
    buffers = []
    blob = pickle.dumps(MetricTable.from_dicts([{"x": 1.0}, {"x": 2.0}]), protocol=5, buffer_callback=buffers.append)
    table = pickle.loads(blob, buffers=[b.raw().toreadonly() for b in buffers])
    table.set_column("x", 3.0)
    np.testing.assert_array_equal(table.column("x"), [3.0, 3.0])
