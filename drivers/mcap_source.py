"""Reading fluxcal MCAP recordings: replay's Source (drivers/kinds/replay.py), and the record reader shared with
fluxcal.service.io.recordings.reader.

A recording is one .mcap file or a directory of rotated files, read in name order (the logger's
names `<unit>-<YYYYmmddTHHMMSS>-<NNNN>.mcap` sort in time order). Each file's records are read in file
order by fluxcal.drivers.mcap_scan, which keeps going past what happened to the file and says it:

    no footer, or a record cut short at the end     read to the last complete chunk; one line in
      (a killed writer)                             report.truncated per file
    a damaged record inside the file (a chunk       damage, not a stopped writer: one line in report.damaged;
      whose CRC fails, a length or opcode hit)      reading goes on with the next indexed chunk (a finished
                                                    file) or the next readable record (no footer); what is
                                                    lost is a Hole in report.holes, with the seq and time span
                                                    of the samples lost; strict=True refuses the file instead
    a repaired copy                                 its "fluxcal.repair" metadata: the holes the repair found
                                                    (report.holes) and the cut tail (report.repaired)
    not an MCAP file, missing path, no raw samples  RecordingError

The replay Source yields the recorded raw SampleBlocks bit for bit, one per recorded message, and
counts what the live source counted (samples, sequence gaps, saturated axes, invalid temperatures).
Its `events` (and `take_events(seq)`) give the recorded commands with the seq they applied from,
so a replay re-applies them at the same samples.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .assemble import SeqGapCounter
from .block import FLAG_TEMP_INVALID, SampleBlock
from .config import spec
from .declare import SourceTable
from .encoding import RAW_ENCODING, decode_raw
from .errors import DataError, RecordingError
from .kinds.replay import KIND
from .mcap_records import MCAP_MAGIC, Hole, HoleTracker, ReadReport
from .mcap_scan import iter_file_records
from .registry import source_kind
from .source import Counters, Source

log = logging.getLogger("fluxcal.replay")


@dataclass
class McapRecord:
    """One message of a recording, with its channel's topic and message encoding."""

    topic: str
    encoding: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int = 0
    schema_name: str = ""


def recording_files(path: str | Path) -> list[Path]:
    """The .mcap files of a recording: the file itself, or a directory's files in name order."""
    p = Path(path)
    if p.is_dir():
        files = sorted(f for f in p.glob("*.mcap") if f.is_file())
        if not files:
            raise RecordingError(f"{p}: no .mcap files in this directory")
        return files
    if not p.exists():
        raise RecordingError(f"{p}: no such recording")
    return [p]


def _metadata(report: ReadReport, name: str, values: dict[str, str]) -> None:
    """The metadata records fluxcal reads: "fluxcal" (unit, configuration, ...), "fluxcal.time" (the log_time
    rule), "fluxcal.arithmetic" (the machine's arithmetic), "fluxcal.repair" (a repaired copy's holes and cut)."""
    if name == "fluxcal":
        report.metadata.update(values)
    elif name == "fluxcal.time":
        report.time.update(values)
    elif name == "fluxcal.arithmetic":
        report.arithmetic.update(values)
    elif name == "fluxcal.repair":
        report.repaired.update(values)
        try:
            holes = json.loads(values.get("holes", "[]"))
        except json.JSONDecodeError:
            holes = []
        report.holes += [Hole.from_json(h) for h in holes if isinstance(h, dict)]


