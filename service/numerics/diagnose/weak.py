"""Whether the held-out test can judge these data: each time block is predicted by the fit to the others, which
means something only where the others saw the same orientations. A record made of separate turns (a hand-turned
board turned about one axis, then another) puts each turn in its own blocks: a block is then predicted by
extrapolation to orientations no other block saw, and a held-out gain of -94,788 % says nothing of the effect.

The field directions of probe 1 (in its aligned frame) are binned into cells of about CELL_DEG on the sphere;
a block's overlap is the share of its samples in cells that the other blocks visited (MIN_VISITS samples). The
held-out test is weak where the median block's overlap is below OVERLAP, or a block holds fewer than MIN_ROWS rows.

Numerics only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.numerics.engine import FitResult

CELL_DEG = 20.0
MIN_VISITS = 3
OVERLAP = 0.5
MIN_ROWS = 40


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


def heldout_weakness(fit: FitResult) -> dict[str, Any] | None:
    """None where the held-out test can judge these data; else {"reason", "overlap", "advice"} (JSON-ready)."""
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
    if med >= OVERLAP:
        return None
    return {"reason": f"the held-out blocks see different orientations: the median block has {100 * med:.0f} % of "
                      f"its samples in directions the other blocks saw (the blocks are separate turns), so each is "
                      f"predicted by extrapolation and the held-out gains say little of an effect",
            "overlap": overlap.tolist(),
            "advice": "a recording that repeats its motion would decide: turn over the whole sphere two or three "
                      "times (or each turn twice, one after the other), so that every part of the record sees the "
                      "orientations the others see"}
