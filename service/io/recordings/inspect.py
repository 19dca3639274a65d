"""`fluxcal inspect FILE`'s logic: what a recording holds and how fit and diagnose would map it, as a typed
Inspection (formats.py); the command module prints it. Nothing is printed here."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import DataError
from service.io.recordings.formats import Inspection, StreamInfo, detect_format, rate


def inspect_file(path: str | Path, mapping: Any = None) -> Inspection:
    """What the file at path holds (its streams, counts, rates) and how it would be mapped onto probes and columns;
    DataError naming the file where it cannot be read."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: no such file")
    fmt = detect_format(p)
    if fmt in ("ros2-mcap", "ros2-bag"):
        from service.io.recordings.ros2 import inspect_ros2

        return inspect_ros2(p, mapping)
    if fmt == "px4-ulog":
        from service.io.recordings.px4 import inspect_px4

        return inspect_px4(p, mapping)
    if fmt == "ardupilot-bin":
        from service.io.recordings.ardupilot import inspect_ardupilot

        return inspect_ardupilot(p, mapping)
    return _inspect_lab(p, fmt)


def _inspect_lab(p: Path, fmt: str) -> Inspection:
    """A lab CSV or a fluxcal recording: its probes and columns as load_data reads them."""
    from service.io.recordings.load import load_data

    lab = load_data(p)
    b = lab.block
    t = b.t_s
    streams = [StreamInfo(name, "probe", b.n_samples, rate(t), f"probe {name}") for name in lab.probe_names]
    temps = [f"{n}_temp" for k, n in enumerate(lab.probe_names) if np.isfinite(b.temp_C[:, k]).any()]
    streams += [StreamInfo(c, "temperature", b.n_samples, rate(t), c) for c in temps]
    streams += [StreamInfo(c, "column", b.n_samples, rate(t), c) for c in sorted(b.extras)]
    return Inspection(str(p), fmt, streams, list(lab.probe_names), temps + sorted(b.extras), list(lab.warnings),
                      duration_s=float(t[-1] - t[0]) if t.size else None)
