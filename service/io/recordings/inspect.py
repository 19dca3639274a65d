"""`fluxcal inspect FILE`'s logic: what a recording holds and how fit and diagnose would map it, as a typed
Inspection (formats.py); the command module prints it. Nothing is printed here."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.recordings.formats import Inspection, StreamInfo, detect_format, rate, refuse_pointer


def inspect_file(path: str | Path, mapping: Any = None, *, read: bool = True) -> Inspection:
    """What the file at path holds (its streams, counts, rates) and how it would be mapped onto probes and columns;
    DataError naming the file where it cannot be read. read: the probes, columns, samples, duration and clock from
    the one reader (as_read); False for a caller that reads the file itself (the inspect command, as fit does)."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: no such file")
    refuse_pointer(p)
    fmt = detect_format(p)
    if fmt in ("ros2-mcap", "ros2-bag"):
        from fluxcal.service.io.recordings.ros2 import inspect_ros2

        return as_read(inspect_ros2(p, mapping), p, mapping) if read else inspect_ros2(p, mapping)
    if fmt == "px4-ulog":
        from fluxcal.service.io.recordings.px4 import inspect_px4

        return as_read(inspect_px4(p, mapping), p, mapping) if read else inspect_px4(p, mapping)
    if fmt == "ardupilot-bin":
        from fluxcal.service.io.recordings.ardupilot import inspect_ardupilot

        return as_read(inspect_ardupilot(p, mapping), p, mapping) if read else inspect_ardupilot(p, mapping)
    return _inspect_lab(p, fmt)


def as_read(i: Inspection, p: Path, mapping: Any) -> Inspection:
    """The inspection's probes, columns, samples, duration and clock as the one reader fit and diagnose use
    (load.load_data) gives them, never a second reading of the file; where that reader gives nothing to calibrate,
    none, and why (`fit_refuses`)."""
    from fluxcal.service.io.recordings.load import load_data

    try:
        lab = load_data(p, mapping=mapping)
    except DataError as e:
        return replace(i, probes=[], columns=[], samples=0, fit_refuses=str(e),
                       warnings=[w for w in i.warnings if "nothing to calibrate" not in w])
    return replace(i, **reading(lab))


def reading(lab: Any) -> dict[str, Any]:
    """What an Inspection says of LabData: probes, columns (temperatures, then the rest by name), samples, duration,
    and the clock its t runs on."""
    b = lab.block
    t = b.t_s
    temps = [f"{n}_temp" for k, n in enumerate(lab.probe_names) if np.isfinite(b.temp_C[:, k]).any()]
    t0 = lab.metadata.get("t0_unix_s")
    own = ", on the log's own clock" if lab.metadata.get("format") in ("px4", "ardupilot", "ros2") else ""
    # what --skip and the commands' times are in: said as it is (a recording's t is its unit's clock, which does not
    # start at its first sample: "from the first sample" sent a --skip to the wrong stretch)
    first = float(t[0]) if t.size else 0.0
    clock = {"t_s": f"seconds from the first sample{own}" if first == 0.0 else
             f"seconds of the data's own time{own}, {first:g}-{float(t[-1]):g} s (--skip takes these)",
             "t0_unix_s": float(t0) if t0 is not None else None}
    return {"probes": list(lab.probe_names), "columns": temps + sorted(b.extras), "samples": int(b.n_samples),
            "duration_s": float(t[-1] - t[0]) if t.size else None, "clock": clock}


def _inspect_lab(p: Path, fmt: str) -> Inspection:
    """A lab CSV or a fluxcal recording: its probes and columns as load_data reads them."""
    from fluxcal.service.io.recordings.load import load_data

    lab = load_data(p)
    b = lab.block
    t = b.t_s
    read = reading(lab)
    streams = [StreamInfo(name, "probe", b.n_samples, rate(t), f"probe {name}") for name in lab.probe_names]
    streams += [StreamInfo(c, "temperature" if c.endswith("_temp") else "column", b.n_samples, rate(t), c)
                for c in read["columns"]]
    return Inspection(str(p), fmt, streams, warnings=list(lab.warnings), **read)
