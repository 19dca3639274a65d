"""PX4 flight logs (ULog, read by pyulog) as lab data:

    sensor_mag (every instance)    -> a probe s1, s2, ... (instance order): x, y, z in gauss x 1e5 = nT (PX4's unit
                                      for sensor_mag), at timestamp_sample (else timestamp), us since boot;
                                      its temperature -> s<k>_temp where the log has one (not all 0 or NaN)
    vehicle_magnetometer           -> the probes instead, only when asked (Px4Mapping.compass; `--topics
                                      mag=vehicle_magnetometer`): magnetometer_ga[0..2], PX4's output after its own
                                      calibration, each instance's samples of its most frequent compass and
                                      calibration (device_id, calibration_count), the others left out and said
    vehicle_attitude q[0..3]       -> heel_deg, pitch_deg, azimuth_deg (PX4's q: FRD body -> NED, as fluxcal's)
    vehicle_gps_position/sensor_gps-> lat_deg, lon_deg, alt_m (above the ellipsoid where logged, else MSL: said);
                                      samples without a 3D fix left out
    battery_status[i].current_a    -> battery_current_a (instance 0), battery<i>_current_a (A; -1: not measured)

On one time base by fluxcal.service.numerics.merge. The date comes from the GPS's UTC time where the log has a fix.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError
from fluxcal.drivers.inputs import check_head, magic
from fluxcal.service.io.recordings.damage import damage_note, library_output, ulog_walk
from fluxcal.service.io.recordings.formats import ULOG_MAGIC, Inspection, StreamInfo, lab_data, missing_package, rate
from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.numerics.merge import Series, merge

#: PX4's sensor_mag is in gauss
NT_PER_GAUSS = 1e5
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")
WANTED = ("sensor_mag", "sensor_combined", "vehicle_magnetometer", "vehicle_attitude", *GPS_TOPICS, "battery_status")
#: PX4's "no sample" in sensor_combined's relative timestamps
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF


#: the topics a PX4 log's probes may come from: the raw field (the default), or PX4's output after its calibration
COMPASS_TOPICS = ("sensor_mag", "vehicle_magnetometer")


@dataclass(frozen=True)
class Px4Mapping:
    """Which streams become what. compass: the topic the probes come from (COMPASS_TOPICS); mags: its instances to take
    as probes, in order (None: every one); the others on or off."""

    mags: Sequence[int] | None = None
    attitude: bool = True
    position: bool = True
    currents: bool = True
    temperatures: bool = True
    compass: str = "sensor_mag"


def _ulog(path: Path, only: Sequence[str] | None = WANTED) -> tuple[Any, list[str]]:
    """The ULog read by pyulog (what it prints kept off the output) and the warning of a damaged or cut log."""
    check_head(path, "a PX4 ULog", magic(ULOG_MAGIC, "a ULog"))     # garbage refused before pyulog reads it
    try:
        from pyulog import ULog
    except ImportError:
        raise missing_package("pyulog", "px4", "a PX4 log (ULog)") from None
    try:
        with library_output():
            ulog = ULog(str(path), list(only) if only is not None else None)
    except Exception as e:  # noqa: BLE001 - pyulog raises bare exceptions on a damaged file
        raise DataError(f"{path}: not a readable PX4 ULog ({type(e).__name__}: {e})") from None
    cut, at = ulog_walk(path)
    return ulog, damage_note(path, cut=cut, corrupt=bool(ulog.file_corruption), at=at) + _dropouts(path, ulog)


def _dropouts(path: Path, ulog: Any) -> list[str]:
    """What the logger itself says it lost (its dropout messages: the storage did not keep up)."""
    lost = [int(getattr(d, "duration", 0)) for d in getattr(ulog, "dropouts", []) or []]
    if not lost:
        return []
    return [f"{path}: the logger dropped data {len(lost):,} time(s), {sum(lost):,} ms in all (PX4's dropouts: its "
            f"storage did not keep up); the samples in them are lost"]


def _time_us(d: Any) -> np.ndarray:
    t = d.data.get("timestamp_sample")
    return np.asarray(t if t is not None and np.any(t) else d.data["timestamp"], np.int64)


def _instances(ulog: Any, name: str) -> list[Any]:
    return sorted((d for d in ulog.data_list if d.name == name), key=lambda d: d.multi_id)


@dataclass(frozen=True)
class _CombinedMag:
    """An older PX4's one magnetometer, logged in sensor_combined (magnetometer_ga[0..2], gauss) at the gyroscope's
    rate: each magnetometer sample once, at its own instant (timestamp + magnetometer_timestamp_relative)."""

    data: dict
    multi_id: int = 0
    name: str = "sensor_combined.magnetometer_ga"


def _combined_mag(ulog: Any) -> _CombinedMag | None:
    d = next((x for x in ulog.data_list if x.name == "sensor_combined" and "magnetometer_ga[0]" in x.data), None)
    if d is None:
        return None
    rel = np.asarray(d.data.get("magnetometer_timestamp_relative", np.zeros(len(d.data["timestamp"]))), np.int64)
    t = np.asarray(d.data["timestamp"], np.int64) + rel
    ok = rel != RELATIVE_TIMESTAMP_INVALID
    first = np.concatenate([[True], np.diff(t) != 0]) & ok      # the rows between two samples repeat the last one
    take = np.flatnonzero(first)
    return _CombinedMag({"timestamp": t[take], **{a: np.asarray(d.data[f"magnetometer_ga[{i}]"], float)[take]
                                                  for i, a in enumerate("xyz")}})


@dataclass(frozen=True)
class _VehicleMag:
    """One vehicle_magnetometer instance as a probe: magnetometer_ga[0..2] (gauss) of the samples of its most frequent
    (device_id, calibration_count), PX4's compass and calibration; `left_out` says what else it held."""

    data: dict
    multi_id: int
    left_out: str = ""
    name: str = "vehicle_magnetometer"


