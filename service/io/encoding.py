"""Encodings of fluxcal's streams for Zenoh payloads and MCAP messages: binary blocks and small JSON.

Raw SampleBlocks use `fluxcal.raw.v1` (layout in drivers/encoding.py, re-exported here).
CorrectedBlocks use `fluxcal.corrected.v1`. Little-endian, tightly packed, C-order arrays,
written and read whole with numpy tobytes / frombuffer:

Layout `fluxcal.corrected.v1` (the MCAP message encoding and the Zenoh schema name):

    offset              type               field
    0                   3 bytes            kind "FXc" (0x46 0x58 0x63)
    3                   1 byte             layout revision, ASCII "0" (0x30); any other is refused
    4                   u8                 presence bits: 1 diff_nT, 2 tensor_nT_m, 4 center_nT (others refused)
    5                   u16                P, probes
    7                   u32                N, samples
    11                  i64                cal_id, the calibration that produced the block
    19                  f64[N]             t_s, unit time in s (as in the raw block)
    19 + 8N             i64[N]             seq, unwrapped sample counter (as in the raw block)
    19 + 16N            f64[N, P, 3]       corrected_nT, calibrated and aligned, platform frame
    then, if bit 1:     f64[N, P-1, 3]     diff_nT, probe k minus probe 1
    then, if bit 2:     f64[N, 3, 3]       tensor_nT_m, row-major G[i, j] = dB_j/dx_i
    then, if bit 4:     f64[N, 3]          center_nT, field at the array centre

    size = 19 + N (16 + 24 P) + [24 N (P-1)] + [72 N] + [24 N]

Round trips are bit for bit (NaN payloads included). JSON streams (calibration state and events,
health counters, decimated vectors) are UTF-8 JSON objects made with `encode_json`: numpy values
become plain numbers, NaN and infinities become null (strict JSON readers reject NaN). Their JSON
schemas (draft 2020-12) are here too, so MCAP files and dashboards describe themselves.
"""

from __future__ import annotations

import json
import math
import struct
import weakref
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from fluxcal.drivers.encoding import RAW_ENCODING, RAW_LAYOUT, check_magic, decode_raw, encode_raw, layout_text
from fluxcal.drivers.errors import DataError
from fluxcal.service.numerics.outputs import CorrectedBlock

CORRECTED_KIND = b"FXc"
CORRECTED_REVISION = b"0"
CORRECTED_MAGIC = CORRECTED_KIND + CORRECTED_REVISION
#: the message encoding name of the corrected layout (MCAP channel encoding, Zenoh schema)
CORRECTED_ENCODING = "fluxcal.corrected.v1"
#: the layout above as text (schema data of MCAP corrected channels)
CORRECTED_LAYOUT = layout_text(__doc__)
_COR_HEAD = struct.Struct("<4sBHIq")
_BIT_DIFF, _BIT_TENSOR, _BIT_CENTER = 1, 2, 4


def encode_corrected(block: CorrectedBlock) -> bytes:
    """The block as `fluxcal.corrected.v1` bytes (layout in the module docstring)."""
    bits = ((block.diff_nT is not None) * _BIT_DIFF | (block.tensor_nT_m is not None) * _BIT_TENSOR
            | (block.center_nT is not None) * _BIT_CENTER)
    parts = [_COR_HEAD.pack(CORRECTED_MAGIC, bits, block.n_probes, block.n_samples, int(block.cal_id)),
             np.ascontiguousarray(block.t_s, "<f8").tobytes(), np.ascontiguousarray(block.seq, "<i8").tobytes(),
             np.ascontiguousarray(block.corrected_nT, "<f8").tobytes()]
    for a in (block.diff_nT, block.tensor_nT_m, block.center_nT):
        if a is not None:
            parts.append(np.ascontiguousarray(a, "<f8").tobytes())
    return b"".join(parts)


