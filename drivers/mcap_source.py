"""Reading fluxcal MCAP recordings: the replay Source and a record iterator shared with `service.recording`.

A recording is one .mcap file or a directory of rotated files (read in name order). Files are
streamed record by record, so a file whose writer was killed (no footer, a cut chunk) yields every
complete chunk and reports the cut tail instead of failing.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from .block import SampleBlock
from .encoding import decode_raw
from .errors import RecordingError
from .source import Source

RAW_ENCODING = "fluxcal.raw.v1"


@dataclass
class McapRecord:
    topic: str
    encoding: str
    data: bytes
    log_time_ns: int


@dataclass
class ReadReport:
    files: list[str] = field(default_factory=list)
    truncated: list[str] = field(default_factory=list)     # files whose tail was cut (writer killed)
    metadata: dict[str, str] = field(default_factory=dict)


def recording_files(path: str | Path) -> list[Path]:
    p = Path(path)
    if p.is_dir():
        files = sorted(p.glob("*.mcap"))
        if not files:
            raise RecordingError(f"{p}: no .mcap files in this directory")
        return files
    if not p.exists():
        raise RecordingError(f"{p}: no such recording")
    return [p]


def iter_records(path: str | Path, report: ReadReport | None = None) -> Iterator[McapRecord]:
    """Every message of the recording in file order; metadata records go into `report`."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Metadata
    from mcap.stream_reader import StreamReader

    report = report if report is not None else ReadReport()
    for f in recording_files(path):
        report.files.append(str(f))
        channels: dict[int, Channel] = {}
        n = 0
        try:
            with f.open("rb") as fh:
                magic = fh.read(8)
                if len(magic) < 8 and b"\x89MCAP0\r\n".startswith(magic):
                    report.truncated.append(f"{f}: empty (its writer stopped before writing anything)")
                    continue
                if magic != b"\x89MCAP0\r\n":
                    raise RecordingError(f"{f}: not an MCAP file")
                fh.seek(0)
                try:
                    for rec in StreamReader(fh, skip_magic=False).records:
                        if isinstance(rec, Channel):
                            channels[rec.id] = rec
                        elif isinstance(rec, Message):
                            ch = channels.get(rec.channel_id)
                            if ch is not None:
                                n += 1
                                yield McapRecord(ch.topic, ch.message_encoding, rec.data, rec.log_time)
                        elif isinstance(rec, Metadata) and rec.name == "fluxcal":
                            report.metadata.update(rec.metadata)
                except (McapError, EOFError, ValueError, OSError, struct.error) as e:
                    # a killed writer leaves no footer and may cut a chunk: keep what was complete
                    report.truncated.append(f"{f}: {type(e).__name__}: {e}".strip())
        except OSError as e:
            raise RecordingError(f"{f}: cannot read: {e.strerror}") from None


def iter_raw_blocks(path: str | Path, report: ReadReport | None = None) -> Iterator[SampleBlock]:
    for rec in iter_records(path, report):
        if rec.encoding == RAW_ENCODING:
            yield decode_raw(rec.data)


class McapSource(Source):
    """Replays the raw channel of a recording as the same SampleBlocks it recorded."""

    def __init__(self, path: str | Path) -> None:
        self.report = ReadReport()
        first = None
        self._it = iter_raw_blocks(path, self.report)
        for first in self._it:
            break
        if first is None:
            raise RecordingError(f"{path}: no raw samples in this recording")
        super().__init__(first.n_probes)
        self._pending: SampleBlock | None = first
        self._done = False
        self.path = str(path)

    @property
    def exhausted(self) -> bool:
        return self._done

    def _read_block(self, timeout: float | None) -> SampleBlock | None:
        if self._pending is not None:
            b, self._pending = self._pending, None
        else:
            b = next(self._it, None)
        if b is None:
            self._done = True
            return None
        self.counters.frames_accepted += b.n_samples
        return b


def open_source(path: str | Path, **_: object) -> McapSource:
    return McapSource(path)


def metadata_json(report: ReadReport, key: str, default=None):
    text = report.metadata.get(key)
    return default if text is None else json.loads(text)
