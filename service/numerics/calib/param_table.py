"""The parameters of a calibration as table rows for the report: value, standard error, unit, and a
warning where the data leave the parameter undetermined.

A row is flagged when its standard error is missing where one was fitted (the fit found it
undetermined), when the fit's own warnings name it, or when the standard error is too large for
its size: an offset's above OFFSET_SE_MAX_FRACTION of the field, a scale's above SCALE_SE_MAX of
the scale (calib.order's thresholds, the ones the fit's order choice uses), any other parameter's
above its own size. Numerics only: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from .model import ProbeCalibration
from .order import OFFSET_SE_MAX_FRACTION, SCALE_SE_MAX

#: entries of ProbeCalibration.params that describe the fit rather than the sensor
_NOT_PARAMETERS = {"offset_nT", "samples", "align", "condition", "residual_rms_nT", "vector_residual_rms_nT",
                   "memory_samples", "axis_rms_nT",
                   "sine_amplitude_nT", "sine_phase_deg", "sine_mean_nT"}
_SCALES = {"scale"}


@dataclass(frozen=True)
class ParamRow:
    """One parameter: `se` None where there is none; `warning` "" when the parameter is determined."""

    owner: str                      # the probe, or the effect for effect parameters
    name: str                       # "offset_nT.x", "scale.c_x", "nonorth_deg.phi", "s1.x nT/degC"
    value: float
    se: float | None
    unit: str
    warning: str = ""
    note: str = ""


def _finite(x: Any) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def _judge(key: str, value: float, se: float | None, field_nT: float | None, named: bool) -> str:
    if named:
        return "named in the fit's warnings"
    if se is None:
        return ""
    if key == "offset_nT" and field_nT and se > OFFSET_SE_MAX_FRACTION * field_nT:
        return f"not determined: SE above {OFFSET_SE_MAX_FRACTION:.0%} of the field"
    if key in _SCALES:
        return f"not determined: SE above {SCALE_SE_MAX:.0%} of the scale" if se > SCALE_SE_MAX * abs(value) else ""
    if key != "offset_nT" and se > abs(value):
        return "SE exceeds the value"
    return ""


def probe_rows(p: ProbeCalibration, warnings: Iterable[str] = (), field_nT: float | None = None,
               undetermined: Iterable[str] = (), with_matrix: bool | None = None) -> list[ParamRow]:
    """Rows of one probe's linear calibration: offsets, then every named physical parameter, then the
    matrix elements when there is no physical parameter (or `with_matrix`). `undetermined`: row names
    whose missing standard error means the fit could not determine them."""
    said = [w for w in warnings if w.startswith(f"{p.name}:")]
    flagged = set(undetermined)

    def row(key: str, label: str, value: Any, se: Any, unit: str, note: str = "") -> ParamRow:
        name = f"{key}.{label}"
        v, s = float(value), _finite(se)
        named = any(f"{name} " in w or f"{name}=" in w or f"{name}:" in w for w in said)
        warn = ("not determined by these data" if name in flagged and s is None
                else _judge(key, v, s, field_nT, named))
        if not warn and s is None and note.startswith("not determined"):
            warn, note = note, ""
        return ParamRow(p.name, name, v, s, unit, warn, note)

    rows = [row("offset_nT", a, v, s, "nT") for a, v, s in zip("xyz", p.offset_nT, p.offset_se_nT)]
    physical = False
    for key, entry in p.params.items():
        if key in _NOT_PARAMETERS or not isinstance(entry, dict):
            continue
        value = entry.get("value")
        try:
            vals = np.atleast_1d(np.asarray(value, dtype=float))
        except (TypeError, ValueError):
            continue
        if value is None or vals.size == 0:
            continue
        se = entry.get("se")
        ses = np.atleast_1d(np.asarray(se, dtype=float)) if se is not None else np.full(vals.size, np.nan)
        labels = entry.get("names") or (list("xyz") if vals.size == 3 else [str(i) for i in range(vals.size)])
        if vals.size == 1:
            labels = [key if not entry.get("names") else labels[0]]
        note = str(entry.get("note", ""))
        rows += [row(key, lab, v, s, entry.get("unit", ""), note) for lab, v, s in zip(labels, vals, ses)]
        physical = physical or key in _SCALES | {"nonorth_deg", "misalign_deg"}
    if with_matrix or (with_matrix is None and not physical):
        rows += [row("matrix", f"{'xyz'[i]}{'xyz'[j]}", p.matrix[i, j], p.matrix_se[i, j], "")
                 for i in range(3) for j in range(3)]
    return rows


def effect_rows(effect_params: dict[str, dict[str, dict[str, Any]]]) -> list[ParamRow]:
    """Rows of the effect terms' parameters {effect: {name: {"value", "se", "unit", "note"}}}; a term's fixed
    reference ("fixed": true) is said to be fixed, a parameter held at its floor ("at_floor") to be there, never
    undetermined."""
    out = []
    for eff, params in (effect_params or {}).items():
        for name, v in params.items():
            se, note = _finite(v.get("se")), str(v.get("note", ""))
            value = float(v["value"])
            if v.get("fixed"):
                out.append(ParamRow(eff, name, value, None, v.get("unit", ""), "",
                                    f"fixed: {note}" if note else "fixed: held at this value, not fitted"))
                continue
            if v.get("at_floor"):             # held at the lowest value its physics allows: said so, as fit says it
                out.append(ParamRow(eff, name, value, None, v.get("unit", ""), "", f"at its floor: {v['at_floor']}"))
                continue
            warn = "" if note or se is not None else "not determined by these data"
            if se is not None and se > abs(value):
                warn = "SE exceeds the value"
            out.append(ParamRow(eff, name, value, se, v.get("unit", ""), warn, note))
    return out


__all__ = ["ParamRow", "probe_rows", "effect_rows"]
