"""Bounded reading of the files a user hands fluxcal (lab CSVs, captures, CAN logs, configurations): regular
files only, within a size limit, lines within a length limit, read in pieces so that Ctrl-C and SIGTERM stop it.

    open_regular(path, what)        a binary file object, or a DataError: a directory, FIFO, device or socket
                                    (also behind a symlink) is refused before it is opened for reading
    check_size(path, size, what)    a DataError beyond max_input_bytes() (FLUXCAL_MAX_INPUT_MB raises it)
    read_text(path, what)           the whole text of a regular file within both limits (utf-8, a BOM dropped;
                                    what is not UTF-8 refused in the piece where it is, not after the whole)
    scan_lines(path, what)          the same checks, nothing held (before a reader that reads line by line)
    check_head(path, what, problem) the file's first HEAD_BYTES judged by its reader (`problem`) before it reads
                                    the rest: a garbage file of any size is refused after at most HEAD_BYTES

`fit` on 1 GB of random bytes named .csv read it whole, then decoded it: 2.06 GB at its peak, a MemoryError under a
2.5 GB limit. Every reader (lab CSV, fluxcal MCAP, ROS 2, PX4 ULog, ArduPilot DataFlash) now calls check_head first.

Why pieces: a Python signal handler (the CLI turns SIGTERM into KeyboardInterrupt) runs only between bytecodes.
`Path.read_text()` is one C call that loops over read(2) until end of file and looks at pending signals only
when read(2) fails with EINTR, which a read of /dev/zero never does: SIGTERM waited (9 GB after 60 s). A loop
over 4 MiB pieces gives the handler a turn after each.
"""

from __future__ import annotations

import codecs
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .errors import ConfigError, DataError, FluxcalError

#: the environment variable that raises (or lowers) the size limit, in MiB
MAX_INPUT_ENV = "FLUXCAL_MAX_INPUT_MB"
#: the size limit without it: a lab CSV is held as text and parsed in memory, about 3.5 times its size in all
#: (measured: a 180 MB CSV of 2,000,000 rows, 2 probes, peaks at 640 MB resident, read in 2.6 s)
DEFAULT_MAX_INPUT_MB = 1024
#: the longest line of a text input: a 64-probe header is under 2 kB; the zero device, a binary file or one
#: without line breaks stops here at once instead of being read to its end
MAX_LINE_BYTES = 1 << 20
#: what one read takes: the handler of a signal runs between two
CHUNK_BYTES = 4 << 20
#: the most of an input read to judge whether it is what it claims to be (check_head; a text's first piece)
HEAD_BYTES = CHUNK_BYTES

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def max_input_bytes() -> int:
    """The size limit: FLUXCAL_MAX_INPUT_MB MiB, else DEFAULT_MAX_INPUT_MB."""
    text = os.environ.get(MAX_INPUT_ENV)
    if text is None or not text.strip():
        return DEFAULT_MAX_INPUT_MB << 20
    try:
        mb = int(text.strip())
    except ValueError:
        mb = 0
    if mb < 1:
        raise ConfigError(f"{MAX_INPUT_ENV}: {text!r} is not allowed (allowed: a whole number of MiB, at least 1; "
                          f"default {DEFAULT_MAX_INPUT_MB})")
    return mb << 20


def _mib(n: int) -> str:
    if n % (1 << 20) == 0:
        return f"{n >> 20:,} MiB"
    return f"{n / (1 << 20):,.1f} MiB" if n >= 10 << 20 else f"{n:,} bytes"


def not_regular(path: Path, mode: int, error: type[FluxcalError] = DataError) -> FluxcalError | None:
    """The refusal (an `error`) of a file of this st_mode that is not a regular file, naming what it is (and the
    target of a symlink); None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    target = ""
    if path.is_symlink():
        try:
            target = f" ({os.path.realpath(path)})"
        except OSError:
            pass
    return error(f"{path}: is {kind}{target}, not a regular file: give a file (nothing was read)")


def open_regular(path: str | Path, what: str = "input", error: type[FluxcalError] = DataError) -> BinaryIO:
    """Open a regular file for reading in binary. Anything else is refused before it is opened for reading
    (stat first: opening a FIFO without a writer blocks, and opening a device can act on it), and again from
    the open descriptor (O_NONBLOCK: a FIFO put in its place meanwhile cannot hang the open)."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise error(f"{p}: no such file") from None
    except OSError as e:
        raise error(f"{p}: cannot read {what}: {e.strerror}") from None
    refused = not_regular(p, st.st_mode, error)
    if refused:
        raise refused
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise error(f"{p}: cannot read {what}: {e.strerror}") from None
    try:
        refused = not_regular(p, os.fstat(fd).st_mode, error)
        if refused:
            raise refused
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_small(path: str | Path, what: str, limit: int, error: type[FluxcalError], too_large: str) -> bytes:
    """The bytes of a small file (a configuration, a calibration), refused as open_regular refuses, when missing
    ("{path}: {what} not found") or beyond `limit` bytes ("{path}: " + too_large); at most limit + 1 bytes are
    read, so /dev/zero behind a link cannot hold the reader."""
    p = Path(path)
    if not p.exists() and not p.is_symlink():
        raise error(f"{p}: {what} not found")
    with open_regular(p, f"the {what}", error) as f:
        try:
            data = f.read(limit + 1)
        except OSError as e:
            raise error(f"{p}: cannot read the {what}: {e.strerror or e}") from None
    if len(data) > limit:
        raise error(f"{p}: {too_large}")
    return data


