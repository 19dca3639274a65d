"""MCAP logging of one unit's raw and corrected streams, calibration events, health and plot-ready vectors.

Channels (topic, MCAP message encoding, schema):

    /fluxcal/<unit>/raw          fluxcal.raw.v1        fluxcal.layout: the layout table (drivers/encoding.py)
    /fluxcal/<unit>/corrected    fluxcal.corrected.v1  fluxcal.layout: the layout table (service/io/encoding.py)
    /fluxcal/<unit>/vectors      json                  jsonschema: per probe mean corrected x, y, z and mean |B|
                                                       over 0.1 s of unit time (10 Hz), and the array centre,
                                                       for Foxglove's plot panel (`.s1.total`, `.center.x`)
    /fluxcal/<unit>/diff         json                  jsonschema: 10 Hz means of the gradiometer differences,
                                                       per probe k (minus probe 1): x, y, z, magnitude, nT
    /fluxcal/<unit>/tensor       json                  jsonschema: 10 Hz means of the gradient tensor, dBx_dx ...
                                                       dBz_dz and trace, nT/m
    /fluxcal/<unit>/error        json                  jsonschema: 10 Hz RMS of the error metric per channel, nT
    /fluxcal/<unit>/params       json                  jsonschema: on every calibration record: parameters with
                                                       standard errors, the gate's coverage, condition, residual
    /fluxcal/<unit>/calibration  json                  jsonschema: calibration replaced, quality-gate refusals
    /fluxcal/<unit>/events       json                  jsonschema: commands applied (with the seq they apply from)
    /fluxcal/<unit>/health       json                  jsonschema: source counters and this logger's status

The JSON channels Foxglove plots (vectors, diff, tensor, error, params) are built by
fluxcal.service.io.foxglove_schemas, which the live bridge (`fluxcal foxglove`) uses too; the binary channels stay
the replay's exact record.

Each file starts with a "fluxcal" metadata record (unit, stream encodings, file_index and what the
caller passes: n_probes, lsb_nT, probe_names, positions_m, config), a "fluxcal.arithmetic" record naming
this machine's arithmetic (numpy and scipy versions, the CPU features numpy dispatches to, each one's BLAS
and the kernels it chose: arithmetic.py; replay says where its own differs) and, once the first sample time
is known, a "fluxcal.time" record stating the time base:

    log_time     = epoch_ns + round(t_s * 1e9), t_s the unit time of the message's first sample;
                   epoch_ns = wall clock at the first timed message minus its t_s (or `epoch_ns=` given,
                   0 for plain unit time). Unit-clock spacing, wall-clock placement: Foxglove shows a
                   real date, and the exact t_s is in every binary payload anyway.
    publish_time = wall clock when written, ns since 1970.
    sequence     = per-channel message counter of this logger (a gap means a message was dropped).

Files are chunked and compressed (lz4 by default, zstd or none on request; the mcap package
requires both lz4 and zstandard, so they are installed with it). A chunk is written when it holds
`chunk_size` bytes or `flush_interval_s` (1 s) has passed since the last one, whichever is first, so
a killed process loses at most the last second: the next write or `poll()` after the interval
flushes. Files rotate by size (`rotate_mb`) or age (`rotate_s`) into

    <dir>/<unit>-<YYYYmmddTHHMMSS, UTC>-<NNNN>.mcap      (NNNN = 0001, 0002, ... per logger)

the UTC time the run's first file was opened, in every file of the run, so that its files sort by name in their
order whatever the host's clock does; given a file path instead of a directory, the logger writes
that one file (no rotation; after a write error it resumes in <stem>_0002.mcap, ...).

Write errors (a full disk: OSError ENOSPC; a pulled USB stick) are never raised: each is counted,
the last one is kept in `status()`, the broken file is cut back to its last complete chunk (it
reads like a killed writer's file), and the messages of the unfinished chunk are kept and written
first into the next file, which is tried every `retry_s` (5 s). Messages that arrive while no file
can be opened are dropped and counted. Nothing is lost silently.

Not thread-safe (neither is mcap's Writer): one thread feeds a logger.
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError
from fluxcal.drivers.outputs import open_output
from fluxcal.service.io.encoding import corrected_payload, encode_json, health_record, raw_payload
from fluxcal.service.io.foxglove_schemas import Products
from fluxcal.service.numerics.outputs import CorrectedBlock

from .files import COMPRESSIONS, FileDeleted, McapFiles

STREAMS = ("raw", "corrected", "vectors", "diff", "tensor", "error", "params", "calibration", "events", "health")
_UNIT_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")
_RETRY_S = 5.0
_monotonic = time.monotonic           # tests replace these two to move time
_wall_ns = time.time_ns


def _default_opener(path: Path, mode: str):
    return open_output(path, mode)          # never through a link planted at the path (fluxcal.drivers.outputs)


class ChunkedLog:
    """Messages of named streams into a series of chunked, compressed MCAP files (files.McapFiles): a
    chunk ends when full or `flush_interval_s` old, files rotate by size and age, a failed file is cut
    back to its last chunk and the unfinished one rewritten into the next file after `retry_s`, with at
    most `backlog_bytes` kept meanwhile. Everything is counted. McapLogger is fluxcal's streams on it."""

    def __init__(self, files: McapFiles, *, single_file: bool, rotate_bytes: float, rotate_s: float, chunk_size: int,
                 flush_interval_s: float, epoch_ns: int | None, retry_s: float | None, backlog_bytes: float) -> None:
        self._files, self.single_file = files, single_file
        self.rotate_bytes, self.rotate_s = rotate_bytes, rotate_s           # a file's size and age, at most
        self.chunk_size, self.flush_interval_s = chunk_size, flush_interval_s   # a chunk's, likewise
        self.epoch_ns, self.retry_s, self.backlog_bytes = epoch_ns, retry_s, backlog_bytes
        self.messages = 0                  # messages handed to the logger
        self.messages_written = 0          # messages in chunks that reached the file
        self.dropped = 0                   # messages that could not be written
        self.errors = 0                    # write errors (each failed attempt)
        self.last_error = ""
        self.last_error_wall_s: float | None = None

        self._sequence = dict.fromkeys(STREAMS, 0)
        self._pending: list[tuple[str, bytes, int, int, int]] = []   # the unflushed chunk: rewritten after a failure
        self._pending_bytes = 0
        self._opened_at = 0.0
        self._last_flush = 0.0
        self._retry_at = 0.0
        self._last_log_ns: int | None = None
        self._closed = False
        self._open()

    # --- files (fluxcal.service.io.recordings.files) --------------------------------------------------------

    @property
    def files(self) -> list[str]:
        """Every file this logger opened, in order."""
        return self._files.files

    @property
    def bytes_written(self) -> int:
        """Bytes that reached files (all files)."""
        return self._files.bytes_written

    def _open(self) -> bool:
        """Open the next file and write its header; False (and counted) if that failed."""
        try:
            self._files.open(_wall_ns(), self._pending,
                             self.epoch_ns if self.epoch_ns is not None and self._last_log_ns is not None else None)
        except OSError as e:
            self._error(e)
            return False
        self._opened_at = _monotonic()
        self._last_flush = self._opened_at
        return True

    def _error(self, e: OSError) -> None:
        self.errors += 1
        self.last_error = f"{type(e).__name__}: {e}"
        self.last_error_wall_s = _wall_ns() / 1e9
        deleted = isinstance(e, FileDeleted)            # what the deleted file held is lost; no disk fault to wait
        self.dropped += e.lost if deleted else 0        # out: the next message opens a new file
        self._retry_at = _monotonic() + (0.0 if deleted else _RETRY_S if self.retry_s is None else self.retry_s)

    def _fail(self, e: OSError) -> None:
        """A write failed: cut the file back to its last complete chunk and close it; keep the pending
        messages for the next file."""
        self._error(e)
        self.last_error += self._files.fail()
        # bounded memory while the disk stays full: the oldest unwritten messages go first
        while self._pending and self._pending_bytes > self.backlog_bytes:
            _, data, *_ = self._pending.pop(0)
            self._pending_bytes -= len(data) + 40
            self.dropped += 1

    def _chunk_done(self) -> None:
        """The pending messages are in the file now."""
        self._files.chunk_done(len(self._pending))
        self.messages_written += len(self._pending)
        self._pending.clear()
        self._pending_bytes = 0
        self._last_flush = _monotonic()

    def _flush(self) -> None:
        self._files.flush()
        self._chunk_done()

    def _finish(self) -> None:
        """Footer and index; then the file is complete."""
        if self._files.writer is None or self._files.fh is None:
            return
        try:
            self._files.finish()
            self._chunk_done()
            self._files.close_finished()
        except OSError as e:
            self._fail(e)

    # --- writing ----------------------------------------------------------------------------------

    def _log_time(self, t_s: float | None) -> int:
        """log_time of a message whose first sample is at unit time t_s (the last one's when t_s is unknown), and
        that message's time becomes the last one's when t_s is known."""
        if t_s is None or not math.isfinite(t_s):
            if self._last_log_ns is not None:
                return self._last_log_ns
            return _wall_ns()
        if self.epoch_ns is None:
            self.epoch_ns = _wall_ns() - round(t_s * 1e9)
        log_ns = self._last_log_ns = max(self.epoch_ns + round(t_s * 1e9), 0)
        return log_ns

    def _write(self, stream: str, data: bytes, t_s: float | None) -> None:
        self.messages += 1
        if self._closed:
            self.dropped += 1
            self.last_error = "write after close"
            return
        log_ns = self._log_time(t_s)
        now = _monotonic()
        self._rotate_if_due(now)
        files = self._files
        if files.writer is None:
            if now < self._retry_at or not self._open():
                self.dropped += 1
                return
        assert files.writer is not None
        seq = self._sequence[stream] = (self._sequence[stream] + 1) & 0xFFFFFFFF
        pub_ns = _wall_ns()
        try:
            if not files.time_written and self.epoch_ns is not None:
                files.write_time_record(self.epoch_ns)
            files.writer.add_message(files.channels[stream], log_time=log_ns, data=data, publish_time=pub_ns,
                                     sequence=seq)
            self._pending.append((stream, data, log_ns, pub_ns, seq))
            self._pending_bytes += len(data) + 40          # + the message record's header, about
            self._flush_if_due(now)
        except OSError as e:
            self._fail(e)

    def _flush_if_due(self, now: float) -> None:
        if self._pending and (self._pending_bytes >= self.chunk_size or now - self._last_flush >= self.flush_interval_s):
            self._flush()

    def _rotate_if_due(self, now: float) -> None:
        """Before a message: a file holds what arrived in [opened, opened + rotate_s) and about rotate_mb."""
        fh = self._files.fh
        if self._files.writer is None or fh is None or self.single_file:
            return
        if fh.pos + self._pending_bytes >= self.rotate_bytes or now - self._opened_at >= self.rotate_s:
            self._finish()
            if self._files.writer is None and not self._pending:     # finished cleanly (else: retried later)
                self._open()

    def poll(self) -> None:
        """End the chunk if it is full or `flush_interval_s` old, rotate if due, retry a failed file.
        Writing does this; a caller whose input stalls calls it about once a second so the last data
        reaches the disk."""
        if self._closed:
            return
        if self._files.writer is None:
            if self._pending and _monotonic() >= self._retry_at:
                self._open()
            return
        now = _monotonic()
        try:
            self._flush_if_due(now)
        except OSError as e:
            self._fail(e)
        self._rotate_if_due(now)

    def flush(self) -> None:
        """Write the unfinished chunk now (e.g. before a planned stop)."""
        if self._files.writer is not None and self._pending:
            try:
                self._flush()
            except OSError as e:
                self._fail(e)

    def status(self) -> dict[str, Any]:
        """What has been written and what went wrong, for the health stream and the state query."""
        return {"files": len(self.files), "current": self.files[-1] if self._files.writer is not None else None,
                "messages": self.messages, "messages_written": self.messages_written,
                "pending": len(self._pending), "bytes_written": self.bytes_written, "dropped": self.dropped,
                "errors": self.errors, "last_error": self.last_error, "last_error_wall_s": self.last_error_wall_s,
                "compression": self._files.compression}

    def _close_files(self) -> None:
        """The last chunk and the footer; what cannot be written then is counted as dropped."""
        self._finish()
        if self._pending:                     # the last file failed: one more try for its last chunk
            if self._files.writer is None and self._open():
                self._finish()
            if self._pending:
                self.dropped += len(self._pending)
                self._pending.clear()
        self._closed = True


