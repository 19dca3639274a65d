"""The JSON channels Foxglove reads, in one place for the MCAP logger and the live bridge (`fluxcal foxglove`):
their JSON schemas, the messages built from the decimated products, and `Products`, which turns corrected
blocks, error metrics and calibration records into those messages. Both writers use it, so a recording and
a live connection never differ.

Streams (topic `/fluxcal/<unit>/<stream>`, MCAP message encoding "json", schema encoding "jsonschema"); the
per-sample ones are means over 0.1 s of unit time (fluxcal.service.numerics.decimate), stamped with the unit time
`t_s` of the interval's first sample:

    vectors  {t_s, seq, n, cal_id, <probe>: {x, y, z, total}, center: {...}}     nT; total = mean |B|
    diff     {t_s, seq, n, cal_id, reference, <probe k>: {x, y, z, magnitude}}   nT; probe k minus `reference`
                                                                                 (probe 1); magnitude = mean |d|
    tensor   {t_s, seq, n, cal_id, dBx_dx, dBy_dx, ..., dBz_dz, trace}           nT/m; G[i, j] = dB_j/dx_i
    error    {t_s, seq, n, rms_nT: {channel: nT}, rms: {path_safe_channel: nT}}  RMS over the blocks starting
                                                                                 in the interval
    params   {t_s, seq, kind, cal_id, usable, frozen, method, samples_seen, coverage, condition, gate_usable,
              gate_rms_nT: [..], probes: [{name, offset_nT[3], offset_se_nT[3], matrix[9], matrix_se[9],
              <param>[..], <param>_se[..]}]}                                     on every calibration record

Field names are plain identifiers so Foxglove's plot panel can address every number
(`/fluxcal/grad1/diff.s2.magnitude`, `.probes[0].offset_nT[0]`); unknown figures (NaN) are null.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from fluxcal.service.numerics.decimate import RmsMeans, VectorMeans
from fluxcal.service.numerics.outputs import CorrectedBlock

from .encoding import CALIBRATION_SCHEMA, EVENT_SCHEMA, HEALTH_SCHEMA

_DRAFT = "https://json-schema.org/draft/2020-12/schema"
_NUM = {"type": ["number", "null"]}
_NUMS = {"type": "array", "items": _NUM}
_HEAD = {"t_s": {**_NUM, "description": "unit time of the interval's first sample, s"},
         "seq": {"type": ["integer", "null"], "description": "sample counter of the interval's first sample"},
         "n": {"type": "integer", "description": "samples in the interval"},
         "cal_id": {"type": "integer", "description": "the calibration that produced the values"}}
_VEC = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "total": _NUM},
        "description": "mean corrected field in nT over the interval; total = mean of |B| per sample"}
_DIFF = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "magnitude": _NUM},
         "description": "mean difference to the reference probe in nT over the interval; magnitude = mean |d|"}
#: tensor fields, row-major: G[i, j] = dB_j/dx_i is `dB<j>_d<i>`
TENSOR_FIELDS = tuple(f"dB{j}_d{i}" for i in "xyz" for j in "xyz")


def _schema(title: str, properties: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"$schema": _DRAFT, "title": title, "type": "object", "properties": properties, **extra}


def vectors_schema(probe_names: Sequence[str]) -> dict[str, Any]:
    """JSON schema of the decimated vectors channel for these probe names (Foxglove offers the paths)."""
    return _schema("fluxcal vectors", {**_HEAD, "center": _VEC, **{name: _VEC for name in probe_names}},
                   additionalProperties=_VEC)


def diff_schema(probe_names: Sequence[str]) -> dict[str, Any]:
    return _schema("fluxcal diff", {**_HEAD, "reference": {"type": "string", "description": "probe subtracted"},
                                    **{name: _DIFF for name in probe_names[1:]}},
                   required=["t_s", "reference"], additionalProperties=_DIFF)


TENSOR_SCHEMA = _schema("fluxcal tensor", {**_HEAD, **{f: {**_NUM, "description": f"{f}, nT/m"} for f in TENSOR_FIELDS},
                                           "trace": {**_NUM, "description": "trace of the mean tensor, nT/m "
                                                                            "(div B: near 0 in a source-free field)"}},
                        required=["t_s", *TENSOR_FIELDS, "trace"])
ERROR_SCHEMA = _schema("fluxcal error", {
    **_HEAD,
    "rms_nT": {"type": "object", "additionalProperties": _NUM,
               "description": "RMS residual per channel of `fluxcal diagnose` (s1.scalar, s2-s1.x, ...), nT"},
    "rms": {"type": "object", "additionalProperties": _NUM,
            "description": "the same figures under path-safe names (s1_scalar, s2_minus_s1_x, ...)"}},
    required=["t_s", "rms_nT", "rms"])
_PROBE_PARAMS = {"type": "object", "properties": {
    "name": {"type": "string"}, "offset_nT": _NUMS, "offset_se_nT": _NUMS,
    "matrix": {**_NUMS, "description": "M row-major (corrected = M (raw - offset))"},
    "matrix_se": {**_NUMS, "description": "standard errors of M, row-major"}},
    "additionalProperties": {"anyOf": [_NUM, _NUMS]}}


def params_schema() -> dict[str, Any]:
    return _schema("fluxcal params", {
        "t_s": _NUM, "seq": {"type": ["integer", "null"]}, "kind": {"type": "string"},
        "cal_id": {"type": ["integer", "null"]}, "usable": {"type": "boolean"}, "frozen": {"type": "boolean"},
        "method": {"type": ["string", "null"]}, "samples_seen": {"type": ["integer", "null"]},
        "coverage": {**_NUM, "description": "the quality gate's direction coverage (0..1)"},
        "condition": {**_NUM, "description": "the gate's condition number"},
        "gate_usable": {"type": ["boolean", "null"]}, "gate_rms_nT": _NUMS,
        "probes": {"type": "array", "items": _PROBE_PARAMS}}, required=["kind", "probes"])


def json_channels(probe_names: Sequence[str]) -> dict[str, tuple[str, dict[str, Any]]]:
    """stream -> (schema name, JSON schema) of every JSON channel, in the order the logger registers them."""
    return {"vectors": ("fluxcal.vectors", vectors_schema(probe_names)),
            "diff": ("fluxcal.diff", diff_schema(probe_names)),
            "tensor": ("fluxcal.tensor", TENSOR_SCHEMA),
            "error": ("fluxcal.error", ERROR_SCHEMA),
            "params": ("fluxcal.params", params_schema()),
            "calibration": ("fluxcal.calibration", CALIBRATION_SCHEMA),
            "events": ("fluxcal.event", EVENT_SCHEMA),
            "health": ("fluxcal.health", HEALTH_SCHEMA)}


#: the JSON streams made from the data (the bridge serves these and calibration, health)
PRODUCT_STREAMS = ("vectors", "diff", "tensor", "error", "params")


def path_safe(channel: str) -> str:
    """A name Foxglove's message paths accept: `s2-s1.x` -> `s2_minus_s1_x`."""
    return re.sub(r"[^A-Za-z0-9_]", "_", channel.replace("-", "_minus_"))