def _vehicle_mag(d: Any) -> _VehicleMag:
    x = d.data
    n = len(x["timestamp"])
    keys = np.column_stack([np.asarray(x.get(k, np.zeros(n)), np.int64) for k in ("device_id", "calibration_count")])
    runs, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    best = int(np.argmax(counts))
    keep = np.flatnonzero(inverse.ravel() == best)
    left_out = ""
    if keep.size < n:
        others = ", ".join(f"{c:,} of device {int(r[0]):#x} calibration {int(r[1])}"
                           for r, c in zip(runs, counts) if not np.array_equal(r, runs[best]))
        left_out = (f"vehicle_magnetometer[{d.multi_id}]: PX4 changed compass or calibration during the log: the "
                    f"{keep.size:,} samples of device {int(runs[best][0]):#x} calibration {int(runs[best][1])} taken, "
                    f"{others} left out (one probe is one compass under one calibration)")
    data = {k: np.asarray(x[k])[keep] for k in ("timestamp", "timestamp_sample") if k in x}
    data.update({a: np.asarray(x[f"magnetometer_ga[{i}]"], float)[keep] for i, a in enumerate("xyz")})
    if "device_id" in x:
        data["device_id"] = np.asarray(x["device_id"])[keep]
    return _VehicleMag(data, d.multi_id, left_out)


#: sensor_mag instances holding fewer samples than this each are said beside a vehicle_magnetometer holding more
SPARSE_SAMPLES = 100


def _sparse_note(ulog: Any, mags: Sequence[Any]) -> list[str]:
    """Where every sensor_mag instance is sparse (SPARSE_SAMPLES: the logging profile's rate) while the log holds
    vehicle_magnetometer at a higher rate: why that one is not taken, and what gives a calibration."""
    counts = [int(_time_us(d).size) for d in mags]
    if not counts or max(counts) >= SPARSE_SAMPLES:
        return []
    vm = [int(np.asarray(d.data["timestamp"]).size) for d in _instances(ulog, "vehicle_magnetometer")]
    if not vm or max(vm) <= max(counts):
        return []
    said = (f"sensor_mag holds {', '.join(f'{c:,}' for c in counts)} sample(s) (the logging profile's rate) where "
            f"vehicle_magnetometer holds {max(vm):,}: that one is not taken, being PX4's output after its own "
            f"calibration and its choice among the compasses, not the raw field a calibration is fitted to; for a "
            f"calibration flight log sensor_mag at its rate (SDLOG_PROFILE's high-rate sensors), or take "
            f"vehicle_magnetometer knowingly (--topics mag=vehicle_magnetometer): a fit then calibrates what PX4's "
            f"own calibration left")
    return [said]


