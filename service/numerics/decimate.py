"""Decimation of the corrected streams for dashboards and recordings: interval means of the vectors, the
gradiometer differences and the tensor (VectorMeans), and interval RMS of the per-block error metric
(RmsMeans)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from .outputs import CorrectedBlock


class VectorMeans:
    """Means of the corrected vectors over intervals of `period_s` of unit time: per probe x, y, z
    (NaN-aware) and mean |B|, and the same of the array centre, of the differences (probe k minus
    probe 1, with mean |d|) and of the tensor (with the trace of the mean) when the blocks have them. Interval k
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
                    or any((getattr(block, k) is None) != (getattr(prev, k) is None) for k in _OPTIONAL)):
                done.append(self._emit())
        if first == last:
            if not self.parts:
                self.bin = first
            self.parts.append(block)
            return done
        bins = np.floor(t / self.period_s + 1e-9).astype(np.int64)
        cuts = np.concatenate([[0], np.flatnonzero(np.diff(bins)) + 1, [t.size]])
        whole = cuts[1:-1]
        if whole.size - 1 >= self.BATCH:
            # the intervals between the first (it may end one begun by earlier blocks) and the last (left open)
            # lie in this block alone: in a long block (replay) they are computed together, with the same rounding
            if not self.parts:
                self.bin = int(bins[0])
            self.parts.append(block_rows(block, slice(0, whole[0])))
            done.append(self._emit())
            done += self._whole(block, whole[:-1], whole[1:])
            self.bin = int(bins[whole[-1]])
            self.parts.append(block_rows(block, slice(whole[-1], t.size)))
            return done
        for a, b in zip(cuts[:-1], cuts[1:]):
            if a > 0:
                done.append(self._emit())
            if not self.parts:
                self.bin = int(bins[a])
            self.parts.append(block_rows(block, slice(a, b)))
        return done

    def flush(self) -> list[dict[str, Any]]:
        return [self._emit()] if self.parts else []

    #: whole intervals in one block from which they are computed together
    BATCH = 4

    @staticmethod
    def _sums(x: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Σ of the rows [start, end) of x (N, ...) for every interval (consecutive: each ends where the next
        starts), as ndarray.sum(axis=0) of each interval alone sums them: a run of intervals of one length n is one
        view (k, n, ...) of x summed over its second axis, which sums each interval as that does (row after row
        where a row holds several values, pairwise where it holds one), without copying x."""
        out = np.empty((len(starts),) + x.shape[1:], x.dtype)
        length = ends - starts
        runs = np.flatnonzero(np.diff(length)) + 1
        for i, j in zip(np.r_[0, runs].tolist(), np.r_[runs, len(starts)].tolist()):
            n, a = int(length[i]), int(starts[i])
            out[i:j] = x[a:a + (j - i) * n].reshape((j - i, n) + x.shape[1:]).sum(axis=1)
        return out

    def _means(self, c: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """_mean of every interval of c at once: (K, P, 3) and (K, P), bit for bit."""
        ok = np.isfinite(c)
        norm = np.sqrt(np.einsum("npk,npk->np", c, c))          # row by row: the same for any rows
        nok = np.isfinite(norm)
        if ok.all() and nok.all():          # nothing to leave out: the same sums, over the interval's samples
            n = (ends - starts)[:, None]
            return self._sums(c, starts, ends) / n[..., None], self._sums(norm, starts, ends) / n
        with np.errstate(invalid="ignore", divide="ignore"):
            return (self._sums(np.where(ok, c, 0.0), starts, ends) / self._sums(ok.astype(np.int64), starts, ends),
                    self._sums(np.where(nok, norm, 0.0), starts, ends) / self._sums(nok.astype(np.int64), starts, ends))

    def _whole(self, block: CorrectedBlock, starts: np.ndarray, ends: np.ndarray) -> list[dict[str, Any]]:
        """The intervals [start, end) of one block, each as _emit gives it."""
        mean, total = self._means(block.corrected_nT, starts, ends)
        n = len(starts)
        center = diff = tensor = [None] * n
        if block.center_nT is not None:
            cm, ct = self._means(block.center_nT[:, None, :], starts, ends)
            center = [(cm[k, 0], ct[k, 0]) for k in range(n)]
        if block.diff_nT is not None:
            dm, dt = self._means(block.diff_nT, starts, ends)
            diff = [(dm[k], dt[k]) for k in range(n)]
        if block.tensor_nT_m is not None:
            g, _ = self._means(block.tensor_nT_m, starts, ends)
            tensor = [(g[k], float(np.trace(g[k]))) for k in range(n)]
        return [{"t_s": float(block.t_s[a]), "seq": int(block.seq[a]), "n": int(b - a), "cal_id": int(block.cal_id),
                 "mean": mean[k], "total": total[k], "center": center[k], "diff": diff[k], "tensor": tensor[k]}
                for k, (a, b) in enumerate(zip(starts, ends))]

    @staticmethod
    def _mean(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """NaN-aware mean over samples of (N, P, 3): (P, 3) of x, y, z and (P,) of |B|; NaN if none."""
        ok = np.isfinite(c)
        norm = np.sqrt(np.einsum("npk,npk->np", c, c))          # |B| = sqrt(x^2 + y^2 + z^2), NaN if an axis is
        nok = np.isfinite(norm)
        if ok.all() and nok.all():          # the usual interval: the same sums over every sample, without the masks
            n = c.shape[0]
            return c.sum(axis=0) / n, norm.sum(axis=0) / n
        with np.errstate(invalid="ignore", divide="ignore"):
            return (np.where(ok, c, 0.0).sum(axis=0) / ok.sum(axis=0),
                    np.where(nok, norm, 0.0).sum(axis=0) / nok.sum(axis=0))

    def _emit(self) -> dict[str, Any]:
        """{"t_s", "seq", "n", "cal_id", "mean" (P, 3) nT, "total" (P,) nT, "center": (mean (3,), total) or None,
        "diff": (mean (P-1, 3), mean |d| (P-1,)) nT or None, "tensor": (mean (3, 3), its trace) nT/m or None}."""
        parts, self.parts = self.parts, []

        def joined(name: str) -> np.ndarray:
            arrays = [getattr(p, name) for p in parts]
            return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)

        c = joined("corrected_nT")
        mean, total = self._mean(c)
        center = diff = tensor = None
        if parts[0].center_nT is not None:
            cm, ct = self._mean(joined("center_nT")[:, None, :])
            center = (cm[0], ct[0])
        if parts[0].diff_nT is not None:
            diff = self._mean(joined("diff_nT"))
        if parts[0].tensor_nT_m is not None:
            g, _ = self._mean(joined("tensor_nT_m"))                 # rows of G as if probes: (3, 3)
            tensor = (g, float(np.trace(g)))                         # trace = div B, ~0 in a source-free field
        return {"t_s": float(parts[0].t_s[0]), "seq": int(parts[0].seq[0]), "n": int(c.shape[0]),
                "cal_id": int(parts[-1].cal_id), "mean": mean, "total": total, "center": center,
                "diff": diff, "tensor": tensor}


_OPTIONAL = ("center_nT", "diff_nT", "tensor_nT_m")


def block_rows(b: CorrectedBlock, rows: Any) -> CorrectedBlock:
    """The rows `rows` of a corrected block (every array and the calibration id kept)."""
    def pick(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[rows]

    return CorrectedBlock(b.t_s[rows], b.seq[rows], b.corrected_nT[rows], pick(b.diff_nT), pick(b.tensor_nT_m),
                          pick(b.center_nT), b.cal_id)


class RmsMeans:
    """The per-block error metric ({channel: rms nT} over n samples) combined over intervals of `period_s` of
    unit time: an interval holds the blocks that start in it, and a channel's figure is the RMS over all their
    samples, sqrt(sum n_i rms_i^2 / sum n_i). A channel missing in a block counts over the blocks that have it."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.bin: int | None = None
        self.head: tuple[float, int | None] = (0.0, None)        # t_s, seq of the interval's first block
        self.n = 0
        self.sums: dict[str, list[float]] = {}                   # channel -> [sum n rms^2, sum n]

    def add(self, rms_nT: Mapping[str, float | None], *, t_s: float, seq: int | None, n: int) -> list[dict[str, Any]]:
        """Feed one block's metric; returns the interval it completed, if any."""
        if not math.isfinite(t_s) or n <= 0:
            return []
        b = math.floor(t_s / self.period_s + 1e-9)
        done = self.flush() if self.bin is not None and b != self.bin else []
        if self.bin is None:
            self.bin, self.head = b, (t_s, seq)
        self.n += n
        for ch, r in rms_nT.items():
            if r is not None and math.isfinite(r):
                acc = self.sums.setdefault(ch, [0.0, 0.0])
                acc[0] += n * r * r
                acc[1] += n
        return done

    def flush(self) -> list[dict[str, Any]]:
        """{"t_s", "seq", "n", "rms_nT": {channel: nT}} of the interval being filled, if any."""
        if self.bin is None:
            return []
        rec = {"t_s": self.head[0], "seq": self.head[1], "n": self.n,
               "rms_nT": {ch: math.sqrt(s / w) for ch, (s, w) in self.sums.items()}}
        self.bin, self.n, self.sums = None, 0, {}
        return [rec]
