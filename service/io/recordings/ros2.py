"""ROS 2 bags as lab data: an MCAP file of CDR messages (decoded by mcap-ros2-support) or a rosbag2 directory
(sqlite3 .db3 or MCAP storage, read by rosbags), mapped onto fluxcal's columns:

    sensor_msgs/msg/MagneticField  -> a probe (s1, s2, ... in topic order): tesla x 1e9 = nT, header stamps as time,
                                      in the message's frame (header.frame_id) as recorded
    sensor_msgs/msg/Imu            -> heel_deg, pitch_deg, azimuth_deg: its orientation (REP 103: the Imu's frame in
                                      an ENU world) turned into the platform -> NED attitude fluxcal's attitude
                                      columns hold (docs/csv.md); an Imu whose orientation_covariance[0] is -1 says
                                      it gives no orientation and is not used
    sensor_msgs/msg/Temperature    -> s<k>_temp of the probe whose MagneticField topic shares its namespace
                                      (/mag1/temperature -> the probe of /mag1/field), or as mapped; else none
    sensor_msgs/msg/NavSatFix      -> lat_deg, lon_deg, alt_m (above the WGS84 ellipsoid); samples without a fix
                                      (status < 0) or without an altitude are left out
    sensor_msgs/msg/BatteryState   -> battery_current_a (A; a current beside a compass is a platform effect)

The streams are put on one time base by fluxcal.service.numerics.merge (the probe with the fewest samples gives the
instants; other probes nearest within half an interval, one to one; the rest interpolated, never extrapolated).
Ros2Mapping chooses the topics; `inspect_ros2(path)` lists what a bag holds and how it would be mapped.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError
from fluxcal.drivers.inputs import check_head, magic
from fluxcal.service.io.recordings.formats import MCAP_MAGIC, Inspection, StreamInfo, lab_data, missing_package, rate
from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.numerics.merge import Series, merge, ned_from_enu_quaternion

MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"
TEMPERATURE = "sensor_msgs/msg/Temperature"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
BATTERY = "sensor_msgs/msg/BatteryState"
#: a field of Ros2Mapping left at AUTO takes the only topic of its type (several: none, and said)
AUTO = "auto"
#: stamps beyond this (2001-09-09) are UNIX time; smaller ones a simulation's or a boot clock, whose date is unknown
EPOCH_STAMP_S = 1.0e9


@dataclass(frozen=True)
class Ros2Mapping:
    """Which topics become what. probes: probe name -> MagneticField topic (None: every MagneticField topic, named
    s1, s2, ... in topic-name order); temperatures: probe name -> Temperature topic (None: by shared namespace);
    imu, navsatfix, battery: a topic, AUTO (the only one of its type) or None (not used)."""

    probes: Mapping[str, str] | None = None
    temperatures: Mapping[str, str] | None = None
    imu: str | None = AUTO
    navsatfix: str | None = AUTO
    battery: str | None = AUTO


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


@dataclass(frozen=True)
class _Plan:
    """The topics a mapping takes from a bag, and what it says about the others."""

    probes: dict[str, str]
    temperatures: dict[str, str]
    imu: str | None
    navsatfix: str | None
    battery: str | None
    unused: dict[str, str]          # topic -> why it is not used


def plan(topics: Mapping[str, str], mapping: Ros2Mapping | None = None) -> _Plan:
    """The mapping applied to a bag's topics (topic -> message type); DataError for a named topic the bag lacks or
    of another type, or for a bag without a MagneticField topic."""
    m = mapping or Ros2Mapping()
    of = {t: [n for n, k in sorted(topics.items()) if k == t] for t in (MAGNETIC_FIELD, IMU, TEMPERATURE, NAVSATFIX,
                                                                       BATTERY)}
    unused: dict[str, str] = {}

    def named(topic: str, kind: str, key: str) -> str:
        if topic not in topics:
            raise DataError(f"{key}: {topic!r} is not a topic of the bag (its {kind} topics: "
                            f"{', '.join(of[kind]) or 'none'})")
        if topics[topic] != kind:
            raise DataError(f"{key}: {topic!r} carries {topics[topic]}, not {kind}")
        return topic

    if m.probes is None:
        probes = {f"s{k + 1}": t for k, t in enumerate(of[MAGNETIC_FIELD])}
    else:
        probes = {str(name): named(t, MAGNETIC_FIELD, f"probes.{name}") for name, t in m.probes.items()}
        for t in of[MAGNETIC_FIELD]:
            if t not in probes.values():
                unused[t] = "not in the mapping's probes"
    if not probes:
        raise DataError(f"no {MAGNETIC_FIELD} topic in the bag (its topics: "
                        f"{', '.join(f'{t} ({k})' for t, k in sorted(topics.items())) or 'none'}): nothing to "
                        f"calibrate")
    if m.temperatures is None:
        temps: dict[str, str] = {}
        for t in of[TEMPERATURE]:
            owners = [p for p, mt in probes.items() if _namespace(mt) == _namespace(t)]
            same_ns = [x for x in of[TEMPERATURE] if _namespace(x) == _namespace(t)]
            if len(owners) == 1 and len(same_ns) == 1:
                temps[owners[0]] = t
            else:
                unused[t] = ("no probe's MagneticField topic shares its namespace" if not owners else
                             f"its namespace is shared by several {'probes' if len(owners) > 1 else 'Temperature topics'}"
                             f": map it with temperatures={{probe: topic}}")
    else:
        temps = {}
        for p, t in m.temperatures.items():
            if p not in probes:
                raise DataError(f"temperatures.{p}: {p!r} is not a probe (probes: {', '.join(probes)})")
            temps[p] = named(t, TEMPERATURE, f"temperatures.{p}")
        for t in of[TEMPERATURE]:
            if t not in temps.values():
                unused[t] = "not in the mapping's temperatures"

    def one(choice: str | None, kind: str, key: str) -> str | None:
        if choice is None:
            for t in of[kind]:
                unused[t] = f"{key} not mapped"
            return None
        if choice != AUTO:
            taken = named(choice, kind, key)
            for t in of[kind]:
                if t != taken:
                    unused[t] = f"{key} is {taken}"
            return taken
        if len(of[kind]) == 1:
            return of[kind][0]
        for t in of[kind]:
            unused[t] = f"one of {len(of[kind])} {kind} topics: choose one ({key}=TOPIC)"
        return None

    imu = one(m.imu, IMU, "imu")
    nav = one(m.navsatfix, NAVSATFIX, "navsatfix")
    bat = one(m.battery, BATTERY, "battery")
    for t, k in topics.items():
        if k not in of and t not in unused:
            unused[t] = "a message type fluxcal does not map"
    return _Plan(probes, temps, imu, nav, bat, unused)


# --- the two storages ---------------------------------------------------------------------------------------


class _Bag:
    """A bag's topics and its messages, decoded, whatever the storage."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def topics(self) -> dict[str, str]:
        raise NotImplementedError

    def times(self) -> dict[str, np.ndarray]:
        """Per topic, the messages' log times in ns (for counts and rates, without decoding)."""
        raise NotImplementedError

    def messages(self, topics: set[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time ns, decoded message) of the given topics, in log-time order."""
        raise NotImplementedError


class _McapBag(_Bag):
    """A ROS 2 MCAP file, decoded by mcap-ros2-support."""

    def _reader(self, f):
        from mcap.reader import make_reader

        try:
            from mcap_ros2.decoder import DecoderFactory
        except ImportError:
            raise missing_package("mcap-ros2-support", "ros2", "a ROS 2 bag in MCAP") from None
        return make_reader(f, decoder_factories=[DecoderFactory()])

    def _unreadable(self, e: Exception, where: str) -> DataError:
        """The DataError of a damaged file: mcap, zstd and the CDR decoder raise their own exceptions, or bare ones
        (struct.error on a record cut short, KeyError, OverflowError, a message definition's parse error)."""
        import struct

        from mcap.exceptions import EndOfFile

        what = ("it ends inside a record" if isinstance(e, EndOfFile) else "a record cut short"
                if isinstance(e, struct.error) else f"{type(e).__name__}: {e}")
        return DataError(f"{self.path}: {where} ({what}); a bag whose writer was killed can be finished with "
                         f"`mcap recover`, a damaged one cannot be read here")

    @contextmanager
    def _damage(self, where: str) -> Iterator[None]:
        """What the readers raise on a damaged file (their own exceptions, or bare ones) said as _unreadable."""
        try:
            yield
        except DataError:
            raise
        except Exception as e:  # noqa: BLE001 - the readers raise bare exceptions on a damaged file
            raise self._unreadable(e, where) from None

    def _log_time(self, topic: str, ns: int) -> int:
        """A message's log time (ns, an unsigned 64-bit field), refused beyond 2**63 - 1 (the year 2262): damage."""
        if ns >= 1 << 63:
            raise DataError(f"{self.path}: a message on {topic} has the log time {ns} ns, beyond 2**63 (the year "
                            f"2262): the file is damaged")
        return ns

    def topics(self) -> dict[str, str]:
        with open(self.path, "rb") as f, self._damage("not a readable MCAP file"):
            summary = self._reader(f).get_summary()
        if summary is None:
            raise DataError(f"{self.path}: the MCAP file has no summary (its writer was killed?): finish it with "
                            f"`mcap recover IN OUT` first")
        return {ch.topic: summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else ""
                for ch in summary.channels.values() if ch.message_encoding == "cdr"}

    def times(self) -> dict[str, np.ndarray]:
        out: dict[str, list[int]] = {}
        with open(self.path, "rb") as f, self._damage("a message could not be read"):
            for _, ch, msg in self._reader(f).iter_messages(log_time_order=False):
                out.setdefault(ch.topic, []).append(self._log_time(ch.topic, msg.log_time))
        return {k: np.asarray(v, np.int64) for k, v in out.items()}

    def messages(self, topics: set[str]) -> Iterator[tuple[str, int, Any]]:
        with open(self.path, "rb") as f, self._damage("a message could not be read or decoded"):
            for _, ch, msg, decoded in self._reader(f).iter_decoded_messages(topics=sorted(topics)):
                yield ch.topic, self._log_time(ch.topic, msg.log_time), decoded


class _RosbagsBag(_Bag):
    """A rosbag2 directory (metadata.yaml and .db3 or .mcap files), read by rosbags."""

    def _open(self):
        try:
            from rosbags.highlevel import AnyReader
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            raise missing_package("rosbags", "ros2", "a ROS 2 bag (rosbag2 directory, .db3)") from None
        # older bags store no message definitions: the standard ones of Humble stand in for them
        return AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))

    def _reader(self):
        from rosbags.highlevel import AnyReaderError

        try:
            r = self._open()
            r.open()
            return r
        except (AnyReaderError, FileNotFoundError) as e:
            raise DataError(f"{self.path}: not a readable rosbag2 bag ({e})") from None

    def topics(self) -> dict[str, str]:
        r = self._reader()
        try:
            return {c.topic: c.msgtype for c in r.connections}
        finally:
            r.close()

    def times(self) -> dict[str, np.ndarray]:
        r = self._reader()
        out: dict[str, list[int]] = {}
        try:
            for conn, ts, _ in r.messages():
                out.setdefault(conn.topic, []).append(ts)
        finally:
            r.close()
        return {k: np.asarray(v, np.int64) for k, v in out.items()}

    def messages(self, topics: set[str]) -> Iterator[tuple[str, int, Any]]:
        r = self._reader()
        try:
            conns = [c for c in r.connections if c.topic in topics]
            for conn, ts, raw in r.messages(connections=conns):
                yield conn.topic, ts, r.deserialize(raw, conn.msgtype)
        finally:
            r.close()


