"""Numbers made fit for JSON, which has neither NaN nor infinity: one home for the results' `as_dict`s and the
calibration file's contract (an estimate the data do not determine is written as null, never as a number)."""

from __future__ import annotations

from typing import Any

import numpy as np


def finite_or_none(x: Any) -> float | None:
    """A float, or None for None, NaN and infinity."""
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def json_safe(x: Any) -> Any:
    """Plain JSON through dicts, lists, tuples and arrays: floats finite or None, numpy integers as int."""
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (float, np.floating)):
        return finite_or_none(x)
    if isinstance(x, np.integer):
        return int(x)
    return x
