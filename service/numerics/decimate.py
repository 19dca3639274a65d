"""Decimation of the corrected streams for dashboards and recordings: interval means of the vectors."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .outputs import CorrectedBlock


class VectorMeans:
    """Means of the corrected vectors over intervals of `period_s` of unit time: per probe x, y, z
    (NaN-aware) and mean |B|, and the same of the array centre when the blocks have it. Interval k
    holds k·period <= t < (k+1)·period; it also ends early when the calibration (cal_id) changes.
    Blocks inside one interval are only kept; the arithmetic runs once per interval (10 Hz)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.parts: list[CorrectedBlock] = []      # the interval being filled
        self.bin = 0

    def _bin(self, t: float) -> int:
        # the 1e-9 keeps a sample on a boundary in the interval it starts (0.3 s is
        # 2.9999999999999996 periods of 0.1 s in binary)
        return math.floor(t / self.period_s + 1e-9)

    def add(self, block: CorrectedBlock) -> list[dict[str, Any]]:
        """Feed a block; returns the intervals it completed."""
        done: list[dict[str, Any]] = []
        t = block.t_s
        if not np.isfinite(t).all():
            keep = np.flatnonzero(np.isfinite(t))
            block = block_rows(block, keep)
            t = block.t_s
        if t.size == 0:
            return done
        first, last = self._bin(float(t[0])), self._bin(float(t[-1]))
        if self.parts:
            prev = self.parts[-1]
            if (first != self.bin or block.cal_id != prev.cal_id or block.n_probes != prev.n_probes
                    or (block.center_nT is None) != (prev.center_nT is None)):
                done.append(self._emit())
        if first == last:
            if not self.parts:
                self.bin = first
            self.parts.append(block)
            return done
        bins = np.floor(t / self.period_s + 1e-9).astype(np.int64)
        cuts = np.concatenate([[0], np.flatnonzero(np.diff(bins)) + 1, [t.size]])
        for a, b in zip(cuts[:-1], cuts[1:]):
            if a > 0:
                done.append(self._emit())
            if not self.parts:
                self.bin = int(bins[a])
            self.parts.append(block_rows(block, slice(a, b)))
        return done

    def flush(self) -> list[dict[str, Any]]:
        return [self._emit()] if self.parts else []

    @staticmethod
    def _mean(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """NaN-aware mean over samples of (N, P, 3): (P, 3) of x, y, z and (P,) of |B|; NaN if none."""
        ok = np.isfinite(c)
        norm = np.sqrt(np.einsum("npk,npk->np", c, c))          # |B| = sqrt(x^2 + y^2 + z^2), NaN if an axis is
        nok = np.isfinite(norm)
        with np.errstate(invalid="ignore", divide="ignore"):
            return (np.where(ok, c, 0.0).sum(axis=0) / ok.sum(axis=0),
                    np.where(nok, norm, 0.0).sum(axis=0) / nok.sum(axis=0))

    def _emit(self) -> dict[str, Any]:
        """{"t_s", "seq", "n", "cal_id", "mean" (P, 3) nT, "total" (P,) nT, "center": (mean (3,), total) or None}."""
        parts, self.parts = self.parts, []
        c = parts[0].corrected_nT if len(parts) == 1 else np.concatenate([p.corrected_nT for p in parts])
        mean, total = self._mean(c)
        center = None
        if parts[0].center_nT is not None:
            cm, ct = self._mean(np.concatenate([p.center_nT for p in parts])[:, None, :])
            center = (cm[0], ct[0])
        return {"t_s": float(parts[0].t_s[0]), "seq": int(parts[0].seq[0]), "n": int(c.shape[0]),
                "cal_id": int(parts[-1].cal_id), "mean": mean, "total": total, "center": center}


def block_rows(b: CorrectedBlock, rows: Any) -> CorrectedBlock:
    """The rows `rows` of a corrected block (probes, centre and calibration id kept; differences and tensor dropped)."""
    return CorrectedBlock(b.t_s[rows], b.seq[rows], b.corrected_nT[rows], None, None,
                          None if b.center_nT is None else b.center_nT[rows], b.cal_id)