def open_bag(path: str | Path) -> _Bag:
    """The bag at path: a ROS 2 MCAP file, a rosbag2 directory, or a .db3 file of one (its directory is read)."""
    p = Path(path)
    if p.is_dir():
        if not (p / "metadata.yaml").is_file():
            raise DataError(f"{p}: a directory without metadata.yaml is not a rosbag2 bag")
        return _RosbagsBag(p)
    if p.suffix.lower() == ".db3":
        check_head(p, "a rosbag2 SQLite file", magic(b"SQLite format 3\x00", "an SQLite database"))
        if not (p.parent / "metadata.yaml").is_file():
            raise DataError(f"{p}: a .db3 file without the metadata.yaml of its bag beside it: give the bag's "
                            f"directory (rosbag2 needs both)")
        return _RosbagsBag(p.parent)
    check_head(p, "a ROS 2 bag (MCAP)", magic(MCAP_MAGIC, "an MCAP file"))   # garbage refused before it is read
    return _McapBag(p)


# --- messages to arrays -------------------------------------------------------------------------------------


def _stamp_ns(msg: Any, log_time_ns: int) -> tuple[int, bool]:
    """The header stamp in ns, or the log time where the stamp is unset (0): (ns, from the log)."""
    st = msg.header.stamp
    ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return (ns, False) if ns else (int(log_time_ns), True)


