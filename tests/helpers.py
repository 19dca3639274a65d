"""Helpers several test modules share: reading a source until it has given enough or all it has, writing
blocks to a recording, a recording written again as the service rotates a long run, and a recording refused."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import pytest

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import RecordingError
from fluxcal.service.io.recordings.writer import McapLogger


def read_samples(src, k: int, timeout: float = 5.0) -> SampleBlock:
    """At least k samples from a live source (fewer if `timeout` passes first), as one block."""
    blocks, got, deadline = [], 0, time.monotonic() + timeout
    while got < k and time.monotonic() < deadline:
        b = src.read(timeout=0.2)
        if b is not None:
            blocks.append(b)
            got += len(b)
    return SampleBlock.concat(blocks) if blocks else SampleBlock.empty(src.n_probes)


def drain(src) -> list[SampleBlock]:
    """Every block a finite source gives until it is exhausted."""
    out = []
    while not src.exhausted:
        b = src.read(0.1)
        if b is not None:
            out.append(b)
    return out


def write_raw(directory: Path, blocks: list[SampleBlock], **logger_kw: Any) -> McapLogger:
    """The blocks written by an McapLogger (unit "u") into `directory`, closed; the logger, for its files."""
    log = McapLogger(directory, unit="u", **logger_kw)
    for b in blocks:
        log.write_raw(b)
    log.close()
    return log


def write_rotated(source: Path, folder: Path, unit: str = "grad1") -> list[Path]:
    """A recording written again into `folder` as the service writes a long run: rotated into several files of
    one run, with its stored configuration and arithmetic (its corrected stream was computed where it was made)."""
    from fluxcal.service.io.recordings.reader import read_recording

    rec = read_recording(source)
    keep = {k: v for k, v in rec.metadata.items()
            if k in ("n_probes", "lsb_nT", "probe_names", "positions_m", "config")}
    log = McapLogger(folder, unit=unit, rotate_mb=0.12, chunk_size=16 << 10, metadata=keep, arithmetic=rec.arithmetic)
    for ev in rec.events:
        log.write_event(ev)
    cor = iter(rec.corrected_blocks)
    nxt = next(cor, None)
    for b in rec.raw_blocks:
        log.write_raw(b)
        while nxt is not None and nxt.seq[-1] <= b.seq[-1]:
            log.write_corrected(nxt)
            nxt = next(cor, None)
    log.close()
    return sorted(folder.glob(f"{unit}-*.mcap"))


def assert_refused(read: Callable[[Path], Any], path: Path, match: str) -> None:
    """`read(path)` raises RecordingError saying `match`."""
    with pytest.raises(RecordingError, match=match):
        read(path)
