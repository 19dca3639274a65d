"""Whole recordings for `fit`, `diagnose` and `replay`: read, and rebuild a killed file."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.block import SampleBlock
from drivers.encoding import decode_raw
from drivers.errors import DataError, RecordingError
from drivers.mcap_source import RAW_ENCODING, ReadReport, iter_records

from .encoding import decode_corrected
from .mcap_sink import CORRECTED_ENCODING
from .outputs import CorrectedBlock


@dataclass
class Recording:
    raw_blocks: list[SampleBlock]
    corrected_blocks: list[CorrectedBlock]
    events: list[dict[str, Any]]
    calibration: list[dict[str, Any]]
    metadata: dict[str, str]
    files: list[str] = field(default_factory=list)
    truncated: list[str] = field(default_factory=list)

    @property
    def raw(self) -> SampleBlock:
        return SampleBlock.concat(self.raw_blocks)

    @property
    def n_probes(self) -> int:
        return self.raw_blocks[0].n_probes

    @property
    def probe_names(self) -> list[str]:
        text = self.metadata.get("probe_names")
        return json.loads(text) if text else [f"s{k + 1}" for k in range(self.n_probes)]


def read_recording(path: str | Path) -> Recording:
    report = ReadReport()
    raw, cor, events, cal = [], [], [], []
    try:
        for rec in iter_records(path, report):
            if rec.encoding == RAW_ENCODING:
                raw.append(decode_raw(rec.data))
            elif rec.encoding == CORRECTED_ENCODING:
                cor.append(decode_corrected(rec.data))
            elif rec.topic.endswith("/events"):
                events.append(json.loads(rec.data))
            elif rec.topic.endswith("/calibration"):
                cal.append(json.loads(rec.data))
    except (DataError, json.JSONDecodeError) as e:
        raise RecordingError(f"{path}: damaged recording: {e}") from None
    if not raw:
        raise RecordingError(f"{path}: no raw samples in this recording"
                             + (f" ({'; '.join(report.truncated)})" if report.truncated else ""))
    return Recording(raw, cor, events, cal, report.metadata, report.files, report.truncated)


def repair_recording(src: str | Path, dst: str | Path) -> Recording:
    """Rebuild an indexed file (with footer) from one whose writer was killed."""
    from .mcap_sink import McapLogger

    rec = read_recording(src)
    d = Path(dst)
    log = McapLogger(d.parent, unit=rec.metadata.get("unit", "unit"), filename=d.name,
                     metadata={k: v for k, v in rec.metadata.items() if k != "unit"}, flush_interval_s=1e9)
    try:
        for ev in rec.events:
            log.write_event(ev)
        for b in rec.raw_blocks:
            log.write_raw(b)
        for c in rec.corrected_blocks:
            log.write_corrected(c)
        for c in rec.calibration:
            log.write_calibration(c)
    finally:
        log.close()
    return rec
