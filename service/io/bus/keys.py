"""The key space under ``fluxcal/<unit>/``, the encodings of its streams, and the commands a unit obeys
(docs/zenoh.md has the full table).
"""

from __future__ import annotations

import json
import math
import re
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
import zenoh

from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.io.encoding import decode_corrected, decode_raw, encode_json


@dataclass(frozen=True)
class Series:
    """A per-sample array stream (`diff`, `tensor`): values[i] belongs to sample seq[i] at t_s[i]."""

    t_s: np.ndarray         # (N,) float64, unit time, s
    seq: np.ndarray         # (N,) int64, unwrapped sample counter
    values: np.ndarray      # (N, ...) float64: diff (N, P-1, 3) nT, tensor (N, 3, 3) nT/m
    cal_id: int             # calibration that produced it


_SERIES_HEAD = struct.Struct("<4sBIq")        # magic b"FXS1", ndim of one sample, n_samples, cal_id


def encode_series(t_s: np.ndarray, seq: np.ndarray, values: np.ndarray, cal_id: int) -> bytes:
    """`diff`/`tensor` payload: header, u32 dims of one sample, then t_s f8[N], seq i8[N], values f8[N, ...].

    >>> s = decode_series(encode_series(np.array([0.5]), np.array([7]), np.ones((1, 3, 3)), 2))
    >>> (s.values.shape, int(s.seq[0]), s.cal_id)
    ((1, 3, 3), 7, 2)
    """
    values = np.ascontiguousarray(values, "<f8")
    n = values.shape[0]
    if np.shape(t_s) != (n,) or np.shape(seq) != (n,):
        raise ValueError(f"series: expected t_s and seq of shape ({n},), got {np.shape(t_s)} and {np.shape(seq)}")
    tail = values.shape[1:]
    return b"".join([_SERIES_HEAD.pack(b"FXS1", len(tail), n, int(cal_id)),
                     struct.pack(f"<{len(tail)}I", *tail),
                     np.ascontiguousarray(t_s, "<f8").tobytes(), np.ascontiguousarray(seq, "<i8").tobytes(),
                     values.tobytes()])


def decode_series(data: bytes) -> Series:
    """Inverse of `encode_series`; a malformed payload is a DataError."""
    try:
        magic, ndim, n, cal_id = _SERIES_HEAD.unpack_from(data, 0)
        if magic != b"FXS1":
            raise ValueError(f"not a series (magic {magic!r})")
        off = _SERIES_HEAD.size
        tail = struct.unpack_from(f"<{ndim}I", data, off)
        off += 4 * ndim
        t_s = np.frombuffer(data, "<f8", n, off).astype(float)
        off += 8 * n
        seq = np.frombuffer(data, "<i8", n, off).astype(np.int64)
        off += 8 * n
        count = n * math.prod(tail)
        values = np.frombuffer(data, "<f8", count, off).astype(float).reshape((n, *tail))
        if off + 8 * count != len(data):
            raise ValueError(f"{len(data) - off - 8 * count} trailing bytes")
    except (struct.error, ValueError) as e:
        raise DataError(f"series: {e}") from None
    return Series(t_s=t_s, seq=seq, values=values, cal_id=int(cal_id))


def _json_bytes(obj: Any) -> bytes:
    return encode_json(obj, ensure_ascii=True)


_UNIT_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


_KEY_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


JSON = zenoh.Encoding.APPLICATION_JSON


RAW_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("fluxcal.raw.v1")


CORRECTED_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("fluxcal.corrected.v1")


SERIES_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("fluxcal.series.v1")


@dataclass(frozen=True)
class StreamSpec:
    """How one stream is encoded and what Zenoh may do with it under congestion."""

    encoding: zenoh.Encoding
    lossless: bool            # CongestionControl.BLOCK (True) or DROP
    priority: zenoh.Priority
    decode: Callable[[bytes], Any]


def _decode_json(data: bytes) -> Any:
    try:
        return json.loads(data)
    except (ValueError, UnicodeDecodeError) as e:
        raise DataError(f"JSON payload: {e}") from None


