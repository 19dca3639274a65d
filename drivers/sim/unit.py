"""The simulated acquisition unit: digitises the world (ADC counts, temperatures, flags, seq, clock)
and turns it into ICD bytes and CAN frames, with faults injected on request and a record of them.

Samples are addressed by index i from 0: world time i / rate_hz, seq = seq_start + i (wraps at 2^16),
t_us = t_us_start + round(i 1e6 / rate_hz) (wraps at 2^32); after a restart at index r (faults.restart_at_s)
seq = i - r and t_us = round((i - r) 1e6 / rate_hz). Every random decision is drawn by sample
index (world.ChunkedRandom), so any stretch of the run can be produced again, exactly.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..block import FLAG_SATURATED, FLAG_TEMP_INVALID, SampleBlock

#: the flag bit the simulated unit sets for faults.reserved_flag_fraction (bits 3..7 are 0 in the ICD)
FLAG_RESERVED_SIM = 0x08
from ..icd import SATURATED_COUNTS, TEMP_LSB_C, encode_can, encode_serial, frame_length
from ..outputs import replacing
from .config import SimConfig
from .streams import (STREAM_CAN, STREAM_GARBAGE, STREAM_GARBLE, STREAM_IMPLAUSIBLE, STREAM_SERIAL,
                      STREAM_TEMP_INVALID, STREAM_WIRE_REPEAT, ChunkedRandom)
from .world import World, WorldSamples

INT32_MAX, INT32_MIN = SATURATED_COUNTS
INT16_MIN, INT16_MAX = -32768, 32767


@dataclass
class UnitSamples:
    """Samples [start, stop) as the unit digitised them (what goes on the wire), plus the world behind."""

    index: np.ndarray          # (N,) int64 sample index
    seq: np.ndarray            # (N,) int64 unwrapped counter (seq_start + index)
    t_us: np.ndarray           # (N,) int64 unwrapped unit clock, us
    counts: np.ndarray         # (N, P, 3) int32
    temp_raw: np.ndarray       # (N, P) int16, 0.01 degC
    flags: np.ndarray          # (N,) uint8
    ref_total_nT: np.ndarray | None
    lsb_nT: float
    world: WorldSamples
    #: lat_deg, lon_deg, alt_m of each sample ([sim.track]), or None
    position: dict[str, np.ndarray] | None = None

    def __len__(self) -> int:
        return int(self.index.shape[0])

    @property
    def seq_raw(self) -> np.ndarray:
        return (self.seq & 0xFFFF).astype(np.uint16)

    @property
    def t_us_raw(self) -> np.ndarray:
        return (self.t_us & 0xFFFFFFFF).astype(np.uint32)

    @property
    def saturated(self) -> np.ndarray:
        """(N, P, 3) bool: axes at the int32 rails."""
        return (self.counts == INT32_MAX) | (self.counts == INT32_MIN)

    @property
    def field_nT(self) -> np.ndarray:
        """(N, P, 3) counts x lsb_nT, the rails included (no NaN); to_block() has NaN there."""
        return self.counts.astype(np.float64) * self.lsb_nT

    @property
    def temp_C(self) -> np.ndarray:
        return self.temp_raw.astype(np.float64) * TEMP_LSB_C

    def to_block(self) -> SampleBlock:
        """The SampleBlock a decoder of these frames yields: NaN where saturated or temperature invalid,
        t_s from the unit clock; ref_total (not on the wire) in extras when the reference is enabled."""
        field = self.field_nT
        field[self.saturated] = np.nan
        temp = self.temp_C
        temp[(self.flags & FLAG_TEMP_INVALID) != 0] = np.nan
        extras = {} if self.ref_total_nT is None else {"ref_total": self.ref_total_nT.copy()}
        if self.position is not None:
            extras.update({k: v.copy() for k, v in self.position.items()})
        return SampleBlock(t_s=self.t_us / 1e6, seq=self.seq.copy(), field_nT=field,
                           temp_C=temp, flags=self.flags.copy(), extras=extras)


class _Growing:
    """int64 values appended in place to one array whose capacity doubles when full. A record of many
    small additions then costs 8 bytes a value (up to twice that, the spare capacity), not a numpy
    array of its own per addition (~170 bytes resident for one index)."""

    __slots__ = ("buf", "n")

    def __init__(self) -> None:
        self.buf = np.empty(64, np.int64)
        self.n = 0

    def extend(self, values: np.ndarray) -> None:
        k = values.size
        if self.n + k > self.buf.size:
            grown = np.empty(max(2 * self.buf.size, self.n + k), np.int64)
            grown[:self.n] = self.buf[:self.n]
            self.buf = grown
        self.buf[self.n:self.n + k] = values
        self.n += k

    def view(self) -> np.ndarray:
        return self.buf[:self.n]


class _Indices:
    """The sample indices of one kind: single indices (`points`), and ranges [start, stop) as pairs
    (`ranges`), a range that continues the last one extending it (a reader away for an hour is one pair)."""

    __slots__ = ("points", "ranges")

    def __init__(self) -> None:
        self.points, self.ranges = _Growing(), _Growing()

    def add_range(self, start: int, stop: int) -> None:
        r = self.ranges
        if r.n and r.buf[r.n - 1] == start:
            r.buf[r.n - 1] = stop
        else:
            r.extend(np.array([start, stop], np.int64))

    def all(self) -> np.ndarray:
        """Every index (a new array): the points in the order added, then the ranges spelled out."""
        pairs = self.ranges.view().reshape(-1, 2)
        start, length = pairs[:, 0], pairs[:, 1] - pairs[:, 0]
        spelled = np.repeat(start - (np.cumsum(length) - length), length) + np.arange(length.sum(), dtype=np.int64)
        return np.concatenate([self.points.view(), spelled])


class FaultRecord:
    """Exactly what was done to the stream, by sample index; thread-safe (an emitter thread writes it).

    kinds (sample indices): drop_frame, bitflip, drop_byte (serial frames corrupted or never sent),
    garbage_after (frames followed by garbage bytes; no frame is lost by garbage), duplicate (frames sent
    twice), stale (frames followed by the one faults.stale_frames before them, sent again), wrong_baud
    (frames that arrived garbled), outage (samples produced while the port was closed), silence (samples
    never sent while the port stayed open), no_reader (produced while no reader had the port open, thrown
    away like a real unit's UART would); CAN: can_dropped holds (sample, probe, axis) rows.

    It keeps every index on purpose, so it grows with every fault, but by the index only: one growing
    array per kind (not an array per batch), and ranges (outage, no_reader) as [start, stop) pairs."""

    SERIAL_LOSSES = ("drop_frame", "bitflip", "drop_byte", "wrong_baud", "outage", "silence", "no_reader")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._kinds: dict[str, _Indices] = {}
        self.garbage_bytes = 0

    def _of(self, kind: str) -> _Indices:
        got = self._kinds.get(kind)
        if got is None:
            got = self._kinds[kind] = _Indices()
        return got

    def add(self, kind: str, values: np.ndarray) -> None:
        values = np.asarray(values, dtype=np.int64).reshape(-1)
        if values.size:
            with self._lock:
                self._of(kind).points.extend(values)

    def add_garbage_bytes(self, n: int) -> None:
        with self._lock:
            self.garbage_bytes += n

    def add_range(self, kind: str, start: int, stop: int) -> None:
        if stop > start:
            with self._lock:
                self._of(kind).add_range(int(start), int(stop))

    def _all(self, kind: str) -> np.ndarray | None:
        with self._lock:
            got = self._kinds.get(kind)
            return None if got is None else got.all()

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays the record holds (spare capacity included)."""
        with self._lock:
            return sum(g.buf.nbytes for i in self._kinds.values() for g in (i.points, i.ranges))

    def samples(self, kind: str) -> np.ndarray:
        """Sorted unique sample indices of one kind (for can_dropped: the samples hit)."""
        joined = self._all(kind)
        if joined is None:
            return np.empty(0, np.int64)
        if kind == "can_dropped":
            joined = joined.reshape(-1, 3)[:, 0]
        return np.unique(joined)

    def can_dropped(self) -> np.ndarray:
        """(M, 3) int64 rows (sample, probe, axis) of CAN frames never sent."""
        joined = self._all("can_dropped")
        return joined.reshape(-1, 3) if joined is not None else np.empty((0, 3), np.int64)

    def serial_lost(self) -> np.ndarray:
        """Samples a serial reader cannot get intact: corrupted, dropped, or sent while nobody listened."""
        return np.unique(np.concatenate([self.samples(k) for k in self.SERIAL_LOSSES]))

    def can_incomplete(self) -> np.ndarray:
        """Samples a CAN reader cannot complete: a frame dropped, or the bus silent."""
        return np.unique(np.concatenate([self.samples(k) for k in ("can_dropped", "outage", "silence", "no_reader")]))

    def save(self, path: str, **meta: int) -> None:
        """Write the whole record (every index of every kind, the garbage byte count) and integer `meta`
        (e.g. the emitter's start and next index) to an .npz file: how a simulator run in another process
        tells its reader exactly what it did. FaultRecord.load reads it back."""
        with self._lock:
            arrays = {f"kind_{k}": i.all() for k, i in self._kinds.items()}
            garbage = self.garbage_bytes
        meta_arrays = {f"meta_{k}": np.int64(v) for k, v in meta.items()}
        with replacing(path) as f:                     # whole or absent: a killed writer leaves no half file
            np.savez(f, garbage_bytes=np.int64(garbage), **arrays, **meta_arrays)

    @classmethod
    def load(cls, path: str) -> tuple["FaultRecord", dict[str, int]]:
        """The record FaultRecord.save wrote, and its meta."""
        rec, meta = cls(), {}
        with np.load(path, allow_pickle=False) as z:
            for name in z.files:
                if name.startswith("kind_"):
                    rec.add(name[len("kind_"):], z[name])
                elif name.startswith("meta_"):
                    meta[name[len("meta_"):]] = int(z[name])
            rec.garbage_bytes = int(z["garbage_bytes"])
        return rec, meta

    def as_dict(self) -> dict[str, Any]:
        """Counts per kind, for a summary or a log line."""
        with self._lock:
            kinds = list(self._kinds)
        out: dict[str, Any] = {k: int(self.samples(k).size) for k in kinds}
        if "can_dropped" in kinds:
            out["can_dropped_frames"] = int(self.can_dropped().shape[0])
        out["garbage_bytes"] = self.garbage_bytes
        return out


class Unit:
    """The acquisition unit in front of a World: digitisation, ICD encoding, faults."""

    def __init__(self, config: SimConfig, world: World | None = None) -> None:
        self.config = config
        self.world = world if world is not None else World(config)
        self.n_probes = config.n_probes
        self.rate_hz = config.rate_hz
        self.n_samples = config.n_samples
        self.lsb_nT = config.lsb_nT
        self.frame_length = frame_length(self.n_probes)
        seed = config.seed
        self._temp_invalid = ChunkedRandom(seed, STREAM_TEMP_INVALID, (), kind="uniform")
        self._serial_u = ChunkedRandom(seed, STREAM_SERIAL, (8,), kind="uniform")
        self._garbage = ChunkedRandom(seed, STREAM_GARBAGE, (config.faults.garbage_max_bytes,), kind="bytes")
        self._can_u = ChunkedRandom(seed, STREAM_CAN, (3 * self.n_probes,), kind="uniform")
        self._implausible_u = ChunkedRandom(seed, STREAM_IMPLAUSIBLE, (4,), kind="uniform")
        self._repeat_u = ChunkedRandom(seed, STREAM_WIRE_REPEAT, (2,), kind="uniform")
        self._garble = ChunkedRandom(seed, STREAM_GARBLE, (self.frame_length,), kind="bytes")
        # what digitise has made so far (a range digitised twice counts twice): for a writer's summary
        self.saturated_samples = np.zeros(self.n_probes, dtype=np.int64)    # per probe, any axis on a rail
        self.temp_invalid_samples = 0

    # -- time --------------------------------------------------------------------------------------
    def index_at(self, t_s: float) -> int:
        """First sample index at or after world time t_s."""
        return max(0, math.ceil(t_s * self.rate_hz - 1e-9))

    def _stretches(self, at_s: list[float], span_s: float) -> list[tuple[int, int]]:
        out = [(self.index_at(a), self.index_at(a + span_s)) for a in at_s]
        if self.n_samples is not None:
            out = [(a, min(b, self.n_samples)) for a, b in out if a < self.n_samples]
        return [(a, b) for a, b in out if b > a]

    def outages(self) -> list[tuple[int, int]]:
        """Sample ranges [a, b) during which the port is closed (faults.outage_at_s, outage_s)."""
        f = self.config.faults
        return self._stretches(f.outage_at_s, f.outage_s)

    def silences(self) -> list[tuple[int, int]]:
        """Sample ranges [a, b) the unit does not send, the port staying open (faults.silence_at_s, silence_s)."""
        f = self.config.faults
        return self._stretches(f.silence_at_s, f.silence_s)

    def wrong_baud(self) -> list[tuple[int, int]]:
        """Sample ranges [a, b) whose bytes arrive garbled (faults.wrong_baud_at_s, wrong_baud_s)."""
        f = self.config.faults
        return self._stretches(f.wrong_baud_at_s, f.wrong_baud_s)

    def restarts(self) -> np.ndarray:
        """Sample indices at which the unit restarts (faults.restart_at_s), increasing."""
        return np.array([self.index_at(a) for a in self.config.faults.restart_at_s], np.int64)

    # -- digitisation ------------------------------------------------------------------------------
    def digitise(self, start: int, stop: int) -> UnitSamples:
        """Samples [start, stop): counts = round(raw / lsb_nT), saturating at the int32 rails (flag
        bit0) or beyond range_nT; temperatures in 0.01 degC; temperature-invalid flags on request."""
        w = self.world.samples(start, stop)
        raw = w.raw_nT
        x = raw / self.lsb_nT
        # a value that rounds onto a rail would read as saturated: count it as saturated
        sat = (x > INT32_MAX - 0.5) | (x < INT32_MIN + 0.5)
        if self.config.range_nT is not None:
            sat |= np.abs(raw) > self.config.range_nT
        counts = np.where(sat, np.where(x > 0, INT32_MAX, INT32_MIN), np.rint(np.where(sat, 0.0, x)))
        counts = counts.astype(np.int32)
        temp_raw = np.clip(np.rint(w.temp_C / TEMP_LSB_C), INT16_MIN, INT16_MAX).astype(np.int16)
        flags = np.where(sat.any(axis=(1, 2)), FLAG_SATURATED, 0).astype(np.uint8)
        f = self.config.faults
        if f.temp_invalid_fraction > 0:
            bad = self._temp_invalid.draw(start, stop) < f.temp_invalid_fraction
            flags[bad] |= FLAG_TEMP_INVALID
            self.temp_invalid_samples += int(np.count_nonzero(bad))
        self.saturated_samples += np.count_nonzero(sat.any(axis=2), axis=0)
        if f.reserved_flag_fraction or f.full_scale_fraction or f.zero_vector_fraction or f.temp_rail_fraction:
            # valid frames with values no probe gives: set after the counters above, on purpose
            u = self._implausible_u.draw(start, stop)
            flags[u[:, 0] < f.reserved_flag_fraction] |= FLAG_RESERVED_SIM
            counts[u[:, 1] < f.full_scale_fraction, 0, 0] = INT32_MAX - 1
            counts[u[:, 2] < f.zero_vector_fraction, -1, :] = 0
            temp_raw[u[:, 3] < f.temp_rail_fraction, 0] = INT16_MAX
        index = np.arange(start, stop, dtype=np.int64)
        seq = self.config.seq_start + index
        t_us = self.config.t_us_start + np.rint(index * (1e6 / self.rate_hz)).astype(np.int64)
        restarts = self.restarts()
        if restarts.size:
            k = np.searchsorted(restarts, index, side="right") - 1
            since = index - restarts[np.maximum(k, 0)]
            seq = np.where(k >= 0, since, seq)
            t_us = np.where(k >= 0, np.rint(since * (1e6 / self.rate_hz)).astype(np.int64), t_us)
        return UnitSamples(index=index, seq=seq, t_us=t_us, counts=counts,
                           temp_raw=temp_raw, flags=flags, ref_total_nT=w.ref_total_nT, lsb_nT=self.lsb_nT,
                           world=w, position=None if self.world.track is None else self.world.track.position(w.t_s))

    # -- serial ------------------------------------------------------------------------------------
    def serial_bytes(self, start: int, stop: int, *, faults: bool = True, record: FaultRecord | None = None,
                     samples: UnitSamples | None = None) -> bytes:
        """ICD serial frames of samples [start, stop), with the configured serial faults applied
        (garbage, bit flips, dropped bytes, dropped frames, duplicated and stale frames, garbled stretches)
        and written into `record`."""
        s = samples if samples is not None else self.digitise(start, stop)
        frames = encode_serial(s.seq_raw, s.t_us_raw, s.counts, s.temp_raw, s.flags)
        f = self.config.faults
        garbled = np.zeros(len(s), bool)
        for a, b in self.wrong_baud():
            garbled[max(a, start) - start:max(min(b, stop) - start, 0)] = True
        if not faults or not (f.garbage_fraction or f.bitflip_fraction or f.drop_byte_fraction
                              or f.drop_frame_fraction or f.duplicate_fraction or f.stale_fraction or garbled.any()):
            return frames
        k, fl = len(s), self.frame_length
        a = np.frombuffer(frames, np.uint8).reshape(k, fl).copy()
        u = self._serial_u.draw(start, stop)              # (K, 8): one row of decisions per frame
        rows = np.arange(k)
        drop = u[:, 0] < f.drop_frame_fraction
        flip = (u[:, 1] < f.bitflip_fraction) & ~drop
        lose = (u[:, 2] < f.drop_byte_fraction) & ~drop
        garbage = u[:, 3] < f.garbage_fraction
        flip_byte = np.minimum((u[:, 4] * fl).astype(np.int64), fl - 1)
        flip_bit = np.minimum((u[:, 5] * 8).astype(np.int64), 7)
        a[rows[flip], flip_byte[flip]] ^= (1 << flip_bit[flip]).astype(np.uint8)
        keep = np.ones((k, fl), bool)
        keep[drop] = False
        lose_byte = np.minimum((u[:, 6] * fl).astype(np.int64), fl - 1)
        keep[rows[lose], lose_byte[lose]] = False
        gmax = f.garbage_max_bytes
        glen = np.where(garbage, 1 + np.minimum((u[:, 7] * gmax).astype(np.int64), gmax - 1), 0)
        gbytes = self._garbage.draw(start, stop)           # (K, gmax)
        gkeep = np.arange(gmax)[None, :] < glen[:, None]
        # a frame sent twice (as it went out, damage and all); a stale frame (stale_frames back, intact) after it
        r = self._repeat_u.draw(start, stop) if f.duplicate_fraction or f.stale_fraction else np.ones((k, 2))
        dup = (r[:, 0] < f.duplicate_fraction) & ~drop
        stale = (r[:, 1] < f.stale_fraction) & (s.index >= f.stale_frames)
        old = np.zeros((k, fl), np.uint8)
        if stale.any():
            idx = np.flatnonzero(stale)
            inside = idx - f.stale_frames >= 0
            old[idx[inside]] = np.frombuffer(frames, np.uint8).reshape(k, fl)[idx[inside] - f.stale_frames]
            for i in idx[~inside]:                         # the stale frame comes from before this stretch
                j = int(s.index[i]) - f.stale_frames
                p = self.digitise(j, j + 1)
                old[i] = np.frombuffer(encode_serial(p.seq_raw, p.t_us_raw, p.counts, p.temp_raw, p.flags), np.uint8)
        if garbled.any():
            # read at a wrong baud rate: every byte of those frames arrives as another; nothing else comes
            a[garbled] = self._garble.draw(start, stop)[garbled]
            keep[garbled] = True
            dup &= ~garbled
            stale &= ~garbled
            gkeep[garbled] = False
        parts = np.concatenate([a, a, old, gbytes], axis=1)
        mask = np.concatenate([keep, keep & dup[:, None], np.repeat(stale[:, None], fl, axis=1), gkeep], axis=1)
        out = parts[mask]
        if record is not None:
            idx = s.index
            record.add("drop_frame", idx[drop & ~garbled])
            record.add("bitflip", idx[flip & ~garbled])
            record.add("drop_byte", idx[lose & ~garbled])
            record.add("garbage_after", idx[garbage & ~garbled])
            record.add("duplicate", idx[dup])
            record.add("stale", idx[stale])
            record.add("wrong_baud", idx[garbled])
            record.add_garbage_bytes(int(glen[~garbled].sum()))
        return out.tobytes()

    # -- CAN ---------------------------------------------------------------------------------------
    def can_frames(self, start: int, stop: int, *, faults: bool = True, record: FaultRecord | None = None,
                   samples: UnitSamples | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ICD CAN frames of samples [start, stop) in sending order (sample, probe, axis), less those
        dropped on purpose (faults.can_drop_fraction, written into `record`).

        Returns arbitration ids (M,), payloads (M, 8) uint8 and the sample index of each frame (M,)."""
        s = samples if samples is not None else self.digitise(start, stop)
        ids, payloads = encode_can(s.seq_raw, s.counts, s.temp_raw, self.config.can_base_id)
        per = 3 * self.n_probes
        sample_of = np.repeat(s.index, per)
        p = self.config.faults.can_drop_fraction
        if faults and p > 0:
            dropped = (self._can_u.draw(start, stop) < p).reshape(-1)
            if record is not None and dropped.any():
                j = np.flatnonzero(dropped)
                record.add("can_dropped", np.stack([sample_of[j], (j % per) // 3, j % 3], axis=1).reshape(-1))
            keep = ~dropped
            ids, payloads, sample_of = ids[keep], payloads[keep], sample_of[keep]
        return ids, payloads, sample_of


__all__ = ["Unit", "UnitSamples", "FaultRecord"]
