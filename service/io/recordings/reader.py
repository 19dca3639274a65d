"""Whole recordings for `fit`, `diagnose` and `replay`: read one into memory, rebuild a killed file.

    read_recording(path, unit=None) -> Recording   raw and corrected blocks, events, calibration
                                                   events, health, the "fluxcal" metadata, warnings, holes
    repair_recording(src, dst) -> ReadReport       a killed writer's or a damaged file copied record for
                                                   record into an indexed, finished file (repair.py)
    FluxcalDecoderFactory                          for mcap's own readers: make_reader(f,
                                                   decoder_factories=[FluxcalDecoderFactory()])

Reading goes through fluxcal.drivers.mcap_source (streaming; a cut tail read to its last chunk, damage read past and
said, what it lost a hole with its samples' span); files that are no recording raise RecordingError with
the file and what is wrong.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.decoder import DecoderFactory

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.encoding import decode_raw_runs
from fluxcal.drivers.errors import DataError, RecordingError
from fluxcal.drivers.mcap_source import (
    Hole,
    ReadReport,
    iter_records,
    metadata_json,
    unit_of_topic,
)
from fluxcal.service.io.encoding import CORRECTED_ENCODING, RAW_ENCODING, decode_corrected, decode_json, decode_raw
from fluxcal.service.io.recordings.gaps import gaps_between, message_spans
from fluxcal.service.io.recordings.labdata import keep_every
from fluxcal.service.io.recordings.repair import repair_recording  # noqa: F401 - read and repair from one module, as before
from fluxcal.service.numerics.outputs import CorrectedBlock


def concat_corrected(blocks: list[CorrectedBlock]) -> CorrectedBlock:
    """One CorrectedBlock of many; an optional output is kept only if every block has it; cal_id is
    the last block's (Recording.corrected_cal_id has it per sample)."""
    if not blocks:
        raise ValueError("concat_corrected: no blocks")

    def cat(name: str) -> np.ndarray | None:
        parts = [getattr(b, name) for b in blocks]
        return None if any(p is None for p in parts) else np.concatenate(parts)

    return CorrectedBlock(t_s=np.concatenate([b.t_s for b in blocks]), seq=np.concatenate([b.seq for b in blocks]),
                          corrected_nT=np.concatenate([b.corrected_nT for b in blocks]), diff_nT=cat("diff_nT"),
                          tensor_nT_m=cat("tensor_nT_m"), center_nT=cat("center_nT"), cal_id=blocks[-1].cal_id)


