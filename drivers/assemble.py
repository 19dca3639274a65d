"""From wire frames to SampleBlocks: the serial stream framer, the CAN sample assembler and the
scaling to physical units, shared by the live sources (serial, CAN) and `fluxcal decode`.

Pure numpy over whole batches (no per-sample Python loop) and no I/O: the sources read bytes or
CAN frames, these classes turn them into samples and keep the health counters.

    SerialFramer    bytes in arbitrary chunks -> RawFrames (keeps the unconsumed tail; counters)
    SerialTimeline  orders frames by their counter and clock: duplicates, stale frames and unit restarts
    FrameAssembler  RawFrames -> SampleBlock (seq and the unit clock unwrapped, monotonic; gaps counted)
    CanAssembler    CAN frames (id, 8-byte payload) -> complete samples, in seq order, bounded memory
    scale_samples   counts -> nT, raw temperature -> degC, saturation and invalid temperature -> NaN,
                    implausible values flagged (Plausibility)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .block import FLAG_SATURATED, FLAG_TEMP_INVALID, SampleBlock
from .can_settled import SettledFrames, earlier_in_batch_differs, slot_differs
from .can_unwrap import CanUnwrap
from .icd import DEFAULT_CAN_BASE_ID, SATURATED_COUNTS, TEMP_LSB_C, RawFrames, decode_can, frame_length, parse_serial
from .plausibility import Plausibility
from .source import Counters
from .timeline import SerialTimeline, _steps

_SEQ_MODULUS = 1 << 16


def scale_samples(seq: np.ndarray, t_s: np.ndarray, counts: np.ndarray, temp_raw: np.ndarray,
                  flags: np.ndarray, *, lsb_nT: float, counters: Counters | None = None,
                  plausibility: Plausibility | None = None) -> SampleBlock:
    """Scale integer samples to a SampleBlock.

    field_nT = counts * lsb_nT, NaN where an axis is saturated (exactly int32 max or min);
    temp_C = temp_raw * 0.01, NaN for a sample whose flags say the temperature is invalid.
    Saturated axes and invalid-temperature samples are added to `counters`; with `plausibility`,
    implausible samples are flagged FLAG_IMPLAUSIBLE (their values kept) and counted.
    """
    counts = np.asarray(counts)
    field_nT = counts * float(lsb_nT)                        # nT = counts x lsb_nT
    flags = np.asarray(flags, dtype=np.uint8)
    temp_C = np.asarray(temp_raw) * TEMP_LSB_C                # degC = raw x 0.01
    n = counts.shape[0]
    # the usual block has no axis at a rail and no flag: two reductions say so, and no mask is made
    lo, hi = (int(counts.min()), int(counts.max())) if counts.size else (0, 0)
    railed = lo == SATURATED_COUNTS[1] or hi == SATURATED_COUNTS[0]
    saturated = (counts == SATURATED_COUNTS[0]) | (counts == SATURATED_COUNTS[1]) if railed else None
    flagged = bool(n) and bool(flags.any())
    temp_bad = (flags & FLAG_TEMP_INVALID) != 0 if flagged else None
    if plausibility is not None and n:
        # the field's extremes are the counts' scaled (x lsb_nT > 0 rounds monotonically), element for element
        flags = plausibility.flag(field_nT, saturated, counts, temp_C, temp_bad, flags, counters,
                                  field_range_nT=(lo * float(lsb_nT), hi * float(lsb_nT)))
    if saturated is not None:
        field_nT[saturated] = np.nan
    if temp_bad is not None:
        temp_C[temp_bad] = np.nan
    if counters is not None:
        counters.saturated_axes += 0 if saturated is None else int(np.count_nonzero(saturated))
        counters.temp_invalid += 0 if temp_bad is None else int(np.count_nonzero(temp_bad))
    return SampleBlock(t_s=np.asarray(t_s, dtype=np.float64), seq=np.asarray(seq, dtype=np.int64),
                       field_nT=field_nT, temp_C=temp_C, flags=flags)


class SeqGapCounter:
    """Counts gaps in an unwrapped sample counter across blocks: a step of d > 1 is one gap and
    d - 1 missed samples. Steps of 0 or backwards (a duplicate, a unit restart) are not gaps."""

    def __init__(self) -> None:
        self.last: int | None = None

    def update(self, seq: np.ndarray, counters: Counters) -> None:
        if seq.size == 0:
            return
        steps = _steps(seq, int(seq[0]) if self.last is None else self.last)
        self.last = int(seq[-1])
        if steps.max() <= 1:              # the usual block: no gap, one reduction
            return
        gaps = steps > 1
        counters.seq_gaps += int(np.count_nonzero(gaps))
        counters.samples_missed += int((steps[gaps] - 1).sum())


class SerialFramer:
    """Turns a serial byte stream, fed in chunks of any size, into RawFrames.

    Keeps the unconsumed tail (at most one frame) between chunks and counts frames accepted,
    CRC failures and bytes skipped, so that at any time
    frames_accepted x frame_length + bytes_skipped + pending_bytes == bytes_fed
    (the port counts the bytes it read: bytes_received).
    """

    def __init__(self, n_probes: int, counters: Counters | None = None) -> None:
        self.n_probes = n_probes
        self.frame_length = frame_length(n_probes)
        self.counters = counters if counters is not None else serial_icd_counters()
        self.bytes_fed = 0
        self._tail = b""

    @property
    def pending_bytes(self) -> int:
        return len(self._tail)

    def feed(self, data: bytes | bytearray | memoryview, final: bool = False) -> RawFrames:
        """Parse the tail plus `data`; with `final`, the stream ends here and no tail is kept."""
        self.bytes_fed += len(data)
        buf = self._tail + bytes(data) if self._tail else bytes(data)
        parsed = parse_serial(buf, self.n_probes, final=final)
        self._tail = buf[parsed.consumed:]
        c = self.counters
        c.frames_accepted += len(parsed.frames)
        c.crc_failures += parsed.crc_failures
        c.bytes_skipped += parsed.bytes_skipped
        return parsed.frames

    def finish(self) -> RawFrames:
        """End of stream: whatever is left can no longer complete a frame."""
        return self.feed(b"", final=True)

    def discard_tail(self) -> None:
        """Forget a partial frame (the port was reopened: its rest will never come); count it skipped."""
        self.counters.bytes_skipped += len(self._tail)
        self._tail = b""


class FrameAssembler:
    """RawFrames from one unit -> SampleBlocks: frames ordered by SerialTimeline (seq and the unit clock t_us
    unwrapped, strictly increasing; duplicates and stale frames dropped, restarts followed), t_s = t_us / 1e6,
    scaled with lsb_nT, implausible samples flagged, gaps counted."""

    def __init__(self, n_probes: int, lsb_nT: float, counters: Counters | None = None,
                 plausibility: Plausibility | None = Plausibility()) -> None:
        self.n_probes = n_probes
        self.lsb_nT = float(lsb_nT)
        self.counters = counters if counters is not None else serial_icd_counters()
        self.plausibility = plausibility
        self._timeline = SerialTimeline(self.counters)
        self._gaps = SeqGapCounter()

    def block(self, frames: RawFrames, rx_time_s: float | None = None) -> SampleBlock:
        """The samples of `frames`; rx_time_s (host monotonic time they were read) times a unit restart."""
        if len(frames) == 0:
            return SampleBlock.empty(self.n_probes)
        keep, seq, t_us = self._timeline.order(frames, rx_time_s)
        counts, temp_raw, flags = frames.counts, frames.temp_raw, frames.flags
        if keep is not None and not keep.all():
            counts, temp_raw, flags = counts[keep], temp_raw[keep], flags[keep]
        held = self._timeline.carried                       # frames of earlier blocks a restart confirmed now
        if held is not None:
            counts, temp_raw, flags = (np.concatenate([held.counts, counts]), np.concatenate([held.temp_raw, temp_raw]),
                                       np.concatenate([held.flags, flags]))
        # division, not x 1e-6: t_us / 1e6 is the double nearest the exact time, so printing
        # it with 6 decimals gives back the unit's microseconds exactly
        t_s = t_us / 1e6
        if self._timeline.contiguous and self._gaps.last is not None:
            self._gaps.last = int(seq[-1])               # every step one count: no gap to count
        else:
            self._gaps.update(seq, self.counters)
        return scale_samples(seq, t_s, counts, temp_raw, flags, lsb_nT=self.lsb_nT, counters=self.counters,
                             plausibility=self.plausibility)


def serial_icd_counters() -> Counters:
    """The counters of a serial unit speaking the ICD (drivers/kinds/serial.py), all 0."""
    from .kinds.serial import KIND

    return Counters.of(KIND.words())


def can_icd_counters() -> Counters:
    """The counters of a CAN unit speaking the ICD (drivers/kinds/can.py), all 0."""
    from .kinds.can import KIND

    return Counters.of(KIND.words())


@dataclass(frozen=True)
class CanSamples:
    """Complete CAN samples in seq order, before scaling."""

    seq: np.ndarray        # (K,) int64 unwrapped
    counts: np.ndarray     # (K, n, 3) int32
    temp_raw: np.ndarray   # (K, n) int16
    rx_time_s: np.ndarray  # (K,) float64 earliest receive time of the sample's frames

    def __len__(self) -> int:
        return int(self.seq.shape[0])

    @property
    def flags(self) -> np.ndarray:
        """CAN carries no flags byte: bit0 (saturated) is derived from the counts; the
        temperature-invalid and clock bits cannot be known and stay 0."""
        sat = (self.counts == SATURATED_COUNTS[0]) | (self.counts == SATURATED_COUNTS[1])
        return np.where(sat.any(axis=(1, 2)), FLAG_SATURATED, 0).astype(np.uint8)

    @staticmethod
    def empty(n_probes: int) -> "CanSamples":
        return CanSamples(seq=np.empty(0, np.int64), counts=np.empty((0, n_probes, 3), np.int32),
                          temp_raw=np.empty((0, n_probes), np.int16), rx_time_s=np.empty(0))

    @staticmethod
    def concat(parts: "list[CanSamples]", n_probes: int) -> "CanSamples":
        parts = [p for p in parts if len(p)]
        if not parts:
            return CanSamples.empty(n_probes)
        return CanSamples(seq=np.concatenate([p.seq for p in parts]),
                          counts=np.concatenate([p.counts for p in parts]),
                          temp_raw=np.concatenate([p.temp_raw for p in parts]),
                          rx_time_s=np.concatenate([p.rx_time_s for p in parts]))

    def to_block(self, *, rate_hz: float, lsb_nT: float, counters: Counters | None = None,
                 plausibility: Plausibility | None = Plausibility()) -> SampleBlock:
        """Scale to a SampleBlock. CAN has no unit clock, so t_s = seq / rate_hz (seq unwrapped)."""
        return scale_samples(self.seq, self.seq / float(rate_hz), self.counts, self.temp_raw, self.flags,
                             lsb_nT=lsb_nT, counters=counters, plausibility=plausibility)


class CanAssembler:
    """Collects the 3n CAN frames of each sample (ICD: id = base + 4k + a, payload value, seq, temp)
    and releases complete samples in seq order.

    Frames of neighbouring samples may interleave and frames may be lost. An incomplete sample is
    dropped and counted (can_incomplete) once seq has moved on by more than `window_samples`
    beyond it, or once `window_s` has passed since its first frame: nothing is held forever and
    at most window_samples + 1 samples (plus one batch) are held. Complete samples behind an
    incomplete one wait for it so that output stays in seq order.

    Frames with foreign or reserved ids are ignored (the bus is shared). A frame for a sample
    already settled (released or given up), or for a slot of a pending sample already filled, is
    ignored and counted in `duplicates`, unless it steps back to a counter near zero with another
    value than the slot holds: the unit started again (can_settled keeps the last 4 windows' frames
    to compare). seq is unwrapped by fluxcal.drivers.can_unwrap.CanUnwrap: across wraps and
    restarts of the unit (counted in `restarts`), with the old run's frames that come after a restart's first
    frame kept in the old run: the unwrapped seq (and t_s = seq / rate_hz) never goes back, and no sample is
    counted missed that never existed.
    """

    def __init__(self, n_probes: int, *, base_id: int = DEFAULT_CAN_BASE_ID, window_samples: int = 32,
                 window_s: float = 0.5, counters: Counters | None = None, rate_hz: float | None = None) -> None:
        self.n_probes = n_probes
        self.rate_hz = rate_hz
        self.base_id = base_id
        self.window_samples = int(window_samples)
        self.window_s = float(window_s)
        self.restart_samples = max(4 * self.window_samples, 1024)
        self.counters = counters if counters is not None else can_icd_counters()
        self._unwrap = CanUnwrap(window_samples=self.window_samples, restart_samples=self.restart_samples,
                                 rate_hz=rate_hz, counters=self.counters, frames_per_sample=3 * n_probes)
        self._max_seen: int | None = None
        self._done_upto: int | None = None     # every sample <= this was released or dropped
        self._settled = SettledFrames(n_probes, 4 * self.window_samples)   # their frames, to tell a repeat
        self._clear_pending()

    def _clear_pending(self) -> None:
        n = self.n_probes
        self._p_seq = np.empty(0, np.int64)
        self._p_counts = np.zeros((0, n, 3), np.int32)
        self._p_temp = np.zeros((0, n, 3), np.int16)
        self._p_have = np.zeros((0, n, 3), bool)
        self._p_first = np.empty(0)

    @property
    def pending_samples(self) -> int:
        return int(self._p_seq.size)

    def push(self, ids: np.ndarray, payloads: np.ndarray, rx_time_s: np.ndarray | float,
             now_s: float | None = None) -> CanSamples:
        """Add a batch of frames (ids (M,), payloads (M, 8) uint8, receive times) and return the
        samples that are complete and due, in seq order. `now_s` (default: the latest receive
        time) drives the time limit."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        payloads = np.asarray(payloads, dtype=np.uint8).reshape(-1, 8)
        rx = np.broadcast_to(np.asarray(rx_time_s, dtype=np.float64), ids.shape)
        if now_s is None:
            now_s = float(rx.max()) if rx.size else -np.inf
        probe, axis, value, seq, temp = decode_can(ids, payloads, self.n_probes, self.base_id)
        mine = probe >= 0
        probe, axis, value, seq, temp, rx = (x[mine] for x in (probe, axis, value, seq, temp, rx))
        self.counters.frames_accepted += int(probe.size)
        self.counters.foreign_frames += int(mine.size - probe.size)      # other nodes' ids, or reserved ones

        def differs(u: np.ndarray, idx: np.ndarray) -> np.ndarray:
            """Frames idx (numbered u) on a slot settled, held or earlier in this batch with another value."""
            args = (u[idx], probe[idx], axis[idx], value[idx], temp[idx])
            return (slot_differs(*args, *self._settled.held())
                    | slot_differs(*args, self._p_seq, self._p_counts, self._p_temp, self._p_have)
                    | earlier_in_batch_differs(u, probe, axis, value, temp, idx, self.n_probes))

        u = self._unwrap(seq, rx, self._done_upto, differs)
        self._merge(u, probe, axis, value, temp, rx)
        return self._release(now_s, final=False)

    def flush(self) -> CanSamples:
        """End of input: release every complete sample, drop (and count) the incomplete ones."""
        return self._release(np.inf, final=True)

    def _merge(self, u: np.ndarray, probe: np.ndarray, axis: np.ndarray, value: np.ndarray,
               temp: np.ndarray, rx: np.ndarray) -> None:
        if self._done_upto is not None:
            late = u <= self._done_upto
            if late.any():
                self.counters.duplicates += int(np.count_nonzero(late))
                keep = ~late
                u, probe, axis, value, temp, rx = (x[keep] for x in (u, probe, axis, value, temp, rx))
        if u.size == 0:
            return
        old = self._p_seq.size
        seqs, inverse = np.unique(np.concatenate([self._p_seq, u]), return_inverse=True)
        g, n = seqs.size, self.n_probes
        counts = np.zeros((g, n, 3), np.int32)
        temps = np.zeros((g, n, 3), np.int16)
        have = np.zeros((g, n, 3), bool)
        first = np.full(g, np.inf)
        rows_old, rows_new = inverse[:old], inverse[old:]
        counts[rows_old] = self._p_counts
        temps[rows_old] = self._p_temp
        have[rows_old] = self._p_have
        first[rows_old] = self._p_first
        # a slot filled before, or twice in this batch: a repeated frame (the last one counts)
        slot = (rows_new * n + probe) * 3 + axis
        self.counters.duplicates += int(np.count_nonzero(have.reshape(-1)[slot])) + slot.size - np.unique(slot).size
        counts[rows_new, probe, axis] = value
        temps[rows_new, probe, axis] = temp
        have[rows_new, probe, axis] = True
        np.minimum.at(first, rows_new, rx)
        self._p_seq, self._p_counts, self._p_temp, self._p_have, self._p_first = seqs, counts, temps, have, first
        top = int(seqs[-1])
        self._max_seen = top if self._max_seen is None else max(self._max_seen, top)

    def _release(self, now_s: float, final: bool) -> CanSamples:
        seqs = self._p_seq
        if seqs.size == 0:
            return CanSamples.empty(self.n_probes)
        complete = self._p_have.all(axis=(1, 2))
        if final:
            expired = ~complete
        else:
            too_old = seqs < self._max_seen - self.window_samples
            too_late = (now_s - self._p_first) > self.window_s
            expired = ~complete & (too_old | too_late)
        waiting = ~complete & ~expired
        release_below = seqs[waiting][0] if waiting.any() else np.iinfo(np.int64).max
        emit = complete & (seqs < release_below)
        self.counters.can_incomplete += int(np.count_nonzero(expired))
        settled = emit | expired
        if settled.any():
            self._settled.add(seqs[settled], self._p_counts[settled], self._p_temp[settled], self._p_have[settled])
            top = int(seqs[settled].max())
            self._done_upto = top if self._done_upto is None else max(self._done_upto, top)
        out = CanSamples(seq=seqs[emit], counts=self._p_counts[emit],
                         temp_raw=self._p_temp[emit][:, :, 0].copy(), rx_time_s=self._p_first[emit])
        keep = ~settled
        self._p_seq, self._p_counts, self._p_temp, self._p_have, self._p_first = (
            x[keep] for x in (self._p_seq, self._p_counts, self._p_temp, self._p_have, self._p_first))
        return out