@dataclass
class _Collected:
    """Per topic: stamps (ns), values, how many took the log time for a missing stamp, how many were left out."""

    stamps: list[int]
    values: list[Any]
    from_log: int = 0
    left_out: int = 0
    frame_id: str = ""


def _collect(bag: _Bag, p: _Plan) -> dict[str, _Collected]:
    kinds: dict[str, str] = {t: MAGNETIC_FIELD for t in p.probes.values()}
    kinds.update({t: TEMPERATURE for t in p.temperatures.values()})
    kinds.update({t: k for t, k in ((p.imu, IMU), (p.navsatfix, NAVSATFIX), (p.battery, BATTERY)) if t})
    got = {t: _Collected([], []) for t in kinds}
    for topic, log_ns, msg in bag.messages(set(kinds)):
        try:
            _take(got[topic], kinds[topic], log_ns, msg)
        except (AttributeError, TypeError, ValueError, IndexError) as e:
            raise DataError(f"{bag.path}: a message on {topic} is not the {kinds[topic]} fluxcal reads ({e}): its "
                            f"message definition in the file differs from the standard one (damaged?)") from None
    return got


def _take(c: _Collected, kind: str, log_ns: int, msg: Any) -> None:
    """One decoded message of its kind into its topic's collection (or counted as left out)."""
    if kind == MAGNETIC_FIELD:
        v = msg.magnetic_field
        value: Any = (v.x * 1e9, v.y * 1e9, v.z * 1e9)                 # tesla -> nT
        c.frame_id = c.frame_id or str(msg.header.frame_id)
    elif kind == TEMPERATURE:
        value = float(msg.temperature)
    elif kind == IMU:
        if float(msg.orientation_covariance[0]) == -1.0:               # REP 145: no orientation given
            c.left_out += 1
            return
        o = msg.orientation
        value = (o.w, o.x, o.y, o.z)
        c.frame_id = c.frame_id or str(msg.header.frame_id)
    elif kind == NAVSATFIX:
        if int(msg.status.status) < 0 or not math.isfinite(float(msg.altitude)):
            c.left_out += 1
            return
        value = (float(msg.latitude), float(msg.longitude), float(msg.altitude))
    else:                                                               # BatteryState
        if not math.isfinite(float(msg.current)):
            c.left_out += 1
            return
        value = float(msg.current)
    ns, from_log = _stamp_ns(msg, log_ns)
    c.stamps.append(ns)
    c.values.append(value)
    c.from_log += from_log


