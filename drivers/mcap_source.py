"""Reading fluxcal MCAP recordings: the "replay" Source, and the record reader shared with service.io.recordings.reader.

A recording is one .mcap file or a directory of rotated files, read in name order (the logger's
names `<unit>-<YYYYmmddTHHMMSS>-<NNNN>.mcap` sort in time order). Files are read record by record
from the start, never through the footer's index, so a file whose writer was killed (no footer, a
chunk cut short) yields every complete chunk and the cut is reported in `ReadReport.truncated`
instead of failing. What is reported and what is refused:

    no footer, or a record cut short at the end     read; one line in report.truncated per file
    a chunk whose CRC fails, an unreadable record   RecordingError (strict, the default), or skipped
      inside the file                               and listed in report.damaged (strict=False)
    not an MCAP file, missing path, no raw samples  RecordingError

The replay Source yields the recorded raw SampleBlocks bit for bit, one per recorded message, and
counts what the live source counted (samples, sequence gaps, saturated axes, invalid temperatures).
Its `events` (and `take_events(seq)`) give the recorded commands with the seq they applied from,
so a replay re-applies them at the same samples.
"""

from __future__ import annotations

import io
import json
import logging
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .assemble import SeqGapCounter
from .block import FLAG_TEMP_INVALID, SampleBlock
from .encoding import RAW_ENCODING, decode_raw
from .errors import DataError, RecordingError
from .source import Source

log = logging.getLogger("fluxcal.replay")

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = 9                      # u8 opcode, u64 length


@dataclass
class McapRecord:
    """One message of a recording, with its channel's topic and message encoding."""

    topic: str
    encoding: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int = 0
    schema_name: str = ""


@dataclass
class ReadReport:
    """What reading a recording found besides the messages: files, cut tails, damage, metadata."""

    files: list[str] = field(default_factory=list)
    truncated: list[str] = field(default_factory=list)    # one line per file whose tail was cut (writer killed)
    damaged: list[str] = field(default_factory=list)      # records skipped as corrupt (strict=False only)
    messages: int = 0                                      # messages read
    skipped_messages: int = 0                              # messages whose channel record was lost
    truncated_bytes: int = 0                               # bytes at file ends that held no complete record
    metadata: dict[str, str] = field(default_factory=dict)  # the "fluxcal" metadata record(s)
    time: dict[str, str] = field(default_factory=dict)      # the "fluxcal.time" metadata record (log_time rule)

    @property
    def warnings(self) -> list[str]:
        out = list(self.truncated) + list(self.damaged)
        if self.skipped_messages:
            out.append(f"{self.skipped_messages} message(s) skipped: their channel was declared in a lost chunk")
        return out


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


def _all_zero(fh: io.BufferedReader) -> bool:
    while chunk := fh.read(1 << 20):
        if chunk.count(0) != len(chunk):
            return False
    return True


