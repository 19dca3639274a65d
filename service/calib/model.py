"""The probe model: corrected = matrix · (raw − offset_nT), per probe, and the array of probes.

`matrix` maps a probe's raw output (nT at nominal scale) to an orthogonal frame: the probe's own
triangular frame after a single-probe fit (001 eq. 12: upper-triangular, the z axis along the
sensor's z winding, y in its y-z plane), or the common (platform / probe-1) frame after alignment.
Effect terms (service.effects) add to this linear part; they are not applied here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


def _nan3() -> np.ndarray:
    return np.full(3, np.nan)


def _nan33() -> np.ndarray:
    return np.full((3, 3), np.nan)


@dataclass
class ProbeCalibration:
    """One probe's linear calibration with standard errors (NaN where unknown).

    >>> p = ProbeCalibration("s1", offset_nT=np.array([1.0, 2.0, 3.0]), matrix=2 * np.eye(3))
    >>> p.apply(np.array([[2.0, 2.0, 2.0]])).tolist()
    [[2.0, 0.0, -2.0]]
    """

    name: str
    offset_nT: np.ndarray
    matrix: np.ndarray
    offset_se_nT: np.ndarray = field(default_factory=_nan3)
    matrix_se: np.ndarray = field(default_factory=_nan33)
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.offset_nT = np.asarray(self.offset_nT, dtype=float).reshape(3)
        self.matrix = np.asarray(self.matrix, dtype=float).reshape(3, 3)
        self.offset_se_nT = np.asarray(self.offset_se_nT, dtype=float).reshape(3)
        self.matrix_se = np.asarray(self.matrix_se, dtype=float).reshape(3, 3)

    def apply(self, field_nT: np.ndarray) -> np.ndarray:
        """corrected = M (raw − o) for (N, 3) raw samples."""
        return (np.asarray(field_nT, dtype=float) - self.offset_nT) @ self.matrix.T

    def rotated(self, rotation: np.ndarray, **params: Any) -> "ProbeCalibration":
        """The same probe expressed in another orthogonal frame: M' = R M (standard errors of M kept
        to first order by rotating |se|, an approximation that ignores the rotation's own error)."""
        r = np.asarray(rotation, float)
        return ProbeCalibration(self.name, self.offset_nT.copy(), r @ self.matrix, self.offset_se_nT.copy(),
                                np.sqrt((r ** 2) @ (self.matrix_se ** 2)), {**self.params, **params})

    def is_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.matrix)) and np.all(np.isfinite(self.offset_nT)))


@dataclass
class ArrayCalibration:
    """Every probe's calibration in one common frame, with how it was obtained."""

    method: str
    align: str | None
    probes: list[ProbeCalibration]
    total_nT: float | None = None
    effects: list[str] = field(default_factory=list)
    effect_params: dict[str, Any] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    span: tuple[float, float, int] = (0.0, 0.0, 0)      # t0_s, t1_s, n_samples of the data it came from

    @property
    def n_probes(self) -> int:
        return len(self.probes)

    @property
    def probe_names(self) -> list[str]:
        return [p.name for p in self.probes]

    def matrices(self) -> np.ndarray:
        return np.stack([p.matrix for p in self.probes])

    def offsets(self) -> np.ndarray:
        return np.stack([p.offset_nT for p in self.probes])

    def apply(self, field_nT: np.ndarray) -> np.ndarray:
        """(N, P, 3) raw -> (N, P, 3) corrected, all probes at once."""
        f = np.asarray(field_nT, dtype=float)
        if f.ndim != 3 or f.shape[1] != self.n_probes or f.shape[2] != 3:
            raise ValueError(f"field_nT: expected shape (N, {self.n_probes}, 3), got {f.shape}")
        # b_k = M_k (raw_k - o_k)
        return np.einsum("pij,npj->npi", self.matrices(), f - self.offsets()[None])