def iter_records(path: str | Path, report: ReadReport | None = None, *, strict: bool = False,
                 topics: set[str] | None = None) -> Iterator[McapRecord]:
    """Every message of the recording in file order (files in name order); the metadata records fluxcal
    reads go into `report` (_metadata), and the holes found get the samples on each side (HoleTracker)."""
    from mcap.records import Channel, Message, Metadata, Schema

    report = report if report is not None else ReadReport()
    holes = HoleTracker(report)
    for f in recording_files(path):
        report.files.append(str(f))
        schemas: dict[int, str] = {}
        channels: dict[int, Channel] = {}
        raw_units: dict[int, str] = {}             # channel id -> unit, of the raw channels
        for rec in iter_file_records(f, report, strict=strict):
            if len(report.holes) != holes.seen:
                holes.sync()
            if isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None and strict:
                    # channels come before their messages: in a file read whole, a message on an unknown
                    # channel is damage (a record header hit), not a channel lost with a damaged chunk
                    raise RecordingError(f"{f}: a message on channel {rec.channel_id}, which no channel record "
                                         f"declared: the recording is damaged (repair_recording salvages the rest)")
                if ch is None:
                    report.skipped_messages += 1
                    continue
                unit = raw_units.get(rec.channel_id)
                if unit is not None:
                    holes.raw(unit, rec.data)
                if topics is None or ch.topic in topics:
                    report.messages += 1
                    yield McapRecord(ch.topic, ch.message_encoding, rec.data, rec.log_time, rec.publish_time,
                                     schemas.get(ch.schema_id, ""))
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
                unit = unit_of_topic(rec.topic)
                if rec.message_encoding == RAW_ENCODING and unit is not None:
                    raw_units[rec.id] = unit
            elif isinstance(rec, Schema):
                schemas[rec.id] = rec.name
            elif isinstance(rec, Metadata):
                _metadata(report, rec.name, rec.metadata)
        holes.sync()
    holes.finish()


def unit_of_topic(topic: str) -> str | None:
    """"/fluxcal/<unit>/<stream>" -> unit, else None."""
    parts = topic.split("/")
    return parts[2] if len(parts) == 4 and parts[0] == "" and parts[1] == "fluxcal" else None


def iter_raw_blocks(path: str | Path, report: ReadReport | None = None, *, unit: str | None = None,
                    strict: bool = False) -> Iterator[SampleBlock]:
    """The raw SampleBlocks of one unit, in recorded order. unit=None: the only unit recorded
    (a recording that holds several units is refused: name one)."""
    chosen = unit
    for rec in iter_records(path, report, strict=strict):
        if rec.encoding != RAW_ENCODING:
            continue
        u = unit_of_topic(rec.topic)
        if chosen is None:
            chosen = u
        elif u != chosen:
            if unit is not None:
                continue
            raise RecordingError(f"{path}: holds raw samples of several units ({chosen!r}, {u!r}): "
                                 f"choose one with unit=")
        try:
            yield decode_raw(rec.data)
        except DataError as e:
            raise RecordingError(f"{path}: {rec.topic}: {e}") from None