class McapLogger(ChunkedLog):
    """Writes one unit's streams into chunked, compressed, rotating MCAP files (see the module docstring).

    path: a directory (rotating files) or a file path ending in .mcap (that one file).
    unit: the unit name in the topics and file names (letters, digits, _ and -).
    rotate_mb, rotate_s: start a new file after this many MB or seconds (directory mode).
    chunk_size: bytes of messages per chunk before compression; flush_interval_s: at most this
    long between chunks. compression: "lz4", "zstd" or "none". metadata: strings for the "fluxcal"
    metadata record. probe_names: names in the vectors and diff channels (default from metadata["probe_names"],
    else s1, s2, ...). vectors_period_s: averaging interval of the vectors, diff, tensor and error channels
    (0 disables them).
    epoch_ns: log_time epoch (None: the wall clock at the first sample). fsync: also fsync every chunk
    (survives power loss, costs a disk round trip per chunk). retry_s: after a write error, try a new
    file this much later (default 5 s). backlog_mb: at most this much of unwritten messages is kept
    while files fail (the oldest are dropped, and counted, beyond it). opener(path, mode) -> binary file:
    for fault injection in tests. filename: directory + this fixed file name, as if path were the file.
    arithmetic: the "fluxcal.arithmetic" record (None: this machine's, arithmetic.machine_arithmetic(); {}: none,
    for a copy of corrected output computed where it is not known).
    """

    def __init__(self, path: str | Path, *, unit: str, rotate_mb: float = 256.0, rotate_s: float = 3600.0,
                 chunk_size: int = 1 << 20, compression: str = "lz4", flush_interval_s: float = 1.0,
                 metadata: dict[str, Any] | None = None, probe_names: Sequence[str] | None = None,
                 vectors_period_s: float = 0.1, epoch_ns: int | None = None, fsync: bool = False,
                 retry_s: float | None = None, backlog_mb: float = 16.0, filename: str | None = None,
                 opener: Callable[[Path, str], Any] | None = None, arithmetic: dict[str, str] | None = None) -> None:
        if not isinstance(unit, str) or not _UNIT_NAME.fullmatch(unit):
            raise ConfigError(f"mcap logger: unit {unit!r} is not allowed (allowed: 1-64 letters, digits, '_' or '-')")
        if compression not in COMPRESSIONS:
            raise ConfigError(f"mcap.compression: {compression!r} is not allowed (allowed: {', '.join(COMPRESSIONS)})")
        for key, value in (("rotate_mb", rotate_mb), ("rotate_s", rotate_s), ("chunk_size", chunk_size)):
            if not (isinstance(value, (int, float)) and value > 0):
                raise ConfigError(f"mcap.{key}: {value!r} is not allowed (allowed: a number > 0)")
        if not (isinstance(flush_interval_s, (int, float)) and flush_interval_s >= 0):
            raise ConfigError(f"mcap.flush_interval_s: {flush_interval_s!r} is not allowed "
                              f"(allowed: a number >= 0; 0 ends a chunk after every message)")
        p = Path(path)
        if filename is not None:
            p = p / filename
        self.single_file = filename is not None or (p.suffix == ".mcap" and not p.is_dir())
        self.dir = p.parent if self.single_file else p
        self.path = p if self.single_file else None
        self.unit = unit
        self.compression = compression
        self.metadata = {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in (metadata or {}).items()}
        if probe_names is None and "probe_names" in self.metadata:
            try:
                probe_names = [str(n) for n in json.loads(self.metadata["probe_names"])]
            except (json.JSONDecodeError, TypeError):
                probe_names = None
        self.probe_names = list(probe_names or [])
        self.fsync = fsync
        self._products = Products(self.probe_names, vectors_period_s) if vectors_period_s > 0 else None
        files = McapFiles(self.dir, self.path, unit=unit, compression=compression, probe_names=self.probe_names,
                          metadata=self.metadata, fsync=fsync, opener=opener or _default_opener,
                          arithmetic=arithmetic)
        super().__init__(files, single_file=self.single_file, rotate_bytes=rotate_mb * 1e6, rotate_s=rotate_s,
                         chunk_size=int(chunk_size), flush_interval_s=flush_interval_s, epoch_ns=epoch_ns,
                         retry_s=retry_s, backlog_bytes=max(backlog_mb * 1e6, 2.0 * int(chunk_size)))

    def write_raw(self, block: SampleBlock) -> None:
        self._write("raw", raw_payload(block), float(block.t_s[0]) if block.n_samples else None)

    def write_corrected(self, block: CorrectedBlock) -> None:
        self._write("corrected", corrected_payload(block), float(block.t_s[0]) if block.n_samples else None)
        if self._products is not None:
            self._write_products(self._products.corrected(block))

    def write_error(self, rms_nT: dict[str, float], *, seq: int | None, t_s: float, n: int) -> None:
        """The error metric of one block of n samples (the bus's `error` stream); recorded as 10 Hz RMS."""
        if self._products is not None:
            self._write_products(self._products.error(rms_nT, t_s=t_s, seq=seq, n=n))

    def _write_products(self, messages: list[tuple[str, dict[str, Any]]]) -> None:
        for stream, msg in messages:
            t = msg.get("t_s")
            self._write(stream, encode_json(msg), float(t) if isinstance(t, (int, float)) else None)

    def _write_json(self, stream: str, record: dict[str, Any]) -> None:
        t = record.get("t_s")
        self._write(stream, encode_json(record), float(t) if isinstance(t, (int, float)) else None)

    def write_calibration(self, record: dict[str, Any]) -> None:
        """A calibration event: {"kind": ..., "seq": ..., "t_s": ..., "state": {...}, ...}; with a state, also its
        parameters, standard errors and gate figures as plain numbers (params)."""
        self._write_json("calibration", record)
        if self._products is not None and isinstance(record.get("state"), dict):
            self._write_products(Products.calibration(record))

    def write_event(self, record: dict[str, Any]) -> None:
        """A command or other event, with the seq it applies from: {"kind": "command", "seq": ..., ...}."""
        self._write_json("events", record)

    def write_health(self, counters: dict[str, Any], faults: dict[str, Any] | None = None) -> None:
        """The source's counters, this logger's status and the faults said; call it about once a second."""
        self._write("health", encode_json(health_record(counters, self.status(), faults)), None)

    def close(self) -> None:
        """Write the last 10 Hz intervals, the last chunk and the footer. Safe to call twice."""
        if self._closed:
            return
        if self._products is not None:
            self._write_products(self._products.flush())
        self._close_files()

    def __enter__(self) -> "McapLogger":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: write_recording's chunks and messages: a file cut short (a full disk, a copy stopped half way, `head -c`)
