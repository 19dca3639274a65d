"""The serial unit's frames put in order by their counter and clock: duplicates and stale frames dropped and
counted, a unit restart told from a counter wrap (both counter and clock back near zero).

Each frame is compared with the last frame accepted:

  duplicate  bit for bit that frame, or (stepping back) one of the last 4,096 frames accepted (FrameHistory:
             counter, clock and content): a frame sent again. Dropped, counted in `duplicates`.
  forward    clock and counter advanced together, by no more frames than the host's time since the last one holds
             (where the host reads the unit in its own time): accepted. The counter's step is the one congruent to it mod
             2^16 that the clock supports at the unit's frame period (estimated from the frames since the start
             or the last restart), so a loss longer than 65,536 frames is counted right; a step > 1 is a gap.
  counter    the clock stepped a whole number k <= 16 of periods but the counter by something else: the counter
  jump       jumped (a glitch), the clock ran on. Accepted k frames on, counted in `counter_jumps`; no sample is
             counted missed that the clock says never existed (before: a jump of 1,000 was 999 missed, or near
             zero a restart with thousands missed).
  restart    counter and clock both back near zero (seq < 4096 and t_us < 60 s, and no more frames than the host's
             time since the unit was last heard holds), either further back than 1,024 frames or forward by a step
             the unit's period does not explain: the unit restarted.
             Accepted and counted in `restarts`; seq goes on from the last frame's + 1 + the new counter
             (the new run's earlier frames are a gap), time from the last frame's by the host's clock
             across the restart (the unit's own clock restarted): no missed sample is made up, and time
             never goes back.
  clock      the counter stepped forward (by less than 2^15; by at most 1,024 when the clock went back) but the
  jump       clock by a step its period does not explain: the clock jumped, the counter ran on. Accepted, time
             repaired from the counter (the step times the period), counted in `clock_jumps`: no sample made up
             or lost (before: +1,000 s with the counter at +1 was 196,608 samples missed). A clock that stands
             still frame after frame is one jump until it runs again.
  stale      anything else: the counter or the clock stood still or stepped back. Held, and counted in
             `seq_backsteps`; dropped when a frame comes on the line they left. After 8 such frames in a row,
             each following on from the one before, the unit is taken to have jumped back and gone on from
             there (a restart soon after another, a counter glitch that stays): the held frames are accepted
             as a restart from the first of them (not counted stale: given with the block that confirms them,
             `carried`), seq going on from the last frame's + 1, plus its counter where it is back near zero
             (the new run's frames before it, lost). Before, the 7 held ones were dropped: a unit restarting
             3 s after a restart lost them, counted as stale frames and never as missed.
"""

from __future__ import annotations

from dataclasses import dataclass

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


def _tolerance(dt: np.ndarray | float, p: float) -> np.ndarray | float:
    """How far a clock step may be from the counter's step times the period: half a period, plus 1e-4."""
    return 0.5 * p + 1e-4 * dt


@dataclass(frozen=True)
class _Held:
    """A held stale frame: a one-row copy, the block it came from and its index there."""

    frame: RawFrames
    source: RawFrames
    index: int


def _row(frames: RawFrames, i: int, si: int, ti: int) -> _Held:
    one = RawFrames(seq=np.array([si], np.uint16), t_us=np.array([ti], np.uint32),
                    counts=frames.counts[i:i + 1].copy(), temp_raw=frames.temp_raw[i:i + 1].copy(),
                    flags=frames.flags[i:i + 1].copy())
    return _Held(one, frames, i)


def _rows(held: list[RawFrames]) -> RawFrames:
    """Frames joined in order."""
    return RawFrames(*(np.concatenate([getattr(h, f) for h in held]) for f in ("seq", "t_us", "counts", "temp_raw",
                                                                               "flags")))


