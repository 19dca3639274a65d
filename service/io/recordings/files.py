"""The files of one MCAP logger, one open at a time: names that never overwrite another run's, the header
(schemas, channels, metadata: "fluxcal" and this machine's "fluxcal.arithmetic"), what has surely reached the
disk, cutting a failed file back to its last complete chunk, and the footer. Bytes in, bytes out: no policy
(McapLogger retries and rotates)."""

from __future__ import annotations

import errno
import json
import os
import time
from pathlib import Path
from typing import Any, Callable, Sequence

from mcap.writer import CompressionType, Writer

from fluxcal.service.io.encoding import CORRECTED_ENCODING, CORRECTED_LAYOUT, RAW_ENCODING, RAW_LAYOUT
from fluxcal.service.io.foxglove_schemas import json_channels

from .arithmetic import ARITHMETIC_RECORD, machine_arithmetic

#: schema encoding of the binary layouts: the schema data is the layout table as UTF-8 text
LAYOUT_SCHEMA_ENCODING = "fluxcal.layout"
COMPRESSIONS = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}
_NO_AUTO_CHUNK = 1 << 62              # the logger ends chunks itself (it must know what reached the disk)


class _CountingFile:
    """The output file as the mcap Writer sees it: every byte is written (a raw file may take fewer
    bytes than offered just before the disk fills), bytes are counted, and the position is known
    without a system call. Not an io.RawIOBase, so the Writer adds no buffer of its own."""

    def __init__(self, f: Any) -> None:
        self.f = f
        self.pos = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data).cast("B")
        total = len(view)
        while view:
            n = self.f.write(view)
            n = len(view) if n is None else n      # buffered wrappers return None or the full length
            if n <= 0:
                raise OSError(errno.EIO, "the file took no bytes")
            self.pos += n
            view = view[n:]
        return total

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        flush = getattr(self.f, "flush", None)
        if flush is not None:
            flush()

    def truncate(self, size: int) -> None:
        self.f.truncate(size)
        self.pos = size

    def fileno(self) -> int:
        return self.f.fileno()

    def close(self) -> None:
        self.f.close()


class FileDeleted(OSError):
    """The open file was deleted while it was written: `lost` messages that were in it are gone."""

    def __init__(self, path: str, lost: int) -> None:
        super().__init__(errno.ENOENT, f"{path} was deleted while it was written: the {lost:,} message(s) in it are "
                                       f"lost")
        self.lost = lost


