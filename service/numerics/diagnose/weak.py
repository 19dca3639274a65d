"""Whether the held-out test can judge these data: each time block is predicted by the fit to the others, which
means something only where the others saw the same orientations. A record made of separate turns (a hand-turned
board turned about one axis, then another) puts each turn in its own blocks: a block is then predicted by
extrapolation to orientations no other block saw, and a held-out gain of -94,788 % says nothing of the effect.

The field directions of probe 1 (in its aligned frame) are binned into cells of about CELL_DEG on the sphere;
a block's overlap is the share of its samples in cells that the other blocks visited (MIN_VISITS samples). The
held-out test is weak where the median block's overlap is below OVERLAP, where a block holds fewer than MIN_ROWS
rows, or where the model's own held-out error is HELDOUT_RATIO times its in-sample error or more (the blocks differ
from one another in a way the orientations alone do not show: measured 1.21 on a real hand-turned sphere of 106 s,
1.13 on an hour-long one whose residual follows time, 1.04 on a real sphere of 395 s, at most 1.07 on simulated
worlds with 1/f noise up to 5 nT/sqrt(Hz)). diagnose asks this of the best model it found: a missing effect that
changes in time makes the blocks differ by itself (a simulated temperature effect: 1.38 without it, 1.00 with it).

Numerics only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.engine import FitResult

CELL_DEG = 20.0
MIN_VISITS = 3
OVERLAP = 0.5
MIN_ROWS = 40
HELDOUT_RATIO = 1.15


def direction_cells(n: np.ndarray, cell_deg: float = CELL_DEG) -> np.ndarray:
    """(N,) cell index of unit vectors n (N, 3): bands of equal width in polar angle, each cut in azimuth into cells
    of about the same width."""
    step = np.radians(cell_deg)
    bands = int(np.ceil(np.pi / step))
    theta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
    band = np.minimum((theta / (np.pi / bands)).astype(int), bands - 1)
    centre = (band + 0.5) * np.pi / bands
    per = np.maximum(1, np.round(2 * np.pi * np.sin(centre) / step)).astype(int)
    phi = np.mod(np.arctan2(n[:, 1], n[:, 0]), 2 * np.pi)
    cell = np.minimum((phi / (2 * np.pi) * per).astype(int), per - 1)
    return band * 1000 + cell


def block_overlap(fit: FitResult) -> np.ndarray:
    """(K,) per time block, the share of its samples in direction cells the other blocks visited."""
    pr = fit.problem
    cells = direction_cells(np.asarray(fit.ev.nhat[0], float))
    uniq, inv = np.unique(cells, return_inverse=True)
    counts = np.zeros((len(pr.blocks), uniq.size), int)
    for b, sl in enumerate(pr.blocks):
        counts[b] = np.bincount(inv[sl], minlength=uniq.size)
    total = counts.sum(0)
    out = np.zeros(len(pr.blocks))
    for b, sl in enumerate(pr.blocks):
        others = total - counts[b]
        seen = others >= MIN_VISITS
        out[b] = float(np.sum(counts[b][seen])) / max(int(counts[b].sum()), 1)
    return out


def heldout_weakness(fit: FitResult, heldout_rms_nT: float | None = None) -> dict[str, Any] | None:
    """None where the held-out test can judge these data; else {"reason", "overlap", "advice"} (JSON-ready).
    heldout_rms_nT: the model's held-out error, for the third test of the module doc."""
    pr = fit.problem
    sizes = [sl.stop - sl.start for sl in pr.blocks]
    if min(sizes) < MIN_ROWS:
        return {"reason": f"the record is too short for the held-out test: {len(sizes)} blocks of at least "
                          f"{min(sizes)} samples each",
                "overlap": None,
                "advice": "record longer (several minutes, each motion repeated) so that every time block holds "
                          "enough samples of every orientation"}
    overlap = block_overlap(fit)
    med = float(np.median(overlap))
    ratio = None if heldout_rms_nT is None or not fit.rms_nT > 0 else heldout_rms_nT / fit.rms_nT
    if med >= OVERLAP and (ratio is None or ratio < HELDOUT_RATIO):
        return None
    if med >= OVERLAP:
        seconds = fit.problem.data.duration_s
        return {"reason": f"the model's own held-out error is {ratio:.2f} times its in-sample error: the time blocks "
                          f"differ from one another ({seconds:.0f} s of data), so each is predicted "
                          f"by extrapolation and a held-out gain, or its standard error, says little of an effect",
                "overlap": overlap.tolist(), "ratio": ratio,
                "advice": "a longer recording that repeats its motion would decide (the whole sphere two or three "
                          "times, each part of the record seeing what the others see)"}
    return {"reason": f"the held-out blocks see different orientations: the median block has {100 * med:.0f} % of "
                      f"its samples in directions the other blocks saw (the blocks are separate turns), so each is "
                      f"predicted by extrapolation and the held-out gains say little of an effect",
            "overlap": overlap.tolist(),
            "advice": "a recording that repeats its motion would decide: turn over the whole sphere two or three "
                      "times (or each turn twice, one after the other), so that every part of the record sees the "
                      "orientations the others see"}