class Jumps:
    """The last jump of the counter and of the clock (the raw reading and the unwrapped value each left from): a
    later jump back onto the line one left, within 64 frames, ends that jump rather than being another."""

    def __init__(self) -> None:
        self.counter: tuple[int, int] | None = None
        self.clock: tuple[int, int] | None = None

    def counter_rejoins(self, si: int, S: int, left: tuple[int, int]) -> bool:
        """Whether a counter jump to raw si (seq S) rejoins the last one's line; notes this jump (from `left`)
        if not."""
        was, self.counter = self.counter, left
        if was is None or S - was[1] > 64 or (si - was[0]) & 0xFFFF != (S - was[1]) & 0xFFFF:
            return False
        self.counter = None
        return True

    def on_clock_line(self, ti: int, T: int, p: float) -> bool:
        """Whether clock reading ti at time T (us) is back on the line the clock's last jump left."""
        was = self.clock
        return was is not None and T - was[1] <= 64 * p and \
            abs(((ti - was[0]) & 0xFFFFFFFF) - (T - was[1])) <= _tolerance(T - was[1], p)

    def clock_rejoins(self, ti: int, T: int, p: float, left: tuple[int, int]) -> bool:
        back = self.on_clock_line(ti, T, p)
        self.clock = None if back else left
        return back


class FrameHistory:
    """The last `size` frames accepted (raw counter, clock and content): a frame that steps back and equals one of
    them bit for bit was sent again (a link that replays its buffer, a unit that resends), a duplicate; one that
    equals none is stale. A ring of slices copied in (no per-frame Python on the common path)."""

    def __init__(self, size: int = 4096) -> None:
        self.size = size
        self._n = 0                          # frames added so far
        self._rows: tuple[np.ndarray, ...] | None = None      # raw counter, clock, counts, temperatures, flags

    def add(self, frames: RawFrames, start: int = 0, stop: int | None = None) -> None:
        cols = (frames.seq, frames.t_us, frames.counts, frames.temp_raw, frames.flags)
        stop = len(frames) if stop is None else stop
        start = max(start, stop - self.size)                        # at most the last `size` of them
        k = stop - start
        if k <= 0:
            return
        if self._rows is None:
            self._rows = tuple(np.zeros((self.size, *c.shape[1:]), c.dtype) for c in cols)
        at = self._n % self.size
        first = min(k, self.size - at)
        for ring, c in zip(self._rows, cols):
            ring[at:at + first] = c[start:start + first]
            if first < k:
                ring[:k - first] = c[start + first:stop]
        self._n += k

    def holds(self, frames: RawFrames, i: int) -> bool:
        if self._rows is None:
            return False
        filled = min(self._n, self.size)
        seq, t, counts, temp, flags = (r[:filled] for r in self._rows)
        hit = np.flatnonzero((seq == frames.seq[i]) & (t == frames.t_us[i]))
        return any(np.array_equal(counts[j], frames.counts[i]) and np.array_equal(temp[j], frames.temp_raw[i])
                   and flags[j] == frames.flags[i] for j in hit)