def _gps(ulog: Any) -> Any | None:
    for name in GPS_TOPICS:
        got = _instances(ulog, name)
        if got:
            return got[0]
    return None


def _position(d: Any) -> tuple[np.ndarray, np.ndarray, str]:
    """(t_us, (n, 3) lat, lon, alt m, which altitude) of a GPS topic's samples with a 3D fix."""
    x = d.data
    fix = np.asarray(x.get("fix_type", np.full(len(x["timestamp"]), 3)))
    if "latitude_deg" in x:                                            # PX4 1.14 on: degrees and metres
        lat, lon = np.asarray(x["latitude_deg"], float), np.asarray(x["longitude_deg"], float)
        ell, msl = x.get("altitude_ellipsoid_m"), x.get("altitude_msl_m")
        scale = 1.0
    else:                                                              # 1e-7 degrees and mm
        lat, lon = np.asarray(x["lat"], float) * 1e-7, np.asarray(x["lon"], float) * 1e-7
        ell, msl = x.get("alt_ellipsoid"), x.get("alt")
        scale = 1e-3
    if ell is not None and np.any(np.asarray(ell)[fix >= 3] != 0):
        alt, which = np.asarray(ell, float) * scale, "above the WGS84 ellipsoid"
    else:
        alt, which = np.asarray(msl, float) * scale, "above mean sea level (no ellipsoidal height logged: the geoid's " \
                                                    "undulation, up to about 100 m, is in it)"
    ok = fix >= 3
    return np.asarray(x["timestamp"], np.int64)[ok], np.column_stack([lat, lon, alt])[ok], which


def _utc_offset_s(d: Any | None) -> float | None:
    """UNIX time minus boot time, s, from the GPS's UTC time (None without one)."""
    if d is None or "time_utc_usec" not in d.data:
        return None
    utc = np.asarray(d.data["time_utc_usec"], np.int64)
    ok = utc > 0
    if not ok.any():
        return None
    return float(np.median(utc[ok] - np.asarray(d.data["timestamp"], np.int64)[ok])) / 1e6


def _temperature(d: Any) -> np.ndarray | None:
    t = d.data.get("temperature")
    if t is None:
        return None
    t = np.asarray(t, float)
    return None if not np.any(np.isfinite(t) & (t != 0)) else t


def _stream_name(d: Any) -> str:
    """How inspect names a topic instance (and what is said of it names it so): battery_status, battery_status[1],
    sensor_mag[0]."""
    return d.name if d.multi_id == 0 and d.name != "sensor_mag" else f"{d.name}[{d.multi_id}]"


def _currents(ulog: Any) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """Each battery_status instance's measured current_a by its column: (timestamp us, amperes, the stream's name)."""
    out = {}
    for d in _instances(ulog, "battery_status"):
        c = np.asarray(d.data.get("current_a", []), float)
        ok = np.isfinite(c) & (c != -1.0)                         # -1: not measured
        if ok.any():
            key = "battery_current_a" if d.multi_id == 0 else f"battery{d.multi_id}_current_a"
            out[key] = (np.asarray(d.data["timestamp"], np.int64)[ok], c[ok], _stream_name(d))
    return out


