"""The records of one MCAP file in file order, whatever happened to the file: a killed writer's cut tail, a
damaged record in the middle, a hole where a chunk was lost. fluxcal.drivers.mcap_source reads recordings through it.

    a file with a footer and a chunk index    the index says where every chunk, metadata and attachment record
                                              starts and how long it is: a record whose header disagrees is
                                              damage (read by its index entry when its CRC holds, else lost),
                                              and reading goes on with the next indexed record
    no footer (a killed writer) or no index   records are followed by their lengths; a damaged one is left for
                                              the next readable record (resynchronised on a record opcode: a
                                              chunk whose CRC holds, a message index, metadata, an attachment,
                                              the data end), and a record running past the end of the file is
                                              a cut tail only if no readable record follows it

What is lost is a Hole (file, byte span, log-time span when indexed, and the samples' seq and time span on each
side, filled in by HoleTracker from the raw messages around it); what is damaged is a line in
ReadReport.damaged; a cut tail a line in ReadReport.truncated. strict=True refuses any damage instead.
"""

from __future__ import annotations

import bisect
import io
import re
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MCAP_MAGIC = b"\x89MCAP0\r\n"
RECORD_HEAD = 9                       # u8 opcode, u64 length
_FOOTER = RECORD_HEAD + 20            # u64 summary start, u64 summary offset start, u32 summary crc
_DATA_END = RECORD_HEAD + 4           # u32 data section crc
# opcodes (mcap.opcode.Opcode), as plain ints for the byte scans
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX = 1, 2, 3, 4, 5, 6, 7, 8
ATTACHMENT, ATTACHMENT_INDEX, STATISTICS, METADATA, METADATA_INDEX, SUMMARY_OFFSET, DATA_END = range(9, 16)
NAMES = {HEADER: "header", FOOTER: "footer", SCHEMA: "schema", CHANNEL: "channel", MESSAGE: "message",
         CHUNK: "chunk", MESSAGE_INDEX: "message index", CHUNK_INDEX: "chunk index", ATTACHMENT: "attachment",
         ATTACHMENT_INDEX: "attachment index", STATISTICS: "statistics", METADATA: "metadata",
         METADATA_INDEX: "metadata index", SUMMARY_OFFSET: "summary offset", DATA_END: "data end"}
#: the summary's records belong after Data End: met before it, they are damage (a chunk whose opcode was hit)
SUMMARY_ONLY = {CHUNK_INDEX, ATTACHMENT_INDEX, METADATA_INDEX, STATISTICS, SUMMARY_OFFSET, FOOTER}
#: where reading may start again after damage: records it can tell from noise (a CRC, or lengths that agree).
#: A record header of one of these opcodes has a length below 4 GiB: its four high bytes are 0.
_RESYNC = re.compile(rb"[\x06\x07\x09\x0c\x0f][\x00-\xff]{4}\x00{4}", re.S)


def _name(opcode: int) -> str:
    return NAMES.get(opcode, f"opcode {opcode:#04x}")


@dataclass
class Hole:
    """Data lost from the middle of a recording: where in the file, why, and per unit the raw samples on each
    side (`units[unit]` = {"seq_before", "t_before", "seq_after", "t_after"}: the last sample before the hole and
    the first after it; None where the hole starts or ends the recording). `recorded`: read from a repaired
    file's "fluxcal.repair" metadata (found when the original was repaired)."""

    file: str
    at_byte: int
    n_bytes: int
    why: str
    log_time_ns: tuple[int, int] | None = None
    units: dict[str, dict[str, Any]] = field(default_factory=dict)
    recorded: bool = False

    def seq_span(self, unit: str | None = None) -> tuple[int | None, int | None] | None:
        """(first, last) seq lost for `unit` (None: the only one); first None: from the recording's start, last
        None: to its end; None when no raw sample of the unit is on either side."""
        side = self._side(unit)
        if side is None:
            return None
        a, b = side.get("seq_before"), side.get("seq_after")
        return (None if a is None else int(a) + 1, None if b is None else int(b) - 1)

    def _side(self, unit: str | None) -> dict[str, Any] | None:
        if unit is None and len(self.units) == 1:
            unit = next(iter(self.units))
        side = self.units.get(unit) if unit is not None else None
        if side is None or (side.get("seq_before") is None and side.get("seq_after") is None):
            return None
        return side

    def describe(self, unit: str | None = None) -> str:
        """"a hole of N samples at seq A-B (t X-Y s): lost with ... at byte P of FILE"."""
        where = f"{self.n_bytes} bytes at byte {self.at_byte} of {Path(self.file).name}"
        side = self._side(unit)
        if side is None:
            return f"a hole of {where}: {self.why}"
        a, b = side.get("seq_before"), side.get("seq_after")
        ta, tb = side.get("t_before"), side.get("t_after")
        if a is not None and b is not None and int(b) - int(a) > 1:
            what = (f"a hole of {int(b) - int(a) - 1} samples at seq {int(a) + 1}-{int(b) - 1} "
                    f"(unit time {float(ta):.3f}-{float(tb):.3f} s, between the samples kept)")
        elif a is not None and b is not None:
            what = f"no raw sample missing between seq {int(a)} and {int(b)}, yet data lost"
        elif b is not None:
            what = f"a hole at the start: the samples before seq {int(b)} (unit time {float(tb):.3f} s)"
        else:
            what = (f"a hole at the end of {Path(self.file).name}: the samples after seq {int(a)} "
                    f"(unit time {float(ta):.3f} s)")
        return f"{what}: {where}, {self.why}"

    def to_json(self) -> dict[str, Any]:
        return {"file": Path(self.file).name, "at_byte": self.at_byte, "bytes": self.n_bytes, "why": self.why,
                "log_time_ns": list(self.log_time_ns) if self.log_time_ns else None, "units": self.units}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Hole":
        lt = d.get("log_time_ns")
        return cls(str(d.get("file", "")), int(d.get("at_byte", 0)), int(d.get("bytes", 0)), str(d.get("why", "")),
                   tuple(lt) if lt else None, dict(d.get("units") or {}), recorded=True)


