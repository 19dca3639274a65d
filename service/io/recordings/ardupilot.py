"""ArduPilot DataFlash logs (.bin, read by pymavlink) as lab data:

    MAG, MAG2, MAG3 (older logs) or MAG with an instance field I (4.0 on)
                         -> a probe s1, s2, ... (instance order): MagX, MagY, MagZ in milligauss x 100 = nT, at TimeUS
                            (us since boot; TimeMS in very old logs). ArduPilot logs the field with its own compass
                            calibration applied (offsets OfsX..Z, scale and motor compensation), in the body frame:
                            fluxcal then calibrates what is left
    ATT Roll, Pitch, Yaw -> heel_deg, pitch_deg, azimuth_deg (ArduPilot's 3-2-1 Euler angles of the FRD body in NED,
                            fluxcal's convention: R = Rz(yaw) Ry(pitch) Rx(roll))
    GPS (first instance) -> lat_deg, lon_deg, alt_m (Alt: above mean sea level); samples without a 3D fix (Status < 3)
                            left out
    BAT / CURR Curr      -> battery_current_a (instance 0), battery<i>_current_a (A; the older CURR, to 3.4, logs it as
                            an integer in hundredths of an ampere: scaled)

On one time base by fluxcal.service.numerics.merge: the log's own clock (us since boot), never a GPS time; an older log's
GPS message carries the GPS time of week in TimeMS (beside Week) and its boot time in T (ms), which is taken. The
date comes from the GPS week and time of week where the log has a fix. Streams are named as the log names them
(MAG2, CURR; MAG[1] where the message has an instance field).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError
from fluxcal.drivers.inputs import check_head, magic
from fluxcal.service.io.recordings.damage import (
    damage_said,
    damage_warning,
    dataflash_cut,
    library_output,
    skipped_bytes,
)
from fluxcal.service.io.recordings.formats import (
    DATAFLASH_HEAD,
    Inspection,
    StreamInfo,
    lab_data,
    missing_package,
    rate,
)
from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.numerics.merge import Series, merge, quaternion_from_euler

#: ArduPilot logs the field in milligauss
NT_PER_MILLIGAUSS = 100.0
#: the older CURR message (ArduPilot to 3.4) logs Curr as an integer: the current in amperes x 100
AMPERES_PER_INTEGER_CURR = 0.01
#: GPS time = UNIX time + leap seconds (18 since 2017-01-01) from 1980-01-06
GPS_EPOCH_UNIX_S = 315964800.0
GPS_LEAP_S = 18.0
MESSAGES = ("MAG", "MAG2", "MAG3", "ATT", "GPS", "GPS2", "BAT", "BAT2", "CURR")


@dataclass(frozen=True)
class ArduPilotMapping:
    """Which streams become what. mags: the compass instances (0, 1, 2, ...) to take as probes, in order (None: every
    one); the others on or off."""

    mags: tuple[int, ...] | None = None
    attitude: bool = True
    position: bool = True
    currents: bool = True


def _stream(name: str, msg: Any) -> tuple[str, int]:
    """(kind, instance) of a message: MAG2 -> (MAG, 1); MAG with I = 2 -> (MAG, 2)."""
    base = name.rstrip("0123456789")
    inst = int(name[len(base):]) - 1 if name[len(base):] else 0
    for f in ("I", "Inst", "Instance"):
        v = getattr(msg, f, None)
        if v is not None and base != "ATT":
            return base, int(v)
    return ("BAT" if base == "CURR" else base), inst


def _unit(msg: Any, field: str) -> float:
    """What a field's logged number is multiplied by to give fluxcal's unit: 1, but for a current logged as an integer
    (CURR to ArduPilot 3.4: hundredths of an ampere; its CurrTot in mAh agrees with that scale)."""
    if field != "Curr":
        return 1.0
    fmt = msg.fmt
    i = fmt.colhash.get(field)
    return AMPERES_PER_INTEGER_CURR if i is not None and fmt.format[i] in "bBhHiI" else 1.0


def _boot_time_us(msg: Any) -> float:
    """A message's instant on the log's own clock (us since boot): TimeUS, else TimeMS; an older GPS message's TimeMS
    is the GPS time of week (beside Week), its boot time is T (ms)."""
    t_us = getattr(msg, "TimeUS", None)
    if t_us is not None:
        return float(t_us)
    if getattr(msg, "Week", None) is not None and getattr(msg, "T", None) is not None:
        return float(msg.T) * 1000.0
    return float(getattr(msg, "TimeMS", 0)) * 1000.0


def _gps_time(msg: Any, field: str) -> float:
    """GWk and GMS of a GPS message: an older log's Week and TimeMS (the GPS time of week, ms)."""
    old = {"GWk": "Week", "GMS": "TimeMS"}
    v = getattr(msg, field, None)
    if v is None and getattr(msg, "TimeUS", None) is None:
        v = getattr(msg, old[field], None)
    return float(v) if v is not None else np.nan


