"""MCAP logging of raw and corrected streams, calibration events and health.

Channels of one unit (topics):

    /fluxcal/<unit>/raw          fluxcal.raw.v1        binary SampleBlock (drivers/encoding.py)
    /fluxcal/<unit>/corrected    fluxcal.corrected.v1  binary CorrectedBlock (service/encoding.py)
    /fluxcal/<unit>/vectors      json (jsonschema)     per block: mean corrected x, y, z and |B| per probe,
                                                       for Foxglove's plot panel
    /fluxcal/<unit>/calibration  json (jsonschema)     calibration replaced, gate refusals
    /fluxcal/<unit>/events       json (jsonschema)     commands applied (with the seq they apply from), start
    /fluxcal/<unit>/health       json (jsonschema)     source counters, about once a second

log_time is the unit time of a block's first sample in ns; publish_time the wall clock. Files are
chunked and lz4-compressed (zstd on request), flushed about once a second (a SIGKILL loses at most that), rotated by
size or age into `<unit>-<YYYYmmddTHHMMSS>-<NNNN>.mcap`, each starting with a "fluxcal" metadata
record (unit, probes, configuration). Write errors (a full disk) are counted and reported, never
raised: logging resumes in a new file once writing works again. One thread feeds a logger.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from mcap.writer import CompressionType, Writer

from drivers.block import SampleBlock
from drivers.encoding import encode_raw
from drivers.mcap_source import RAW_ENCODING

from .encoding import encode_corrected, json_ready
from .outputs import CorrectedBlock

CORRECTED_ENCODING = "fluxcal.corrected.v1"
_LAYOUT_RAW = (b"fluxcal raw block v1: see drivers/encoding.py (magic FXr0; u16 P, u16 E, u32 N; f64 t_s[N], "
               b"i64 seq[N], f64 field_nT[N,P,3], f64 temp_C[N,P], u8 flags[N]; extras)")
_LAYOUT_COR = (b"fluxcal corrected block v1: see service/encoding.py (magic FXc0; u8 bits, u16 P, u32 N, "
               b"i64 cal_id; f64 t_s[N], i64 seq[N], f64 corrected_nT[N,P,3]; optional diff, tensor, centre)")
_OBJECT_SCHEMA = json.dumps({"type": "object"}).encode()
_RETRY_S = 5.0


class McapLogger:
    """Writes one unit's streams into rotating MCAP files in `directory`."""

    def __init__(self, directory: str | Path, *, unit: str, rotate_mb: float = 256.0, rotate_s: float = 3600.0,
                 chunk_size: int = 1 << 20, flush_interval_s: float = 1.0, metadata: dict[str, str] | None = None,
                 filename: str | None = None, compression: str = "lz4", opener=open) -> None:
        self.dir = Path(directory)
        self.unit = unit
        self.rotate_bytes = rotate_mb * 1e6
        self.rotate_s = rotate_s
        self.chunk_size = chunk_size
        self.flush_interval_s = flush_interval_s
        self.metadata = {k: str(v) for k, v in (metadata or {}).items()}
        self.filename = filename
        self.compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                            "none": CompressionType.NONE}[compression]
        self._opener = opener
        self.files: list[str] = []
        self.messages = 0
        self.errors = 0
        self.dropped = 0
        self.last_error = ""
        self._writer: Writer | None = None
        self._fh = None
        self._channels: dict[str, int] = {}
        self._opened_at = 0.0
        self._last_flush = 0.0
        self._retry_at = 0.0
        self._last_log_ns = 0
        self._closed = False
        self._seq = 0
        self._open()

    # --- files --------------------------------------------------------------------------

    def _next_path(self) -> Path:
        if self.filename:
            return self.dir / self.filename
        self._seq += 1
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        return self.dir / f"{self.unit}-{stamp}-{self._seq:04d}.mcap"

    def _open(self) -> bool:
        path = None
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            path = self._next_path()
            self._fh = self._opener(path, "wb")
            w = Writer(self._fh, chunk_size=self.chunk_size, compression=self.compression)
            w.start(profile="", library="fluxcal")
            t = f"/fluxcal/{self.unit}"
            raw_schema = w.register_schema("fluxcal.raw.v1", "", _LAYOUT_RAW)
            cor_schema = w.register_schema("fluxcal.corrected.v1", "", _LAYOUT_COR)
            js = w.register_schema("fluxcal.json", "jsonschema", _OBJECT_SCHEMA)
            self._channels = {
                "raw": w.register_channel(f"{t}/raw", RAW_ENCODING, raw_schema),
                "corrected": w.register_channel(f"{t}/corrected", CORRECTED_ENCODING, cor_schema),
                "vectors": w.register_channel(f"{t}/vectors", "json", js),
                "calibration": w.register_channel(f"{t}/calibration", "json", js),
                "events": w.register_channel(f"{t}/events", "json", js),
                "health": w.register_channel(f"{t}/health", "json", js),
            }
            w.add_metadata("fluxcal", {"unit": self.unit, **self.metadata})
            self._writer = w
            self.files.append(str(path))
            self._opened_at = time.monotonic()
            self._last_flush = self._opened_at
            return True
        except OSError as e:
            self._fail(e)
            if path is not None:
                try:
                    path.unlink()             # a file that never got its header is no recording
                except OSError:
                    pass
            return False

    def _fail(self, e: OSError) -> None:
        self.errors += 1
        self.last_error = f"{type(e).__name__}: {e}"
        self._writer = None
        try:
            if self._fh is not None:
                self._fh.close()
        except OSError:
            pass
        self._fh = None
        self._retry_at = time.monotonic() + _RETRY_S

    def _rotate_due(self) -> bool:
        if self.filename:
            return False
        try:
            size = self._fh.tell()
        except (OSError, AttributeError):
            size = 0
        return size >= self.rotate_bytes or time.monotonic() - self._opened_at >= self.rotate_s

    def _finish(self) -> None:
        if self._writer is None:
            return
        try:
            self._writer.finish()
            self._fh.close()
        except OSError as e:
            self._fail(e)
        self._writer = None
        self._fh = None

    # --- writing --------------------------------------------------------------------------

    def _write(self, channel: str, data: bytes, log_time_ns: int) -> None:
        if self._closed:
            return
        if self._writer is None:
            if time.monotonic() < self._retry_at or not self._open():
                self.dropped += 1
                return
        log_time_ns = max(int(log_time_ns), 0)
        self._last_log_ns = max(self._last_log_ns, log_time_ns)
        try:
            self._writer.add_message(self._channels[channel], log_time=log_time_ns, data=data,
                                     publish_time=time.time_ns())
            self.messages += 1
            now = time.monotonic()
            if now - self._last_flush >= self.flush_interval_s:
                self._last_flush = now
                self._writer.flush()           # ends the chunk: a killed process loses at most this interval
            if self._rotate_due():
                self._finish()
                self._open()
        except OSError as e:
            self.dropped += 1
            self._fail(e)

    @staticmethod
    def _t_ns(t_s: np.ndarray) -> int:
        return int(t_s[0] * 1e9) if t_s.size and np.isfinite(t_s[0]) else 0

    def write_raw(self, block: SampleBlock) -> None:
        self._write("raw", encode_raw(block), self._t_ns(block.t_s))

    def write_corrected(self, block: CorrectedBlock) -> None:
        t = self._t_ns(block.t_s)
        self._write("corrected", encode_corrected(block), t)
        mean = np.nanmean(block.corrected_nT, axis=0) if block.n_samples else np.full((block.n_probes, 3), np.nan)
        vec = {f"s{k + 1}": {"x": v[0], "y": v[1], "z": v[2], "total": float(np.linalg.norm(v))}
               for k, v in enumerate(mean)}
        self._write("vectors", json.dumps(json_ready({"seq": int(block.seq[0]) if block.n_samples else None,
                                                       "cal_id": block.cal_id, **vec})).encode(), t)

    def _write_json(self, channel: str, record: dict[str, Any]) -> None:
        t = record.get("t_s")
        t_ns = int(t * 1e9) if isinstance(t, (int, float)) and math.isfinite(t) else self._last_log_ns
        self._write(channel, json.dumps(json_ready(record)).encode(), t_ns)

    def write_calibration(self, record: dict[str, Any]) -> None:
        self._write_json("calibration", record)

    def write_event(self, record: dict[str, Any]) -> None:
        self._write_json("events", record)

    def write_health(self, counters: dict[str, Any]) -> None:
        self._write_json("health", {"counters": counters, "recording": self.status()})

    def status(self) -> dict[str, Any]:
        return {"files": len(self.files), "current": self.files[-1] if self._writer is not None and self.files else None,
                "messages": self.messages, "errors": self.errors, "dropped": self.dropped,
                "last_error": self.last_error}

    def close(self) -> None:
        if self._closed:
            return
        self._finish()
        self._closed = True


def write_recording(path: str | Path, blocks: Iterable[SampleBlock], *, unit: str, probe_names: list[str],
                    truth: dict | None = None) -> None:
    """One MCAP file of raw blocks (for `simulate` and `decode`), with probe names and the truth."""
    p = Path(path)
    meta = {"probe_names": json.dumps(probe_names)}
    if truth is not None:
        meta["truth"] = json.dumps(truth)
    tmp = p.with_name(p.name + ".partial")
    log = McapLogger(p.parent, unit=unit, filename=tmp.name, metadata=meta, flush_interval_s=1e9)
    try:
        for b in blocks:
            log.write_raw(b)
    finally:
        log.close()
    if log.errors:
        tmp.unlink(missing_ok=True)
        raise OSError(f"{p}: could not write the recording: {log.last_error}")
    tmp.replace(p)