def load_px4(path: str | Path, mapping: Px4Mapping | None = None) -> LabData:
    """A PX4 ULog as LabData (module docstring)."""
    m = mapping or Px4Mapping()
    ulog, damaged = _ulog(Path(path))
    mags, older = _compasses(ulog, m, Path(path))
    processed = m.compass == "vehicle_magnetometer"
    t_all = [_time_us(d) for d in mags]
    origin = min(int(t.min()) for t in t_all if t.size)

    def s(t_us: np.ndarray) -> np.ndarray:
        return (np.asarray(t_us, np.int64) - origin) / 1e6

    notes = ["sensor_mag: x, y, z taken in gauss (PX4's unit) and in the frame PX4 logs them (rotated to the "
             "board/body frame by CAL_MAGn_ROT), as raw as PX4 logs them (before its calibration)"]
    notes += _sparse_note(ulog, mags) if older is None and not processed else []
    if processed:
        notes = ["vehicle_magnetometer.magnetometer_ga[0..2] taken as the probes (--topics mag=vehicle_magnetometer), "
                 "in gauss and in the body frame: PX4's output after its own calibration (CAL_MAGn_*: its offsets, "
                 "scales and rotation taken out) and its choice among the compasses, so a fit calibrates what that "
                 "calibration left: its offsets and matrix are on top of PX4's, not the sensor's own"]
    if older is not None:
        notes = ["sensor_combined.magnetometer_ga[0..2] (an older PX4's log: no sensor_mag) taken in gauss, each "
                 "magnetometer sample once at its own instant (the rows between two samples repeat the last one), "
                 "in the body frame, after PX4's own calibration of the day (CAL_MAG0_*: its offsets are taken out)"]
    probes, temps, sources = [], {}, {}
    for k, (d, t) in enumerate(zip(mags, t_all)):
        name = f"s{k + 1}"
        v = np.column_stack([np.asarray(d.data[a], float) for a in "xyz"]) * NT_PER_GAUSS
        what = d.name if isinstance(d, _CombinedMag) else f"{d.name}[{d.multi_id}] device {_device(d)}"
        probes.append((name, Series(s(t), v, what)))
        sources[name] = d.name if isinstance(d, _CombinedMag) else f"{d.name}[{d.multi_id}]"
        temp = _temperature(d) if m.temperatures else None
        if temp is not None:
            temps[name] = Series(s(t), temp, f"sensor_mag[{d.multi_id}].temperature")
            sources[f"{name}_temp"] = f"sensor_mag[{d.multi_id}].temperature"
    columns: dict[str, Series] = {}
    attitude = None
    if m.attitude:
        att = _instances(ulog, "vehicle_attitude")
        if att:
            q = np.column_stack([np.asarray(att[0].data[f"q[{i}]"], float) for i in range(4)])
            attitude = Series(s(att[0].data["timestamp"]), q, "vehicle_attitude q (FRD -> NED)")
            sources.update(dict.fromkeys(("heel_deg", "pitch_deg", "azimuth_deg"), "vehicle_attitude"))
    gps = _gps(ulog)
    if m.position and gps is not None:
        t_us, pos, which = _position(gps)
        if t_us.size:
            for c, col in enumerate(("lat_deg", "lon_deg", "alt_m")):
                columns[col] = Series(s(t_us), pos[:, c], f"{_stream_name(gps)} (3D fix)")
                sources[col] = _stream_name(gps)
            notes.append(f"alt_m from {_stream_name(gps)}: {which}")
    if m.currents:
        for col, (t_us, c, stream) in _currents(ulog).items():
            columns[col] = Series(s(t_us), c, f"{stream}.current_a")
            sources[col] = f"{stream}.current_a"
    try:
        merged = merge(probes, temperatures=temps, columns=columns, attitude=attitude)
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None
    offset = _utc_offset_s(gps)
    if offset is None:
        notes.append("no GPS UTC time in the log: the date of the flight is unknown")
    return lab_data(merged, [n for n, _ in probes], path, fmt="px4", sources=sources,
                    origin_unix_s=None if offset is None else offset + origin / 1e6, notes=notes,
                    warnings=damaged + [d.left_out for d in mags if getattr(d, "left_out", "")])


