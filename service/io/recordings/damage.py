"""A flight log that is damaged or cut short, said once in fluxcal's words.

The readers of other ecosystems' logs print what they find on the process's own output: pyulog "File corruption
detected ..." on stdout, pymavlink's C indexer a line per unreadable byte on the stderr file descriptor and its
reader "Skipped N bad bytes ..." on stderr. That broke `--json` (one object on stdout) and said nothing a user could act
on. `library_output()` takes what they print while they read; the readers say what it means as one warning each:

    library_output()                     context: the lines a reader library printed, off stdout and stderr
    ulog_walk(path) -> (int, int|None)   bytes missing from a ULog's last message, where it is first damaged
    dataflash_cut(reader) -> int         the same of a DataFlash log read by pymavlink
    skipped_bytes(lines) -> (n, places)  what pymavlink skipped as unreadable
    damage_note(path, ...) -> [str]      the warning: what was lost, what was read
    damage_said(...) -> str              its clause, for a refusal that rests on it; damage_warning(path, clause)
"""

from __future__ import annotations

import contextlib
import io
import mmap
import os
import re
import struct
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any


def _flush_c_stdio() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)          # what a C extension wrote to its stdio buffers
    except (OSError, AttributeError, TypeError):
        pass


@contextlib.contextmanager
def library_output() -> Iterator[list[str]]:
    """While the block runs, what is printed to stdout or stderr (from Python and from C, at the file descriptors) is
    kept off the process's output; the list yielded holds its lines once the block ends. Where the descriptors cannot
    be redirected (none open), only Python's streams are."""
    lines: list[str] = []
    py_out, py_err = io.StringIO(), io.StringIO()
    saved: list[tuple[int, int]] = []
    with tempfile.TemporaryFile() as tmp:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        for fd in (1, 2):
            try:
                saved.append((fd, os.dup(fd)))
                os.dup2(tmp.fileno(), fd)
            except OSError:
                continue
        try:
            with contextlib.redirect_stdout(py_out), contextlib.redirect_stderr(py_err):
                yield lines
        finally:
            for stream in (sys.__stdout__, sys.__stderr__):     # a library holding the process's own streams
                with contextlib.suppress(Exception):
                    stream.flush()
            _flush_c_stdio()
            for fd, keep in saved:
                os.dup2(keep, fd)
                os.close(keep)
            tmp.seek(0)
            text = py_out.getvalue() + py_err.getvalue() + tmp.read().decode("utf-8", "replace")
            lines.extend(line for line in text.splitlines() if line.strip())


#: the ULog message types (pyulog.core.ULog.MSG_TYPE_*): a header of another is no message's
ULOG_TYPES = frozenset(b"FDIMPQARSOLCB")


def ulog_walk(path: Path) -> tuple[int, int | None]:
    """(bytes missing from the last message, the offset of the first header that is no ULog message's or None) of the
    ULog at `path`: its messages (a 3-byte header: size, type) walked from the end of its 16-byte file header; the
    walk stops at such a header (what follows is damaged, and where the next message starts is not known)."""
    size = path.stat().st_size
    if size <= 16:
        return 0, None
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        pos, unpack = 16, struct.Struct("<HB").unpack_from
        while pos + 3 <= size:
            length, kind = unpack(buf, pos)
            if kind not in ULOG_TYPES:
                return 0, pos
            pos += 3 + length
    if pos == size:
        return 0, None
    return (pos - size if pos > size else 3 - (size - pos)), None       # a body missing, or part of a header


def dataflash_cut(reader: Any) -> int:
    """Bytes missing from the last message of a DataFlash log (pymavlink's DFReader after its index): the last
    message indexed runs past the end, or the log ends on a message's header without its body. Trailing bytes that
    are no message's start (a block log's padding) are not a cut."""
    last = max(((offs[-1], t) for t, offs in enumerate(getattr(reader, "offsets", []) or []) if offs), default=None)
    if last is None or last[1] not in reader.formats:
        return 0
    fmt = reader.formats[last[1]]
    end = last[0] + fmt.len
    if end > reader.data_len:
        return end - reader.data_len
    tail = bytes(reader.data_map[end:end + 3])
    if len(tail) >= 2 and tail[:2] == bytes([reader.HEAD1, reader.HEAD2]):
        kind = tail[2] if len(tail) > 2 else None
        want = reader.formats[kind].len if kind in reader.formats else 3
        return max(want - (reader.data_len - end), 1)
    return 0


_SKIPPED = re.compile(r"Skipped (\d+) bad bytes")


def skipped_bytes(lines: list[str]) -> tuple[int, int]:
    """(bytes, places) pymavlink skipped as unreadable, from what it printed."""
    found = [int(m.group(1)) for m in map(_SKIPPED.search, lines) if m]
    return sum(found), len(found)


def damage_note(path: Path, *, cut: int = 0, skipped: tuple[int, int] = (0, 0), corrupt: bool = False,
                at: int | None = None) -> list[str]:
    """The warning of a damaged or cut log (none where it is whole)."""
    return damage_warning(path, damage_said(cut=cut, skipped=skipped, corrupt=corrupt, at=at))


def damage_warning(path: Path | str, said: str) -> list[str]:
    """The warning of damage_said's clause (none for "")."""
    return [f"{path}: {said}. Copy the log again from the vehicle if it can be; the samples read are fitted as they "
            f"are"] if said else []


def damage_said(*, cut: int = 0, skipped: tuple[int, int] = (0, 0), corrupt: bool = False,
                at: int | None = None) -> str:
    """What is wrong with a damaged or cut log, in one clause ("" where it is whole); at: the byte where the damage
    was first found."""
    said = []
    if corrupt or at is not None:
        said.append(f"damaged{f' at byte {at:,}' if at is not None else ''}: the reader found messages it could not "
                    f"decode and read on from the next it could; what the damaged parts held is lost")
    if skipped[0]:
        said.append(f"damaged: {skipped[0]:,} byte(s) in {skipped[1]:,} place(s) are no message and were skipped; "
                    f"the messages there are lost")
    if cut:
        said.append(f"cut short: its last message lacks {cut:,} byte(s) (the copy ended early, or the logger was "
                    f"stopped by a power loss); everything before it is read")
    return "; ".join(said)