def encode_probes(block: CorrectedBlock) -> list[bytes]:
    """The block as one `fluxcal.corrected.v1` message per probe (P = 1, corrected_nT only: the bus's
    `corrected/<probe>` streams), each the bytes encode_corrected gives that probe alone. Made in one pass over
    the block: the P messages are rows of one array, cut apart at the end."""
    n, p = block.n_samples, block.n_probes
    rows = np.empty((p, _COR_HEAD.size + 40 * n), np.uint8)           # header, t_s, seq, corrected (N, 1, 3)
    rows[:, :_COR_HEAD.size] = np.frombuffer(_COR_HEAD.pack(CORRECTED_MAGIC, 0, 1, n, int(block.cal_id)), np.uint8)
    body = rows[:, _COR_HEAD.size:]
    body[:, :8 * n] = np.ascontiguousarray(block.t_s, "<f8").view(np.uint8)
    body[:, 8 * n:16 * n] = np.ascontiguousarray(block.seq, "<i8").view(np.uint8)
    body[:, 16 * n:].reshape(p, n, 24)[:] = np.ascontiguousarray(block.corrected_nT, "<f8").view(np.uint8).reshape(
        n, p, 24).transpose(1, 0, 2)
    whole = rows.tobytes()
    size = rows.shape[1]
    return [whole[k * size:(k + 1) * size] for k in range(p)]


class _Shared:
    """An encoding of the last block asked for, kept while that block lives: the recording and the bus take the
    same block one after the other and send the same bytes (one encoding per block, not one per output)."""

    def __init__(self, encode: Callable[[Any], Any]) -> None:
        self._encode = encode
        self._last: tuple[weakref.ref, Any] | None = None

    def __call__(self, block: Any) -> Any:
        last = self._last
        if last is not None and last[0]() is block:
            return last[1]
        data = self._encode(block)
        self._last = (weakref.ref(block, self._forget), data)
        return data

    def _forget(self, ref: weakref.ref) -> None:
        last = self._last
        if last is not None and last[0] is ref:
            self._last = None


#: encode_raw, encode_corrected and encode_probes of a block, made once however many outputs send it
raw_payload = _Shared(encode_raw)
corrected_payload = _Shared(encode_corrected)
probe_payloads = _Shared(encode_probes)


def decode_corrected(data: bytes | memoryview) -> CorrectedBlock:
    """Inverse of encode_corrected; anything else is a DataError that says what is wrong."""
    if len(data) < _COR_HEAD.size:
        raise DataError(f"corrected block: {len(data)} bytes, shorter than the {_COR_HEAD.size}-byte header")
    check_magic(data, CORRECTED_KIND, CORRECTED_REVISION, "corrected block")
    _, bits, p, n, cal_id = _COR_HEAD.unpack_from(data, 0)
    if bits & ~(_BIT_DIFF | _BIT_TENSOR | _BIT_CENTER):
        raise DataError(f"corrected block: unknown presence bits {bits:#04x} (known: diff 1, tensor 2, centre 4)")
    shapes: list[tuple[int, ...] | None] = [(n,), (n,), (n, p, 3)]
    shapes += [s if bits & bit else None
               for bit, s in ((_BIT_DIFF, (n, max(p - 1, 0), 3)), (_BIT_TENSOR, (n, 3, 3)), (_BIT_CENTER, (n, 3)))]
    need = _COR_HEAD.size + sum(8 * math.prod(s) for s in shapes if s is not None)
    if len(data) != need:
        raise DataError(f"corrected block: {len(data)} bytes, the header (N={n}, P={p}, bits {bits}) needs {need}"
                        + (" (truncated?)" if len(data) < need else " (trailing bytes)"))
    off = _COR_HEAD.size
    out: list[np.ndarray | None] = []
    for k, shape in enumerate(shapes):
        if shape is None:
            out.append(None)
            continue
        a = np.frombuffer(data, "<i8" if k == 1 else "<f8", math.prod(shape), off).reshape(shape)
        off += a.nbytes
        out.append(a.astype(a.dtype.newbyteorder("=")))   # aligned, writable, native order
    return CorrectedBlock(t_s=out[0], seq=out[1], corrected_nT=out[2], diff_nT=out[3], tensor_nT_m=out[4],
                          center_nT=out[5], cal_id=int(cal_id))


# --- JSON streams ---------------------------------------------------------------------------------