@dataclass
class Recording:
    """A recording in memory: one unit's streams, in recorded order. The raw samples are held as runs
    (consecutive messages of one layout decoded into one block); `raw_blocks` gives them message by message."""

    raw_runs: list[SampleBlock]
    corrected_blocks: list[CorrectedBlock]
    events: list[dict[str, Any]]
    calibration: list[dict[str, Any]]
    metadata: dict[str, str]
    files: list[str] = field(default_factory=list)
    truncated: list[str] = field(default_factory=list)       # files whose tail was cut (writer killed)
    health: list[dict[str, Any]] = field(default_factory=list)
    unit: str | None = None
    report: ReadReport = field(default_factory=ReadReport)
    every: int = 1                 # read_samples(max_probe_samples=...): every k-th sample kept
    n_read: int | None = None      # the samples in the recording (before keeping every k-th)
    run_sizes: list[np.ndarray] | None = None    # per run, the samples of each message (None: a message per run)
    health_at: list[int] = field(default_factory=list)   # per health message, the raw messages recorded before it
    gaps: list = field(default_factory=list)     # where the recorder itself lost raw samples (gaps.RecorderGap)

    @property
    def raw_blocks(self) -> list[SampleBlock]:
        """The raw samples as recorded, a block per message (views into the runs)."""
        if self.run_sizes is None:
            return self.raw_runs
        out = []
        for run, sizes in zip(self.raw_runs, self.run_sizes):
            if len(sizes) == 1:
                out.append(run)
                continue
            edges = np.concatenate([[0], np.cumsum(sizes)]).tolist()
            out += [run.slice(a, b) for a, b in zip(edges[:-1], edges[1:])]
        return out

    @property
    def raw(self) -> SampleBlock:
        """Every raw sample in one block (the block itself when there is one: no copy)."""
        return self.raw_runs[0] if len(self.raw_runs) == 1 else SampleBlock.concat(self.raw_runs)

    @property
    def corrected(self) -> CorrectedBlock | None:
        """Every corrected sample in one block (None if the recording has none)."""
        return concat_corrected(self.corrected_blocks) if self.corrected_blocks else None

    @property
    def corrected_cal_id(self) -> np.ndarray:
        """(N,) int64: the calibration that produced each corrected sample."""
        return np.concatenate([np.full(b.n_samples, b.cal_id, np.int64) for b in self.corrected_blocks]
                              or [np.empty(0, np.int64)])

    @property
    def warnings(self) -> list[str]:
        return self.report.warnings

    @property
    def holes(self) -> list[Hole]:
        """Data lost in the middle of the recording: found while reading (damage) or recorded by a repair."""
        return self.report.holes

    @property
    def arithmetic(self) -> dict[str, str]:
        """The arithmetic of the machine that made the recording ("fluxcal.arithmetic"; {} if not said)."""
        return self.report.arithmetic

    @property
    def n_probes(self) -> int:
        return self.raw_runs[0].n_probes

    def _json(self, key: str) -> Any:
        report = ReadReport(metadata=self.metadata)
        return metadata_json(report, key, where=self.files[0] if self.files else "recording")

    @property
    def probe_names(self) -> list[str]:
        names = self._json("probe_names")
        return [str(n) for n in names] if names else [f"s{k + 1}" for k in range(self.n_probes)]

    @property
    def lsb_nT(self) -> float | None:
        """nT per ADC count of the unit, if the recording says."""
        text = self.metadata.get("lsb_nT")
        return float(text) if text else None

    @property
    def positions_m(self) -> list[list[float]] | None:
        """Probe positions in the platform frame, m, if the recording says."""
        return self._json("positions_m")


