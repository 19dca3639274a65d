"""The residuals of one evaluation of a fit: the values of each residual channel on the fitted rows (Channels)
and what an evaluation carries besides (_Eval). The channels' names have their one home in
fluxcal.service.numerics.channels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Channels:
    """Residual channels of a model on the fitted rows: names, values (rows, C) in nT, time."""

    names: list[str]
    values: np.ndarray
    t_s: np.ndarray
    rows: np.ndarray

    @property
    def rms_nT(self) -> np.ndarray:
        return np.sqrt(np.mean(self.values ** 2, axis=0))

    @property
    def total_rms_nT(self) -> float:
        """RMS over all channels (`rms_nT` of docs/contracts.md)."""
        return float(np.sqrt(np.mean(self.values ** 2)))

    def as_dict(self) -> dict[str, np.ndarray]:
        return {n: self.values[:, i] for i, n in enumerate(self.names)}


@dataclass
class _Eval:
    v0: list[np.ndarray]           # full length (N, 3) per probe, before corrected-frame corrections
    v: list[np.ndarray]            # rows (M, 3)
    nhat: list[np.ndarray]         # rows (M, 3)
    scalar: np.ndarray             # (M, P)
    diff: np.ndarray               # (M, P-1, 3)
    vec: np.ndarray | None = None  # (M, P, 3) corrected minus the reference vector
    _matrix: np.ndarray | None = field(default=None, repr=False)

    def channel_matrix(self) -> np.ndarray:
        """(M, C) every residual channel (built once; treat as read-only)."""
        if self._matrix is None:
            m = self.scalar.shape[0]
            parts = [self.scalar, self.diff.reshape(m, -1)]
            if self.vec is not None:
                parts.append(self.vec.reshape(m, -1))
            self._matrix = np.concatenate(parts, axis=1)
        return self._matrix