#: loses its unfinished chunk only, so chunks are small; a block is split into messages of about
#: RECORDING_MESSAGE_BYTES so that one large block (simulate writes 100,000 samples at a time) is not one chunk
RECORDING_CHUNK_BYTES = 256 << 10
RECORDING_MESSAGE_BYTES = 64 << 10


def _message_rows(block: SampleBlock) -> int:
    """Rows of `block` per message of about RECORDING_MESSAGE_BYTES (its arrays' bytes per sample)."""
    n = block.n_samples
    size = sum(a.nbytes for a in (block.t_s, block.seq, block.field_nT, block.temp_C, block.flags,
                                  *block.extras.values()))
    return max(1, int(RECORDING_MESSAGE_BYTES * n // max(size, 1)))


def write_recording(path: str | Path, blocks: Iterable[SampleBlock], *, unit: str, probe_names: list[str],
                    truth: dict | None = None, metadata: dict[str, Any] | None = None) -> None:
    """One MCAP file of raw blocks (for `simulate` and `decode`), with probe names and the truth, in chunks of
    about RECORDING_CHUNK_BYTES (a truncated copy keeps what came before its cut).
    Written to `<path>.partial` and renamed at the end: a failed write leaves no half file; OSError."""
    p = Path(path)
    meta: dict[str, Any] = {"probe_names": json.dumps(probe_names), **(metadata or {})}
    if truth is not None:
        meta["truth"] = json.dumps(truth)
    tmp = p.with_name(p.name + ".partial")
    log = McapLogger(p.parent, filename=tmp.name, unit=unit, metadata=meta, flush_interval_s=1e9,
                     chunk_size=RECORDING_CHUNK_BYTES)
    try:
        for b in blocks:
            step = _message_rows(b)
            for lo in range(0, max(b.n_samples, 1), step):
                log.write_raw(b if step >= b.n_samples else b.slice(lo, lo + step))
    finally:
        log.close()
    if log.errors:
        for f in log.files:
            Path(f).unlink(missing_ok=True)
        raise OSError(f"{p}: could not write the recording: {log.last_error}")
    tmp.replace(p)
