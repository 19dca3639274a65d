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

from .block import FLAG_IMPLAUSIBLE, FLAG_SATURATED, FLAG_TEMP_INVALID, FLAGS_RESERVED, SampleBlock
from .config import spec
from .errors import ConfigError
from .icd import (DEFAULT_CAN_BASE_ID, SATURATED_COUNTS, TEMP_LSB_C, RawFrames, decode_can,
                  frame_length, parse_serial)
from .source import Counters

_SEQ_MODULUS = 1 << 16


@dataclass(frozen=True)
class Plausibility:
    """What a frame that passed its CRC may still not hold. A sample is flagged FLAG_IMPLAUSIBLE (kept, recorded,
    kept out of the estimator) when its flags have a bit the ICD says is 0, an axis not at a rail reads beyond
    `full_scale_nT`, a probe's vector is exactly (0, 0, 0) (an ADC that stopped converting), or a probe's
    temperature not flagged invalid lies outside [temp_min_C, temp_max_C].

    The defaults are wide on purpose: 1,000,000 nT (1 mT) is the largest range of common fluxgate families
    (the Earth's field is below 70,000 nT), so only values no fluxgate gives are caught, such as
    2,147,483.646 nT, one count inside the int32 rail at 0.001 nT per count; -100..200 degC is the simulated
    unit's range, and the int16 temperature rails are +-327.68 degC. Configure the probe's own range."""

    full_scale_nT: float = 1_000_000.0
    temp_min_C: float = -100.0
    temp_max_C: float = 200.0

    def flag(self, field_nT: np.ndarray, saturated: np.ndarray, counts: np.ndarray, temp_C: np.ndarray,
             temp_bad: np.ndarray, flags: np.ndarray, counters: Counters | None) -> np.ndarray:
        """flags with FLAG_IMPLAUSIBLE set where a check fails (a new array only then); counts the reasons."""
        zero = ~counts.any(axis=2)                                                 # (N, P)
        high = max(-float(field_nT.min()), float(field_nT.max())) > self.full_scale_nT
        hot = float(temp_C.min()) < self.temp_min_C or float(temp_C.max()) > self.temp_max_C
        if not (high or hot or zero.any() or (flags & FLAGS_RESERVED).any()):
            return flags                       # the common case: a few reductions, no array of its own
        reserved = (flags & FLAGS_RESERVED) != 0                                   # (N,)
        beyond = (np.abs(field_nT) > self.full_scale_nT) & ~saturated               # (N, P, 3)
        temp_out = ~((temp_C >= self.temp_min_C) & (temp_C <= self.temp_max_C)) & ~temp_bad[:, None]
        bad = reserved | beyond.any(axis=(1, 2)) | zero.any(axis=1) | temp_out.any(axis=1)
        if not bad.any():
            return flags
        if counters is not None:
            counters.implausible_samples += int(np.count_nonzero(bad))
            counters.reserved_flags += int(np.count_nonzero(reserved))
            counters.beyond_full_scale += int(np.count_nonzero(beyond))
            counters.zero_vectors += int(np.count_nonzero(zero))
            counters.temp_out_of_range += int(np.count_nonzero(temp_out))
        return np.where(bad, flags | FLAG_IMPLAUSIBLE, flags).astype(np.uint8)


def plausibility_spec() -> dict:
    """The [source] keys of the plausibility checks (Plausibility), shared by the serial and CAN configs."""
    return {
        "full_scale_nT": spec(Plausibility().full_scale_nT, min=1.0, max=1e12,
                              doc="the probes' full scale: a larger |axis| not at a rail flags the sample "
                                  "implausible (kept out of the estimator)"),
        "temp_min_C": spec(Plausibility().temp_min_C, min=-327.68, max=327.67,
                           doc="the lowest plausible probe temperature"),
        "temp_max_C": spec(Plausibility().temp_max_C, min=-327.68, max=327.67,
                           doc="the highest plausible probe temperature"),
    }