def load_ros2(path: str | Path, mapping: Ros2Mapping | None = None) -> LabData:
    """A ROS 2 bag as LabData (module docstring); DataError naming the file where it cannot be."""
    bag = open_bag(path)
    p = plan(bag.topics(), mapping)
    got = _collect(bag, p)
    warnings: list[str] = []
    notes: list[str] = []
    empty = [t for t in p.probes.values() if not got[t].stamps]
    if empty:
        raise DataError(f"{path}: no messages on {', '.join(empty)}")
    # the time origin: the earliest stamp of any mapped topic, subtracted in integers (float64 of a UNIX stamp in
    # seconds keeps only 0.2 us)
    origin = min(min(c.stamps) for c in got.values() if c.stamps)

    def series(topic: str, what: str) -> Series:
        c = got[topic]
        if c.from_log:
            warnings.append(f"{topic}: {c.from_log:,} message(s) without a header stamp: their log time taken")
        return Series((np.asarray(c.stamps, np.int64) - origin) / 1e9, np.asarray(c.values, np.float64),
                      f"{topic} ({what})")

    probes = [(name, series(t, "MagneticField")) for name, t in p.probes.items()]
    temps = {name: series(t, "Temperature") for name, t in p.temperatures.items() if got[t].stamps}
    columns: dict[str, Series] = {}
    attitude = None
    if p.imu and got[p.imu].stamps:
        s = series(p.imu, "Imu orientation")
        attitude = Series(s.t_s, ned_from_enu_quaternion(s.values), s.source)
        frames = {got[t].frame_id for t in p.probes.values()}
        if frames != {got[p.imu].frame_id}:
            notes.append(f"attitude from {p.imu} is that of its frame {got[p.imu].frame_id!r}; the probes are in "
                         f"{', '.join(sorted(map(repr, frames)))}: a mounting rotation between them is not read "
                         f"(tf is not used), so the attitude columns take them as one platform frame")
    elif p.imu:
        warnings.append(f"{p.imu}: no orientation in any message (orientation_covariance[0] = -1): no attitude")
    if p.navsatfix and got[p.navsatfix].stamps:
        s = series(p.navsatfix, "NavSatFix")
        columns.update(lat_deg=Series(s.t_s, s.values[:, 0], s.source), lon_deg=Series(s.t_s, s.values[:, 1], s.source),
                       alt_m=Series(s.t_s, s.values[:, 2], s.source))
    if p.battery and got[p.battery].stamps:
        columns["battery_current_a"] = series(p.battery, "BatteryState current")
    for t, c in got.items():
        if c.left_out and t in (p.navsatfix, p.battery):
            warnings.append(f"{t}: {c.left_out:,} message(s) without a fix or a finite value left out")
    try:
        merged = merge(probes, temperatures=temps, columns=columns, attitude=attitude)
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None
    sources = {name: t for name, t in p.probes.items()}
    sources.update({f"{name}_temp": t for name, t in p.temperatures.items()})
    sources.update({c: p.navsatfix for c in ("lat_deg", "lon_deg", "alt_m") if c in columns})
    if attitude is not None:
        sources.update({c: p.imu for c in ("heel_deg", "pitch_deg", "azimuth_deg")})
    if "battery_current_a" in columns:
        sources["battery_current_a"] = p.battery
    epoch = origin / 1e9 >= EPOCH_STAMP_S
    if not epoch:
        notes.append(f"stamps start at {origin / 1e9:.3f} s: not UNIX time (a simulation's or a boot clock), so the "
                     f"date of the recording is unknown")
    return lab_data(merged, list(p.probes), path, fmt="ros2", sources=sources,
                    origin_unix_s=origin / 1e9 if epoch else None, notes=notes, warnings=warnings)


