"""Which reader a file needs, told by its content (formats.detect_format): a lab CSV, a fluxcal MCAP recording (a
file, or a folder of one run's rotated files), or another ecosystem's log (a ROS 2 bag, a PX4 ULog, an ArduPilot
DataFlash log); each read into one LabData."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError
from fluxcal.drivers.inputs import not_regular

from .labdata import LabData, check_one_run, check_time_increases, keep_every, load_csv


def load_data(path: str | Path, *, max_samples: int | None = None, max_probe_samples: int | None = None,
              mapping: Any = None) -> LabData:
    """Load a lab CSV, an MCAP recording written by fluxcal (a file, or a directory of one run's rotated
    files: `-0001.mcap`, `-0002.mcap`, ...), or another ecosystem's log: a ROS 2 bag (an MCAP file of CDR
    messages, or a rosbag2 directory or its .db3), a PX4 ULog (.ulg) or an ArduPilot DataFlash log (.bin),
    told apart by their content (formats.detect_format).

    max_samples, max_probe_samples: keep every k-th sample, k the smallest that brings the samples (and
    samples x probes) within them (an MCAP's other samples are never held; a CSV's are parsed, then let go).
    LabData.every says k. mapping: the reader's options for another ecosystem's log (ros2.Ros2Mapping,
    px4.Px4Mapping, ardupilot.ArduPilotMapping; None: their defaults)."""
    from .formats import detect_format, refuse_pointer

    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: no such file")
    refuse_pointer(p)
    if not p.is_dir():
        refused = not_regular(p, p.stat().st_mode)     # a FIFO, a device (/dev/zero): before anything opens it
        if refused:
            raise refused
    fmt = detect_format(p)
    if fmt in ("ros2-mcap", "ros2-bag", "px4-ulog", "ardupilot-bin"):
        return thinned(load_log(p, fmt, mapping), max_samples, max_probe_samples)
    if p.is_dir():
        check_one_run(p)
    if p.is_dir() or p.suffix.lower() == ".mcap" or fmt == "fluxcal":
        from .reader import read_samples  # only when an MCAP file is given

        rec = read_samples(p, max_samples=max_samples, max_probe_samples=max_probe_samples)
        names = list(rec.probe_names) if getattr(rec, "probe_names", None) else \
            [f"s{k + 1}" for k in range(rec.raw.n_probes)]
        check_time_increases(p, rec.raw)
        return LabData(block=rec.raw.without_implausible(), probe_names=names, path=str(p),
                       warnings=rec.report.warnings, every=rec.every, n_read=rec.n_read, metadata=dict(rec.metadata))
    return thinned(load_csv(p), max_samples, max_probe_samples)


def thinned(lab: LabData, max_samples: int | None = None, max_probe_samples: int | None = None) -> LabData:
    """The data read whole, with every k-th sample kept (keep_every: k the smallest within the limits; LabData.every
    says k, n_read the samples read). A copy where k > 1; the same samples where k = 1."""
    n, probes = lab.block.n_samples, lab.block.n_probes
    every = keep_every(n, probes, max_samples, max_probe_samples)
    if every == 1:
        return replace(lab, n_read=n if lab.n_read is None else lab.n_read)
    return replace(lab, block=lab.block.rows(np.arange(0, n, every)), every=every, n_read=n)


def load_log(p: Path, fmt: str, mapping: Any = None) -> LabData:
    """Another ecosystem's log (formats.detect_format's fmt) through its reader, imported only when given."""
    if fmt in ("ros2-mcap", "ros2-bag"):
        from .ros2 import load_ros2 as load
    elif fmt == "px4-ulog":
        from .px4 import load_px4 as load
    else:
        from .ardupilot import load_ardupilot as load
    return load(p, mapping)