@dataclass
class ReadReport:
    """What reading a recording found besides the messages: files, cut tails, damage, holes, metadata."""

    files: list[str] = field(default_factory=list)
    truncated: list[str] = field(default_factory=list)    # one line per file whose tail was cut (writer killed)
    damaged: list[str] = field(default_factory=list)      # one line per damaged record (what, where, what came of it)
    holes: list[Hole] = field(default_factory=list)       # data lost in the middle (found, or recorded by a repair)
    messages: int = 0                                      # messages read
    skipped_messages: int = 0                              # messages whose channel record was lost
    truncated_bytes: int = 0                               # bytes at file ends that held no complete record
    metadata: dict[str, str] = field(default_factory=dict)  # the "fluxcal" metadata record(s)
    time: dict[str, str] = field(default_factory=dict)      # the "fluxcal.time" metadata record (log_time rule)
    arithmetic: dict[str, str] = field(default_factory=dict)  # "fluxcal.arithmetic": the machine's, when written
    repaired: dict[str, str] = field(default_factory=dict)  # "fluxcal.repair": a repaired copy's record of its cut
    recorder_gaps: list[str] = field(default_factory=list)  # one line per gap the recorder itself left (a full disk)

    @property
    def problems(self) -> list[str]:
        """What reading met in the files (a cut tail, damage, messages skipped), one line each."""
        out = list(self.truncated) + list(self.damaged)
        if self.skipped_messages:
            out.append(f"{self.skipped_messages} message(s) skipped: their channel was declared in a lost chunk")
        return out

    @property
    def warnings(self) -> list[str]:
        """The problems, then the holes (the samples lost, found now or recorded by a repair), then the recorder's
        gaps (service/io/recordings/gaps.py: found from the recording's own health)."""
        return self.problems + [h.describe() for h in self.holes] + list(self.recorder_gaps)


def raw_span(data: bytes) -> tuple[int, float, int, float] | None:
    """(first seq, its t_s, last seq, its t_s) of a fluxcal.raw.v1 payload, read from its header and arrays
    without decoding it (drivers/encoding.py has the layout); None for another payload or an empty one."""
    if len(data) < 12 or data[:4] != b"FXr0":
        return None
    n = int.from_bytes(data[8:12], "little")
    if n == 0 or len(data) < 12 + 16 * n:
        return None
    t0, t1 = struct.unpack_from("<d", data, 12)[0], struct.unpack_from("<d", data, 12 + 8 * (n - 1))[0]
    s0, s1 = struct.unpack_from("<q", data, 12 + 8 * n)[0], struct.unpack_from("<q", data, 12 + 16 * n - 8)[0]
    return s0, t0, s1, t1


