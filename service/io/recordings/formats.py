"""Which kind of file a recording is, and what every reader of another ecosystem's log returns.

    detect_format(path) -> str      "csv", "fluxcal" (its own MCAP), "ros2-mcap", "ros2-bag" (a rosbag2 directory:
                                    sqlite3 .db3 or MCAP storage), "px4-ulog", "ardupilot-bin"
    StreamInfo, Inspection          what `fluxcal inspect FILE` shows: the file's streams and how each would be mapped
    lab_data(merged, ...)           a reader's streams, merged on one time base, as the LabData fit and diagnose take
    missing_package(pkg, extra)     the DataError of a reader whose optional package is not installed

The readers (ros2.py, px4.py, ardupilot.py) return the same LabData as a lab CSV; the columns they give are the
CSV's (docs/csv.md): s<k>_x/y/z in nT, s<k>_temp, heel_deg/pitch_deg/azimuth_deg, and lat_deg, lon_deg, alt_m
(a track, for the reference field along it: fluxcal.service.numerics.calib.track), plus currents and other logged values.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.numerics.merge import Merged

#: a logged field value beyond this (in any axis, whatever the unit: a field of the Earth is 7e7 in pT) is a damaged
#: record's, not a measurement
DAMAGED_NT = 1e12
#: the formats detect_format names, and what they are called in what is said
FORMAT_NAMES = {"csv": "lab CSV", "fluxcal": "fluxcal recording (MCAP)", "ros2-mcap": "ROS 2 bag (MCAP, CDR)",
                "ros2-bag": "ROS 2 bag (rosbag2 directory)", "px4-ulog": "PX4 flight log (ULog)",
                "ardupilot-bin": "ArduPilot DataFlash log (.bin)"}
ULOG_MAGIC = b"ULog\x01\x12\x35"
#: an ArduPilot DataFlash message starts with these two bytes, and the first is a FMT (type 128)
DATAFLASH_HEAD = b"\xa3\x95\x80"
MCAP_MAGIC = b"\x89MCAP0\r\n"


def detect_format(path: str | Path) -> str:
    """The kind of recording at `path`, by its content where the content says (an MCAP's profile and channels, a
    log's magic bytes), else by its name. A directory is a rosbag2 bag when it holds metadata.yaml, else a run of
    fluxcal's rotated files."""
    p = Path(path)
    if p.is_dir():
        return "ros2-bag" if (p / "metadata.yaml").is_file() else "fluxcal"
    suffix = p.suffix.lower()
    if suffix == ".db3":
        return "ros2-bag"
    try:
        with open(p, "rb") as f:
            head = f.read(16)
    except OSError:
        head = b""
    if head.startswith(ULOG_MAGIC[:4]) or suffix == ".ulg":
        return "px4-ulog"
    if head.startswith(DATAFLASH_HEAD) or suffix == ".bin":        # its reader says when it is not one
        return "ardupilot-bin"
    if head.startswith(MCAP_MAGIC) or suffix == ".mcap":
        return "ros2-mcap" if mcap_is_ros2(p) else "fluxcal"
    return "csv"


#: the first line of a Git LFS pointer: a repository's stand-in for a file it did not fetch
LFS_POINTER = b"version https://git-lfs.github.com/spec/"


def refuse_pointer(path: str | Path) -> None:
    """DataError for a Git LFS pointer given as a recording: the file it stands for was never fetched."""
    p = Path(path)
    if p.is_file() and p.stat().st_size < 1024:
        with open(p, "rb") as f:
            head = f.read(1024)
        if head.startswith(LFS_POINTER):
            size = next((ln.split()[1].decode(errors="replace") for ln in head.splitlines()
                         if ln.startswith(b"size ") and len(ln.split()) > 1), "?")
            raise DataError(f"{p}: a Git LFS pointer, not a recording: the file it stands for ({size} bytes) was never "
                            f"fetched; run `git lfs pull` in its repository (or download the file itself)")


def mcap_is_ros2(path: Path) -> bool:
    """An MCAP file holds a ROS 2 bag (not a fluxcal recording) when its header's profile is "ros2", or, with no
    profile, when its first channel carries CDR messages (fluxcal writes profile "" and its own encodings)."""
    import struct

    from mcap.exceptions import McapError
    from mcap.records import Channel, Header
    from mcap.stream_reader import StreamReader

    try:
        with open(path, "rb") as f:
            for n, rec in enumerate(StreamReader(f, skip_magic=False).records):
                if isinstance(rec, Header):
                    if rec.profile == "ros2":
                        return True
                    if rec.library.startswith("fluxcal") or rec.profile:
                        return False
                elif isinstance(rec, Channel):
                    return rec.message_encoding == "cdr"
                if n > 10_000:
                    return False
    except (McapError, OSError, ValueError, EOFError, struct.error):
        # struct.error: mcap's reader unpacks a record cut short (a file of 1-7 bytes, a header cut) as it is
        return False                             # the fluxcal reader says what is wrong with the file
    return False


@dataclass(frozen=True)
class StreamInfo:
    """One stream of a file (a topic, a uORB instance, a log message type) and what fluxcal makes of it."""

    name: str                        # "/imu/mag", "sensor_mag[1]", "MAG2"
    kind: str                        # "sensor_msgs/msg/MagneticField", "sensor_mag", "MAG"
    count: int
    rate_hz: float | None            # messages per second over its own span (None with fewer than two)
    maps_to: str = ""                # "probe s1", "s1_temp", "heel_deg, pitch_deg, azimuth_deg", ... ("": not used)
    note: str = ""                   # why it is not used, or what is assumed (a unit, a frame)


@dataclass(frozen=True)
class Inspection:
    """What a file holds and how a reader would map it (fluxcal inspect)."""

    path: str
    format: str                      # a key of FORMAT_NAMES
    streams: list[StreamInfo]
    probes: list[str] = field(default_factory=list)
    columns: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    duration_s: float | None = None
    samples: int | None = None       # the samples fit and diagnose take (one per instant of the time base)
    clock: dict[str, Any] | None = None   # the time base: the log's own clock, and where its t = 0 lies in UNIX time
    verdict: list[dict[str, Any]] = field(default_factory=list)   # each probe's determinacy (the commands' one gate)
    fit_refuses: str | None = None   # why fit would refuse the file (nothing to calibrate), as fit says it

    @property
    def format_name(self) -> str:
        return FORMAT_NAMES.get(self.format, self.format)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["format_name"] = self.format_name
        return d


def rate(t_s: Any) -> float | None:
    """Messages per second of instants t_s over their own span (None with fewer than two, or no span)."""
    import numpy as np

    t = np.asarray(t_s, float)
    if t.size < 2:
        return None
    span = float(np.max(t) - np.min(t))
    return (t.size - 1) / span if span > 0 else None


def lab_data(merged: Merged, probe_names: list[str], path: str | Path, *, fmt: str, sources: dict[str, str],
             origin_unix_s: float | None, notes: list[str] | None = None, warnings: list[str] | None = None) -> LabData:
    """The LabData of merged streams: t from the first kept instant; metadata says the format, each probe's and
    column's source, and where t = 0 lies in UNIX time when the log says (for the date of the reference field)."""
    import numpy as np

    block, lost = merged.block, []
    damaged = ~(np.abs(block.field_nT) <= DAMAGED_NT).all(axis=2) & np.isfinite(block.field_nT).all(axis=2)
    if damaged.any():                          # a flipped byte's 1e300: no unit gives that; NaN, as a lost sample
        field_nT = block.field_nT.copy()
        field_nT[damaged] = np.nan
        block = block.__class__(t_s=block.t_s, seq=block.seq, field_nT=field_nT, temp_C=block.temp_C,
                                flags=block.flags, extras=block.extras)
        lost = [f"{probe_names[k]}: {int(np.count_nonzero(damaged[:, k])):,} sample(s) beyond ±{DAMAGED_NT:.0e} in "
                f"some axis (no unit's field: a damaged record) left out" for k in range(damaged.shape[1])
                if damaged[:, k].any()]
        merged = replace(merged, block=block)
    meta = {"format": fmt, "sources": json.dumps(sources)}
    if origin_unix_s is not None:
        meta["t0_unix_s"] = repr(float(origin_unix_s) + merged.t0_s)
    return LabData(block=merged.block, probe_names=list(probe_names), path=str(path),
                   warnings=list(warnings or []) + merged.warnings + lost, metadata=meta,
                   notes=list(notes or []) + merged.notes)


def missing_package(package: str, extra: str, what: str) -> DataError:
    """The error of a reader whose optional package is not installed: which to install, two ways."""
    return DataError(f"reading {what} needs the package {package}, which is not installed: pip install {package} "
                     f"(or pip install 'fluxcal[{extra}]')")
