"""fluxcal.service.numerics.jsonsafe: what the data do not determine leaves as null in JSON, never as NaN (which JSON does
not have) nor as a number; numpy's types leave as Python's."""

from __future__ import annotations

import json
import math

import numpy as np

from fluxcal.service.numerics.jsonsafe import finite_or_none, json_safe


def test_numbers_finite_or_null():
    assert finite_or_none(None) is None
    assert finite_or_none(float("nan")) is None
    assert finite_or_none(np.inf) is None
    assert finite_or_none(-np.float32(np.inf)) is None
    assert finite_or_none(3) == 3.0 and isinstance(finite_or_none(3), float)
    assert finite_or_none(np.float64(-2.5)) == -2.5


def test_structures_become_plain_json():
    x = {"a": np.array([[1.0, np.nan], [np.inf, 4.0]]), "b": (np.int64(7), np.float32(0.5), "s"),
         "c": [None, True, {"d": -np.inf}]}
    out = json_safe(x)
    assert out == {"a": [[1.0, None], [None, 4.0]], "b": [7, 0.5, "s"], "c": [None, True, {"d": None}]}
    assert type(out["b"][0]) is int and type(out["b"][1]) is float
    text = json.dumps(out, allow_nan=False)          # raises on any NaN or infinity left
    assert json.loads(text) == out
    assert not any(isinstance(v, float) and not math.isfinite(v) for v in out["b"])
