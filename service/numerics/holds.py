"""Held values: a logger that writes a probe's previous value again when no new sample came (a 100 Hz log of a
25 Hz magnetometer, a bus read faster than the sensor converts) repeats it exactly, all three axes, bit for bit.
Those rows are no measurements: kept, they make the second differences zero (a noise floor of 0.001 nT, a residual
"6.4 x the noise") and a staircase whose steps show as a disturbance at tens of Hz. They are found per probe,
counted, and left out of the noise floor, the fits and the spectra (the row goes for every probe: the probes are
compared sample by sample), and said.

A quantised sensor at rest repeats a reading by chance too: exact repeats are taken for holds only where they are
more than CHANCE_FACTOR times as many as the per-axis repeat rates would give by chance (the rate at which each axis
repeats on the pairs where another axis changed, which no hold is and where independent axes repeat at their own
rate, multiplied over the three axes). A coarse sensor at rest whose every axis repeats most of the time by chance
is thereby kept whole; a hold among such repeats cannot be told from them, and is kept too.

>>> f = np.zeros((8, 1, 3)); f[:, 0, 0] = [1.0, 2.0, 2.0, 2.0, 5.0, 6.0, 6.0, 7.1]; f[:, 0, 1] = np.arange(8) ** 0.5
>>> f[2:4, 0, 1] = f[1, 0, 1]; f[6, 0, 1] = f[5, 0, 1]
>>> h = find_holds(f, ["s1"]); h.held[:, 0].tolist(), h.counts
([False, False, True, True, False, False, True, False], {'s1': 3})
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from fluxcal.drivers.block import SampleBlock

#: exact repeats are holds when they are more than this many times as many as chance gives
CHANCE_FACTOR = 3.0


@dataclass(frozen=True)
class Holds:
    """held (N, P) bool: the sample repeats the probe's previous one exactly (taken for a hold); per probe the count
    of exact repeats, how many chance would give, and what is said."""

    held: np.ndarray
    counts: dict[str, int]
    by_chance: dict[str, float]
    notes: list[str] = field(default_factory=list)

    @property
    def keep(self) -> np.ndarray:
        """(N,) bool: the rows no probe holds."""
        return ~self.held.any(axis=1)

    @property
    def n_left_out(self) -> int:
        return int(np.count_nonzero(self.held.any(axis=1)))


def find_holds(field_nT: np.ndarray, probe_names: Sequence[str]) -> Holds:
    """The exact repeats of each probe's three axes that are holds (module docstring)."""
    f = np.asarray(field_nT, np.float64)
    n, p = f.shape[:2]
    held = np.zeros((n, p), bool)
    counts: dict[str, int] = {}
    chance: dict[str, float] = {}
    notes: list[str] = []
    if n < 2:
        return Holds(held, {k: 0 for k in probe_names}, {k: 0.0 for k in probe_names})
    for k, name in enumerate(probe_names):
        finite = np.isfinite(f[:, k]).all(axis=1)
        pair = finite[1:] & finite[:-1]
        axis_same = (f[1:, k] == f[:-1, k]) & pair[:, None]          # (N-1, 3)
        whole = axis_same.all(axis=1)
        m = int(np.count_nonzero(whole))
        pairs = int(np.count_nonzero(pair))
        expected = float(pairs * np.prod(_chance_rates(axis_same, pair)))
        counts[name], chance[name] = m, expected
        if m and m > CHANCE_FACTOR * expected:
            held[1:, k] = whole
            share = f"{m / n:.0%}" if m / n >= 0.01 else f"{m / n:.1%}" if m / n >= 0.001 else "under 0.1%"
            notes.append(f"{name}: {m:,} of {n:,} samples ({share}) repeat the previous one exactly, all three "
                         f"axes (a logger's hold: {expected:.3g} expected by chance from how often each axis repeats): "
                         f"left out of the noise floor, the fits and the spectra")
        elif m and m < pairs:        # (a probe whose every sample repeats did not measure: usable.refuse_stuck says)
            notes.append(f"{name}: {m:,} exact repeats of the previous sample, about as many as the sensor's "
                         f"resolution gives by chance ({expected:.3g}): kept as measurements")
    if held.any() and p > 1:
        rows = int(np.count_nonzero(held.any(axis=1)))
        notes.append(f"{rows:,} of {n:,} rows left out for holds in all: a row held for one probe is left out for every "
                     f"probe (the probes are compared sample by sample)")
    return Holds(held, counts, chance, notes)


def _chance_rates(axis_same: np.ndarray, pair: np.ndarray) -> np.ndarray:
    """(3,) how often each axis repeats by chance: on the pairs where another axis changed (a hold never is one of
    them; for independent axes the rate there is the axis' own). Where the other two never change, all pairs."""
    rates = np.empty(3)
    for a in range(3):
        moved = pair & ~axis_same[:, [b for b in range(3) if b != a]].all(axis=1)
        base = moved if moved.any() else pair
        rates[a] = np.count_nonzero(axis_same[:, a] & base) / max(int(np.count_nonzero(base)), 1)
    return rates


def without_holds(block: SampleBlock, probe_names: Sequence[str]) -> tuple[SampleBlock, Holds]:
    """The block without the rows any probe holds (the block itself when there are none), and what was found."""
    h = find_holds(block.field_nT, probe_names)
    if not h.held.any():
        return block, h
    return block.rows(h.keep), h
