"""Corrected (and raw) probe vectors as `sensor_msgs/msg/MagneticField` in a ROS 2 bag: a rosbag2 directory with MCAP
storage (DIR/metadata.yaml and DIR/DIR_0.mcap, as `ros2 bag record -s mcap` writes it), CDR-encoded, readable by
`ros2 bag` and rosbags. Written with the mcap package fluxcal already uses; no ROS 2 package is needed.

Each probe is a topic /fluxcal/<unit>/<probe>/magnetic_field (raw: .../magnetic_field_raw), one message per sample:
header.stamp = the sample's time (unit clock + stamp_origin_ns), header.frame_id = the probe's name, magnetic_field in
tesla (nT x 1e-9), magnetic_field_covariance all zero ("unknown", as the message's definition says). A sample whose
vector is not finite (a saturated axis) is not written, and counted.

The CDR of a block of samples is built at once (numpy, one record layout per topic); only the MCAP writer takes the
messages one by one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import RecordingError
from fluxcal.drivers.outputs import open_output, refuse_linked_folder, replacing
from fluxcal.service.numerics.outputs import CorrectedBlock

MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
#: the message definition as rosbag2's MCAP storage stores it (ros2msg, dependencies after "====" lines)
MAGNETIC_FIELD_DEF = (
    "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\nfloat64[9] magnetic_field_covariance\n"
    + "=" * 80 + "\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    + "=" * 80 + "\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    + "=" * 80 + "\nMSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n")
#: CDR, little endian (XCDR1 encapsulation PL_CDR_LE = 0x0001)
CDR_LE = b"\x00\x01\x00\x00"
TESLA_PER_NT = 1e-9


def magnetic_field_cdr(stamp_ns: np.ndarray, frame_id: str, tesla: np.ndarray) -> list[bytes]:
    """The CDR payloads of MagneticField messages, one per sample: stamps (n,) int64 ns, vectors (n, 3) tesla."""
    name = frame_id.encode() + b"\x00"
    # after the 4-byte encapsulation header, offsets count from 0: sec 0, nanosec 4, string length 8, chars 12..,
    # then the float64s aligned to 8
    at = 12 + len(name)
    vec = at + (-at) % 8
    dtype = np.dtype({"names": ["enc", "sec", "nanosec", "len", "name", "vec", "cov"],
                      "formats": ["V4", "<i4", "<u4", "<u4", f"V{len(name)}", "<3f8", "<9f8"],
                      "offsets": [0, 4, 8, 12, 16, 4 + vec, 4 + vec + 24], "itemsize": 4 + vec + 96})
    n = int(np.shape(stamp_ns)[0])
    rec = np.zeros(n, dtype)
    stamp = np.asarray(stamp_ns, np.int64)
    rec["enc"] = np.void(CDR_LE)
    rec["sec"] = stamp // 1_000_000_000
    rec["nanosec"] = stamp % 1_000_000_000
    rec["len"] = len(name)
    rec["name"] = np.void(name)
    rec["vec"] = tesla
    raw = rec.tobytes()
    size = dtype.itemsize
    return [raw[i * size:(i + 1) * size] for i in range(n)]


@dataclass
class _Topic:
    channel: int
    count: int = 0


@dataclass
class Ros2BagWriter:
    """A ROS 2 bag (rosbag2 directory, MCAP storage) of MagneticField messages. `close()` writes metadata.yaml;
    until then the directory is not a complete bag (a killed writer's .mcap is recovered with `mcap recover`)."""

    path: Path
    unit: str
    probe_names: list[str]
    stamp_origin_ns: int = 0
    chunk_size: int = 1 << 20
    _topics: dict[str, _Topic] = field(default_factory=dict, init=False)
    _first_ns: int | None = field(default=None, init=False)
    _last_ns: int = field(default=0, init=False)
    skipped: int = field(default=0, init=False)
    closed: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        from mcap.writer import Writer

        self.path = Path(self.path)
        refuse_linked_folder(self.path, "ROS 2 bag")
        if self.path.exists() and any(self.path.iterdir()) if self.path.is_dir() else self.path.exists():
            raise RecordingError(f"{self.path}: exists already: a ROS 2 bag is written into a new directory")
        self.path.mkdir(parents=True, exist_ok=True)
        self.file_name = f"{self.path.name}_0.mcap"
        self._f = open_output(self.path / self.file_name, "xb", buffering=-1)    # a new bag's: nothing there
        self._w = Writer(self._f, chunk_size=self.chunk_size)
        self._w.start(profile="ros2", library="fluxcal")
        self._schema = self._w.register_schema(MAGNETIC_FIELD, "ros2msg", MAGNETIC_FIELD_DEF.encode())

    def _topic(self, name: str) -> _Topic:
        t = self._topics.get(name)
        if t is None:
            t = self._topics[name] = _Topic(self._w.register_channel(name, "cdr", self._schema, {}))
        return t

    def topic_of(self, probe: str, raw: bool = False) -> str:
        return f"/fluxcal/{self.unit}/{probe}/magnetic_field" + ("_raw" if raw else "")

    def _write(self, t_s: np.ndarray, vectors_nT: np.ndarray, raw: bool) -> None:
        if self.closed:
            raise RecordingError(f"{self.path}: the bag is closed")
        if vectors_nT.shape[1] != len(self.probe_names):
            raise ValueError(f"expected {len(self.probe_names)} probes, got {vectors_nT.shape[1]}")
        stamps = self.stamp_origin_ns + np.round(np.asarray(t_s, np.float64) * 1e9).astype(np.int64)
        for k, probe in enumerate(self.probe_names):
            v = vectors_nT[:, k]
            ok = np.isfinite(v).all(axis=1) & (stamps >= 0)
            self.skipped += int(np.count_nonzero(~ok))
            if not ok.any():
                continue
            st = stamps[ok]
            topic = self._topic(self.topic_of(probe, raw))
            for ns, data in zip(st.tolist(), magnetic_field_cdr(st, probe, v[ok] * TESLA_PER_NT)):
                self._w.add_message(topic.channel, log_time=ns, publish_time=ns, data=data, sequence=topic.count)
                topic.count += 1
            self._first_ns = int(st.min()) if self._first_ns is None else min(self._first_ns, int(st.min()))
            self._last_ns = max(self._last_ns, int(st.max()))

    def write_corrected(self, block: CorrectedBlock) -> None:
        self._write(block.t_s, block.corrected_nT, raw=False)

    def write_raw(self, block: SampleBlock) -> None:
        self._write(block.t_s, block.field_nT, raw=True)

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    def status(self) -> dict[str, Any]:
        return {"path": str(self.path), "messages": self.message_count, "skipped_not_finite": self.skipped,
                "topics": {k: t.count for k, t in self._topics.items()}}

    def close(self) -> None:
        """Finish the MCAP file and write metadata.yaml (safe to call twice)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._w.finish()
        finally:
            self._f.close()
        with replacing(self.path / "metadata.yaml", "w") as f:
            f.write(self._metadata())

    def _metadata(self) -> str:
        """rosbag2's metadata.yaml, version 5 (what ROS 2 Humble writes and later versions read)."""
        start = self._first_ns or 0
        duration = max(0, self._last_ns - start)
        n = self.message_count
        topics = "".join(
            f"    - topic_metadata:\n        name: {name}\n        type: {MAGNETIC_FIELD}\n"
            f"        serialization_format: cdr\n        offered_qos_profiles: \"\"\n"
            f"      message_count: {t.count}\n" for name, t in self._topics.items())
        return ("rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n"
                f"  duration:\n    nanoseconds: {duration}\n"
                f"  starting_time:\n    nanoseconds_since_epoch: {start}\n"
                f"  message_count: {n}\n"
                f"  topics_with_message_count:{' []' if not topics else ''}\n{topics}"
                "  compression_format: \"\"\n  compression_mode: \"\"\n"
                f"  relative_file_paths:\n    - {self.file_name}\n"
                f"  files:\n    - path: {self.file_name}\n      starting_time:\n"
                f"        nanoseconds_since_epoch: {start}\n      duration:\n        nanoseconds: {duration}\n"
                f"      message_count: {n}\n")