def _compasses(ulog: Any, m: Px4Mapping, path: Path) -> tuple[list[Any], _CombinedMag | None]:
    """The instances the probes come from (the mapping's compass topic and mags; an older PX4's sensor_combined where
    the log has no sensor_mag) and that older magnetometer, if taken; DataError where there is none."""
    if m.compass not in COMPASS_TOPICS:
        raise DataError(f"compass: {m.compass!r} is not a topic a PX4 log's probes come from (allowed: "
                        f"{', '.join(COMPASS_TOPICS)})")
    mags = _instances(ulog, m.compass)
    if m.mags is not None:
        have = {d.multi_id: d for d in mags}
        missing = [i for i in m.mags if i not in have]
        if missing:
            raise DataError(f"mags: instance(s) {missing} not in {path} (its {m.compass} instances: "
                            f"{sorted(have) or 'none'})")
        mags = [have[i] for i in m.mags]
    processed = m.compass == "vehicle_magnetometer"
    if processed and not mags:
        raise DataError(f"{path}: no vehicle_magnetometer in the log (asked by --topics mag=vehicle_magnetometer); "
                        f"its sensor_mag holds the raw field (the default)")
    if processed:
        mags = [_vehicle_mag(d) for d in mags]
    older = None
    if not mags and m.mags in (None, (0,), [0]):
        older = _combined_mag(ulog)           # a PX4 before sensor_mag was logged: its one magnetometer
        mags = [older] if older is not None else []
    if not mags:
        topics = sorted({d.name for d in _ulog(Path(path), None)[0].data_list})
        if not topics:
            raise DataError(f"{path}: no logged topic at all in its {Path(path).stat().st_size:,} bytes: the log is "
                            f"cut short (it ends before its first data) or empty; copy it again from the vehicle")
        raise DataError(f"{path}: no sensor_mag in the log (its topics: {', '.join(topics)}): nothing to "
                        f"calibrate (PX4 logs sensor_mag with SDLOG_PROFILE's default set)")
    return mags, older


def _device(d: Any) -> str:
    dev = d.data.get("device_id")
    return f"{int(dev[0]):#x}" if dev is not None and len(dev) else "?"


def inspect_px4(path: str | Path, mapping: Px4Mapping | None = None) -> Inspection:
    """What a ULog holds (every topic instance, counts, rates) and how load_px4 would map it."""
    m = mapping or Px4Mapping()
    ulog, damaged = _ulog(Path(path), None)
    mags = [d.multi_id for d in _instances(ulog, m.compass)]
    chosen = list(m.mags) if m.mags is not None else mags
    gps = _gps(ulog)
    currents = _currents(ulog) if m.currents else {}
    streams = []
    for d in sorted(ulog.data_list, key=lambda d: (d.name, d.multi_id)):
        t = np.asarray(d.data["timestamp"], np.int64)
        maps, note = "", ""
        if d.name == m.compass == "vehicle_magnetometer":
            if d.multi_id in chosen:
                maps = f"probe s{chosen.index(d.multi_id) + 1} (magnetometer_ga[0..2], gauss x 1e5 = nT)"
                note = "after PX4's own calibration (--topics mag=vehicle_magnetometer)"
            else:
                note = "not in the mapping's mags"
        elif d.name == "sensor_mag" and m.compass == "vehicle_magnetometer":
            note = "not taken: --topics mag=vehicle_magnetometer"
        elif d.name == "sensor_mag":
            if d.multi_id in chosen:
                k = chosen.index(d.multi_id) + 1
                temp = _temperature(d) is not None and m.temperatures
                maps = f"probe s{k} (gauss x 1e5 = nT)" + (f", s{k}_temp" if temp else "")
                note = f"device {_device(d)}" + ("" if temp else "; no temperature logged")
            else:
                note = "not in the mapping's mags"
        elif d.name == "sensor_combined" and m.compass == "sensor_mag" and not mags and "magnetometer_ga[0]" in d.data:
            maps = "probe s1 (magnetometer_ga[0..2], gauss x 1e5 = nT)"
            note = "an older PX4's log: no sensor_mag; after PX4's own calibration"
        elif d.name == "vehicle_attitude" and d.multi_id == 0 and m.attitude:
            maps = "heel_deg, pitch_deg, azimuth_deg"
        elif gps is not None and d is gps and m.position:
            maps = "lat_deg, lon_deg, alt_m"
            note = f"{int(np.count_nonzero(np.asarray(d.data.get('fix_type', [3] * t.size)) >= 3)):,} with a 3D fix"
        elif d.name == "battery_status":
            key = "battery_current_a" if d.multi_id == 0 else f"battery{d.multi_id}_current_a"
            maps = key if key in currents else ""
            note = "" if maps else "current_a not measured (-1)"
        streams.append(StreamInfo(_stream_name(d), d.name, int(t.size), rate((t - t[:1]) / 1e6), maps, note))
    warnings = damaged + ([] if mags or (m.compass == "sensor_mag" and _combined_mag(ulog) is not None) else
                          [f"no {m.compass} in the log: nothing to calibrate"])
    return Inspection(str(path), "px4-ulog", streams, warnings=warnings)
