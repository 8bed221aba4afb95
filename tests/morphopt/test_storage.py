"""Study storage: the bulk JSON encoding of a generation is json.dumps, text for text."""

import json
import math

from morphopt.storage import json_rows


def test_json_rows_writes_what_json_dumps_writes():
    rows = [
        {"crank": 0.1, "n": 3, "family": "jansen_leg", "flag": True},
        {"crank": 1e-300, "n": -2, "family": 'quote " and 100 %', "flag": False},
        {"crank": math.nan, "n": 0, "family": "", "flag": None},
        {"crank": -math.inf, "n": 2**70, "family": "ü", "flag": [1, 2.5]},
        {},
        {"stride": -0.0, "path": [[0.0, 1.0]], "%s": 1.5},
        {1: 2.0},
        {"crank": 0.30000000000000004, "n": 7, "family": "klann_leg", "flag": True},
    ]
    assert json_rows(rows) == [json.dumps(r) for r in rows]
    assert [json.loads(text) for text in json_rows(rows[:2])] == rows[:2]