def inspect_ros2(path: str | Path, mapping: Ros2Mapping | None = None) -> Inspection:
    """What a ROS 2 bag holds (topics, types, counts, rates) and how load_ros2 would map it."""
    from fluxcal.service.io.recordings.formats import detect_format

    bag = open_bag(path)
    topics = bag.topics()
    times = bag.times()
    warnings: list[str] = []
    try:
        p = plan(topics, mapping)
    except DataError as e:
        p, warnings = None, [str(e)]
    maps: dict[str, str] = {}
    if p is not None:
        maps.update({t: f"probe {name} (tesla x 1e9 = nT)" for name, t in p.probes.items()})
        maps.update({t: f"{name}_temp" for name, t in p.temperatures.items()})
        if p.imu:
            maps[p.imu] = "heel_deg, pitch_deg, azimuth_deg (orientation, ENU -> NED)"
        if p.navsatfix:
            maps[p.navsatfix] = "lat_deg, lon_deg, alt_m"
        if p.battery:
            maps[p.battery] = "battery_current_a"
    streams = []
    for t in sorted(topics):
        ts = times.get(t, np.zeros(0, np.int64))
        streams.append(StreamInfo(t, topics[t], int(ts.size), rate((ts - ts[:1]) / 1e9), maps.get(t, ""),
                                  "" if t in maps or p is None else p.unused.get(t, "")))
    return Inspection(str(path), detect_format(path), streams, warnings=warnings)