def _name(msg_type: str, msg: Any) -> str:
    """How the format's documentation names a stream: the message's own name (MAG2, CURR), with its instance field's
    value where it has one (MAG[1] from ArduPilot 4.0 on)."""
    for f in ("I", "Inst", "Instance"):
        v = getattr(msg, f, None)
        if v is not None and not msg_type.startswith("ATT"):
            return f"{msg_type}[{int(v)}]"
    return msg_type


def _read(path: Path, names: dict | None = None) -> tuple[dict[tuple[str, int], dict[str, list[float]]], str, bool]:
    """Per (kind, instance): the fields fluxcal maps, as lists, in log order; what is wrong with a damaged or cut log
    (damage.damage_said; "" where it is whole: what pymavlink prints is kept off the output); whether the log
    defines a compass message (its FMT). names: filled with each one's name as the log has it (_name)."""
    with library_output() as printed:
        out, cut, defines_mag = _messages(path, names)
    return out, damage_said(cut=cut, skipped=skipped_bytes(printed)), defines_mag


def _messages(path: Path, names: dict | None) -> tuple[dict[tuple[str, int], dict[str, list[float]]], int, bool]:
    """_read's messages, the bytes missing from the log's last message (damage.dataflash_cut) and whether a compass
    message is defined."""
    check_head(path, "an ArduPilot DataFlash log", _dataflash_head)    # garbage refused before pymavlink reads it
    try:
        from pymavlink import DFReader
    except ImportError:
        raise missing_package("pymavlink", "ardupilot", "an ArduPilot DataFlash log") from None
    try:
        r = DFReader.DFReader_binary(str(path), zero_time_base=True)
    except Exception as e:  # noqa: BLE001 - pymavlink raises bare exceptions on a damaged file
        raise DataError(f"{path}: not a readable ArduPilot DataFlash log ({type(e).__name__}: {e})") from None
    fields = {"MAG": ("MagX", "MagY", "MagZ", "OfsX", "OfsY", "OfsZ"), "ATT": ("Roll", "Pitch", "Yaw"),
              "GPS": ("Status", "Lat", "Lng", "Alt", "GWk", "GMS"), "BAT": ("Curr",)}
    out: dict[tuple[str, int], dict[str, list[float]]] = {}
    try:
        while True:
            msg = r.recv_match(type=list(MESSAGES))
            if msg is None:
                break
            kind, inst = _stream(msg.get_type(), msg)
            want = fields.get(kind)
            if want is None:
                continue
            d = out.setdefault((kind, inst), {"t_us": []})
            if names is not None and (kind, inst) not in names:
                names[(kind, inst)] = _name(msg.get_type(), msg)
            d["t_us"].append(_boot_time_us(msg))
            for f in want:
                v = _gps_time(msg, f) if f in ("GWk", "GMS") else float(getattr(msg, f, np.nan)) * _unit(msg, f)
                d.setdefault(f, []).append(v)
        cut = dataflash_cut(r)
        defines_mag = any(str(getattr(f, "name", "")).startswith("MAG") for f in r.formats.values())
    finally:
        r.close()
    return out, cut, defines_mag


def _dataflash_head(head: bytes, whole: bool) -> str | None:
    """A DataFlash log begins with a FMT message (a3 95 80); a serial capture of fluxcal's ICD (a5 5a) is said."""
    why = magic(DATAFLASH_HEAD, "a DataFlash log")(head, whole)
    if why and head.startswith(b"\xa5\x5a"):
        why += " (this looks like a serial capture of the unit's ICD frames: fluxcal decode FILE --probes N)"
    return why


