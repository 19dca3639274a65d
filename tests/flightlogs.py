"""Small flight logs built byte for byte from the formats' specifications, for the readers' tests: a PX4 ULog (ULog
file format, docs.px4.io "ULog File Format": header, flag bits, formats, subscriptions, data) and an ArduPilot
DataFlash log (FMT-described messages behind 0xA3 0x95). pyulog's writer only writes back a ULog it read and
pymavlink has no DataFlash writer, so the tests build them here and read them with those packages' own readers."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

_ULOG_TYPES = {"uint64_t": "Q", "int64_t": "q", "uint32_t": "I", "int32_t": "i", "uint16_t": "H", "int16_t": "h",
               "uint8_t": "B", "int8_t": "b", "float": "f", "double": "d", "bool": "?"}


def _msg(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def write_ulog(path: Path, topics: list[tuple[str, int, list[tuple[str, str]], dict[str, np.ndarray]]],
               info: dict[str, str] | None = None) -> None:
    """A ULog (version 1) of topics: (name, multi_id, [(type, field)], {field: values}); every topic has a
    "uint64_t timestamp" field first, in microseconds. Array fields are given as "float[4] q" with values (n, 4)."""
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))
    out += _msg(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    formats: dict[str, list[tuple[str, str]]] = {}
    for name, _, fields, _ in topics:
        formats.setdefault(name, fields)
    for name, fields in formats.items():
        out += _msg(b"F", f"{name}:{''.join(f'{t} {f};' for t, f in fields)}".encode())
    for k, v in (info or {}).items():
        key = f"char[{len(v)}] {k}".encode()
        out += _msg(b"I", bytes([len(key)]) + key + v.encode())
    rows = []
    for msg_id, (name, multi, fields, values) in enumerate(topics):
        out += _msg(b"A", struct.pack("<BH", multi, msg_id) + name.encode())
        fmt = "<" + "".join(_ULOG_TYPES[t.split("[")[0]] * (int(t.split("[")[1][:-1]) if "[" in t else 1)
                            for t, _ in fields)
        n = len(values["timestamp"])
        cols = [np.asarray(values[f]).reshape(n, -1) for _, f in fields]
        cols = [c.astype(np.int64) if _ULOG_TYPES[t.split("[")[0]] not in "fd?" else c.astype(np.float64)
                for c, (t, _) in zip(cols, fields)]
        table = [row for row in zip(*[list(map(tuple, c.tolist())) for c in cols])]
        for row in table:
            flat = [v for part in row for v in part]
            rows.append((int(flat[0]), msg_id, struct.pack("<H", msg_id) + struct.pack(fmt, *flat)))
    rows.sort(key=lambda r: (r[0], r[1]))
    for _, _, payload in rows:
        out += _msg(b"D", payload)
    Path(path).write_bytes(bytes(out))


# --- ArduPilot DataFlash ---------------------------------------------------------------------------------------

_DF_TYPES = {"Q": "Q", "q": "q", "I": "I", "i": "i", "H": "H", "h": "h", "B": "B", "b": "b", "f": "f", "d": "d",
             "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "n": "4s", "N": "16s", "Z": "64s", "M": "B"}
#: the stored integer of a value: c, C, e, E hold 100 x the value, L 1e7 x the degrees
_DF_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}
HEAD = b"\xa3\x95"


def _df_fmt(type_id: int, name: str, fmt: str, columns: str) -> bytes:
    length = 3 + struct.calcsize("<" + "".join(_DF_TYPES[c] for c in fmt))
    return HEAD + bytes([128]) + struct.pack("<BB4s16s64s", type_id, length, name.encode(), fmt.encode(),
                                             columns.encode())


def write_dataflash(path: Path, messages: list[tuple[str, str, str, dict[str, np.ndarray]]]) -> None:
    """A DataFlash log of messages: (name, format chars, columns "TimeUS,I,MagX,...", {column: values}), each
    type's samples written in time order (TimeUS), interleaved across types."""
    out = bytearray(_df_fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    rows = []
    for k, (name, fmt, columns, values) in enumerate(messages):
        type_id = 129 + k
        out += _df_fmt(type_id, name, fmt, columns)
        cols = columns.split(",")
        pack = "<" + "".join(_DF_TYPES[c] for c in fmt)
        n = len(values[cols[0]])
        for i in range(n):
            vals = []
            for c, col in zip(fmt, cols):
                v = values[col][i]
                if c in _DF_SCALE:
                    v = int(round(float(v) * _DF_SCALE[c]))
                elif c in "QqIiHhBbM":
                    v = int(v)
                elif c in "nNZ":
                    v = str(v).encode()
                else:
                    v = float(v)
                vals.append(v)
            rows.append((int(values[cols[0]][i]), k, HEAD + bytes([type_id]) + struct.pack(pack, *vals)))
    rows.sort(key=lambda r: (r[0], r[1]))
    out += b"".join(r[2] for r in rows)
    Path(path).write_bytes(bytes(out))


# --- a simulated flight -------------------------------------------------------------------------------------------

#: nT per ampere of battery current that the first probe sees (a motor lead beside a compass), in its raw frame
CURRENT_COUPLING_NT_A = np.array([30.0, -20.0, 12.0])


def simulated_flight(n: int = 4000, rate_hz: float = 50.0, seed: int = 5, current: bool = True) -> dict:
    """Two probes tumbling (fluxcal.drivers.sim) on a platform with a battery current whose field the first probe sees:
    samples, attitude (Euler angles and quaternions, platform -> NED), a track, the current and the truth."""
    from fluxcal.drivers.sim import Unit, load_sim_config
    from fluxcal.service.numerics.merge import quaternion_from_euler

    rng = np.random.default_rng(seed)
    probes = [{"position_m": [0.15 * k, 0.0, 0.0], "scale": (1 + 0.02 * rng.standard_normal(3)).tolist(),
               "nonorth_deg": rng.uniform(-2, 2, 3).tolist(), "misalign_deg": rng.uniform(-3, 3, 3).tolist(),
               "offset_nT": rng.uniform(-2000, 2000, 3).tolist(), "noise_nT": 2.0} for k in range(2)]
    cfg = load_sim_config({"seed": seed, "rate_hz": rate_hz, "duration_s": n / rate_hz,
                           "field": {"total_nT": 49800.0, "inclination_deg": 66.0, "declination_deg": 3.0},
                           "motion": {"kind": "tumble", "rate_deg_s": 40.0, "tumble_period_s": 9.0},
                           "temperature": {"start_C": 25.0, "ramp_C_per_h": 30.0, "amplitude_C": 2.0,
                                           "period_s": 30.0},
                           "probes": probes})
    s = Unit(cfg).digitise(0, cfg.n_samples)
    b = s.to_block()
    r = s.world.attitude
    euler = np.column_stack([np.degrees(np.arctan2(r[:, 2, 1], r[:, 2, 2])),
                             np.degrees(-np.arcsin(np.clip(r[:, 2, 0], -1, 1))),
                             np.degrees(np.arctan2(r[:, 1, 0], r[:, 0, 0]))])
    t = b.t_s
    amps = 6.0 + 4.0 * np.sin(2 * np.pi * t / 13.0) + 2.0 * np.sin(2 * np.pi * t / 3.1) if current else np.zeros(n)
    field = b.field_nT.copy()
    field[:, 0] += amps[:, None] * CURRENT_COUPLING_NT_A
    return {"t_s": t, "field_nT": field, "temp_C": b.temp_C, "euler": euler,
            "q": quaternion_from_euler(euler[:, 0], euler[:, 1], euler[:, 2]), "current_a": amps,
            "lat": 47.4 + t * 1e-6, "lon": 8.5 + t * 2e-6, "alt": 450.0 + t * 2.0,
            "offsets_nT": np.array([p["offset_nT"] for p in probes])}