def _xyz(m: Sequence[float], extra: str, value: float) -> dict[str, float]:
    return {"x": m[0], "y": m[1], "z": m[2], extra: value}


def vectors_message(iv: Mapping[str, Any], names: Sequence[str]) -> dict[str, Any]:
    rec: dict[str, Any] = {k: iv[k] for k in ("t_s", "seq", "n", "cal_id")}
    for name, m, tot in zip(names, iv["mean"].tolist(), iv["total"].tolist()):
        rec[name] = _xyz(m, "total", tot)
    if iv["center"] is not None:
        rec["center"] = _xyz(iv["center"][0].tolist(), "total", float(iv["center"][1]))
    return rec


def diff_message(iv: Mapping[str, Any], names: Sequence[str]) -> dict[str, Any]:
    mean, mag = iv["diff"]
    rec: dict[str, Any] = {k: iv[k] for k in ("t_s", "seq", "n", "cal_id")}
    rec["reference"] = names[0]
    for name, m, d in zip(names[1:], mean.tolist(), mag.tolist()):
        rec[name] = _xyz(m, "magnitude", d)
    return rec


def tensor_message(iv: Mapping[str, Any]) -> dict[str, Any]:
    g, trace = iv["tensor"]
    return {**{k: iv[k] for k in ("t_s", "seq", "n", "cal_id")}, **dict(zip(TENSOR_FIELDS, g.ravel().tolist())),
            "trace": trace}


def error_message(rec: Mapping[str, Any]) -> dict[str, Any]:
    rms = dict(rec["rms_nT"])
    return {"t_s": rec["t_s"], "seq": rec["seq"], "n": rec["n"], "rms_nT": rms,
            "rms": {path_safe(k): v for k, v in rms.items()}}