def json_ready(obj: Any) -> Any:
    """Plain JSON types for the JSON streams (Zenoh and MCAP); NaN and infinities become null
    (strict JSON readers reject NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, Mapping):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    return str(obj)


def _refuse(obj: Any) -> Any:
    raise TypeError(type(obj).__name__)


def encode_json(record: Mapping[str, Any], *, ensure_ascii: bool = False) -> bytes:
    """One JSON stream message: a compact UTF-8 JSON object, NaN as null. A plain dict of text keys whose values
    are already finite JSON numbers, strings, lists and dicts (the service's own messages, many a second) is dumped
    as it is: the same bytes, without json_ready's walk over every value; anything else (a NaN, an array, a numpy
    number) goes through json_ready."""
    if type(record) is dict:
        try:
            return json.dumps(record, allow_nan=False, separators=(",", ":"), ensure_ascii=ensure_ascii,
                              default=_refuse).encode()
        except (TypeError, ValueError):
            pass
    return json.dumps(json_ready(record), allow_nan=False, separators=(",", ":"), ensure_ascii=ensure_ascii).encode()


def decode_json(data: bytes | str) -> dict[str, Any]:
    """Inverse of encode_json; not UTF-8 JSON or not an object -> DataError."""
    try:
        obj = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(f"JSON message: {e}") from None
    if not isinstance(obj, dict):
        raise DataError(f"JSON message: expected an object, got {type(obj).__name__}")
    return obj


def health_record(counters: Mapping[str, int], recording: Mapping[str, Any] | None = None,
                  faults: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The health message: the source's counters (they only grow), the recorder's status and the faults said
    (service/wiring/faults.py: active, totals, the newest events, at stop the summary)."""
    rec: dict[str, Any] = {"counters": {str(k): int(v) for k, v in counters.items()}}
    if recording is not None:
        rec["recording"] = dict(recording)
    if faults is not None:
        rec["faults"] = dict(faults)
    return rec


def calibration_record(kind: str, *, seq: int | None, t_s: float | None = None,
                       state: Mapping[str, Any] | None = None, **detail: Any) -> dict[str, Any]:
    """A calibration or event message: what happened (`kind`), from which sample on (`seq`), when
    (`t_s`, unit time), the calibration state after it, and event-specific details."""
    rec: dict[str, Any] = {"kind": kind, "seq": seq, "t_s": t_s, **detail}
    if state is not None:
        rec["state"] = state
    return rec


_NUM = {"type": ["number", "null"]}

#: JSON schema of the calibration channel (also the events channel: same shape, other kinds)
CALIBRATION_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema", "title": "fluxcal calibration event",
    "type": "object", "required": ["kind"],
    "properties": {"kind": {"type": "string", "description": "calibration, gate, command, initial, ..."},
                   "seq": {"type": ["integer", "null"], "description": "first sample it applies to"},
                   "t_s": {**_NUM, "description": "unit time, s"},
                   "state": {"type": "object", "description": "calibration state after the event"}}}
EVENT_SCHEMA: dict[str, Any] = {**CALIBRATION_SCHEMA, "title": "fluxcal event"}
HEALTH_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema", "title": "fluxcal health", "type": "object",
    "required": ["counters"],
    "properties": {"counters": {"type": "object", "additionalProperties": {"type": "integer"},
                                "description": "source counters (frames_accepted, crc_failures, ...), ever growing"},
                   "recording": {"type": "object", "description": "McapLogger.status()"},
                   "faults": {"type": "object", "description": "losses and faults said: active, totals, events "
                                                                "(n, kind, phase, count, text), at stop summary"}}}


__all__ = ["RAW_ENCODING", "RAW_LAYOUT", "CORRECTED_ENCODING", "CORRECTED_LAYOUT", "encode_raw", "decode_raw",
           "encode_corrected", "decode_corrected", "encode_probes", "raw_payload", "corrected_payload", "probe_payloads", "json_ready", "encode_json", "decode_json", "health_record",
           "calibration_record", "CALIBRATION_SCHEMA", "EVENT_SCHEMA", "HEALTH_SCHEMA"]
