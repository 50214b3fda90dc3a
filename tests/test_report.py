"""The JSON writer: a non-finite number is data (null, named under ``non_finite``), never a failure, and
never a bare NaN/Infinity token that strict JSON readers reject (issue 22)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from errplan.errors import ErrplanError
from errplan.report import NON_FINITE_KEY, to_json, write_json


def test_finite_values_pass_unchanged():
    obj = {"a": 1, "b": [1.5, np.float64(2.0), np.int64(3)], "c": {"d": np.array([[1.0, 2.0]])}, "e": None}
    assert json.loads(to_json(obj)) == {"a": 1, "b": [1.5, 2.0, 3], "c": {"d": [[1.0, 2.0]]}, "e": None}


def test_non_finite_values_become_null_and_are_named_where_they_stand():
    obj = {
        "certified_G_norm": math.inf,
        "gain": 0.9,
        "verification": {"grid_G_norm": np.float64(np.inf), "phi": -np.inf, "ratio": float("nan"), "ok": 1.0},
        "path": [[0.0, 1.0], [np.nan, 2.0]],
        "runs": [{"final_error": np.inf}, {"final_error": 0.001}],
    }
    out = json.loads(to_json(obj))  # strict: allow_nan=False inside to_json, and json.loads of the text
    assert out["certified_G_norm"] is None and out["gain"] == 0.9
    assert out[NON_FINITE_KEY] == {"certified_G_norm": "inf", "path[1][0]": "nan"}
    v = out["verification"]
    assert v["grid_G_norm"] is None and v["phi"] is None and v["ratio"] is None and v["ok"] == 1.0
    assert v[NON_FINITE_KEY] == {"grid_G_norm": "inf", "phi": "-inf", "ratio": "nan"}
    assert out["path"] == [[0.0, 1.0], [None, 2.0]]
    assert out["runs"][0] == {"final_error": None, NON_FINITE_KEY: {"final_error": "inf"}}
    assert NON_FINITE_KEY not in out["runs"][1]
    assert "Infinity" not in to_json(obj) and "NaN" not in to_json(obj)


def test_a_bare_top_level_list_with_a_non_finite_value_is_an_internal_error():
    with pytest.raises(ErrplanError, match="non-finite"):
        to_json([1.0, math.inf])


def test_a_result_that_already_has_the_key_is_not_silently_overwritten():
    with pytest.raises(ErrplanError, match=NON_FINITE_KEY):
        to_json({"x": math.inf, NON_FINITE_KEY: "mine"})


def test_write_json_is_atomic_and_reads_back(tmp_path):
    p = tmp_path / "out.json"
    write_json(p, {"G": np.inf})
    assert json.loads(p.read_text()) == {"G": None, NON_FINITE_KEY: {"G": "inf"}}
    assert not (tmp_path / "out.json.part").exists()
