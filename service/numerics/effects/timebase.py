"""The time base of a record: steady (a unit's clock, or t = seq / rate: intervals at whole multiples of one step,
a missing sample a hole of two steps) or bursty (a hobby board sending bursts of samples 2 ms apart with 20-60 ms
between them: those pauses are its rhythm, not gaps); its gaps; and its samples laid on a uniform grid.

A steady time base with samples missing here and there (CAN frames lost, saturated samples dropped) was read as a
bursty one once more than 5 % of its intervals were two steps (its 95th percentile then two steps): a missing sample
was then no gap, and smoothing and derivatives ran across the holes as if the samples were adjacent (a lag of 4 ms
read 7.7 standard errors off, and the verdict changed, with 6 % of the samples missing); below 5 %, each missing
sample was a gap and the smoothing window's samples on each side of it were left out (3 % missing: 3,206 of 11,622
rows kept). Now the holes of a steady time base are counted as one step in its rhythm, and a hole of up to BRIDGE
steps is bridged: smoothing and derivatives are taken on the uniform grid (the hole filled by interpolation, read
back at the samples); only a longer hole is a gap.

    TimeBase.of(t_s)        its step (the median interval), whether steady, each sample's slot on the grid
    tb.gap_s                an interval longer than this is a gap
    tb.on_grid(x, f)        f of x laid on the uniform grid, read back at the samples
    sample_grid(t_s)        (positions, step) on which the residual's spectra are taken
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

#: an interval this many times the typical one is a gap, and a time base whose 95th percentile interval (its holes
#: counted as one step) is this many times its median is bursty
GAP_FACTOR = 1.5
#: a hole of up to this many steps (three samples missing) in a steady time base is bridged, not a gap
BRIDGE = 4
#: an interval within this share of a step of a whole number of steps is that many steps
WHOLE = 0.05
#: a record whose grid would be longer than this many times its samples is not laid on one (its gaps would fill it)
MAX_GRID_FILL = 8


@dataclass(frozen=True)
class TimeBase:
    """See the module docstring. positions: each sample's slot on the uniform grid of `step`, where the time base is
    steady and every interval up to a bridged hole is a whole number of steps (None otherwise: a clock with jitter,
    a bursty board)."""

    step: float
    p95: float
    steady: bool
    positions: np.ndarray | None

    @classmethod
    def of(cls, t_s: np.ndarray) -> "TimeBase":
        t = np.asarray(t_s, float)
        d = np.diff(t)
        if d.size == 0:
            return cls(1.0, 1.0, True, np.zeros(t.size, np.int64))
        med = float(np.median(d))
        k = d / med
        n = np.rint(k)
        whole = (n >= 1) & (np.abs(k - n) <= WHOLE)
        # a hole of a few whole steps (one a grid bridges) is one step of the rhythm; a longer pause is the rhythm's
        # own (a hobby board's pauses between bursts, whole by chance where its stamps are rounded to the ms)
        rhythm = np.where(whole & (k > GAP_FACTOR) & (k <= BRIDGE + 0.5), med, d)
        steady = float(np.percentile(rhythm, 95)) <= GAP_FACTOR * med
        positions = None
        if steady and bool(np.all(whole | (k > BRIDGE + 0.5))):
            pos = np.concatenate([[0], np.cumsum(np.maximum(n, 1).astype(np.int64))])
            if pos[-1] + 1 <= MAX_GRID_FILL * t.size:
                positions = pos
        return cls(med, float(np.percentile(d, 95)), steady, positions)

    @property
    def gap_s(self) -> float:
        """An interval longer than this is a gap: on a grid, a hole of more than BRIDGE steps; else GAP_FACTOR times
        the typical interval, the median for a steady time base and the 95th percentile for a bursty one."""
        if self.positions is not None:
            return (BRIDGE + 0.5) * self.step
        return GAP_FACTOR * max(self.step, self.p95)

    @property
    def holes(self) -> bool:
        """Whether some sample is missing from the grid (a bridged hole)."""
        return self.positions is not None and int(self.positions[-1]) + 1 > self.positions.size

    def on_grid(self, x: np.ndarray, f: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """f of x (N, ...) laid on the uniform grid (its holes filled by linear interpolation), read back at the
        samples' slots."""
        assert self.positions is not None
        pos = self.positions
        flat = np.asarray(x, float).reshape(x.shape[0], -1)
        slots = np.arange(int(pos[-1]) + 1)
        grid = np.stack([np.interp(slots, pos, flat[:, c]) for c in range(flat.shape[1])], axis=1)
        return f(grid.reshape((slots.size,) + x.shape[1:]))[pos]

    def filtered(self, x: np.ndarray, window: int, deriv: int = 0) -> np.ndarray:
        """The quadratic Savitzky-Golay filter of x (N, ...) along time over `window` samples (deriv 1: d/dt), on
        the uniform grid where samples are missing from it, else on the samples as they are."""
        from scipy.signal import savgol_filter  # here, not at import (a command's start)

        def f(g: np.ndarray) -> np.ndarray:
            return savgol_filter(g, window, 2, deriv=deriv, delta=self.step, axis=0, mode="interp")
        return self.on_grid(x, f) if self.holes else f(np.asarray(x, float))


def sample_grid(t_s: np.ndarray) -> tuple[np.ndarray, float]:
    """(positions on a uniform grid, its step) for sample times t_s, laid out as the residual's spectra are taken
    (welch_spectra: over the samples in their order). A steady time base: its median interval, a hole or gap held as
    its length. A bursty one: the samples in their order at their mean interval, a gap (an interval over GAP_FACTOR
    times the 95th percentile) held as its length; the bursts' rhythm is far faster than the periods the power law
    serves. On the median interval a bursty record's spectra were read at 4 times their frequencies and over a
    quarter of its duration (a real hand-turned board of 106 s, 8,190 samples 2-58 ms apart: an offset that
    follows a logged heater got 7,600 nT/A for an error whose spread over 60 random heater histories is 281)."""
    t = np.asarray(t_s, float)
    if t.size < 2:
        return np.zeros(t.size, np.int64), 1.0
    tb = TimeBase.of(t)
    if tb.steady:
        return np.rint((t - t[0]) / tb.step).astype(np.int64), tb.step
    d = np.diff(t)
    gap = d > GAP_FACTOR * tb.p95
    step = float(np.mean(d[~gap])) if np.any(~gap) else tb.step
    inc = np.where(gap, np.maximum(np.rint(d / step), 1.0), 1.0).astype(np.int64)
    return np.concatenate([[0], np.cumsum(inc)]), step