def _se(values: Any) -> list[Any]:
    """Standard errors as numbers, unknown as None (the state marks an unknown offset SE with -1)."""
    return [v if isinstance(v, (int, float)) and v >= 0 else None for v in np.ravel(np.asarray(values, float)).tolist()]


def _probe_params(p: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"name": p.get("name"), "offset_nT": list(p.get("offset_nT") or []),
                           "offset_se_nT": _se(p.get("offset_se_nT") or []),
                           "matrix": np.ravel(np.asarray(p.get("matrix") or [], float)).tolist(),
                           "matrix_se": _se(p.get("matrix_se") or [])}
    for key, entry in (p.get("params") or {}).items():
        if key == "offset_nT" or not isinstance(entry, Mapping):
            continue
        value, se = entry.get("value"), entry.get("se")
        numeric = isinstance(value, (int, float)) and not isinstance(value, bool) or (
            isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value))
        if numeric and re.fullmatch(r"[A-Za-z0-9_]+", key):
            out[key] = value
            out[f"{key}_se"] = None if se is None else (_se([se])[0] if not isinstance(se, list) else _se(se))
    return out


def params_message(record: Mapping[str, Any]) -> dict[str, Any]:
    """The calibration's parameters with standard errors and the gate's figures, from a calibration record
    {"kind", "seq", "t_s", ..., "state": {...}} or a bare state (a `state` query's reply)."""
    st = record.get("state") if isinstance(record.get("state"), Mapping) else record
    gate = st.get("gate") if isinstance(st.get("gate"), Mapping) else {}
    rms = gate.get("rms_nT")
    return {"t_s": record.get("t_s"), "seq": record.get("seq"), "kind": str(record.get("kind", "state")),
            "cal_id": st.get("cal_id"), "usable": bool(st.get("usable")), "frozen": bool(st.get("frozen")),
            "method": st.get("method"), "samples_seen": st.get("samples_seen"),
            "coverage": gate.get("coverage", record.get("coverage")),
            "condition": gate.get("condition", record.get("condition")),
            "gate_usable": gate.get("usable"), "gate_rms_nT": rms if isinstance(rms, list) else [rms] if rms else [],
            "probes": [_probe_params(p) for p in st.get("probes") or [] if isinstance(p, Mapping)]}


class Products:
    """Corrected blocks, per-block error metrics and calibration records in; (stream, message) pairs out, each
    message a dict with its `t_s` (None when it has none: place it at the latest data). `period_s` is the
    decimation interval (0.1 s: 10 Hz). `probe_names` name the probes (s1, s2, ... when not given)."""

    def __init__(self, probe_names: Sequence[str] = (), period_s: float = 0.1) -> None:
        self.probe_names = list(probe_names)
        self._means = VectorMeans(period_s)
        self._errors = RmsMeans(period_s)

    def _names(self, n: int) -> list[str]:
        return [self.probe_names[k] if k < len(self.probe_names) else f"s{k + 1}" for k in range(n)]

    def _interval(self, iv: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
        names = self._names(len(iv["total"]))
        out = [("vectors", vectors_message(iv, names))]
        if iv["diff"] is not None:
            out.append(("diff", diff_message(iv, names)))
        if iv["tensor"] is not None:
            out.append(("tensor", tensor_message(iv)))
        return out

    def corrected(self, block: CorrectedBlock) -> list[tuple[str, dict[str, Any]]]:
        """The intervals this block completed: vectors, diff and tensor messages."""
        if not block.n_samples:
            return []
        return [m for iv in self._means.add(block) for m in self._interval(iv)]

    def error(self, rms_nT: Mapping[str, float | None], *, t_s: float, seq: int | None,
              n: int) -> list[tuple[str, dict[str, Any]]]:
        """A block's error metric; the error message of the interval it completed, if any."""
        return [("error", error_message(r)) for r in self._errors.add(rms_nT, t_s=t_s, seq=seq, n=n)]

    @staticmethod
    def calibration(record: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
        return [("params", params_message(record))]

    def flush(self) -> list[tuple[str, dict[str, Any]]]:
        """The intervals being filled (at the end of a recording or a connection)."""
        return ([m for iv in self._means.flush() for m in self._interval(iv)]
                + [("error", error_message(r)) for r in self._errors.flush()])
