"""Shape-free features for discovery's library (library.py): a smooth function of what the data carry, of any form.

Most real couplings are a non-linear function of something logged: a magnet whose distance follows a servo angle
(a field as the inverse cube of that distance), an offset in the square of the temperature, a field that turns with
a gimbal. A linear group of the value, its lags or its phase takes none of them, and the spectral lines they put in
the residual (harmonics and sums of the observable's own lines) chase them without end.

- a spline of the value: cubic B-splines of x with interior knots at its quantiles, less one (their sum is the
  constant the offsets hold), each centred on its mean over the data; SHAPE_ORDERS functions, each order a group of
  the library, so that the order is chosen inside the training blocks like a lag's time constant. A spline of
  SHAPE_ORDERS[i] functions holds the one of SHAPE_ORDERS[i - 1] (their knots are nested) and every spline holds
  the value itself (a cubic spline reproduces x): the selection takes the smaller unless the larger predicts;
- an angle (a column named as one, or one that wraps): cos and sin of K times the angle itself, K = 1..TURN_ORDERS,
  not of time: a field fixed on what turns.

Each feature's recipe holds what the written effect needs to make it again (knots, centres, the angle's unit).
Numerics only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: the number of spline functions a shape group follows (each order its own group; nested knots)
SHAPE_ORDERS = (4, 8)
#: ... of an observable through a first-order lag (a core's temperature lagging the logged one, squared): the
#: smaller order only (the lags multiply the library by their number)
LAG_SHAPE_ORDERS = (4,)
#: the degree of the splines
SPLINE_DEGREE = 3
#: an angle's harmonics: cos and sin of 1..K times the angle, each K its own group
TURN_ORDERS = (1, 2)
#: a column is an angle by its name (a word of these), or where it wraps (jumps of about a turn)
ANGLE_WORDS = ("angle", "deg", "yaw", "heading", "azimuth", "bearing", "gimbal", "servo", "flap", "rudder", "pan",
               "tilt", "roll", "pitch", "heel", "elevator", "aileron", "rotor_pos", "shaft")
#: ... and its periodic functions are tried where it spans at least this share of a turn (a flap's +-30 deg is a
#: smooth function of the angle, which the splines take)
TURN_SPAN = 0.25


def knots_for(x: np.ndarray, n_functions: int, degree: int = SPLINE_DEGREE) -> np.ndarray:
    """The full knot vector of a B-spline basis of `n_functions` + 1 functions of x (one is the constant): interior
    knots at equally spaced quantiles of x (nested for n_functions + 1 - degree - 1 in 1, 5, 9 ...: SHAPE_ORDERS),
    the boundary knots at x's range repeated degree + 1 times."""
    interior = n_functions + 1 - (degree + 1)
    lo, hi = float(np.min(x)), float(np.max(x))
    inner = np.quantile(x, np.arange(1, interior + 1) / (interior + 1)) if interior > 0 else np.zeros(0)
    inner = np.clip(inner, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    return np.concatenate([np.full(degree + 1, lo), np.sort(inner), np.full(degree + 1, hi)])


def spline_values(x: np.ndarray, knots: np.ndarray, degree: int = SPLINE_DEGREE) -> np.ndarray:
    """(N, n) the B-splines of x on `knots` less the last one (their sum is one: the constant); x outside the knots'
    range is clipped to it (the shape's ends are held, never extrapolated as a cubic)."""
    from scipy.interpolate import BSpline               # here, not at import (a command's start)

    lo, hi = float(knots[0]), float(knots[-1])
    z = np.clip(np.asarray(x, dtype=np.float64), lo, hi)
    basis = BSpline.design_matrix(z, knots, degree).toarray()
    return basis[:, :-1]


def turn_values(x: np.ndarray, radians_per_unit: float, harmonics: int) -> np.ndarray:
    """(N, 2K) cos and sin of 1..K times the angle x (in its own unit)."""
    a = np.asarray(x, dtype=np.float64) * radians_per_unit
    return np.column_stack([f(h * a) for h in range(1, harmonics + 1) for f in (np.cos, np.sin)])


def angle_unit(name: str, x: np.ndarray) -> float | None:
    """Radians per unit of a column that is an angle (by its name: degrees unless it says radians; or a column that
    wraps: jumps of about 360 or 2 pi between samples), spanning at least TURN_SPAN of a turn; None otherwise."""
    low = name.lower()
    named = any(w in low for w in ANGLE_WORDS) and not any(w in low for w in ("deg_s", "dps", "rate", "rad_s"))
    span = float(np.ptp(x))
    jumps = np.abs(np.diff(x))
    wraps_deg = bool(np.any((jumps > 300.0) & (jumps < 370.0))) and float(np.max(np.abs(x))) <= 370.0
    wraps_rad = bool(np.any((jumps > 5.2) & (jumps < 6.5))) and float(np.max(np.abs(x))) <= 6.5
    if not (named or wraps_deg or wraps_rad):
        return None
    per = np.pi / 180.0
    if wraps_rad or ("rad" in low and "deg" not in low):
        per = 1.0
    return per if span * per >= TURN_SPAN * 2 * np.pi else None


def centred_columns(v: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """Each column less its mean over the data, and the means (kept with the written effect)."""
    centre = v.mean(axis=0)
    return v - centre, [float(c) for c in centre]


def shape_recipes(name: str, x: np.ndarray, base: dict[str, Any]) -> list[tuple[str, str, dict[str, Any],
                                                                                 np.ndarray]]:
    """The shape features of one observable x (its values, gaps filled; through a lag where `base` says so): (name,
    how, recipe, values (N, m)) for each spline order and, for an angle, each turn order. `base`: the recipe of x
    itself (where it comes from)."""
    out = []
    if float(np.ptp(x)) <= 0:
        return out
    distinct = np.unique(x).size
    for m in (LAG_SHAPE_ORDERS if "low_pass_s" in base else SHAPE_ORDERS):
        if distinct < 2 * (m + 1):                      # a switched column of few levels: nothing smooth to shape
            break
        knots = knots_for(x, m)
        vals, centre = centred_columns(spline_values(x, knots))
        out.append((f"{name} shape ({m})", "shape",
                    {**base, "basis": "spline", "knots": [float(k) for k in knots], "degree": SPLINE_DEGREE,
                     "functions": m, "centre": centre}, vals))
    per = None if "low_pass_s" in base else angle_unit(name, x)
    if per is not None:
        for k in TURN_ORDERS:
            vals, centre = centred_columns(turn_values(x, per, k))
            out.append((f"{name} turn ({k})" if len(TURN_ORDERS) > 1 else f"{name} turn", "turn",
                        {**base, "basis": "turn", "radians_per_unit": per, "harmonics": k, "centre": centre}, vals))
    return out


def basis_of(recipe: dict[str, Any], x: np.ndarray) -> np.ndarray:
    """(N, m) a shape feature's values from its recipe and the observable's values x (centred as recorded)."""
    if recipe["basis"] == "spline":
        v = spline_values(x, np.asarray(recipe["knots"], float), int(recipe["degree"]))
    else:
        v = turn_values(x, float(recipe["radians_per_unit"]), int(recipe["harmonics"]))
    return v - np.asarray(recipe["centre"], float)


def unit_of(recipe: dict[str, Any]) -> str:
    """The observable's unit for a law's parameters in it: degC for a temperature, the unit a column's name ends in
    (flap_deg: deg, coil_A: A), else the column's name (x in units of it)."""
    if recipe["source"] == "temperature":
        return "degC"
    if recipe["source"] == "ref_total":
        return "nT"
    if recipe["source"] == "angular rate":
        return "deg/s"
    name = recipe.get("column", "")
    suffix = name.rsplit("_", 1)[-1] if "_" in name else ""
    known = {"deg": "deg", "rad": "rad", "a": "A", "ma": "mA", "v": "V", "mv": "mV", "c": "degC", "degc": "degC",
             "hz": "Hz", "rpm": "rpm", "m": "m", "mm": "mm", "s": "s", "pct": "%", "w": "W", "k": "K"}
    return known.get(suffix.lower(), name)