class McapSource(Source):
    """Replays the raw channel of a recording (a file or a directory of rotated files) as the same
    SampleBlocks it recorded, one per recorded message, as fast as they are read.

    `exhausted` is True as soon as the last block has been returned. A killed writer's file is read
    to its last complete chunk; `report.truncated` says so and a warning is logged once per file.
    """

    def __init__(self, path: str | Path, *, unit: str | None = None, strict: bool = False) -> None:
        self.path = str(path)
        self.report = ReadReport()
        self._unit = unit
        self._strict = strict
        self._events: list[dict[str, Any]] | None = None
        self._event_pos = 0
        self._it = iter_raw_blocks(path, self.report, unit=unit, strict=strict)
        self._next: SampleBlock | None = next(self._it, None)
        self._warned = self._holes_warned = 0
        if self._next is None:
            raise RecordingError(f"{path}: no raw samples in this recording"
                                 + (f" ({'; '.join(self.report.warnings)})" if self.report.warnings else ""))
        super().__init__(self._next.n_probes, Counters.of(source_kind(KIND.name).words()))
        self._gaps = SeqGapCounter()
        self._warn_new()

    @property
    def exhausted(self) -> bool:
        return self._next is None

    @property
    def metadata(self) -> dict[str, str]:
        """The recording's "fluxcal" metadata record (unit, n_probes, lsb_nT, probe_names, config, ...)."""
        return self.report.metadata

    @property
    def events(self) -> list[dict[str, Any]]:
        """Every message of the recording's events channel (`{"kind": "command" | "initial" | ..., "seq": S,
        ...}`, S the first sample the event applies to), sorted by seq (stable: recorded order within one
        seq). Read in a separate pass over the events channel the first time it is asked for, so a replay
        can re-apply the recorded commands at the same samples as the live run did."""
        if self._events is None:
            events: list[dict[str, Any]] = []
            side = ReadReport()
            for rec in iter_records(self.path, side, strict=self._strict):
                if rec.encoding != "json" or rec.topic.rsplit("/", 1)[-1] != "events":
                    continue
                if self._unit is not None and unit_of_topic(rec.topic) != self._unit:
                    continue
                try:
                    obj = json.loads(rec.data)
                except (UnicodeDecodeError, json.JSONDecodeError) as e:
                    raise RecordingError(f"{self.path}: {rec.topic}: damaged event message: {e}") from None
                if isinstance(obj, dict):
                    events.append(obj)
            seq_key = [e.get("seq") if isinstance(e.get("seq"), int) else -1 for e in events]
            order = sorted(range(len(events)), key=seq_key.__getitem__)
            self._events = [events[k] for k in order]
        return self._events

    def take_events(self, before_seq: int) -> list[dict[str, Any]]:
        """The events not yet taken whose seq is <= `before_seq` (apply them before the sample with
        that seq), in order; events without a seq count as seq -1 (they apply from the start)."""
        events = self.events
        out = []
        while self._event_pos < len(events):
            s = events[self._event_pos].get("seq")
            if (s if isinstance(s, int) else -1) > before_seq:
                break
            out.append(events[self._event_pos])
            self._event_pos += 1
        return out

    def _warn_new(self, final: bool = False) -> None:
        """Log what reading found as it is found; the holes (whose sample spans are known once the samples after
        them were read) when the recording is exhausted or closed."""
        lines = self.report.truncated + self.report.damaged
        for w in lines[self._warned:]:
            log.warning("replay: %s", w)
        self._warned = len(lines)
        if final:
            for h in self.report.holes[self._holes_warned:]:
                log.warning("replay: %s", h.describe(self._unit))
            self._holes_warned = len(self.report.holes)

    def _read_block(self, timeout: float | None) -> SampleBlock | None:
        b = self._next
        if b is None:
            return None
        if b.n_probes != self.n_probes:
            raise RecordingError(f"{self.path}: the number of probes changes from {self.n_probes} to {b.n_probes} "
                                 f"at sample {int(b.seq[0]) if b.n_samples else '?'}: replay one part at a time")
        self._next = next(self._it, None)          # look ahead, so `exhausted` is known with the last block
        c = self.counters
        c.frames_accepted += b.n_samples
        c.saturated_axes += int(np.count_nonzero(np.isnan(b.field_nT)))
        c.temp_invalid += int(np.count_nonzero(b.flags & FLAG_TEMP_INVALID))
        self._gaps.update(b.seq, c)
        self._warn_new(final=self._next is None)
        return b

    def close(self) -> None:
        if not self._closed:
            self._it.close()                     # closes the file being read
            self._warn_new(final=True)
        super().close()


@dataclass(kw_only=True)   # path has no default and follows kind's
class ReplayConfig(SourceTable):
    """The [source] table of replay (drivers/kinds/replay.py)."""

    path: str = spec(doc="an MCAP file or a directory of rotated files")
    rate_hz: float | None = spec(None, min=0.001, max=100_000.0,
                                 doc="the recorded unit's sample rate, Hz (needed without a [sim] section)")


def open_source(config: Any = None, *, path: str | Path | None = None, unit: str | None = None,
                strict: bool = False, **_: Any) -> McapSource:
    """Replay's factory (drivers/kinds/replay.py): open_source("replay", path=REC, unit=None).

    `config` may be the path itself or an object with a `.path` (replay's [source] table, ReplayConfig);
    `path=` wins. Other keyword arguments are accepted and ignored, so every source kind
    can be opened with the same call."""
    if path is None:
        path = config if isinstance(config, (str, Path)) else getattr(config, "path", None)
    if not path:
        from .errors import ConfigError

        raise ConfigError("source.path: a replay source needs the recording (an .mcap file or a directory)")
    return McapSource(path, unit=unit, strict=strict)


def metadata_json(report: ReadReport, key: str, default: Any = None, where: str = "") -> Any:
    """A JSON-valued key of the "fluxcal" metadata record (probe_names, positions_m, config), or default."""
    text = report.metadata.get(key)
    if text is None:
        return default
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise RecordingError(f"{where + ': ' if where else ''}metadata {key!r} is not JSON: {e}") from None


__all__ = ["MCAP_MAGIC", "Hole", "McapRecord", "McapSource", "ReadReport", "RAW_ENCODING", "ReplayConfig",
           "iter_file_records",
           "iter_raw_blocks", "iter_records", "metadata_json", "open_source", "recording_files", "unit_of_topic"]
