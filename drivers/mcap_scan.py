"""One MCAP file's data-section records in file order, read past damage (fluxcal.drivers.mcap_records has the rules,
the records and the report): by the summary's index where the file has one, else record by record,
resynchronising on the next readable record after damage."""

from __future__ import annotations

import mmap
import os
from pathlib import Path
from typing import Any, Iterator

from .errors import RecordingError
from .mcap_records import (
    _RESYNC,
    ATTACHMENT,
    CHANNEL,
    CHUNK,
    DATA_END,
    FOOTER,
    HEADER,
    MCAP_MAGIC,
    MESSAGE,
    MESSAGE_INDEX,
    METADATA,
    NAMES,
    RECORD_HEAD,
    SCHEMA,
    SUMMARY_ONLY,
    Hole,
    ReadReport,
    _all_zero,
    _message_index_ok,
    _name,
    parse_record,
    read_index,
)

_DATA_RECORDS = (HEADER, SCHEMA, CHANNEL, MESSAGE, CHUNK, METADATA, ATTACHMENT)


def _u64(mm: Any, at: int) -> int:
    return int.from_bytes(mm[at:at + 8], "little")


class _FileScan:
    """The records of one mapped file (see the module docstring); `run()` yields them a list at a time (a
    chunk's, or one record), so that each record passes through one generator only (iter_file_records)."""

    def __init__(self, f: Path, mm: Any, size: int, report: ReadReport, strict: bool) -> None:
        self.f, self.mm, self.size, self.report, self.strict = f, mm, size, report, strict
        self.channel_ids: set[int] = set()
        self.index = read_index(mm, size)

    # --- what is said ---------------------------------------------------------------------------------------

    def damaged(self, what: str, pos: int, then: str) -> None:
        line = f"{self.f}: {what} at byte {pos}"
        if self.strict:
            raise RecordingError(f"{line}: the recording is damaged (fluxcal repair salvages the rest)")
        self.report.damaged.append(f"{line}: damaged (not a stopped writer): {then}")

    def lose(self, pos: int, end: int, what: str, then: str, *, samples: bool = True,
             log_time_ns: tuple[int, int] | None = None) -> None:
        """Bytes [pos, end) lost with the damaged record at pos; a Hole where they may have held samples."""
        self.damaged(what, pos, f"{end - pos} bytes lost; {then}")
        if samples:
            self.report.holes.append(Hole(str(self.f), pos, end - pos, f"lost with a damaged record ({what})",
                                          log_time_ns))

    def track(self, recs: list[Any]) -> list[Any]:
        """Records from elsewhere than parse (the summary's channels): their channel ids noted."""
        from mcap.records import Channel

        self.channel_ids.update(r.id for r in recs if isinstance(r, Channel))
        return recs

    def parse(self, op: int, body: bytes) -> list[Any]:
        recs = parse_record(op, body, self.channel_ids)
        if op == MESSAGE and recs[0].channel_id not in self.channel_ids:
            raise ValueError(f"a message on channel {recs[0].channel_id}, which no channel record declared")
        return recs

    def run(self) -> Iterator[list[Any]]:
        return self.indexed() if self.index is not None else self.linear()

    # --- a finished file with an index ----------------------------------------------------------------------

    def indexed(self) -> Iterator[list[Any]]:
        idx, mm = self.index, self.mm
        assert idx is not None
        pos = len(MCAP_MAGIC)
        while pos < idx.data_end:
            span = idx.spans.get(pos)
            if span is not None:
                yield self.by_index(pos, *span)
                pos += span[1]
                continue
            nxt = idx.next_bound(pos)
            op, length = mm[pos], _u64(mm, pos + 1)
            end = pos + RECORD_HEAD + length
            then = f"reading went on with the next indexed record at byte {nxt}"
            if end > nxt or op not in NAMES or op in SUMMARY_ONLY or op == DATA_END:
                what = f"a damaged record header ({_name(op)}, {length} bytes, past the next indexed record)"
                if idx.among_message_indexes(pos):
                    self.damaged(what, pos, f"no data lost (message indexes: chunks are read by their own records); "
                                            f"{then}")
                else:
                    self.lose(pos, nxt, what, then)
                pos = nxt
                continue
            body = mm[pos + RECORD_HEAD:end]
            if idx.among_message_indexes(pos) and op != MESSAGE_INDEX:
                self.damaged(f"a damaged record header among a chunk's message indexes (it says {_name(op)})", pos,
                             "no data lost (chunks are read by their own records)")
            elif op == MESSAGE_INDEX:
                if not _message_index_ok(body):
                    self.damaged("a malformed message index record", pos, "no data lost (chunks are read by their "
                                                                          "own records)")
            else:
                try:
                    yield self.parse(op, body)
                except Exception as e:         # noqa: BLE001 - every decoder's own exception is damage here
                    self.lose(pos, end, f"an unreadable {_name(op)} record ({type(e).__name__}: {e})",
                              f"reading went on at byte {end}")
            pos = end
        if mm[idx.data_end] != DATA_END or _u64(mm, idx.data_end + 1) != 4:
            self.damaged(f"a damaged data end record header ({_name(mm[idx.data_end])})", idx.data_end,
                         "no data lost (the summary says where the data section ends)")

    def by_index(self, pos: int, op_want: int, total: int, ci: Any) -> list[Any]:
        """The record the index places at pos: read with the index's length whatever its header says."""
        mm = self.mm
        op, length = mm[pos], _u64(mm, pos + 1)
        head_ok = op == op_want and RECORD_HEAD + length == total
        name = _name(op_want)
        try:
            recs = self.parse(op_want, mm[pos + RECORD_HEAD:pos + total])
        except Exception as e:                 # noqa: BLE001
            how = "" if head_ok else f"; its header damaged too ({_name(op)}, {length} bytes)"
            self.lose(pos, pos + total, f"an unreadable {name} record ({type(e).__name__}: {e}{how})",
                      f"reading went on with the next indexed record at byte {pos + total}", samples=op_want == CHUNK,
                      log_time_ns=(ci.message_start_time, ci.message_end_time) if ci is not None else None)
            if op_want == CHUNK:               # channels it declared stay known: the summary repeats them
                return self.track([c for c in self.index.schemas + self.index.channels  # type: ignore[union-attr]
                                   if not hasattr(c, "topic") or c.id not in self.channel_ids])
            return []
        if not head_ok:
            self.damaged(f"a {name} record whose header is damaged (it says {_name(op)}, {length} bytes; the "
                         f"summary's index: a {name} of {total - RECORD_HEAD} bytes)", pos,
                         "read by its index entry" + (", its CRC holds: nothing lost" if op_want in (CHUNK, ATTACHMENT)
                                                      else ": nothing lost"))
        return recs

    # --- no index: record by record ---------------------------------------------------------------------------

    def linear(self) -> Iterator[list[Any]]:
        mm, size, f, report = self.mm, self.size, self.f, self.report
        pos = len(MCAP_MAGIC)
        while True:
            if pos >= size:
                report.truncated.append(f"{f}: no footer: its writer was stopped (killed, power lost) or is still "
                                        f"writing; every complete chunk was read")
                return
            op = mm[pos]
            length = _u64(mm, pos + 1) if pos + RECORD_HEAD <= size else -1
            end = pos + RECORD_HEAD + length
            if length < 0 or end > size:
                q = resync(self.mm, self.size, pos + 1)
                if q is None:
                    # the writer died while writing this record: what came before it is whole
                    report.truncated.append(f"{f}: cut inside a {_name(op)} record at byte {pos} of {size}: its "
                                            f"writer was stopped; the {size - pos} bytes of that record are lost, "
                                            f"every complete chunk before it was read")
                    report.truncated_bytes += size - pos
                    return
                yield self.salvage(pos, q, f"a {_name(op)} record whose length field ({length} bytes) runs "
                                                f"past the end of the file")
                pos = q
                continue
            body = mm[pos + RECORD_HEAD:end]
            what = ""
            if op == DATA_END:
                if _data_end_in_place(mm, size, end):
                    return
                what = "a data end record before the end of the data section"
            elif op == MESSAGE_INDEX:
                if _message_index_ok(body):
                    pos = end
                    continue
                what = "a malformed message index record (a damaged record header?)"
            elif op in SUMMARY_ONLY:
                what = f"a {_name(op)} record inside the data section"
            elif op in _DATA_RECORDS:
                try:
                    recs = self.parse(op, body)
                except Exception as e:         # noqa: BLE001 - a CRC mismatch, a corrupt length or stream
                    what = f"an unreadable {_name(op)} record ({type(e).__name__}: {e})"
                else:
                    yield recs
                    pos = end
                    continue
            elif op == 0 and _all_zero(mm, pos, size):
                # a filesystem that lost power may leave a zero-filled tail
                report.truncated.append(f"{f}: ends in {size - pos} zero bytes (power lost while writing?); "
                                        f"every complete chunk before them was read")
                report.truncated_bytes += size - pos
                return
            else:
                what = f"an unknown record opcode {op:#04x}"
            q = resync(self.mm, self.size, pos + 1)
            if q is None:
                self.lose(pos, size, what, "nothing readable follows it")
                return
            yield self.salvage(pos, q, what)
            pos = q

    def salvage(self, pos: int, q: int, what: str) -> list[Any]:
        """The damaged record at pos, whose next readable record starts at q: a whole chunk in between (its
        length or opcode hit, its CRC intact) is read; else the bytes are lost."""
        try:
            recs = self.parse(CHUNK, self.mm[pos + RECORD_HEAD:q])
        except Exception:                      # noqa: BLE001
            self.lose(pos, q, what, f"reading went on at the next readable record, byte {q}")
            return []
        self.damaged(what, pos, f"a whole chunk lies between it and the next readable record at byte {q} (its "
                                f"CRC holds): read, nothing lost")
        return recs