class McapFiles:
    """The file series of one logger (see the module docstring). `open()` raises OSError, leaving no
    file behind that never got its header; `fail()` cuts the open file back and closes it."""

    def __init__(self, directory: Path, path: Path | None, *, unit: str, compression: str,
                 probe_names: Sequence[str], metadata: dict[str, str], fsync: bool,
                 opener: Callable[[Path, str], Any], arithmetic: dict[str, str] | None = None) -> None:
        self.dir, self.path, self.single_file = directory, path, path is not None
        self.unit, self.compression, self.probe_names = unit, compression, list(probe_names)
        self.metadata, self.fsync, self.opener = metadata, fsync, opener
        self.arithmetic = machine_arithmetic() if arithmetic is None else dict(arithmetic)
        self.files: list[str] = []         # every file opened, in order
        self.bytes_written = 0             # bytes that reached files (all files)
        self.writer: Writer | None = None
        self.fh: _CountingFile | None = None
        self.channels: dict[str, int] = {}
        self.good_offset = 0               # the current file up to here holds complete records only
        self.file_base = 0                 # bytes_written before the current file
        self.file_messages = 0             # messages flushed into the current file
        self.time_written = False
        self.gone = False                  # the open file was found deleted (_check_deleted)
        self._file_index = 0
        self._run_stamp: str | None = None   # the first file's UTC time: every file of the run carries it

    def _candidate(self, wall_ns: int) -> tuple[Path, str]:
        self._file_index += 1
        if self.single_file:
            assert self.path is not None
            if self._file_index == 1:
                return self.path, "wb"
            return self.path.with_name(f"{self.path.stem}_{self._file_index:04d}{self.path.suffix}"), "xb"
        # one stamp per run, so its files sort in their order whatever the host clock does (stepped back two hours by
        # a time sync, the rotated files sorted before the first, and the run replayed as two)
        if self._run_stamp is None or self._file_index == 1:
            self._run_stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(wall_ns / 1e9))
        return self.dir / f"{self.unit}-{self._run_stamp}-{self._file_index:04d}.mcap", "xb"

    def open(self, wall_ns: int, pending: Sequence[tuple[str, bytes, int, int, int]], epoch_ns: int | None) -> None:
        """Open the next file, write its header (and the time record when `epoch_ns` is given), then the
        pending messages of a file that failed."""
        raw = path = None
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            for _ in range(100):                         # never overwrite a file of another run
                path, mode = self._candidate(wall_ns)
                try:
                    raw = self.opener(path, mode)
                    break
                except FileExistsError:
                    continue
            else:
                raise OSError(errno.EEXIST, f"no free file name like {path}")
            fh = _CountingFile(raw)
            w = Writer(fh, chunk_size=_NO_AUTO_CHUNK, compression=COMPRESSIONS[self.compression])
            w.start(profile="", library="fluxcal")
            self.channels = self._header(w)
            self.writer, self.fh = w, fh
            self.time_written = False
            self.file_messages = 0
            if epoch_ns is not None:
                self.write_time_record(epoch_ns)
            self.good_offset = fh.pos
            # the unfinished chunk of a file that failed comes first
            for stream, data, log_ns, pub_ns, seq in pending:
                w.add_message(self.channels[stream], log_time=log_ns, data=data, publish_time=pub_ns, sequence=seq)
        except OSError:
            self.writer = None
            if raw is not None:
                try:
                    raw.close()
                    if path is not None:
                        path.unlink()           # a file that never got its header is no recording
                except OSError:
                    pass
            self.fh = None
            raise
        self.files.append(str(path))

    def _header(self, w: Writer) -> dict[str, int]:
        """Schemas, channels and the "fluxcal" metadata record; the channel ids by stream."""
        layout = w.register_schema(RAW_ENCODING, LAYOUT_SCHEMA_ENCODING, RAW_LAYOUT.encode())
        cor = w.register_schema(CORRECTED_ENCODING, LAYOUT_SCHEMA_ENCODING, CORRECTED_LAYOUT.encode())

        t = f"/fluxcal/{self.unit}"
        channels = {
            "raw": w.register_channel(f"{t}/raw", RAW_ENCODING, layout),
            "corrected": w.register_channel(f"{t}/corrected", CORRECTED_ENCODING, cor),
        }
        for stream, (name, schema) in json_channels(self.probe_names).items():     # the ones Foxglove decodes
            channels[stream] = w.register_channel(f"{t}/{stream}", "json",
                                                  w.register_schema(name, "jsonschema", json.dumps(schema).encode()))
        w.add_metadata("fluxcal", {"unit": self.unit, "raw_encoding": RAW_ENCODING,
                                   "corrected_encoding": CORRECTED_ENCODING, **self.metadata,
                                   "file_index": str(self._file_index)})
        # the arithmetic the corrected stream was computed with (none said: unknown); replay says when its own differs
        if self.arithmetic:
            w.add_metadata(ARITHMETIC_RECORD, self.arithmetic)
        return channels

    def write_time_record(self, epoch_ns: int) -> None:
        assert self.writer is not None
        self.writer.add_metadata("fluxcal.time", {
            "epoch_ns": str(epoch_ns),
            "log_time": "epoch_ns + round(t_s * 1e9), t_s the unit time (s) of the message's first sample",
            "publish_time": "wall clock when written, ns since 1970-01-01 UTC"})
        self.time_written = True

    def chunk_done(self, n_messages: int) -> None:
        """`n_messages` pending messages are in the file now."""
        assert self.fh is not None
        self.file_messages += n_messages
        self.good_offset = self.fh.pos
        self.bytes_written = self.file_base + self.fh.pos

    def flush(self) -> None:
        """End the chunk (mcap >= 1.6 flushes the stream too); fsync if asked. OSError passes (FileDeleted too)."""
        assert self.writer is not None and self.fh is not None
        self._check_deleted()
        self.writer.flush()
        if self.fsync:
            os.fsync(self.fh.fileno())

    def finish(self) -> None:
        """Footer and index, then close: the file is complete. OSError passes (call `fail`)."""
        assert self.writer is not None and self.fh is not None
        self._check_deleted()
        self.writer.finish()
        if self.fsync:
            os.fsync(self.fh.fileno())

    def _check_deleted(self) -> None:
        """FileDeleted where the open file was deleted while it was written (its folder or it removed: it has no name
        left): the messages in it are lost. Asked once a chunk."""
        try:
            gone = self.fh is not None and os.fstat(self.fh.fileno()).st_nlink == 0
        except (OSError, AttributeError, ValueError):
            gone = False
        if gone and self.files:
            self.gone = True                 # fail() then takes it off the files written
            raise FileDeleted(self.files[-1], self.file_messages)

    def close_finished(self) -> None:
        assert self.fh is not None
        self.file_base = self.bytes_written
        self.fh.close()
        self.writer = None
        self.fh = None

    def fail(self) -> str:
        """Cut the open file back to its last complete chunk and close it (a file with no message in it
        is removed and its number used again). Returns what could not be done, "" if all was."""
        fh, self.fh, self.writer = self.fh, None, None
        if fh is None:
            return ""
        trouble = ""
        try:
            fh.truncate(self.good_offset)      # needs no space: the file now reads like a killed writer's
        except (OSError, AttributeError, ValueError) as te:
            trouble = f"; could not cut the file back to its last chunk ({te})"
        self.bytes_written = self.file_base + self.good_offset
        try:
            fh.close()
        except OSError:
            pass
        if self.gone:
            self.files.pop()                 # deleted while written: not among the files written
            self.gone = False
        elif self.file_messages == 0 and self.files:
            try:
                Path(self.files[-1]).unlink()
                self.files.pop()
                self._file_index -= 1
                self.bytes_written -= self.good_offset
            except OSError:
                pass
        self.file_base = self.bytes_written
        return trouble