class HoleTracker:
    """Fills in the holes' sample spans from the raw messages read around them: call `sync()` before each record
    (it takes the holes found since, with the last raw sample of each unit), `raw(unit, data)` for each raw message
    (the first sample after a pending hole), `finish()` at the end. Cheap per message: a message's span is read
    only when a hole needs it."""

    def __init__(self, report: ReadReport) -> None:
        self.report, self.seen = report, len(report.holes)
        self.last_message: dict[str, bytes] = {}     # each unit's last raw message holding samples
        self.pending: list[Hole] = []

    def last(self) -> dict[str, tuple[int, float]]:
        """Each unit's last raw sample read: (seq, t_s)."""
        spans = {u: raw_span(d) for u, d in self.last_message.items()}
        return {u: (s[2], s[3]) for u, s in spans.items() if s is not None}

    def sync(self) -> None:
        if len(self.report.holes) == self.seen:
            return
        for hole in self.report.holes[self.seen:]:
            if not hole.recorded:
                hole.units = {u: {"seq_before": s, "t_before": t, "seq_after": None, "t_after": None}
                              for u, (s, t) in self.last().items()}
                self.pending.append(hole)
        self.seen = len(self.report.holes)

    def raw(self, unit: str, data: bytes) -> None:
        if data[8:12] == b"\x00\x00\x00\x00":
            return                                   # no sample in it
        self.last_message[unit] = data
        if not self.pending:
            return
        span = raw_span(data)
        if span is None:
            return
        for hole in self.pending:
            side = hole.units.setdefault(unit, {"seq_before": None, "t_before": None, "seq_after": None,
                                                "t_after": None})
            if side["seq_after"] is None:
                side["seq_after"], side["t_after"] = span[0], span[1]
        self.pending = [h for h in self.pending if any(s["seq_after"] is None for s in h.units.values())]

    def finish(self) -> None:
        self.sync()
        self.pending = []


# --- the summary's index ----------------------------------------------------------------------------------

@dataclass
class _Index:
    """Where the summary says the data section's records are: {offset: (opcode, total bytes, chunk index)}, the
    data end, and every boundary a record may end on."""

    spans: dict[int, tuple[int, int, Any]]
    data_end: int
    bounds: list[int]
    schemas: list[Any]
    channels: list[Any]

    def next_bound(self, pos: int) -> int:
        k = bisect.bisect_right(self.bounds, pos)
        return self.bounds[k] if k < len(self.bounds) else self.data_end

    def among_message_indexes(self, pos: int) -> bool:
        """Whether pos lies among the message index records after a chunk."""
        return any(op == CHUNK and s + n <= pos < s + n + ci.message_index_length
                   for s, (op, n, ci) in self.spans.items())


def read_index(mm: Any, size: int) -> _Index | None:
    """The chunk, metadata and attachment index of a finished file (footer, summary whose CRC holds, offsets
    that tile the data section), or None: no footer, no summary, or one that cannot be trusted."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import AttachmentIndex, Channel, ChunkIndex, MetadataIndex, Schema

    at = size - len(MCAP_MAGIC) - _FOOTER
    if at < len(MCAP_MAGIC) or mm[at] != FOOTER or mm[size - len(MCAP_MAGIC):size] != MCAP_MAGIC:
        return None
    if int.from_bytes(mm[at + 1:at + 9], "little") != 20:
        return None
    start, _, crc = struct.unpack_from("<QQI", mm, at + RECORD_HEAD)
    if not len(MCAP_MAGIC) + _DATA_END <= start <= at:
        return None
    if crc and zlib.crc32(mm[start:at + RECORD_HEAD + 16]) != crc:
        return None
    data_end = start - _DATA_END
    if not crc and (mm[data_end] != DATA_END or int.from_bytes(mm[data_end + 1:data_end + 9], "little") != 4):
        return None
    spans: dict[int, tuple[int, int, Any]] = {}
    bounds = {len(MCAP_MAGIC), data_end}
    schemas, channels = [], []
    pos = start
    try:
        while pos < at:
            op, length = mm[pos], int.from_bytes(mm[pos + 1:pos + 9], "little")
            if pos + RECORD_HEAD + length > at:
                return None
            stream = ReadDataStream(io.BytesIO(mm[pos + RECORD_HEAD:pos + RECORD_HEAD + length]))
            if op == CHUNK_INDEX:
                ci = ChunkIndex.read(stream)
                spans[ci.chunk_start_offset] = (CHUNK, ci.chunk_length, ci)
                end = ci.chunk_start_offset + ci.chunk_length
                bounds.update((ci.chunk_start_offset, end, end + ci.message_index_length))
            elif op in (METADATA_INDEX, ATTACHMENT_INDEX):
                mi = (MetadataIndex if op == METADATA_INDEX else AttachmentIndex).read(stream)
                spans[mi.offset] = (METADATA if op == METADATA_INDEX else ATTACHMENT, mi.length, None)
                bounds.update((mi.offset, mi.offset + mi.length))
            elif op == SCHEMA:
                schemas.append(Schema.read(stream))
            elif op == CHANNEL:
                channels.append(Channel.read(stream))
            pos += RECORD_HEAD + length
    except Exception:                           # noqa: BLE001 - a summary that does not parse is no index
        return None
    ends = sorted((s, s + n) for s, (_, n, _) in spans.items())
    if not spans or any(s < len(MCAP_MAGIC) or e > data_end or s < prev
                        for (s, e), prev in zip(ends, [0] + [e for _, e in ends[:-1]])):
        return None
    return _Index(spans, data_end, sorted(b for b in bounds if b <= data_end), schemas, channels)


# --- records ------------------------------------------------------------------------------------------------

def parse_chunk(body: bytes) -> Any:
    """A Chunk record's body, whose fields must fill it exactly (a length field hit by damage shows here)."""
    from mcap.records import Chunk

    if len(body) < 40:
        raise ValueError(f"a chunk of {len(body)} bytes is shorter than its fixed fields")
    t0, t1, usize, crc, clen = struct.unpack_from("<QQQII", body, 0)
    if 40 + clen > len(body):
        raise ValueError("its compression name runs past the record")
    dlen = int.from_bytes(body[32 + clen:40 + clen], "little")
    if 40 + clen + dlen != len(body):
        raise ValueError(f"its fields take {40 + clen + dlen} bytes, the record has {len(body)}")
    return Chunk(compression=body[32:32 + clen].decode(), data=body[40 + clen:], message_end_time=t1,
                 message_start_time=t0, uncompressed_crc=crc, uncompressed_size=usize)