def resync(mm: Any, size: int, start: int) -> int | None:
    """The first readable record at or after `start` (see mcap_records: a chunk whose fields fill it and
    whose CRC holds, a consistent message index, metadata or attachment, a data end), or None."""
    at = start
    while (m := _RESYNC.search(mm, at)) is not None:
        q = at = m.start()
        at += 1
        op, length = mm[q], _u64(mm, q + 1)
        end = q + RECORD_HEAD + length
        if end > size:
            continue
        follows = end == size or mm[end] in NAMES or (mm[end] == 0 and _all_zero(mm, end, size))
        if op == DATA_END:
            if length == 4 and (end == size or mm[end] in SUMMARY_ONLY or mm[end] in (SCHEMA, CHANNEL)):
                return q
            continue
        body = mm[q + RECORD_HEAD:end]
        if op == MESSAGE_INDEX:
            if _message_index_ok(body) and follows:
                return q
            continue
        try:
            parse_record(op, body)
        except Exception:                  # noqa: BLE001
            continue
        if op == CHUNK or follows:
            return q
    return None


def _data_end_in_place(mm: Any, size: int, end: int) -> bool:
    """Whether a Data End record ending at byte `end` is where the file's footer says the data section ends
    (the summary's start, or the footer itself without a summary). True when there is no footer to ask."""
    footer_len = RECORD_HEAD + 20
    at = size - len(MCAP_MAGIC) - footer_len
    if at < end:
        return True
    if mm[at] != FOOTER or mm[size - len(MCAP_MAGIC):size] != MCAP_MAGIC:
        return True
    summary_start = _u64(mm, at + RECORD_HEAD)
    return end == (summary_start or at)


def iter_file_records(path: str | Path, report: ReadReport | None = None, *, strict: bool = False) -> Iterator[Any]:
    """The data-section records of one MCAP file in file order, chunks broken up: mcap.records Header, Schema,
    Channel, Message, Metadata and Attachment objects. Stops at Data End or at the end of a file without footer
    (noted in `report.truncated`); damage goes into report.damaged and report.holes and reading goes on
    (strict=True: RecordingError at the first damage)."""
    report = report if report is not None else ReadReport()
    f = Path(path)
    try:
        fh = f.open("rb")
    except OSError as e:
        raise RecordingError(f"{f}: cannot read: {e.strerror or e}") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        magic = fh.read(len(MCAP_MAGIC))
        if magic != MCAP_MAGIC:
            if MCAP_MAGIC.startswith(magic):
                what = "empty (0 bytes)" if not size else f"cut inside its magic ({size} of {len(MCAP_MAGIC)} bytes)"
                report.truncated.append(f"{f}: {what}: its writer stopped before writing anything")
                report.truncated_bytes += size
                return
            raise RecordingError(f"{f}: not an MCAP file (starts with {magic[:8]!r})")
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            for recs in _FileScan(f, mm, size, report, strict).run():
                yield from recs
        finally:
            mm.close()