def check_temp_range(temp_min_C: float, temp_max_C: float, path: str) -> None:
    """ConfigError naming the key unless temp_min_C < temp_max_C."""
    if not temp_min_C < temp_max_C:
        raise ConfigError(f"{path}.temp_max_C: {temp_max_C!r} is not allowed (allowed: above "
                          f"{path}.temp_min_C = {temp_min_C!r})")


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
    saturated = (counts == SATURATED_COUNTS[0]) | (counts == SATURATED_COUNTS[1])
    field_nT = counts * float(lsb_nT)                        # nT = counts x lsb_nT
    flags = np.asarray(flags, dtype=np.uint8)
    temp_bad = (flags & FLAG_TEMP_INVALID) != 0
    temp_C = np.asarray(temp_raw) * TEMP_LSB_C                # degC = raw x 0.01
    if plausibility is not None and counts.shape[0]:
        flags = plausibility.flag(field_nT, saturated, counts, temp_C, temp_bad, flags, counters)
    field_nT[saturated] = np.nan
    temp_C[temp_bad] = np.nan
    if counters is not None:
        counters.saturated_axes += int(np.count_nonzero(saturated))
        counters.temp_invalid += int(np.count_nonzero(temp_bad))
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
        steps = np.diff(seq, prepend=seq[0] if self.last is None else self.last)
        gaps = steps > 1
        counters.seq_gaps += int(np.count_nonzero(gaps))
        counters.samples_missed += int((steps[gaps] - 1).sum())
        self.last = int(seq[-1])


class SerialFramer:
    """Turns a serial byte stream, fed in chunks of any size, into RawFrames.

    Keeps the unconsumed tail (at most one frame) between chunks and counts frames accepted,
    CRC failures and bytes skipped, so that at any time
    frames_accepted x frame_length + bytes_skipped + pending_bytes == bytes_fed.
    """

    def __init__(self, n_probes: int, counters: Counters | None = None) -> None:
        self.n_probes = n_probes
        self.frame_length = frame_length(n_probes)
        self.counters = counters if counters is not None else Counters()
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
        c.bytes_received += len(data)
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


def _steps(x: np.ndarray, before: int) -> np.ndarray:
    """x[i] - x[i - 1], with x[-1] = before (np.diff with prepend, without its cost on small blocks)."""
    d = np.empty_like(x)
    d[0] = x[0] - before
    np.subtract(x[1:], x[:-1], out=d[1:])
    return d