#: stream name -> spec. BLOCK for data that must not be lost, DROP for status that the next message replaces.
#: Separate priorities also keep the DROP streams from queueing behind a blocked BLOCK stream.
STREAMS: dict[str, StreamSpec] = {
    "raw": StreamSpec(RAW_ENCODING, True, zenoh.Priority.DATA, decode_raw),
    "corrected": StreamSpec(CORRECTED_ENCODING, True, zenoh.Priority.DATA, decode_corrected),
    "diff": StreamSpec(SERIES_ENCODING, True, zenoh.Priority.DATA, decode_series),
    "tensor": StreamSpec(SERIES_ENCODING, True, zenoh.Priority.DATA, decode_series),
    "calibration": StreamSpec(JSON, True, zenoh.Priority.INTERACTIVE_LOW, _decode_json),
    "health": StreamSpec(JSON, False, zenoh.Priority.DATA_LOW, _decode_json),
    "error": StreamSpec(JSON, False, zenoh.Priority.DATA_LOW, _decode_json),
}


#: commands the service accepts under fluxcal/<unit>/cmd/<name>, and whether they need a payload
COMMANDS: dict[str, str | None] = {
    "freeze": None,                      # stop updating the online estimate; keep the calibration in use
    "unfreeze": None,
    "reset": None,                       # restart the online estimate from nothing
    "apply": "a calibration's JSON content (never a path: the service reads no file a command names)",
    "add-effect": "effect name, e.g. temperature",
}
#: largest command payload the service takes (a calibration JSON is a few kB; the dashboard's body limit too)
MAX_COMMAND_PAYLOAD_BYTES = 1 << 20


class Keys:
    """The key expressions of one unit.

    >>> Keys("grad1").stream("corrected")
    'fluxcal/grad1/corrected'
    >>> Keys("grad1").cmd("freeze")
    'fluxcal/grad1/cmd/freeze'
    """

    def __init__(self, unit: str) -> None:
        if not _UNIT_NAME.match(unit or ""):
            raise ConfigError(f"unit name {unit!r} is not allowed (allowed: 1-64 letters, digits, '_' or '-')")
        self.unit = unit
        self.root = f"fluxcal/{unit}"
        self.alive = f"{self.root}/alive"
        self.state = f"{self.root}/state"

    def stream(self, name: str) -> str:
        return f"{self.root}/{name}"

    def probe(self, probe_name: str) -> str:
        return f"{self.root}/corrected/{probe_name}"

    def cmd(self, name: str) -> str:
        return f"{self.root}/cmd/{name}"


class Command:
    """A command from the bus, applied by the service's own thread; `reply` answers the client once.

    `payload` is the query's payload as text ("" when none). `expires_at` (time.monotonic()) is when the
    bus withdraws it unapplied if the service has not taken it by then (the client is told so).
    """

    def __init__(self, id: int, name: str, payload: str, key: str, query: zenoh.Query | None,
                 expires_at: float = math.inf) -> None:
        self.id = id
        self.name = name
        self.payload = payload
        self.key = key
        self.received_unix_s = time.time()
        self.expires_at = expires_at
        self._query = query
        self._lock = threading.Lock()

    @property
    def answered(self) -> bool:
        return self._query is None

    def reply(self, result: Mapping[str, Any]) -> bool:
        """Send {"id", "command", **result} as JSON on the command's own key; False if already answered or the
        client has gone (its timeout passed)."""
        with self._lock:
            q, self._query = self._query, None
        if q is None:
            return False
        try:
            q.reply(self.key, _json_bytes({"id": self.id, "command": self.name, **result}), encoding=JSON)
            return True
        except zenoh.ZError:
            return False
        finally:
            try:
                q.drop()                  # sends the final reply marker: the client stops waiting now
            except zenoh.ZError:
                pass

    def __repr__(self) -> str:
        return f"Command(id={self.id}, name={self.name!r}, payload={self.payload[:40]!r})"
