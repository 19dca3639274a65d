"""The serial unit's frames put in order by their counter and clock: duplicates and stale frames dropped and
counted, a unit restart told from a counter wrap (both counter and clock back near zero)."""

from __future__ import annotations

import numpy as np

from .icd import RawFrames
from .source import Counters


#: the counter's and the clock's moduli less one, as a column for the (2, K) array of both
_WRAP = np.array([[0xFFFF], [0xFFFFFFFF]], np.int64)


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
        self.contiguous = False              # the last block's frames each followed the one before by one count

    def period_us(self) -> float | None:
        """The unit's frame period from its own clock and counter since the start or the last restart."""
        if self._S0 > self._run_S:
            return (self._T0 - self._run_T) / (self._S0 - self._run_S)
        return self._period_us

    def order(self, frames: RawFrames, rx_time_s: float | None = None) -> tuple[np.ndarray | None, np.ndarray,
                                                                                    np.ndarray]:
        """(keep (K,) bool, seq (M,) int64, t_us (M,) int64) for the M frames kept, in arrival order; keep is None
        when every frame is kept, and then `contiguous` says whether each followed the one before by one count."""
        k = len(frames)
        self.contiguous = False
        p = self.period_us()
        if self._s0 is not None and p is not None:
            # counter and clock as the rows of one array: each step below is one operation for both
            st = np.empty((2, k), np.int64)
            st[0], st[1] = frames.seq, frames.t_us
            d = np.empty_like(st)
            d[:, 0] = st[:, 0]
            d[0, 0] -= self._s0
            d[1, 0] -= self._t0
            np.subtract(st[:, 1:], st[:, :-1], out=d[:, 1:])
            d &= _WRAP                                        # steps modulo 2^16 (counter) and 2^32 (clock)
            (ds_lo, dt_lo), (ds_hi, dt_hi) = d.min(axis=1).tolist(), d.max(axis=1).tolist()
            fast = ds_lo >= 1 and ds_hi < 1 << 15 and dt_lo >= 1 and dt_hi < 16384 * p
            s, t = st[0], st[1]
            if fast and t.min() < self.NEAR_T_US and s.min() < self.NEAR_SEQ:      # (the clock is rarely near 0)
                ds, dt = d[0], d[1]
                near = (s < self.NEAR_SEQ) & (t < self.NEAR_T_US)
                fast = not (near & (np.abs(dt - ds * p) > 0.5 * p + 1e-4 * dt)).any()
            if fast:                         # the common case: every frame steps forward
                np.cumsum(d, axis=1, out=d)
                d[0] += self._S0
                d[1] += self._T0
                seq, t_us = d[0], d[1]
                self._accept(frames, k - 1, int(seq[-1]), int(t_us[-1]), rx_time_s)
                self.contiguous = ds_hi == 1
                return None, seq, t_us
        return self._one_by_one(frames, frames.seq.astype(np.int64), frames.t_us.astype(np.int64), rx_time_s)

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
