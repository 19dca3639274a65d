"""Samples of several streams taken at different instants onto one time base: how a ROS 2 bag's topics, a PX4
log's uORB instances or an ArduPilot log's messages become one SampleBlock (the rows fit and diagnose compare).

The rule, the same for every format (docs/ros2.md says it to users):

- the time base is the instants of the probe with the fewest samples (the slowest magnetometer; the first given
  on a tie);
- every other probe is matched to those instants by its NEAREST sample within half the base's median interval,
  one to one (a sample is never used twice: a second base instant that would take it gets none). A probe value is
  never interpolated (that would filter its noise) and never held. A base instant without a match for some probe
  is a row left out, counted per probe and said;
- slow auxiliary streams (attitude, position, currents, temperatures) are interpolated LINEARLY in time between
  their two samples around each base instant (attitude as a quaternion, normalised, the shorter way round), only
  where those two samples lie at most MAX_GAP_INTERVALS of the stream's own median interval apart; never
  extrapolated before its first or after its last sample. A row that a column cannot give honestly is left out
  (counted and said, with the column's name); a probe temperature that cannot be given is NaN (the temperature
  terms interpolate over it and count it), never another probe's.

Numerics only: no file is read here.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from fluxcal.drivers.block import SampleBlock

#: an auxiliary stream is interpolated across at most this many of its own median intervals (one lost sample
#: passes; two in a row do not)
MAX_GAP_INTERVALS = 2.5


@dataclass(frozen=True)
class Series:
    """One stream: instants t_s (n,) in seconds on the recording's clock, values (n,) or (n, k), and where it
    came from (a topic, a message and instance) for what is said."""

    t_s: np.ndarray
    values: np.ndarray
    source: str

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, np.float64)
        v = np.asarray(self.values, np.float64)
        if t.ndim != 1 or v.shape[0] != t.shape[0]:
            raise ValueError(f"{self.source}: t_s {t.shape} and values {v.shape} differ in length")
        order = np.argsort(t, kind="stable")
        if np.any(np.diff(t) < 0):
            t, v = t[order], v[order]
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "values", v)

    @property
    def n(self) -> int:
        return int(self.t_s.size)


@dataclass(frozen=True)
class Merged:
    """The streams on one time base: the block (t_s from the first kept instant; t0_s says where that lies on the
    recording's clock), and what the merge left out or could not give, as sentences."""

    block: SampleBlock
    t0_s: float
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _median_interval(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if d.size else float("inf")


def nearest_one_to_one(base_t: np.ndarray, t: np.ndarray, tol_s: float) -> np.ndarray:
    """(len(base_t),) index into t of the sample nearest each base instant within tol_s, -1 where none; a sample
    of t goes to one base instant at most (the nearest of those that would take it).

    >>> nearest_one_to_one(np.array([0.0, 1.0, 2.0]), np.array([0.1, 1.45, 1.55]), 0.5).tolist()
    [0, 1, 2]
    >>> nearest_one_to_one(np.array([0.0, 0.1, 2.0]), np.array([0.06]), 0.5).tolist()
    [-1, 0, -1]
    """
    if t.size == 0:
        return np.full(base_t.size, -1, np.int64)
    j = np.clip(np.searchsorted(t, base_t), 1, max(t.size - 1, 1))
    lo = j - 1
    hi = np.minimum(j, t.size - 1)
    pick = np.where(np.abs(t[hi] - base_t) < np.abs(base_t - t[lo]), hi, lo)
    dist = np.abs(t[pick] - base_t)
    idx = np.where(dist <= tol_s, pick, -1)
    # one to one: of the base instants that took the same sample, the nearest keeps it
    ok = np.flatnonzero(idx >= 0)
    if ok.size > 1:
        order = ok[np.lexsort((dist[ok], idx[ok]))]          # by sample, then by distance
        first = np.ones(order.size, bool)
        first[1:] = idx[order][1:] != idx[order][:-1]
        idx[order[~first]] = -1
    return idx


def interpolate(series: Series, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(values at t (m,) or (m, k), valid (m,) bool): linear between the two samples around each instant where
    they lie at most MAX_GAP_INTERVALS median intervals apart; an instant on a sample takes it exactly."""
    st, sv = series.t_s, series.values
    flat = sv.ndim == 1
    v2 = sv[:, None] if flat else sv
    if st.size == 0:
        return np.full((t.size,) + sv.shape[1:], np.nan), np.zeros(t.size, bool)
    if st.size == 1:
        valid = t == st[0]
        out = np.where(valid[:, None], v2[0], np.nan)
        return (out[:, 0] if flat else out), valid
    j = np.clip(np.searchsorted(st, t, side="right"), 1, st.size - 1)
    lo, hi = j - 1, j
    span = st[hi] - st[lo]
    gap = MAX_GAP_INTERVALS * _median_interval(st)
    inside = (t >= st[0]) & (t <= st[-1])
    exact_lo = t == st[lo]
    exact_hi = t == st[hi]
    valid = inside & ((span <= gap) | exact_lo | exact_hi)
    w = np.where(span > 0, (t - st[lo]) / np.where(span > 0, span, 1.0), 0.0)
    out = v2[lo] + w[:, None] * (v2[hi] - v2[lo])
    # a sample's own instant takes its value exactly (no rounding of w into it)
    out = np.where(exact_lo[:, None], v2[lo], np.where(exact_hi[:, None], v2[hi], out))
    out[~valid] = np.nan
    return (out[:, 0] if flat else out), valid


def continuous_quaternions(q: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions with signs chosen so that neighbours lie on the same side (q and -q are one attitude):
    then interpolating the components goes the shorter way round."""
    q = np.asarray(q, np.float64).copy()
    if q.shape[0] < 2:
        return q
    flip = np.einsum("ij,ij->i", q[1:], q[:-1]) < 0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flip) % 2 == 1, -1.0, 1.0)])
    return q * sign[:, None]


def quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of (..., 4) quaternions (w, x, y, z): the rotation b, then a."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


#: ENU -> NED: (x, y, z) -> (y, x, -z), the rotation by 180 degrees about (1, 1, 0)/sqrt(2)
Q_NED_FROM_ENU = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5), 0.0])


def ned_from_enu_quaternion(q_enu: np.ndarray) -> np.ndarray:
    """(n, 4) platform -> NED attitudes of platform -> ENU ones (ROS REP 103's world frame), (w, x, y, z).

    >>> q = ned_from_enu_quaternion(np.array([[1.0, 0, 0, 0]]))          # level, x east, y north, z up
    >>> np.round(euler_from_quaternion(q), 6).tolist()                   # x heads east (90), turned over (180)
    [[180.0, -0.0, 90.0]]
    """
    return quaternion_product(Q_NED_FROM_ENU, np.asarray(q_enu, np.float64))


def quaternion_from_euler(heel_deg: np.ndarray, pitch_deg: np.ndarray, azimuth_deg: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions (w, x, y, z) of R = Rz(azimuth) Ry(pitch) Rx(heel) (the inverse of euler_from_quaternion).

    >>> q = quaternion_from_euler(np.array([10.0]), np.array([-20.0]), np.array([300.0]))
    >>> np.round(euler_from_quaternion(q), 9).tolist()
    [[10.0, -20.0, -60.0]]
    """
    h, p, a = (np.radians(np.asarray(v, np.float64)) / 2 for v in (heel_deg, pitch_deg, azimuth_deg))
    ch, sh, cp, sp, ca, sa = np.cos(h), np.sin(h), np.cos(p), np.sin(p), np.cos(a), np.sin(a)
    return np.column_stack([ca * cp * ch + sa * sp * sh, ca * cp * sh - sa * sp * ch,
                            ca * sp * ch + sa * cp * sh, sa * cp * ch - ca * sp * sh])


def euler_from_quaternion(q: np.ndarray) -> np.ndarray:
    """(n, 3) heel, pitch, azimuth in degrees of the platform -> NED attitudes q (n, 4) = (w, x, y, z), in fluxcal's
    convention R = Rz(azimuth) Ry(pitch) Rx(heel) (fluxcal.service.numerics.effects.base.ATTITUDE_EULER).

    >>> np.round(euler_from_quaternion(np.array([[np.cos(0.25), 0, 0, np.sin(0.25)]])), 6).tolist()
    [[0.0, -0.0, 28.64789]]
    """
    q = np.asarray(q, np.float64)
    big = np.max(np.abs(q), axis=1, keepdims=True)        # scaled first: a damaged log's 1e300 does not overflow
    q = q / np.where(big > 0, big, 1.0)
    w, x, y, z = (q[:, i] / np.linalg.norm(q, axis=1) for i in range(4))
    r20 = 2 * (x * z - y * w)
    r21 = 2 * (y * z + x * w)
    r22 = 1 - 2 * (x * x + y * y)
    r10 = 2 * (x * y + z * w)
    r00 = 1 - 2 * (y * y + z * z)
    heel = np.degrees(np.arctan2(r21, r22))
    pitch = np.degrees(-np.arcsin(np.clip(r20, -1.0, 1.0)))
    azimuth = np.degrees(np.arctan2(r10, r00))
    return np.column_stack([heel, pitch, azimuth])


#: a column is taken only where its samples give a value at this share of the probes' instants, at least
COLUMN_MIN_SHARE = 0.5
#: the name each auxiliary stream has in every log's mapping, by the column it gives (`--topics NAME=none` leaves it
#: out of a ROS 2 bag's, a PX4 log's or an ArduPilot log's mapping: docs/cli.md)
MAPPING_NAMES = {"attitude": "imu", "lat_deg": "gps", "lon_deg": "gps", "alt_m": "gps"}


def mapping_name(col: str) -> str | None:
    """The mapping's name of the stream that gives column `col` (battery1_current_a -> battery), None for another."""
    head = col.split(" ")[0]
    return "battery" if re.fullmatch(r"battery\d*_current_a", head) else MAPPING_NAMES.get(head)


def _columns_on(columns: dict[str, Series], t: np.ndarray, keep: np.ndarray, warnings: list[str],
                cuts: list[tuple[str, Series, np.ndarray]]) -> dict:
    """Each column interpolated at the instants t, `keep` narrowed to where it has a value (each column's
    (name, series, where it has a value) appended to `cuts`, said by _say_cuts). A column whose samples
    cover less than COLUMN_MIN_SHARE of the instants kept (a GPS logged on another clock, a stream that started
    late) is left out instead, not the probes' rows; said."""
    extras: dict[str, np.ndarray] = {}
    for col, s in columns.items():
        v, ok = interpolate(s, t)
        if np.count_nonzero(ok & keep) < COLUMN_MIN_SHARE * np.count_nonzero(keep):
            warnings.append(f"{col} ({s.source}, {s.n:,} samples): a value at only {int(np.count_nonzero(ok & keep)):,} "
                            f"of {int(np.count_nonzero(keep)):,} instants of the probes: the column left out (not the "
                            f"rows: its samples cover less than {COLUMN_MIN_SHARE:.0%} of them)")
            continue
        cuts.append((col, s, ok))
        keep &= ok
        extras[col] = v
    return extras


def merge(probes: list[tuple[str, Series]], *, temperatures: dict[str, Series] | None = None,
          columns: dict[str, Series] | None = None, attitude: Series | None = None) -> Merged:
    """One SampleBlock of the streams, by the rule of the module docstring.

    probes: (name, Series of (n, 3) nT), in the order the probes take; temperatures: probe name -> Series (n,) degC;
    columns: extra column name -> Series (n,); attitude: Series (n, 4) quaternions (w, x, y, z) of the platform ->
    NED attitude, given as the columns heel_deg, pitch_deg, azimuth_deg."""
    if not probes:
        raise ValueError("merge: no probe")
    temperatures, columns = dict(temperatures or {}), dict(columns or {})
    names = [n for n, _ in probes]
    base_k = int(np.argmin([s.n for _, s in probes]))
    base = probes[base_k][1]
    t = base.t_s
    keep = np.isfinite(t)
    warnings: list[str] = []
    notes: list[str] = []
    tol = 0.5 * _median_interval(t)
    if len(probes) > 1:
        notes.append(f"time base: the instants of {names[base_k]} ({base.source}, {base.n:,} samples, the probe with "
                     f"the fewest); every other probe matched to them by its nearest sample within "
                     f"{tol * 1e3:.3g} ms (half their median interval), one to one, never interpolated")
    n = t.size
    fld = np.full((n, len(probes), 3), np.nan)
    for k, (name, s) in enumerate(probes):
        if k == base_k:
            fld[:, k] = s.values
            continue
        idx = nearest_one_to_one(t, s.t_s, tol)
        got = idx >= 0
        fld[got, k] = s.values[idx[got]]
        miss = int(np.count_nonzero(~got & keep))
        if got.any():
            worst = float(np.max(np.abs(s.t_s[idx[got]] - t[got])))
            notes.append(f"{name} ({s.source}): {int(got.sum()):,} of its {s.n:,} samples matched, at most "
                         f"{worst * 1e3:.3g} ms from the time base")
        if miss:
            warnings.append(f"{name} ({s.source}): no sample within {tol * 1e3:.3g} ms of {miss:,} of the {n:,} "
                            f"instants of {names[base_k]}: those rows left out (the probes are compared sample by "
                            f"sample; a value is never borrowed from another instant)")
        keep &= got
    matched, cuts = keep.copy(), []
    extras = _columns_on(columns, t, keep, warnings, cuts)
    if attitude is not None:
        q, ok = interpolate(Series(attitude.t_s, continuous_quaternions(attitude.values), attitude.source), t)
        cuts.append(("attitude (heel_deg, pitch_deg, azimuth_deg)", attitude, ok))
        keep &= ok
        e = np.full((n, 3), np.nan)
        e[ok] = euler_from_quaternion(q[ok])
        extras.update(heel_deg=e[:, 0], pitch_deg=e[:, 1], azimuth_deg=e[:, 2])
    _say_cuts(warnings, cuts, matched)
    temp = np.full((n, len(probes)), np.nan)
    for name, s in temperatures.items():
        if name not in names:
            raise ValueError(f"merge: temperature for {name!r}, which is no probe (probes: {', '.join(names)})")
        v, ok = interpolate(s, t)
        temp[:, names.index(name)] = v
        lost = int(np.count_nonzero(~ok & keep))
        if lost:
            warnings.append(f"{name}_temp ({s.source}): no temperature at {lost:,} of {int(keep.sum()):,} instants "
                            f"(outside its samples or across a gap of more than {MAX_GAP_INTERVALS:g} of its "
                            f"intervals): NaN there, which the temperature terms interpolate over and count")
    for name in names:
        if name not in temperatures:
            notes.append(f"{name}: no temperature stream: its temperature is unknown (NaN), never another probe's")
    rows = np.flatnonzero(keep)
    if rows.size == 0:
        raise ValueError("merge: no instant at which every probe and column has a value"
                         + (f" ({'; '.join(warnings)})" if warnings else ""))
    t0 = float(t[rows[0]])
    block = SampleBlock(t_s=t[rows] - t0, seq=np.arange(rows.size, dtype=np.int64), field_nT=fld[rows],
                        temp_C=temp[rows], flags=np.zeros(rows.size, np.uint8),
                        extras={k: v[rows] for k, v in extras.items()})
    return Merged(block=block, t0_s=t0, warnings=warnings, notes=notes)


def _say_cuts(warnings: list[str], cuts: list[tuple[str, Series, np.ndarray]], keep: np.ndarray) -> None:
    """The rows each auxiliary stream cut (in the order they were taken, from the rows the probes matched: a row is
    told once, by the first stream that lacks it), and what keeps them: every stream that lacks them left out."""
    keep = keep.copy()
    for k, (col, s, ok) in enumerate(cuts):
        lost = ~ok & keep
        also = [c for c, _, other in cuts[k + 1:] if (lost & ~other).any()]
        every = all(not (lost & other).any() for c, _, other in cuts[k + 1:] if c in also)
        _say_cut(warnings, col, s, ok, keep, also, every)
        keep &= ok


def _say_cut(warnings: list[str], col: str, s: Series, ok: np.ndarray, keep: np.ndarray, also: list[str],
             every: bool = True) -> None:
    """One stream's cut rows: where they lie, and the mapping's names that keep them (`also`: the columns of the
    later streams that lack some of them too; `every`: each of those lacks every one of them)."""
    lost = int(np.count_nonzero(~ok & keep))
    if not lost:
        return
    before = int(np.count_nonzero(~ok & keep & (np.cumsum(ok) == 0)))
    after = int(np.count_nonzero(~ok & keep & (np.cumsum(ok[::-1])[::-1] == 0)))
    where = []
    if before:
        where.append(f"{before:,} before its first sample")
    if after:
        where.append(f"{after:,} after its last")
    if lost - before - after:
        where.append(f"{lost - before - after:,} across gaps of more than {MAX_GAP_INTERVALS:g} of its intervals")
    names = list(dict.fromkeys(mapping_name(c) for c in [col, *also]))
    others = list(dict.fromkeys(c.split(" ")[0] for c in also if mapping_name(c) != mapping_name(col)))
    which = (f"the stream and {', '.join(others)}, which {'lacks' if len(others) == 1 else 'lack'} "
             f"{'them' if every else 'some of them'} too," if others else "the stream")
    how = f" (--topics {','.join(f'{n}=none' for n in names)})" if None not in names else ""
    warnings.append(f"{col} ({s.source}, {s.n:,} samples): no value at {lost:,} rows ({', '.join(where)}): those rows "
                    f"left out (interpolated only between two samples, never extrapolated; leave {which} out of "
                    f"the mapping{how} to keep them)")