def iter_file_records(path: str | Path, report: ReadReport | None = None, *, strict: bool = True) -> Iterator[Any]:
    """The data-section records of one MCAP file in file order, chunks broken up: mcap.records
    Header, Schema, Channel, Message, Metadata and Attachment objects. Stops at DataEnd or at the
    end of a file without footer (noted in `report.truncated`)."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Attachment, Channel, Chunk, Header, Message, Metadata, Schema

    readers = {Opcode.HEADER: Header.read, Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read,
               Opcode.CHUNK: Chunk.read, Opcode.METADATA: Metadata.read, Opcode.ATTACHMENT: Attachment.read}
    # the summary section's records belong after Data End, where reading stops: met before it, they are
    # damage (a chunk whose opcode byte was hit reads as one of them, and would vanish without a word)
    summary_only = {Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX, Opcode.METADATA_INDEX, Opcode.STATISTICS,
                    Opcode.SUMMARY_OFFSET, Opcode.FOOTER}
    report = report if report is not None else ReadReport()
    f = Path(path)

    def damaged(what: str, pos: int) -> None:
        msg = f"{f}: {what} at byte {pos}"
        if strict:
            raise RecordingError(f"{msg}: the recording is damaged (repair_recording salvages the rest)")
        report.damaged.append(msg)

    try:
        fh = f.open("rb")
    except OSError as e:
        raise RecordingError(f"{f}: cannot read: {e.strerror or e}") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        magic = fh.read(8)
        if magic != MCAP_MAGIC:
            if MCAP_MAGIC.startswith(magic):
                report.truncated.append(f"{f}: empty ({size} bytes): its writer stopped before writing anything")
                report.truncated_bytes += size
                return
            raise RecordingError(f"{f}: not an MCAP file (starts with {magic[:8]!r})")
        pos = 8
        while True:
            head = fh.read(_RECORD_HEAD)
            if not head:
                report.truncated.append(f"{f}: no footer: its writer was stopped (killed, power lost) or is still "
                                        f"writing; every complete chunk was read")
                return
            opcode, length = head[0], int.from_bytes(head[1:], "little")
            if len(head) < _RECORD_HEAD or pos + _RECORD_HEAD + length > size:
                # the writer died while writing this record: what came before it is whole
                try:
                    name = Opcode(opcode).name.lower().replace("_", " ")
                except ValueError:
                    name = f"opcode {opcode:#04x}"
                report.truncated.append(f"{f}: cut inside a {name} record at byte {pos} of {size}: its writer "
                                        f"was stopped; the {size - pos} bytes of that record are lost, every "
                                        f"complete chunk before it was read")
                report.truncated_bytes += size - pos
                return
            if opcode == Opcode.DATA_END:
                if _data_end_in_place(fh, size, pos + _RECORD_HEAD + length):
                    return
                # a record header hit in the middle of the file: reading must not stop there in silence
                damaged("data end record before the end of the data section", pos)
                fh.seek(length, io.SEEK_CUR)
            elif opcode == Opcode.MESSAGE_INDEX:
                # skipped (the reader does not need the index), but only if it is one: u16 channel id,
                # u32 byte length of its (u64, u64) entries, the entries
                body = fh.read(length)
                n_bytes = int.from_bytes(body[2:6], "little") if length >= 6 else -1
                if n_bytes != length - 6 or n_bytes % 16:
                    damaged("malformed message index record (a damaged record header?)", pos)
            elif opcode in summary_only:
                damaged(f"{Opcode(opcode).name.lower()} record inside the data section", pos)
                fh.seek(length, io.SEEK_CUR)
            elif opcode in readers or opcode == Opcode.MESSAGE:
                body = fh.read(length)
                stream = ReadDataStream(io.BytesIO(body))
                try:
                    rec = Message.read(stream, length) if opcode == Opcode.MESSAGE else readers[opcode](stream)
                    subs = _chunk_records(rec) if isinstance(rec, Chunk) else [rec]
                except Exception as e:
                    # a CRC mismatch, a corrupt length or compressed stream inside the file's bounds; the
                    # decompressors raise their own types (RuntimeError, zstandard.ZstdError), hence Exception
                    damaged(f"unreadable {Opcode(opcode).name.lower()} record ({type(e).__name__}: {e})", pos)
                    subs = []
                yield from subs
            elif opcode == 0 and _all_zero(fh):
                # a filesystem that lost power may leave a zero-filled tail
                report.truncated.append(f"{f}: ends in {size - pos} zero bytes (power lost while writing?); "
                                        f"every complete chunk before them was read")
                report.truncated_bytes += size - pos
                return
            else:
                damaged(f"unknown record opcode {opcode:#04x}", pos)
                fh.seek(length, io.SEEK_CUR)
            pos += _RECORD_HEAD + length


_MESSAGE_HEAD = struct.Struct("<BQHIQQ")     # opcode, length, channel id, sequence, log time, publish time
_RECORD = struct.Struct("<BQ")


def _chunk_records(chunk: Any) -> list[Any]:
    """The Schema, Channel and Message records of a chunk: mcap.stream_reader.breakup_chunk (the same
    decompression, CRC check and records) with its messages parsed by one struct call each, a quarter
    of the time per message (replay reads thousands of small messages a second of recording)."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import get_chunk_data_stream

    stream, size = get_chunk_data_stream(chunk, validate_crc=True)
    data = stream.read(size)
    out: list[Any] = []
    pos, message, head = 0, int(Opcode.MESSAGE), _MESSAGE_HEAD.size
    while pos < size:
        if pos + _RECORD.size > size:
            raise ValueError(f"chunk: a record header cut short at byte {pos} of {size}")
        opcode, length = _RECORD.unpack_from(data, pos)
        end = pos + _RECORD.size + length
        if end > size:
            raise ValueError(f"chunk: a record of {length} bytes at byte {pos} runs past the chunk's {size}")
        if opcode == message:
            if length < head - _RECORD.size:
                raise ValueError(f"chunk: a message record of {length} bytes at byte {pos}")
            _, _, channel, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, pos)
            out.append(Message(channel_id=channel, log_time=log_time, data=data[pos + head:end],
                               publish_time=publish_time, sequence=sequence))
        elif opcode in (Opcode.CHANNEL, Opcode.SCHEMA):
            body = ReadDataStream(io.BytesIO(data[pos + _RECORD.size:end]))
            out.append(Channel.read(body) if opcode == Opcode.CHANNEL else Schema.read(body))
        pos = end                                  # other records inside a chunk: skipped, as breakup_chunk does
    return out