class SerialTimeline:
    """Puts a unit's frames in time order from their counter (seq, uint16) and clock (t_us, uint32), so that
    what leaves the driver has seq and t_s strictly increasing, whatever the unit sends.

    Each frame is compared with the last frame accepted:

      duplicate  bit for bit that frame (counter, clock, values, flags): dropped, counted in `duplicates`.
      forward    clock and counter advanced: accepted. The counter's step is the one congruent to it mod 2^16
                 that the clock supports at the unit's frame period (estimated from the frames since the start
                 or the last restart), so a loss longer than 65,536 frames is counted right; a step > 1 is a gap.
      restart    counter and clock both back near zero (seq < 4096 and t_us < 60 s), either further back than
                 1,024 frames or forward by a step the unit's period does not explain: the unit restarted.
                 Accepted and counted in `restarts`; seq goes on from the last frame's + 1 + the new counter
                 (the new run's earlier frames are a gap), time from the last frame's by the host's clock
                 across the restart (the unit's own clock restarted): no missed sample is made up, and time
                 never goes back. (Before, a restart after more than 32,768 frames read as a wrap, with up to
                 32,767 samples missed that never existed.)
      stale      anything else: the counter or the clock stood still or stepped back. Dropped, counted in
                 `seq_backsteps`. After 8 such frames in a row, each following on from the one before, the
                 unit is taken to have jumped back and gone on from there: the 8th is accepted as a restart
                 (seq goes on from the last frame's + 1).

    A period is known after two frames; before it, forward steps are taken as they come. Blocks whose every
    frame steps forward by less than half the counter's range, with no frame near zero on both counters that
    the period does not explain, take one vectorised pass; others (rare: a fault) one Python step per frame.
    """

    NEAR_SEQ = 4096              # a restarted unit's counter: below this
    NEAR_T_US = 60_000_000       # ... and its clock: below this (60 s after power-on)
    RESYNC_FRAMES = 8            # stale frames in a row, following on from each other, that are taken as a restart
    STALE_MAX = 1024             # a frame back near zero by more than this many frames is a restart, not stale

    def __init__(self, counters: Counters) -> None:
        self.counters = counters
        self._s0: int | None = None          # last accepted frame: raw counter and clock
        self._t0 = 0
        self._S0 = 0                         # ... unwrapped (monotonic) counter and clock, us
        self._T0 = 0
        self._last: tuple[bytes, bytes, int] | None = None     # its counts, temperatures and flags (duplicates)
        self._run_S = 0                      # first frame since the start or the last restart (the period)
        self._run_T = 0
        self._period_us: float | None = None
        self._rx_last: float | None = None   # host time the last accepted frame came
        self._stale = 0                      # stale frames in a row, following on from each other
        self._stale_st: tuple[int, int] | None = None

    def period_us(self) -> float | None:
        """The unit's frame period from its own clock and counter since the start or the last restart."""
        if self._S0 > self._run_S:
            return (self._T0 - self._run_T) / (self._S0 - self._run_S)
        return self._period_us

    def order(self, frames: RawFrames, rx_time_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keep (K,) bool, seq (M,) int64, t_us (M,) int64) for the M frames kept, in arrival order."""
        k = len(frames)
        s = frames.seq.astype(np.int64)
        t = frames.t_us.astype(np.int64)
        p = self.period_us()
        if self._s0 is not None and p is not None:
            ds = _steps(s, self._s0)
            ds &= 0xFFFF
            dt = _steps(t, self._t0)
            dt &= 0xFFFFFFFF
            fast = ds.min() >= 1 and ds.max() < 1 << 15 and dt.min() >= 1 and dt.max() < 16384 * p
            if fast and s.min() < self.NEAR_SEQ and t.min() < self.NEAR_T_US:
                near = (s < self.NEAR_SEQ) & (t < self.NEAR_T_US)
                fast = not (near & (np.abs(dt - ds * p) > 0.5 * p + 1e-4 * dt)).any()
            if fast:                         # the common case: every frame steps forward
                seq = self._S0 + np.cumsum(ds)
                t_us = self._T0 + np.cumsum(dt)
                self._accept(frames, k - 1, int(seq[-1]), int(t_us[-1]), rx_time_s)
                return np.ones(k, bool), seq, t_us
        return self._one_by_one(frames, s, t, rx_time_s)

    def _accept(self, frames: RawFrames, i: int, S: int, T: int, rx_time_s: float | None) -> None:
        self._s0, self._t0 = int(frames.seq[i]), int(frames.t_us[i])
        self._S0, self._T0 = S, T
        self._last = (frames.counts[i].tobytes(), frames.temp_raw[i].tobytes(), int(frames.flags[i]))
        self._rx_last = rx_time_s
        self._stale, self._stale_st = 0, None

    def _restart(self, frames: RawFrames, i: int, s: int, rx_time_s: float | None) -> tuple[int, int]:
        """Accept frame i as the first after a restart; s: the new run's frames before it (lost), if known."""
        p = self.period_us()
        self._period_us = p
        gap_us = 0.0
        if rx_time_s is not None and self._rx_last is not None:
            gap_us = (rx_time_s - self._rx_last) * 1e6
        S = self._S0 + 1 + s
        T = self._T0 + max(int(round(gap_us)), int(round(p)) if p else 1, 1)
        self.counters.restarts += 1
        self._accept(frames, i, S, T, rx_time_s)
        self._run_S, self._run_T = S, T
        return S, T

    def _one_by_one(self, frames: RawFrames, s: np.ndarray, t: np.ndarray,
                    rx_time_s: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        keep = np.zeros(len(frames), bool)
        seq_out: list[int] = []
        t_out: list[int] = []
        c = self.counters
        for i, (si, ti) in enumerate(zip(s.tolist(), t.tolist())):
            if self._s0 is None:                             # the first frame: time and counter start here
                self._accept(frames, i, si, ti, rx_time_s)
                self._run_S, self._run_T = si, ti
                keep[i] = True
                seq_out.append(si)
                t_out.append(ti)
                continue
            if (si == self._s0 and ti == self._t0 and self._last is not None
                    and self._last == (frames.counts[i].tobytes(), frames.temp_raw[i].tobytes(), int(frames.flags[i]))):
                c.duplicates += 1
                continue
            ds_f = (si - self._s0) & 0xFFFF
            dt_f = (ti - self._t0) & 0xFFFFFFFF
            near = si < self.NEAR_SEQ and ti < self.NEAR_T_US
            p = self.period_us()
            verdict = "stale"
            if 0 < dt_f < 1 << 31:                           # the clock went forward
                ds = ds_f
                consistent = None
                if p:
                    # the counter's step that the clock supports: d = ds_f + 65536 j nearest dt / p
                    ds = ds_f + (1 << 16) * max(0, int(round((dt_f / p - ds_f) / (1 << 16))))
                    consistent = ds >= 1 and abs(dt_f - ds * p) <= 0.5 * p + 1e-4 * dt_f
                if near and consistent is False:
                    verdict = "restart"
                elif ds >= 1 and (consistent or ds_f < 1 << 15):
                    verdict = "forward"
            elif near and (((self._s0 - si) & 0xFFFF) > self.STALE_MAX
                           or (p and ((self._t0 - ti) & 0xFFFFFFFF) > self.STALE_MAX * p)):
                verdict = "restart"           # back near zero, and further than a stale frame would be
            if verdict == "forward":
                S, T = self._S0 + ds, self._T0 + dt_f
                self._accept(frames, i, S, T, rx_time_s)
            elif verdict == "restart":
                S, T = self._restart(frames, i, si, rx_time_s)
            else:
                c.seq_backsteps += 1
                prev = self._stale_st
                follows = prev is not None and 1 <= ((si - prev[0]) & 0xFFFF) <= 16 \
                    and 0 < ((ti - prev[1]) & 0xFFFFFFFF) < 1 << 31
                self._stale = self._stale + 1 if follows else 1
                self._stale_st = (si, ti)
                if self._stale < self.RESYNC_FRAMES:
                    continue
                c.seq_backsteps -= 1                         # this one is taken: a restart from here
                S, T = self._restart(frames, i, 0, rx_time_s)  # (how many came before it is not known)
            keep[i] = True
            seq_out.append(S)
            t_out.append(T)
        return keep, np.asarray(seq_out, np.int64), np.asarray(t_out, np.int64)


class FrameAssembler:
    """RawFrames from one unit -> SampleBlocks: frames ordered by SerialTimeline (seq and the unit clock t_us
    unwrapped, strictly increasing; duplicates and stale frames dropped, restarts followed), t_s = t_us / 1e6,
    scaled with lsb_nT, implausible samples flagged, gaps counted."""

    def __init__(self, n_probes: int, lsb_nT: float, counters: Counters | None = None,
                 plausibility: Plausibility | None = Plausibility()) -> None:
        self.n_probes = n_probes
        self.lsb_nT = float(lsb_nT)
        self.counters = counters if counters is not None else Counters()
        self.plausibility = plausibility
        self._timeline = SerialTimeline(self.counters)
        self._gaps = SeqGapCounter()

    def block(self, frames: RawFrames, rx_time_s: float | None = None) -> SampleBlock:
        """The samples of `frames`; rx_time_s (host monotonic time they were read) times a unit restart."""
        if len(frames) == 0:
            return SampleBlock.empty(self.n_probes)
        keep, seq, t_us = self._timeline.order(frames, rx_time_s)
        counts, temp_raw, flags = frames.counts, frames.temp_raw, frames.flags
        if not keep.all():
            counts, temp_raw, flags = counts[keep], temp_raw[keep], flags[keep]
        # division, not x 1e-6: t_us / 1e6 is the double nearest the exact time, so printing
        # it with 6 decimals gives back the unit's microseconds exactly
        t_s = t_us / 1e6
        self._gaps.update(seq, self.counters)
        return scale_samples(seq, t_s, counts, temp_raw, flags, lsb_nT=self.lsb_nT, counters=self.counters,
                             plausibility=self.plausibility)


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
    ignored and counted in `duplicates`. seq is unwrapped frame by frame with the signed step
    ((s - s_prev + 2^15) mod 2^16) - 2^15, so interleaving across a wrap is right. The unit restarting its
    counter: a jump backwards by more than `restart_samples`, or (with `rate_hz`) a jump forwards to a counter
    near zero (< restart_samples) that the receive times do not support (less than half its length in time).
    It is counted in `restarts`, what is pending is settled, and seq goes on from the highest seen + 1 + the
    new counter: the unwrapped seq (and t_s = seq / rate_hz) never goes back, and no sample is counted missed
    that never existed.
    """

    def __init__(self, n_probes: int, *, base_id: int = DEFAULT_CAN_BASE_ID, window_samples: int = 32,
                 window_s: float = 0.5, counters: Counters | None = None, rate_hz: float | None = None) -> None:
        self.n_probes = n_probes
        self.rate_hz = rate_hz
        self.base_id = base_id
        self.window_samples = int(window_samples)
        self.window_s = float(window_s)
        self.restart_samples = max(4 * self.window_samples, 1024)
        self.counters = counters if counters is not None else Counters()
        self._last_raw: int | None = None
        self._last_u = 0
        self._top_u: int | None = None         # the highest unwrapped seq seen, and when it came
        self._top_rx = -np.inf
        self._max_seen: int | None = None
        self._done_upto: int | None = None     # every sample <= this was released or dropped
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
        u, restarts = self._unwrap(seq, rx)

        out: list[CanSamples] = []
        # at a restart of the unit's counter what is pending is settled, then assembly goes on
        start = 0
        for stop in restarts + [u.size]:
            self._merge(u[start:stop], probe[start:stop], axis[start:stop], value[start:stop], temp[start:stop],
                        rx[start:stop])
            if stop < u.size:
                out.append(self._release(now_s, final=True))
            start = stop
        out.append(self._release(now_s, final=False))
        return CanSamples.concat(out, self.n_probes)

    def flush(self) -> CanSamples:
        """End of input: release every complete sample, drop (and count) the incomplete ones."""
        return self._release(np.inf, final=True)

    def _unwrap(self, seq: np.ndarray, rx: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """The unwrapped seq of each frame, and the indices where the unit restarted its counter."""
        raw = seq.astype(np.int64)
        if raw.size == 0:
            return raw, []
        prev = np.empty_like(raw)
        prev[0] = raw[0] if self._last_raw is None else self._last_raw
        prev[1:] = raw[:-1]
        # signed step in (-2^15, 2^15]: d = ((s - s_prev + 2^15) mod 2^16) - 2^15
        step = ((raw - prev + _SEQ_MODULUS // 2) % _SEQ_MODULUS) - _SEQ_MODULUS // 2
        base = raw[0] if self._last_raw is None else self._last_u
        u = base + np.cumsum(step)
        restarts: list[int] = []
        top = -np.inf if self._top_u is None else float(self._top_u)     # the highest so far, and when it came
        top_rx = self._top_rx
        i0 = 0
        while i0 < u.size:                # restarts are rare: one pass over the rest for each
            seg, seg_raw, seg_rx = u[i0:], raw[i0:], rx[i0:]
            run_top = np.maximum.accumulate(np.maximum(seg, top))
            prior = np.concatenate([[top], run_top[:-1]])                # the highest before each frame
            back = seg < prior - self.restart_samples
            if self.rate_hz:
                # forward to a counter near zero, further than the receive time since the highest allows
                new_top = np.where(seg > prior, np.arange(seg.size), -1)
                last = np.concatenate([[-1], np.maximum.accumulate(new_top)[:-1]])
                prior_rx = np.where(last >= 0, seg_rx[np.maximum(last, 0)], top_rx)
                jump = seg - prior
                back |= ((jump > self.restart_samples) & (seg_raw < self.restart_samples)
                         & ((seg_rx - prior_rx) * self.rate_hz < 0.5 * jump))
            hits = np.flatnonzero(back)
            if not hits.size:
                break
            j = i0 + int(hits[0])
            if j > i0:
                k = i0 + int(np.argmax(u[i0:j]))
                if u[k] > top:
                    top, top_rx = float(u[k]), float(rx[k])
            u[j:] += int(top) + 1 + int(raw[j]) - int(u[j])
            restarts.append(j)
            self.counters.restarts += 1
            i0 = j
        self._last_raw = int(raw[-1])
        self._last_u = int(u[-1])
        if self._top_u is None or int(u.max()) > self._top_u:
            k = int(np.argmax(u))
            self._top_u, self._top_rx = int(u[k]), float(rx[k])
        return u, restarts

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
            top = int(seqs[settled].max())
            self._done_upto = top if self._done_upto is None else max(self._done_upto, top)
        out = CanSamples(seq=seqs[emit], counts=self._p_counts[emit],
                         temp_raw=self._p_temp[emit][:, :, 0].copy(), rx_time_s=self._p_first[emit])
        keep = ~settled
        self._p_seq, self._p_counts, self._p_temp, self._p_have, self._p_first = (
            x[keep] for x in (self._p_seq, self._p_counts, self._p_temp, self._p_have, self._p_first))
        return out
