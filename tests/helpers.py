"""Helpers several test modules share: reading a source until it has given enough or all it has, writing
blocks to a recording, and a recording refused."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import pytest

from drivers.block import SampleBlock
from drivers.errors import RecordingError
from service.io.recordings.writer import McapLogger


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


def assert_refused(read: Callable[[Path], Any], path: Path, match: str) -> None:
    """`read(path)` raises RecordingError saying `match`."""
    with pytest.raises(RecordingError, match=match):
        read(path)
