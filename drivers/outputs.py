"""How every writer of fluxcal opens its output: never through a symbolic link planted at the output's path.

    replacing(path, mode)      a new file beside `path` under a name nobody could plant (O_EXCL), renamed onto
                               `path` when the block ends without error (a link there is replaced, its target
                               untouched), removed otherwise
    temp_beside(path)          such a new, empty file, for a writer that opens by name (renamed by the caller)
    open_output(path, mode)    open a file of a fixed name without following a link: "xb" fails on anything there,
                               "wb" replaces a link (removed first) and truncates a regular file
    refuse_linked_folder(path) an output folder that is a symbolic link is a DataError: files are never written
                               into the folder a link points at

`replay --out LINK` wrote through a planted link and overwrote its target, and `--report LINKDIR` wrote into the
linked folder, where every other writer replaced the link; now all of them go through here.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from .errors import DataError


def _as_users_file(path: str | Path) -> None:
    """The permissions of any file the user writes (mkstemp makes it 0600)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def temp_beside(path: str | Path) -> Path:
    """A new empty file in `path`'s folder, named `.NAME.XXXXXXXX.SUFFIX` (created exclusively: no link planted in
    advance can be at that name), with the user's usual permissions; the caller writes it and renames it."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(dir=p.parent if str(p.parent) else ".", prefix=f".{p.stem}.", suffix=p.suffix)
    os.close(fd)
    _as_users_file(tmp)
    return Path(tmp)


@contextmanager
def replacing(path: str | Path, mode: str = "wb", *, encoding: str | None = None, fsync: bool = False,
              newline: str | None = None) -> Iterator[IO[Any]]:
    """Write `path` whole or not at all, never through a link (the module docstring); fsync before the rename when
    asked (the calibration in use: a crash leaves the old file or the new one)."""
    tmp = temp_beside(path)
    try:
        with open(tmp, mode, encoding=None if "b" in mode else (encoding or "utf-8"), newline=newline) as f:
            yield f
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def open_output(path: str | Path, mode: str = "wb", buffering: int = 0) -> IO[bytes]:
    """A binary file at `path` (unbuffered unless asked) opened without following a symbolic link (O_NOFOLLOW):
    with "xb", FileExistsError when anything is there (a link too); with "wb", a link there is removed first, its
    target untouched, and a regular file truncated."""
    if mode not in ("wb", "xb"):
        raise ValueError(f"open_output: mode {mode!r} (allowed: 'wb', 'xb')")
    flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    flags |= os.O_EXCL if mode == "xb" else os.O_TRUNC
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as e:
        if mode == "xb" or e.errno != errno.ELOOP:
            raise
        os.unlink(path)                              # a link: replaced, never written through
        fd = os.open(path, flags | os.O_EXCL, 0o666)
    return os.fdopen(fd, "wb", buffering=buffering)


def refuse_linked_folder(path: str | Path, flag: str) -> None:
    """DataError when the output folder `path` is a symbolic link (naming where it points)."""
    p = Path(path)
    if p.is_symlink():
        raise DataError(f"{flag} {p}: is a symbolic link (to {os.path.realpath(p)}): an output folder is never "
                        f"written through a link; give the folder itself")