class SerialTimeline:
    """Puts a unit's frames in time order from their counter (seq, uint16) and clock (t_us, uint32), so that
    what leaves the driver has seq and t_s strictly increasing, whatever the unit sends.

    Each frame is compared with the last frame accepted, as the module docstring's table says.

    A period is known after two frames; before it, forward steps are taken as they come. Blocks whose every
    frame steps forward by less than half the counter's range, clock and counter agreeing at the period, take one
    vectorised pass; others (rare: a fault) one Python step per frame.
    """

    NEAR_SEQ = 4096              # a restarted unit's counter: below this
    NEAR_T_US = 60_000_000       # ... and its clock: below this (60 s after power-on)
    RESYNC_FRAMES = 8            # stale frames in a row, following on from each other, that are taken as a restart
    STALE_MAX = 1024             # a frame back near zero by more than this many frames is a restart, not stale
    COUNTER_JUMP_FRAMES = 16     # a clock step of at most this many periods is the clock running on
    #: how much later or earlier than their time a unit's frames may reach the reader (an OS buffer, an adapter's
    #: latency, a block read late): a counter beyond what the host time since the last frame holds, with this, is
    #: no restart and no run-on of this unit (_host_allows)
    RX_SLACK_S = 0.5

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
        self._paced: tuple[float, int] | None = None   # (host time, unwrapped clock) of the first frame (_host_allows)
        self._stale = 0                      # stale frames in a row, following on from each other
        self._stale_st: tuple[int, int] | None = None
        self._held: list[_Held] = []         # ... held, each a one-row copy, in case they are a restart
        self.carried: RawFrames | None = None    # held frames of earlier blocks accepted with this one (first)
        self.history = FrameHistory()
        self.jumps = Jumps()
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
        self.carried = None
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
            # the common case: every frame steps forward, its clock and counter agreeing at the period
            if ds_lo >= 1 and ds_hi < 1 << 15 and dt_lo >= 1 and dt_hi < 16384 * p and (
                    max(abs(dt_lo - p), abs(dt_hi - p)) <= _tolerance(dt_lo, p) if ds_hi == 1
                    else not (np.abs(d[1] - d[0] * p) > _tolerance(d[1], p)).any()
                    and self._host_allows(int(d[0].sum()), rx_time_s)):
                np.cumsum(d, axis=1, out=d)
                d[0] += self._S0
                d[1] += self._T0
                seq, t_us = d[0], d[1]
                self._accept(frames, k - 1, int(seq[-1]), int(t_us[-1]), rx_time_s)
                self.history.add(frames)
                self.contiguous = ds_hi == 1
                return None, seq, t_us
        return self._one_by_one(frames, frames.seq.astype(np.int64), frames.t_us.astype(np.int64), rx_time_s)

    def _accept(self, frames: RawFrames, i: int, S: int, T: int, rx_time_s: float | None) -> None:
        self._s0, self._t0 = int(frames.seq[i]), int(frames.t_us[i])
        self._S0, self._T0 = S, T
        self._last = (frames.counts[i].tobytes(), frames.temp_raw[i].tobytes(), int(frames.flags[i]))
        self._rx_last = rx_time_s
        if self._paced is None and rx_time_s is not None:
            self._paced = (rx_time_s, T)
        self._stale, self._stale_st, self._held = 0, None, []

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

    def _host_allows(self, frames: int, rx_time_s: float | None) -> bool:
        """Whether the host time since the last accepted frame holds `frames` of the unit's periods: a unit restarted
        cannot have counted more (a clock frozen 2 s was a restart with 2,400 missed), nor a counter run on further.
        Yes where unknown, and while the host does not read the unit in its own time (a pty fed unpaced, a capture:
        a restart's lost frames were not counted missed)."""
        p = self.period_us()
        if rx_time_s is None or self._rx_last is None or not p or self._paced is None:
            return True
        rx0, t0 = self._paced
        unit_s = (self._T0 - t0) * 1e-6
        if unit_s < 2.0 or self._rx_last - rx0 < 0.5 * unit_s:
            return True
        return frames * p * 1e-6 <= rx_time_s - self._rx_last + self.RX_SLACK_S

    def _verdict(self, si: int, ti: int, rx_time_s: float | None = None) -> tuple[str, int, int]:
        """(verdict, counter step, clock step in us) of a frame against the last accepted (the class docstring)."""
        ds_f = (si - self._s0) & 0xFFFF
        dt_f = (ti - self._t0) & 0xFFFFFFFF
        near = si < self.NEAR_SEQ and ti < self.NEAR_T_US and self._host_allows(si, rx_time_s)
        p = self.period_us()
        if 0 < dt_f < 1 << 31:                           # the clock went forward
            if not p:
                return ("forward", ds_f, dt_f) if 1 <= ds_f < 1 << 15 else ("stale", 0, 0)
            # the counter's step that the clock supports: d = ds_f + 65536 j nearest dt / p
            ds = ds_f + (1 << 16) * max(0, int(round((dt_f / p - ds_f) / (1 << 16))))
            if ds >= 1 and abs(dt_f - ds * p) <= _tolerance(dt_f, p) and self._host_allows(ds, rx_time_s):
                return "forward", ds, dt_f
            if 1 <= ds_f < 1 << 15 and self.jumps.on_clock_line(ti, self._T0 + int(round(ds_f * p)), p):
                return "clock jump", ds_f, int(round(ds_f * p))          # the clock back on its line
            k = int(round(dt_f / p))
            if 1 <= k <= self.COUNTER_JUMP_FRAMES and abs(dt_f - k * p) <= _tolerance(dt_f, p):
                return "counter jump", k, dt_f
            if near:
                return "restart", 0, 0
            if 1 <= ds_f < 1 << 15 and self._host_allows(ds_f, rx_time_s):
                return "clock jump", ds_f, int(round(ds_f * p))
            return "stale", 0, 0
        if p and 1 <= ds_f <= self.STALE_MAX:
            return "clock jump", ds_f, int(round(ds_f * p))     # the clock stood still or went back, the counter on
        if near and (((self._s0 - si) & 0xFFFF) > self.STALE_MAX
                     or (p and ((self._t0 - ti) & 0xFFFFFFFF) > self.STALE_MAX * p)):
            return "restart", 0, 0                       # back near zero, and further than a stale frame would be
        return "stale", 0, 0

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
                S, T = si, ti
            elif (si == self._s0 and ti == self._t0 and self._last is not None
                    and self._last == (frames.counts[i].tobytes(), frames.temp_raw[i].tobytes(), int(frames.flags[i]))):
                c.duplicates += 1
                continue
            else:
                verdict, ds, dt = self._verdict(si, ti, rx_time_s)
                if verdict == "restart":
                    S, T = self._restart(frames, i, si, rx_time_s)
                elif verdict != "stale":
                    if verdict == "counter jump":
                        # a jump back onto the line the counter left (one glitched frame, or a few) ends that jump
                        left = (self._s0, self._S0)
                        c.counter_jumps += 0 if self.jumps.counter_rejoins(si, self._S0 + ds, left) else 1
                    elif verdict == "clock jump":
                        # a clock that stands still frame after frame is the one jump it began (a freeze of 2 s
                        # was 400 jumps), until it runs again
                        still = ti == self._t0 and self.jumps.clock is not None
                        c.clock_jumps += 0 if still or self.jumps.clock_rejoins(
                            ti, self._T0 + dt, self.period_us() or 0.0, (self._t0, self._T0)) else 1
                    S, T = self._S0 + ds, self._T0 + dt
                    self._accept(frames, i, S, T, rx_time_s)
                elif self.history.holds(frames, i):          # a frame accepted before, sent again
                    c.duplicates += 1
                    continue
                else:
                    c.seq_backsteps += 1
                    prev = self._stale_st
                    follows = prev is not None and 1 <= ((si - prev[0]) & 0xFFFF) <= 16 \
                        and 0 < ((ti - prev[1]) & 0xFFFFFFFF) < 1 << 31
                    self._stale = self._stale + 1 if follows else 1
                    self._stale_st = (si, ti)
                    self._held = (self._held if follows else []) + [_row(frames, i, si, ti)]
                    if self._stale < self.RESYNC_FRAMES:
                        continue
                    S, T = _resync(self, frames, keep, seq_out, t_out, rx_time_s)
            keep[i] = True
            seq_out.append(S)
            t_out.append(T)
            self.history.add(frames, i, i + 1)
        return keep, np.asarray(seq_out, np.int64), np.asarray(t_out, np.int64)