def _data_end_in_place(fh: io.BufferedReader, size: int, end: int) -> bool:
    """Whether a Data End record ending at byte `end` is where the file's footer says the data section ends
    (the summary's start, or the footer itself without a summary). True when there is no footer to ask."""
    footer_len = _RECORD_HEAD + 20                   # u64 summary start, u64 summary offset start, u32 crc
    at = size - len(MCAP_MAGIC) - footer_len
    if at < end:
        return True
    here = fh.tell()
    try:
        fh.seek(at)
        tail = fh.read(footer_len + len(MCAP_MAGIC))
    finally:
        fh.seek(here)
    if tail[0] != 0x02 or tail[-len(MCAP_MAGIC):] != MCAP_MAGIC:    # footer opcode, closing magic
        return True
    summary_start = int.from_bytes(tail[_RECORD_HEAD:_RECORD_HEAD + 8], "little")
    return end == (summary_start or at)


def iter_records(path: str | Path, report: ReadReport | None = None, *, strict: bool = True,
                 topics: set[str] | None = None) -> Iterator[McapRecord]:
    """Every message of the recording in file order (files in name order); the "fluxcal" and
    "fluxcal.time" metadata records go into `report`."""
    from mcap.records import Channel, Message, Metadata, Schema

    report = report if report is not None else ReadReport()
    for f in recording_files(path):
        report.files.append(str(f))
        schemas: dict[int, str] = {}
        channels: dict[int, Channel] = {}
        for rec in iter_file_records(f, report, strict=strict):
            if isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None and strict:
                    # channels come before their messages: in a file read whole, a message on an unknown
                    # channel is damage (a record header hit), not a channel lost with a damaged chunk
                    raise RecordingError(f"{f}: a message on channel {rec.channel_id}, which no channel record "
                                         f"declared: the recording is damaged (repair_recording salvages the rest)")
                if ch is None:
                    report.skipped_messages += 1
                elif topics is None or ch.topic in topics:
                    report.messages += 1
                    yield McapRecord(ch.topic, ch.message_encoding, rec.data, rec.log_time, rec.publish_time,
                                     schemas.get(ch.schema_id, ""))
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Schema):
                schemas[rec.id] = rec.name
            elif isinstance(rec, Metadata):
                if rec.name == "fluxcal":
                    report.metadata.update(rec.metadata)
                elif rec.name == "fluxcal.time":
                    report.time.update(rec.metadata)


def unit_of_topic(topic: str) -> str | None:
    """"/fluxcal/<unit>/<stream>" -> unit, else None."""
    parts = topic.split("/")
    return parts[2] if len(parts) == 4 and parts[0] == "" and parts[1] == "fluxcal" else None


def iter_raw_blocks(path: str | Path, report: ReadReport | None = None, *, unit: str | None = None,
                    strict: bool = True) -> Iterator[SampleBlock]:
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

    def __init__(self, path: str | Path, *, unit: str | None = None, strict: bool = True) -> None:
        self.path = str(path)
        self.report = ReadReport()
        self._unit = unit
        self._strict = strict
        self._events: list[dict[str, Any]] | None = None
        self._event_pos = 0
        self._it = iter_raw_blocks(path, self.report, unit=unit, strict=strict)
        self._next: SampleBlock | None = next(self._it, None)
        self._warned = 0
        if self._next is None:
            raise RecordingError(f"{path}: no raw samples in this recording"
                                 + (f" ({'; '.join(self.report.warnings)})" if self.report.warnings else ""))
        super().__init__(self._next.n_probes)
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

    def _warn_new(self) -> None:
        for w in self.report.warnings[self._warned:]:
            log.warning("replay: %s", w)
        self._warned = len(self.report.warnings)

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
        self._warn_new()
        return b

    def close(self) -> None:
        if not self._closed:
            self._it.close()                     # closes the file being read
        super().close()


def open_source(config: Any = None, *, path: str | Path | None = None, unit: str | None = None,
                strict: bool = True, **_: Any) -> McapSource:
    """The "replay" entry of drivers.source.SOURCES: open_source("replay", path=REC, unit=None).

    `config` may be the path itself or an object with a `.path` (the [source] section of kind
    "replay"); `path=` wins. Other keyword arguments are accepted and ignored, so every source kind
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


__all__ = ["McapRecord", "McapSource", "ReadReport", "RAW_ENCODING", "iter_file_records", "iter_raw_blocks",
           "iter_records", "metadata_json", "open_source", "recording_files", "unit_of_topic"]
