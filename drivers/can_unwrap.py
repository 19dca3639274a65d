"""The CAN unit's sample counter (uint16 in every frame) unwrapped into a seq that never goes back: across wraps,
across a restart of the unit, with the frames of the old run that still come after the restart's first frame
(frames of neighbouring samples interleave on the bus) put back into the old run.

Frame by frame the signed step ((s - s_prev + 2^15) mod 2^16) - 2^15, so interleaving across a wrap is right. A
restart: a jump backwards by more than `restart_samples`, or by more than 2 windows to a counter below 2 windows (the
unit started again soon after its last start: no interleaving goes back that far), or (with `rate_hz`) a jump forwards to a counter near zero
(< restart_samples) that the receive times do not support (less than half its length in time), or back to a counter
near zero whose slot already holds another value (`differs`, from the assembler: can_settled; a frame sent again is
bit for bit the same; the unit restarting within two windows of its last start). It is counted in
`restarts` once, and seq goes on from the highest seen + 1 + the new counter (no sample is counted missed that never
existed). A frame after it whose counter is within `window_samples` of the old run's highest (and far from the new
run's) is a straggler of the old run: it keeps the old run's numbering, and completes its sample. Before, each
straggler after a restart was read as one more restart, with tens of thousands of samples "missed" between.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .source import Counters

#: differs(u, idx) -> (len(idx),) bool: which frames idx, numbered u, land on a slot already filled with another value
Differs = Callable[[np.ndarray, np.ndarray], np.ndarray]

_MOD = 1 << 16


def _signed(d: np.ndarray | int) -> np.ndarray | int:
    """d mod 2^16 as a step in (-2^15, 2^15]."""
    return ((d + _MOD // 2) % _MOD) - _MOD // 2


class CanUnwrap:
    """See the module docstring. Call with each batch's counters and receive times, in arrival order."""

    def __init__(self, *, window_samples: int, restart_samples: int, rate_hz: float | None, counters: Counters,
                 frames_per_sample: int = 1) -> None:
        self.window, self.restart_samples, self.rate_hz, self.counters = window_samples, restart_samples, rate_hz, counters
        self.frames_per_sample = max(int(frames_per_sample), 1)
        self._last: tuple[int, int] | None = None      # the last frame of the current run: raw counter, seq
        self._top: tuple[float, int, float] = (-np.inf, 0, -np.inf)   # the highest seq seen: seq, raw, receive time
        self._old: tuple[int, int, int, int] | None = None   # the run before the last restart: its highest raw and
        #                                                      seq, the highest seq kept for it, the new run's start
        self._settled: int | None = None                # every sample up to this one released or given up
        self._differs: Differs | None = None

    def __call__(self, seq: np.ndarray, rx: np.ndarray, settled: int | None = None,
                 differs: Differs | None = None) -> np.ndarray:
        """seq unwrapped; `settled`: the assembler's last sample released or given up (every one up to it);
        `differs`: which frames land on a slot already filled with another value (see the module docstring)."""
        self._settled, self._differs = settled, differs
        raw = seq.astype(np.int64)
        if raw.size == 0:
            return raw
        prev = np.empty_like(raw)
        prev[0] = raw[0] if self._last is None else self._last[0]
        prev[1:] = raw[:-1]
        u = (raw[0] if self._last is None else self._last[1]) + np.cumsum(_signed(raw - prev))
        old = np.zeros(u.size, bool)                   # stragglers of the run before a restart
        i0 = 0
        while i0 < u.size:                              # restarts are rare: one pass over the rest for each
            old[i0:] = self._stragglers(raw[i0:], u[i0:])
            j = self._first_restart(u, raw, rx, old, i0)
            if j is None:
                break
            self._restart(u, raw, rx, old, i0, j)
            i0 = j
        mine = np.flatnonzero(~old)
        if mine.size:
            k = int(mine[-1])
            self._last = (int(raw[k]), int(u[k]))
            best = int(mine[np.argmax(u[mine])])
            if u[best] > self._top[0]:
                self._top = (float(u[best]), int(raw[best]), float(rx[best]))
        if self._old is not None and self._last is not None and self._last[1] > self._old[3] + 4 * self.window:
            self._old = None                            # the old run's frames would be too late by now
        return u

    def _stragglers(self, raw: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Which of these frames belong to the run before the last restart; their u set to its numbering. Only frames
        whose sample is still being assembled (after `settled`) can be: a run that restarted again soon reaches the
        old run's last counters when those samples are long released, and its frames are its own (31 samples of such
        a run were taken for the old run's and dropped as duplicates)."""
        if self._old is None:
            return np.zeros(raw.size, bool)
        top_raw, top_u, kept_u, start_u = self._old
        d_old = _signed(raw - top_raw)
        near_new = np.abs(u - start_u) <= 4 * self.window
        old = (np.abs(d_old) <= self.window) & (top_u + d_old <= kept_u) & ~(near_new & (u >= start_u))
        if self._settled is not None:
            old &= top_u + d_old > self._settled
        u[old] = top_u + d_old[old]
        return old

    def _first_restart(self, u: np.ndarray, raw: np.ndarray, rx: np.ndarray, old: np.ndarray, i0: int) -> int | None:
        seg = np.where(old[i0:], -np.inf, u[i0:].astype(float))
        top, top_rx = self._top[0], self._top[2]
        run_top = np.maximum.accumulate(np.maximum(seg, top))
        prior = np.concatenate([[top], run_top[:-1]])             # the highest before each frame
        back = seg < prior - self.restart_samples
        # back by more than 2 windows to a counter near zero: the unit started again, however soon after its last
        # start (a restart 3 s after a restart, 600 samples at 200 Hz, was read as that many duplicates: lost)
        back |= (seg < prior - 2 * self.window) & (raw[i0:] < 2 * self.window)
        if self.rate_hz:
            # forward to a counter near zero, further than the receive time since the highest allows
            new_top = np.where(seg > prior, np.arange(seg.size), -1)
            last = np.concatenate([[-1], np.maximum.accumulate(new_top)[:-1]])
            prior_rx = np.where(last >= 0, rx[i0:][np.maximum(last, 0)], top_rx)
            jump = seg - prior
            back |= ((jump > self.restart_samples) & (raw[i0:] < self.restart_samples)
                     & ((rx[i0:] - prior_rx) * self.rate_hz < 0.5 * jump))
        small = raw[i0:] < 2 * self.window
        if self._differs is not None and small.any():
            # back to a counter near zero, on a slot already filled with another value: a new run, however soon
            near = np.flatnonzero((seg <= prior) & small & ~back & ~old[i0:])
            if near.size:
                back[near[self._differs(u, i0 + near)]] = True
        hits = np.flatnonzero(back & ~old[i0:])
        return None if not hits.size else i0 + int(hits[0])

    def _restart(self, u: np.ndarray, raw: np.ndarray, rx: np.ndarray, old: np.ndarray, i0: int, j: int) -> None:
        """Frame j starts a new run: the highest so far noted as the old run's, what follows renumbered."""
        mine = np.flatnonzero(~old[i0:j]) + i0
        if mine.size:
            k = int(mine[np.argmax(u[mine])])
            if u[k] > self._top[0]:
                self._top = (float(u[k]), int(raw[k]), float(rx[k]))
        top_u, top_raw = int(self._top[0]), self._top[1]
        # the old run's samples not seen yet but close behind its frames here (interleaved): room kept for them. A
        # frame the new run could have reached by its place in the batch (a sample's frames each) is the new run's: a
        # run that started again soon reaches the old run's last counters within the batch (room kept for them
        # stepped the time on for samples that never were)
        later = np.arange(raw.size - j)
        reach = raw[j] + later // self.frames_per_sample + self.window
        rest = np.flatnonzero((np.abs(_signed(raw[j:] - top_raw)) <= self.window) & (raw[j:] > reach)) + j
        ahead = int(max(0, _signed(raw[rest] - top_raw).max())) if rest.size else 0
        kept_u = top_u + min(ahead, self.window)
        start = kept_u + 1 + int(raw[j])
        u[j:] += start - int(u[j])
        self._old = (top_raw, top_u, kept_u, start)
        self._top = (float(kept_u), top_raw, float(rx[j]))
        self.counters.restarts += 1