def check_size(path: str | Path, size: int, what: str = "input") -> None:
    """A DataError when `size` bytes is beyond the size limit, saying the limit and how to raise it."""
    limit = max_input_bytes()
    if size > limit:
        need = -(-size // (1 << 20))
        raise DataError(f"{path}: {_mib(size)} is beyond the size limit for {what}, {_mib(limit)} (allowed: up to "
                        f"{_mib(limit)}; it is read into memory): to read it anyway set {MAX_INPUT_ENV}={need} or "
                        f"more, or split it")


def read_bytes(path: str | Path, what: str = "input", *, max_line: int | None = MAX_LINE_BYTES,
               keep: bool = True, text: bool = False, head: Callable[[bytes, bool], str | None] | None = None
               ) -> bytearray:
    """The whole content of a regular file within the size limit, read in CHUNK_BYTES pieces; with max_line, a
    line (between two \\n or \\r) longer than it is a DataError as soon as the piece holding it is read; with
    text, bytes that are not UTF-8 likewise; with `head`, the first piece judged as check_head judges it before
    the next is read. keep=False: only the checks, nothing held (and an empty result)."""
    p = Path(path)
    limit = max_input_bytes()
    utf8 = codecs.getincrementaldecoder("utf-8")() if text else None
    with open_regular(p, what) as f:
        size = os.fstat(f.fileno()).st_size
        check_size(p, size, what)
        data = bytearray()
        done = 0             # bytes read
        run = 0              # bytes since the last line break
        lines = 0            # line breaks so far (\r\n one break, as str.splitlines counts them)
        last_cr = False      # the previous piece ended in \r
        while True:
            piece = _read_chunk(f, CHUNK_BYTES)
            if not piece:
                return data
            done += len(piece)
            if done > limit:                                    # the file grew while it was read
                check_size(p, done, what)
            if utf8 is not None:
                _utf8(utf8, piece, done - len(piece), p, what)
            if head is not None and done == len(piece):
                _judge(p, what, head, piece, done >= size, DataError)
            if max_line is not None:
                a = np.frombuffer(piece, np.uint8)
                at = np.flatnonzero((a == 0x0A) | (a == 0x0D))
                # each line ending in this piece, without its break; then the one still open at its end
                open_end = len(piece) - 1 - (int(at[-1]) if at.size else -1 - run)
                lengths = np.append(np.diff(at, prepend=-1 - run) - 1, open_end)
                after_cr = a[np.maximum(at - 1, 0)] == 0x0D
                after_cr[at == 0] = last_cr
                new_line = ~((a[at] == 0x0A) & after_cr)         # \r\n: the \n starts no line of its own
                k = int(np.argmax(lengths))
                if lengths[k] > max_line:
                    line = lines + int(np.count_nonzero(new_line[:k])) + 1
                    raise DataError(f"{p}: line {line} is longer than {_mib(max_line)} without a line break "
                                    f"(allowed: lines up to {_mib(max_line)}): not {what} "
                                    f"(a binary file, or one without line breaks?)")
                run = int(lengths[-1])
                lines += int(np.count_nonzero(new_line))
                last_cr = bool(a[-1] == 0x0D)
            if keep:
                data += piece


def scan_lines(path: str | Path, what: str = "input") -> None:
    """The checks of read_bytes (a regular file, the size and line-length limits) without holding the file."""
    read_bytes(path, what, keep=False)


def _read_chunk(f: BinaryIO, n: int) -> bytes:
    return f.read(n)


def _utf8(decoder: codecs.IncrementalDecoder, piece: bytes, at: int, p: Path, what: str) -> None:
    """A DataError where `piece` (at byte `at` of the file) is not UTF-8 (the decoded text is not kept)."""
    try:
        decoder.decode(piece)
    except UnicodeDecodeError as e:
        raise DataError(f"{p}: not a text file ({e.reason} at byte {at + e.start}): not {what}") from None


def read_text(path: str | Path, what: str = "input", head: Callable[[bytes, bool], str | None] | None = None) -> str:
    """read_bytes as UTF-8 text (a byte-order mark dropped); a file that is not UTF-8 is a DataError, said in the
    piece where it is; `head` judges the first piece (check_head) before the rest is read."""
    data = read_bytes(path, what, text=True, head=head)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DataError(f"{path}: not a text file ({e.reason} at byte {e.start}): not {what}") from None


def check_head(path: str | Path, what: str, problem: Callable[[bytes, bool], str | None],
               error: type[FluxcalError] = DataError) -> None:
    """Refuse `path` ("{path}: not {what}: {why}") when `problem(head, whole)` says what is wrong with its first
    HEAD_BYTES (`whole`: they are all of the file); `problem` may raise a DataError of its own, more precise. A
    regular file only (open_regular). Every reader calls it before it reads the rest (the module docstring)."""
    p = Path(path)
    with open_regular(p, what, error) as f:
        try:
            head = _read_chunk(f, HEAD_BYTES + 1)
        except OSError as e:
            raise error(f"{p}: cannot read {what}: {e.strerror or e}") from None
    _judge(p, what, problem, head[:HEAD_BYTES], len(head) <= HEAD_BYTES, error)


def _judge(p: Path, what: str, problem: Callable[[bytes, bool], str | None], head: bytes, whole: bool,
           error: type[FluxcalError]) -> None:
    why = problem(head, whole)
    if why:
        raise error(f"{p}: not {what}: {why}")


def magic(prefix: bytes, name: str) -> Callable[[bytes, bool], str | None]:
    """A check_head judge: the file begins with `prefix`, as every `name` does."""
    def problem(head: bytes, whole: bool) -> str | None:
        if head.startswith(prefix):
            return None
        shown = head[:len(prefix)].hex(" ") or "nothing (the file is empty)"
        return f"it begins {shown}, where {name} begins {prefix.hex(' ')}"
    return problem
