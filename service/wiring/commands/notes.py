"""What the batch commands share besides the input preparation: outputs checked before any work, --skip's spans
parsed (a field's scale is said by fluxcal.service.wiring.scale_notes)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np


def check_output_file(path: Any, flag: str = "--out", *, suffixes: Sequence[str] = (), example: str = "out.mcap",
                      not_this: Any = None) -> None:
    """Refuse (DataError, exit 2), before any work, an output file that cannot be written: a folder (or a name
    ending in '/'), a missing folder, one this user may not write in, a suffix other than `suffixes` (when given),
    or the input itself (`not_this`)."""
    import os
    import tempfile
    from pathlib import Path

    from fluxcal.drivers.errors import DataError

    p = Path(path)
    if p.is_dir() or str(path).endswith(("/", os.sep)):
        raise DataError(f"{flag} {path}: is a folder; give a file name in it (e.g. {p / example})")
    if suffixes and p.suffix.lower() not in suffixes:
        raise DataError(f"{flag} {p}: this writes {' or '.join(suffixes)} files, not "
                        f"{p.suffix or 'a name without a suffix'} (allowed: {', '.join('FILE' + x for x in suffixes)})")
    if not_this is not None and p.exists() and p.resolve() == Path(not_this).resolve():
        raise DataError(f"{flag} {p}: is the input itself; give another file")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise DataError(f"{flag} {p}: folder {parent} does not exist")
    try:                                  # a file made and removed beside it: what the writer will meet (root too)
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".fluxcal-check-"):
            pass
    except OSError as e:
        raise DataError(f"{flag} {p}: cannot write in {parent} ({e.strerror or e})") from None
    if p.exists() and not os.access(p, os.W_OK):
        raise DataError(f"{flag} {p}: the file exists and is not writable")


def check_output_folder(path: Any, flag: str) -> None:
    """Refuse (DataError, exit 2), before any work, an output folder that cannot be made or written in. The
    folder itself is made when missing, as an output file is; the folder that holds it must exist, as for
    check_output_file (a typo must not grow a tree of folders)."""
    import tempfile
    from pathlib import Path

    from fluxcal.drivers.errors import DataError
    from fluxcal.drivers.outputs import refuse_linked_folder

    p = Path(path)
    refuse_linked_folder(p, flag)
    if p.exists() and not p.is_dir():
        raise DataError(f"{flag} {p}: is a file; give a folder (made if missing, in a folder that exists)")
    parent = p.parent if str(p.parent) else Path(".")
    if not p.exists() and not parent.is_dir():
        raise DataError(f"{flag} {p}: " + (f"{parent} is a file, not a folder" if parent.exists() else
                                            f"folder {parent} does not exist"))
    try:
        p.mkdir(exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=p, prefix=".fluxcal-check-"):
            pass
    except OSError as e:
        raise DataError(f"{flag} {p}: cannot write there ({e.strerror or e})") from None


def parse_spans(text: str) -> list[tuple[float, float]]:
    """--skip's value: T0-T1[,T0-T1 ...] in seconds of the data's own time (argparse type; ValueError says why)."""
    import argparse
    import re

    spans = []
    for part in text.split(","):
        m = re.fullmatch(r"\s*([-+]?[0-9.]+(?:[eE][-+]?\d+)?)\s*-\s*([-+]?[0-9.]+(?:[eE][-+]?\d+)?)\s*", part)
        lo, hi = (float(m[1]), float(m[2])) if m else (float("nan"), float("nan"))
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise argparse.ArgumentTypeError(f"{part.strip()!r}: a stretch of time T0-T1 in seconds of the data's "
                                             f"own time, T1 > T0 (several: 10-20,95.5-140)")
        spans.append((lo, hi))
    return spans
