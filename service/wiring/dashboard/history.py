"""What a dashboard keeps of a unit's streams: the interval means at 10 Hz of unit time that the recorder
writes too (fluxcal.service.numerics.decimate) in bounded rings, noise floors, and the recent raw samples a
diagnosis needs. Everything here is updated block by block
(numpy over the block, a Python step per 0.1-s interval at most), never sample by sample.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.service.numerics.noise import robust_noise
from fluxcal.service.numerics.outputs import CorrectedBlock

#: interval of the plotted means, s of unit time
PERIOD_S = 0.1
#: intervals kept per series: 10 minutes at 10 Hz
HISTORY = 6000
#: the window of unit time over which the difference magnitude and the error table are averaged, s
WINDOW_S = 10.0


class Ring:
    """The newest `size` rows of a table of named columns, each row numbered (a client asks for the rows
    after the last number it has)."""

    def __init__(self, columns: list[str], size: int = HISTORY) -> None:
        self.columns = columns
        self.rows: deque[tuple[int, float, np.ndarray]] = deque(maxlen=size)
        self.next_id = 1

    def append(self, t_s: float, values: np.ndarray) -> None:
        self.rows.append((self.next_id, t_s, values))
        self.next_id += 1

    def since(self, row_id: int, most: int = HISTORY) -> dict[str, Any]:
        """{"columns", "id" (the newest row's number), "t": [...], "v": [[row], ...]} of the rows after `row_id`."""
        rows = [r for r in self.rows if r[0] > row_id] if row_id else list(self.rows)
        rows = rows[-most:]
        return {"columns": self.columns, "id": self.next_id - 1, "t": [round(r[1], 4) for r in rows],
                "v": [[None if not math.isfinite(x) else round(float(x), 4) for x in r[2]] for r in rows]}


class WindowMeans:
    """Means over the newest `window_s` of unit time of per-interval values (K,), each interval weighted by its
    number of samples, NaN-aware per value; the window restarts when the calibration changes or time steps back.
    At most window_s / PERIOD_S rows are kept, and the sums run once per interval (10 Hz)."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self.window_s = window_s
        self.rows: deque[tuple[float, int, np.ndarray]] = deque()
        self.key: Any = None
        self.t_first = 0.0                                            # the start of the first interval since a restart

    def add(self, t_s: float, n: int, values: np.ndarray, key: Any = None) -> np.ndarray:
        """Add one interval (its start t_s, its n samples, its values); returns the window's means (K,)."""
        values = np.asarray(values, dtype=np.float64)
        if key != self.key or (self.rows and (t_s < self.rows[-1][0] or values.shape != self.rows[-1][2].shape)):
            self.rows.clear()
            self.key = key
        if not self.rows:
            self.t_first = t_s
        self.rows.append((t_s, max(int(n), 1), values))
        while self.rows[0][0] <= t_s - self.window_s + 1e-9:
            self.rows.popleft()
        return self.mean()

    def mean(self) -> np.ndarray | None:
        if not self.rows:
            return None
        v = np.array([r[2] for r in self.rows])                       # (R, K)
        w = np.array([r[1] for r in self.rows], dtype=np.float64)[:, None] * np.isfinite(v)
        with np.errstate(invalid="ignore", divide="ignore"):
            return (np.where(np.isfinite(v), v, 0.0) * w).sum(axis=0) / w.sum(axis=0)

    @property
    def span_s(self) -> float:
        """The unit time the window covers now: window_s, or less in its first seconds after a (re)start."""
        return 0.0 if not self.rows else min(self.window_s, self.rows[-1][0] - self.t_first + PERIOD_S)


def corrected_columns(probe_names: list[str], rec: dict[str, Any]) -> list[str]:
    """Column names of one interval of fluxcal.service.numerics.decimate.VectorMeans: <probe>.x/.y/.z/.total,
    centre.*, <pk>-<p1>.x/.y/.z and <pk>-<p1>.norm (see `corrected_row`), G.<ij> and G.trace."""
    cols = [f"{p}.{a}" for p in probe_names for a in ("x", "y", "z", "total")]
    if rec["center"] is not None:
        cols += [f"centre.{a}" for a in ("x", "y", "z", "total")]
    if rec["diff"] is not None:
        cols += [f"{p}-{probe_names[0]}.{a}" for p in probe_names[1:] for a in ("x", "y", "z", "norm")]
    if rec["tensor"] is not None:
        cols += [f"G.{i}{j}" for i in "xyz" for j in "xyz"] + ["G.trace"]
    return cols


def corrected_row(rec: dict[str, Any], diff_norm: np.ndarray | None = None) -> np.ndarray:
    """One interval of VectorMeans as a row in the order of `corrected_columns`. A difference's magnitude is
    `diff_norm` (P-1,): the norm of its components' mean over the window (WindowMeans), not the interval's mean
    of |d|, which the noise biases upward (1.63 nT for 0.51 nT with 1 nT of noise per axis, issue 28)."""
    parts = [np.column_stack([rec["mean"], rec["total"]]).ravel()]
    if rec["center"] is not None:
        parts.append(np.append(rec["center"][0], rec["center"][1]))
    if rec["diff"] is not None:
        norm = np.full(rec["diff"][0].shape[0], np.nan) if diff_norm is None else diff_norm
        parts.append(np.column_stack([rec["diff"][0], norm]).ravel())
    if rec["tensor"] is not None:
        parts.append(np.append(np.ravel(rec["tensor"][0]), rec["tensor"][1]))
    return np.concatenate(parts)


@dataclass
class Floors:
    """Noise floor of each error channel, from the newest `window` samples of the corrected stream: the
    robust white-noise sigma (fluxcal.service.numerics.noise) of each probe's |B| and of each difference axis."""

    window: int = 2048
    recent: deque = field(default_factory=deque)
    n_recent: int = 0
    names: list[str] = field(default_factory=list)

    def add(self, block: CorrectedBlock, probe_names: list[str]) -> None:
        mag = np.linalg.norm(block.corrected_nT, axis=2)
        cols = [mag]
        names = [f"{p}.scalar" for p in probe_names]
        if block.diff_nT is not None:
            cols.append(block.diff_nT.reshape(block.n_samples, -1))
            names += [f"{p}-{probe_names[0]}.{a}" for p in probe_names[1:] for a in "xyz"]
        self.names = names
        self.recent.append(np.concatenate(cols, axis=1))
        self.n_recent += block.n_samples
        while self.recent and self.n_recent - self.recent[0].shape[0] >= self.window:
            self.n_recent -= self.recent.popleft().shape[0]

    def floors(self) -> dict[str, float]:
        if not self.recent or self.n_recent < 16:
            return {}
        x = np.concatenate(list(self.recent))
        if x.shape[1] != len(self.names):
            return {}
        return {n: robust_noise(x[:, k]) for k, n in enumerate(self.names)}


class RawKeep:
    """The newest raw samples, at most `max_samples` and `max_s` seconds, for a diagnosis on request."""

    def __init__(self, max_samples: int = 120_000, max_s: float = 300.0) -> None:
        self.max_samples = max_samples
        self.max_s = max_s
        self.blocks: deque[SampleBlock] = deque()
        self.n = 0

    def add(self, block: SampleBlock) -> None:
        if self.blocks and (block.n_probes != self.blocks[-1].n_probes
                            or set(block.extras) != set(self.blocks[-1].extras)):
            self.blocks.clear()
            self.n = 0
        self.blocks.append(block)
        self.n += block.n_samples
        while len(self.blocks) > 1 and (self.n - self.blocks[0].n_samples >= self.max_samples
                                        or block.t_s[-1] - self.blocks[1].t_s[0] >= self.max_s):
            self.n -= self.blocks.popleft().n_samples

    def block(self) -> SampleBlock | None:
        return SampleBlock.concat(list(self.blocks)) if self.blocks else None