def read_samples(path: str | Path, *, unit: str | None = None, strict: bool = False,
                 max_samples: int | None = None, max_probe_samples: int | None = None) -> Recording:
    """Only the raw samples of a recording, in one block, for fit and diagnose: read in two passes (count,
    then decode into arrays of the final size), so the samples are held once, never as a list of blocks and
    their concatenation too (half the peak memory of read_recording(...).raw). Extras kept: those in every
    block. The same checks and messages as read_recording.

    max_samples, max_probe_samples: keep only every k-th sample, k the smallest that brings the samples (and
    samples x probes) within them, counted over the whole recording, so the rest is never held;
    Recording.every says k (1: all kept)."""
    report = ReadReport()
    chosen, units, n, probes, extras = unit, [], 0, set(), None
    health: dict[str, tuple[list, list]] = {}
    spans: list[np.ndarray] = []
    for topic, b in _raw_runs(path, report, strict, unit, units, health, spans):
        chosen = unit_of_topic(topic)
        n += b.n_samples
        probes.add(b.n_probes)
        extras = set(b.extras) if extras is None else extras & set(b.extras)
    _check_read(path, unit, units, n > 0, probes, report)
    gaps = _gaps_said(report, spans, *health.get(chosen or "", ([], [])))
    p = probes.pop()
    every = keep_every(n, p, max_samples, max_probe_samples)
    m = -(-n // every)                                       # rows 0, every, 2 every, ... of the recording
    t, seq = np.empty(m), np.empty(m, np.int64)
    fld, temp, flags = np.empty((m, p, 3)), np.empty((m, p)), np.empty(m, np.uint8)
    ext = {k: np.empty(m) for k in sorted(extras or ())}
    at = kept = 0
    for _, b in _raw_runs(path, ReadReport(), strict, chosen, []):
        rows = slice((-at) % every, None, every)     # the rows whose index in the recording divides by k
        k_b = len(range(b.n_samples)[rows])
        sl = slice(kept, kept + k_b)
        if kept + k_b > m:
            raise RecordingError(f"{path}: changed while it was read ({n} samples, then more)")
        t[sl], seq[sl], fld[sl], temp[sl] = b.t_s[rows], b.seq[rows], b.field_nT[rows], b.temp_C[rows]
        flags[sl] = b.flags[rows]
        for k, v in ext.items():
            v[sl] = b.extras[k][rows]
        at += b.n_samples
        kept += k_b
    if at != n:
        raise RecordingError(f"{path}: changed while it was read ({n} samples, then {at})")
    block = SampleBlock(t_s=t, seq=seq, field_nT=fld, temp_C=temp, flags=flags, extras=ext)
    return Recording([block], [], [], [], report.metadata, report.files, report.truncated, [], chosen, report,
                     every=every, n_read=n, gaps=gaps)


def _chosen_raw(path: str | Path, report: ReadReport, strict: bool, unit: str | None, units: list[str],
                health: dict[str, tuple[list, list]] | None = None):
    """The raw records of `unit` (None: of the first unit with raw samples); every unit seen goes into `units`;
    `health`, where given, gets each unit's health messages and the raw messages of that unit recorded before each."""
    chosen, n_raw = unit, {}
    for rec in iter_records(path, report, strict=strict):
        u = unit_of_topic(rec.topic)
        if u is None:
            continue
        if u not in units:
            units.append(u)
        if chosen is None and rec.encoding == RAW_ENCODING:
            chosen = u
        if rec.encoding == RAW_ENCODING:
            n_raw[u] = n_raw.get(u, 0) + 1
            if u == chosen:
                yield rec
        elif health is not None and rec.topic.endswith("/health"):
            with contextlib.suppress(DataError):                # a damaged health message says nothing of gaps
                got = health.setdefault(u, ([], []))
                got[0].append(decode_json(rec.data))
                got[1].append(n_raw.get(u, 0))


#: raw messages decoded together (decode_raw_runs), at most so many and so many bytes: what is held undecoded
#: besides the samples (a recording of large messages, `simulate`'s, must not be held twice over)
RAW_BATCH = 4096
RAW_BATCH_BYTES = 16 << 20


class _RawBatches:
    """Raw messages decoded a batch at a time as they are read (decode_raw_runs, a run of one layout at a
    time): a live recording's small messages (8 ms of samples each) without a decode each, and never more
    than RAW_BATCH messages or RAW_BATCH_BYTES of them held undecoded."""

    def __init__(self, path: str | Path) -> None:
        self.path, self.pending, self.held, self.topic = path, [], 0, ""

    def add(self, topic: str, data: bytes) -> list[tuple[SampleBlock, np.ndarray]]:
        """Take one message; the runs decoded when the batch is full (else none)."""
        self.pending.append(data)
        self.held += len(data)
        self.topic = topic
        return self.flush() if len(self.pending) >= RAW_BATCH or self.held >= RAW_BATCH_BYTES else []

    def flush(self) -> list[tuple[SampleBlock, np.ndarray]]:
        """The runs of the messages taken since the last flush: (block, samples per message); a damaged
        message is a RecordingError naming the file and topic."""
        payloads, self.pending, self.held = self.pending, [], 0
        if not payloads:
            return []
        try:
            return decode_raw_runs(payloads)
        except DataError as e:
            raise RecordingError(f"{self.path}: {self.topic}: damaged message: {e}") from None


def _raw_runs(path: str | Path, report: ReadReport, strict: bool, unit: str | None, units: list[str],
              health: dict[str, tuple[list, list]] | None = None, spans: list | None = None):
    """(topic, block) of the raw samples of `unit` (as _chosen_raw), decoded in batches (_RawBatches); `spans`,
    where given, gets each message's first and last seq and time (gaps.message_spans)."""
    batches = _RawBatches(path)
    for rec in _chosen_raw(path, report, strict, unit, units, health):
        for b, sizes in batches.add(rec.topic, rec.data):
            if spans is not None:
                spans.append(message_spans(b, sizes))
            yield rec.topic, b
    for b, sizes in batches.flush():
        if spans is not None:
            spans.append(message_spans(b, sizes))
        yield batches.topic, b


def _gaps_said(report: ReadReport, spans: list, health: list, health_at: list) -> list:
    """The recorder's gaps (gaps.gaps_between), each said among the reading's warnings, as every command reads it."""
    found = gaps_between(np.concatenate(spans) if spans else np.empty((0, 4)), health, health_at)
    report.recorder_gaps += [g.describe() for g in found]
    return found


def _check_read(path: str | Path, unit: str | None, units: list[str], any_raw: bool, probes: set[int],
                report: ReadReport) -> None:
    if unit is None and len(units) > 1:
        raise RecordingError(f"{path}: holds several units ({', '.join(units)}): choose one with unit=")
    if not any_raw:
        why = "; ".join(report.warnings)
        raise RecordingError(f"{path}: no raw samples" + (f" of unit {unit!r}" if unit else "")
                             + " in this recording" + (f" ({why})" if why else ""))
    if len(probes) > 1:
        raise RecordingError(f"{path}: the number of probes changes within the recording ({sorted(probes)}): "
                             f"read its files one at a time")


def read_recording(path: str | Path, *, unit: str | None = None, strict: bool = False) -> Recording:
    """Read a recording (a file or a directory of rotated files) into memory.

    unit=None: the only unit recorded (several -> RecordingError naming them). A killed writer's
    file is read up to its last complete chunk (`truncated` says so); a damaged record is read past
    (report.damaged says it, `holes` what it lost); strict=True refuses a damaged file instead."""
    report = ReadReport()
    raw: list[tuple[SampleBlock, np.ndarray]] = []
    batches = _RawBatches(path)
    cor: list[CorrectedBlock] = []
    events: list[dict[str, Any]] = []
    cal: list[dict[str, Any]] = []
    health: list[dict[str, Any]] = []
    health_at: list[int] = []                          # where each health message lies in the raw stream
    n_raw = 0
    units: list[str] = []
    chosen = unit
    sinks: dict[str, Callable[[bytes], None]] = {
        "events": lambda d: events.append(decode_json(d)), "calibration": lambda d: cal.append(decode_json(d)),
        "health": lambda d: (health.append(decode_json(d)), health_at.append(n_raw))}
    for rec in iter_records(path, report, strict=strict):
        u = unit_of_topic(rec.topic)
        if u is None:
            continue                                   # not a fluxcal stream: ignore
        if chosen is None and rec.encoding == RAW_ENCODING:
            chosen = u
        if u not in units:
            units.append(u)
        if chosen is not None and u != chosen:
            continue
        stream = rec.topic.rsplit("/", 1)[1]
        try:
            if rec.encoding == RAW_ENCODING:
                n_raw += 1
                raw += batches.add(rec.topic, rec.data)
            elif rec.encoding == CORRECTED_ENCODING:
                cor.append(decode_corrected(rec.data))
            elif stream in sinks:
                sinks[stream](rec.data)
        except DataError as e:
            raise RecordingError(f"{path}: {rec.topic}: damaged message: {e}") from None
    runs = raw + batches.flush()
    _check_read(path, unit, units, bool(runs), {b.n_probes for b, _ in runs}, report)
    gaps = _gaps_said(report, [message_spans(b, n) for b, n in runs], health, health_at)
    return Recording([b for b, _ in runs], cor, events, cal, report.metadata, report.files, report.truncated, health,
                     chosen, report, run_sizes=[n for _, n in runs], health_at=health_at, gaps=gaps)


class FluxcalDecoderFactory(DecoderFactory):
    """Decodes fluxcal streams for mcap's readers: raw -> SampleBlock, corrected -> CorrectedBlock,
    json -> dict. `make_reader(f, decoder_factories=[FluxcalDecoderFactory()]).iter_decoded_messages()`."""

    def decoder_for(self, message_encoding: str, schema: Any) -> Callable[[bytes], Any] | None:
        return {RAW_ENCODING: decode_raw, CORRECTED_ENCODING: decode_corrected,
                "json": decode_json}.get(message_encoding)


__all__ = ["FluxcalDecoderFactory", "Recording", "concat_corrected", "read_recording", "repair_recording"]