def _resync(tl: SerialTimeline, frames: RawFrames, keep: np.ndarray, seq_out: list[int], t_out: list[int],
            rx_time_s: float | None) -> tuple[int, int]:
    """tl's held stale run taken as a restart from its first frame (the module docstring): each held frame
    accepted, those of earlier blocks as `carried` (before this block's), those of this block kept; returns
    (seq, t) of the last, this block's frame that confirmed them."""
    held, tl._held = tl._held, []
    tl.counters.seq_backsteps -= len(held)           # not stale: the unit's frames after a jump back
    first = held[0].frame
    s0, t0 = int(first.seq[0]), int(first.t_us[0])
    # back near zero, in no more frames than the host time since the last one holds: its counter says what came before
    near = s0 < tl.NEAR_SEQ and t0 < tl.NEAR_T_US and tl._host_allows(s0, rx_time_s)
    S, T = tl._restart(first, 0, s0 if near else 0, rx_time_s)
    rows = [(S, T)]
    for h in held[1:]:
        ds = (int(h.frame.seq[0]) - int(tl._s0)) & 0xFFFF
        dt = (int(h.frame.t_us[0]) - int(tl._t0)) & 0xFFFFFFFF
        S, T = S + ds, T + dt
        tl._accept(h.frame, 0, S, T, rx_time_s)
        rows.append((S, T))
    before = held[:-1]                                  # the last is this frame: the caller keeps it
    for h in before:
        tl.history.add(h.frame)
    earlier = [k for k, h in enumerate(before) if h.source is not frames]
    if earlier:
        tl.carried = _rows([held[k].frame for k in earlier])
        seq_out[:0], t_out[:0] = [rows[k][0] for k in earlier], [rows[k][1] for k in earlier]
    for k, h in enumerate(before):
        if h.source is frames:
            keep[h.index] = True
            seq_out.append(rows[k][0])
            t_out.append(rows[k][1])
    return S, T