_MESSAGE_HEAD = struct.Struct("<BQHIQQ")     # opcode, length, channel id, sequence, log time, publish time
_RECORD = struct.Struct("<BQ")


def chunk_records(chunk: Any, channel_ids: set[int] | None = None) -> list[Any]:
    """The Schema, Channel and Message records of a chunk: mcap.stream_reader.breakup_chunk (the same
    decompression, CRC check and records) with its messages parsed by one struct call each, a quarter
    of the time per message (replay reads thousands of small messages a second of recording). The ids of the
    channels it declares go into `channel_ids`."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import get_chunk_data_stream

    stream, size = get_chunk_data_stream(chunk, validate_crc=True)
    data = stream.read(size)
    out: list[Any] = []
    pos, head = 0, _MESSAGE_HEAD.size
    while pos < size:
        if pos + _RECORD.size > size:
            raise ValueError(f"chunk: a record header cut short at byte {pos} of {size}")
        opcode, length = _RECORD.unpack_from(data, pos)
        end = pos + _RECORD.size + length
        if end > size:
            raise ValueError(f"chunk: a record of {length} bytes at byte {pos} runs past the chunk's {size}")
        if opcode == MESSAGE:
            if length < head - _RECORD.size:
                raise ValueError(f"chunk: a message record of {length} bytes at byte {pos}")
            _, _, channel, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, pos)
            out.append(Message(channel_id=channel, log_time=log_time, data=data[pos + head:end],
                               publish_time=publish_time, sequence=sequence))
        elif opcode in (CHANNEL, SCHEMA):
            body = ReadDataStream(io.BytesIO(data[pos + _RECORD.size:end]))
            out.append(Channel.read(body) if opcode == CHANNEL else Schema.read(body))
            if opcode == CHANNEL and channel_ids is not None:
                channel_ids.add(out[-1].id)
        pos = end                                  # other records inside a chunk: skipped, as breakup_chunk does
    return out


def _message_index_ok(body: bytes) -> bool:
    """A message index record's body: u16 channel id, u32 byte length of its (u64, u64) entries, the entries."""
    n_bytes = int.from_bytes(body[2:6], "little") if len(body) >= 6 else -1
    return n_bytes == len(body) - 6 and n_bytes % 16 == 0


def parse_record(opcode: int, body: bytes, channel_ids: set[int] | None = None) -> list[Any]:
    """The records a data-section record holds (a chunk's, broken up), checked as far as the record allows
    (a chunk's fields fill it and its CRC holds, an attachment's CRC holds, metadata fills its record);
    ValueError or the decoder's own exception when damaged. The channels declared go into `channel_ids`."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema

    if opcode == CHUNK:
        return chunk_records(parse_chunk(body), channel_ids)
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == MESSAGE:
        if len(body) < 22:
            raise ValueError(f"a message record of {len(body)} bytes")
        return [Message.read(stream, len(body))]
    if opcode == ATTACHMENT:
        crc = int.from_bytes(body[-4:], "little") if len(body) >= 4 else 0
        if crc and zlib.crc32(body[:-4]) != crc:
            raise ValueError("its CRC does not match its contents")
    rec = {HEADER: Header.read, SCHEMA: Schema.read, CHANNEL: Channel.read, METADATA: Metadata.read,
           ATTACHMENT: Attachment.read}[opcode](stream)
    if stream.count != len(body):
        raise ValueError(f"its fields take {stream.count} bytes, the record has {len(body)}")
    if opcode == CHANNEL and channel_ids is not None:
        channel_ids.add(rec.id)
    return [rec]


def _all_zero(mm: Any, pos: int, size: int) -> bool:
    step = 1 << 20
    return all(mm[a:min(a + step, size)].count(0) == min(a + step, size) - a for a in range(pos, size, step))