def load_ardupilot(path: str | Path, mapping: ArduPilotMapping | None = None) -> LabData:
    """An ArduPilot DataFlash log as LabData (module docstring)."""
    m = mapping or ArduPilotMapping()
    names: dict[tuple[str, int], str] = {}       # each stream as the log names it, and inspect and what is said
    data, damaged, defines_mag = _read(Path(path), names)
    mags = sorted(i for k, i in data if k == "MAG")
    if m.mags is not None:
        missing = [i for i in m.mags if i not in mags]
        if missing:
            raise DataError(f"mags: compass instance(s) {missing} not in {path} (its instances: {mags or 'none'})")
        mags = list(m.mags)
    if not mags:
        why = (f"the log is {damaged}, before it defined its compass message: copy it again from the vehicle"
               if damaged and not defines_mag else
               "LOG_BITMASK must log compass" + (f"; the log is also {damaged}" if damaged else ""))
        raise DataError(f"{path}: no MAG messages in the log: nothing to calibrate ({why})")
    origin = min(min(data[("MAG", i)]["t_us"]) for i in mags)

    def s(t_us: list[float] | np.ndarray) -> np.ndarray:
        return (np.asarray(t_us, float) - origin) / 1e6

    probes, sources = [], {}
    offsets: list[str] = []
    for k, i in enumerate(mags):
        d = data[("MAG", i)]
        name = f"s{k + 1}"
        v = np.column_stack([d[f] for f in ("MagX", "MagY", "MagZ")]) * NT_PER_MILLIGAUSS
        probes.append((name, Series(s(d["t_us"]), v, names[("MAG", i)])))
        sources[name] = names[("MAG", i)]
        ofs = np.array([d[f"Ofs{a}"][-1] for a in "XYZ"]) * NT_PER_MILLIGAUSS
        if np.all(np.isfinite(ofs)):
            offsets.append(f"{name} {ofs[0]:.0f}, {ofs[1]:.0f}, {ofs[2]:.0f}")
    notes = ["MAG: MagX..Z taken in milligauss with ArduPilot's own compass calibration applied (its offsets at "
             "the log's end, nT: " + ("; ".join(offsets) or "not logged") + "); fluxcal calibrates what that leaves"]
    columns: dict[str, Series] = {}
    attitude = None
    if m.attitude and ("ATT", 0) in data:
        a = data[("ATT", 0)]
        attitude = Series(s(a["t_us"]), quaternion_from_euler(a["Roll"], a["Pitch"], a["Yaw"]),
                          f"{names[('ATT', 0)]} Roll, Pitch, Yaw")
        sources.update(dict.fromkeys(("heel_deg", "pitch_deg", "azimuth_deg"), names[("ATT", 0)]))
    offset = None
    gps = data.get(("GPS", 0))
    if gps is not None:
        ok = np.asarray(gps["Status"]) >= 3
        if m.position and ok.any():
            t = s(np.asarray(gps["t_us"])[ok])
            for col, f in (("lat_deg", "Lat"), ("lon_deg", "Lng"), ("alt_m", "Alt")):
                columns[col] = Series(t, np.asarray(gps[f])[ok], f"{names[('GPS', 0)]}.{f} (3D fix)")
                sources[col] = f"{names[('GPS', 0)]}.{f}"
            notes.append("alt_m from GPS.Alt: above mean sea level (the geoid's undulation, up to about 100 m, is in "
                         "it)")
        wk, ms = np.asarray(gps["GWk"]), np.asarray(gps["GMS"])
        good = ok & (wk > 0)
        if good.any():
            unix = GPS_EPOCH_UNIX_S + wk[good] * 604800.0 + ms[good] / 1e3 - GPS_LEAP_S
            offset = float(np.median(unix - np.asarray(gps["t_us"])[good] / 1e6))
    if m.currents:
        for (kind, i), d in sorted(data.items()):
            c = np.asarray(d.get("Curr", []), float)
            if kind == "BAT" and np.isfinite(c).any():
                col = "battery_current_a" if i == 0 else f"battery{i}_current_a"
                ok = np.isfinite(c)
                columns[col] = Series(s(np.asarray(d["t_us"])[ok]), c[ok], f"{names[(kind, i)]}.Curr")
                sources[col] = f"{names[(kind, i)]}.Curr"
    try:
        merged = merge(probes, columns=columns, attitude=attitude)
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None
    if offset is None:
        notes.append("no GPS time in the log: the date of the flight is unknown")
    return lab_data(merged, [n for n, _ in probes], path, fmt="ardupilot", sources=sources,
                    origin_unix_s=None if offset is None else offset + origin / 1e6, notes=notes,
                    warnings=damage_warning(path, damaged))


def inspect_ardupilot(path: str | Path, mapping: ArduPilotMapping | None = None) -> Inspection:
    """What a DataFlash log holds of the messages fluxcal maps (counts, rates) and how load_ardupilot would map it."""
    m = mapping or ArduPilotMapping()
    names: dict[tuple[str, int], str] = {}
    data, damaged, _ = _read(Path(path), names)
    mags = sorted(i for k, i in data if k == "MAG")
    chosen = list(m.mags) if m.mags is not None else mags
    streams = []
    for (kind, i), d in sorted(data.items()):
        t = np.asarray(d["t_us"], float)
        maps, note = "", ""
        if kind == "MAG":
            maps = f"probe s{chosen.index(i) + 1} (milligauss x 100 = nT)" if i in chosen else ""
            note = "ArduPilot's compass calibration applied" if maps else "not in the mapping's mags"
        elif kind == "ATT" and m.attitude:
            maps = "heel_deg, pitch_deg, azimuth_deg"
        elif kind == "GPS" and i == 0 and m.position:
            maps = "lat_deg, lon_deg, alt_m"
            note = f"{int(np.count_nonzero(np.asarray(d['Status']) >= 3)):,} with a 3D fix; altitude above MSL"
        elif kind == "BAT" and m.currents:
            maps = "battery_current_a" if i == 0 else f"battery{i}_current_a"
        name = names.get((kind, i), kind)
        streams.append(StreamInfo(name, name.split("[")[0], int(t.size), rate(t / 1e6), maps, note))
    warnings = damage_warning(path, damaged) + ([] if mags else ["no MAG messages in the log: nothing to calibrate"])
    return Inspection(str(path), "ardupilot-bin", streams, warnings=warnings)
