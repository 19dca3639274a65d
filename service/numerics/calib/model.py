"""The probe model: corrected = matrix · (raw − offset_nT), per probe, and the array of probes.

`matrix` maps a probe's raw output (nT at nominal scale) to an orthogonal frame: the probe's own
triangular frame after a single-probe fit ([FastRotation] eq. 12: upper-triangular, the z axis along the
sensor's z winding, y in its y-z plane), or the common (platform / probe-1) frame after alignment.
Effect terms (fluxcal.service.numerics.effects) add to this linear part; they are not applied here.

Two ways of naming the physics of a matrix live here too:

- [FastRotation] eq. 11-12 (the triangular model): raw = C A B_c + I with C = diag(c_x, c_y, c_z) the scale
  factors and A = [[cosθ cosφ, sinθ cosφ, sinφ], [0, cosψ, sinψ], [0, 0, 1]] whose rows are the
  unit sensing axes (φ, θ, ψ the non-orthogonality angles); the correction is M = (C A)⁻¹,
  upper-triangular. `triangular_matrix` and `triangular_params` go each way, exactly.
- [TwoFluxgate] Tables 1-2: a correction matrix A split as A = N K⁻¹ with N of unit columns (the
  "non-orthogonality" matrix) and K = diag(k) [TwoFluxgate]'s column gains, so that the raw output is
  X = K N⁻¹ B + E. `unit_column_split` does it, for [TwoFluxgate]'s tables; the outputs do not use k.

The sensor's scale factor per axis, `params["scale"]` of every method, is c of [FastRotation] eq. 11: raw axis i reads
c_i times the field along its unit sensing direction, so c_i is the norm of row i of M⁻¹ whatever the frame
M maps to (`sensor_scale`); above 1 where the axis reads high. [TwoFluxgate]'s k equals it only for orthogonal axes.
The correction matrix's diagonal is neither (about 1/c), and is called the correction diagonal where shown.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError


def _nan3() -> np.ndarray:
    return np.full(3, np.nan)


def _nan33() -> np.ndarray:
    return np.full((3, 3), np.nan)


def named(value: Any, se: Any = None, unit: str = "", **extra: Any) -> dict[str, Any]:
    """One entry of `ProbeCalibration.params`: {"value", "se", "unit", ...} as plain lists/floats."""

    def plain(x: Any) -> Any:
        if x is None:
            return None
        a = np.asarray(x, dtype=float)
        return a.tolist() if a.ndim else float(a)

    return {"value": plain(value), "se": plain(se), "unit": unit, **extra}


@dataclass
class ProbeCalibration:
    """One probe's linear calibration with standard errors (NaN where unknown).

    `params` holds named physical parameters, each {"value": ..., "se": ..., "unit": ...}
    (e.g. "offset_nT", "scale", "nonorth_deg", "misalign_deg").

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
    #: the terms fitted (calib.order: "full", "axes", "sphere"); fewer when the data determine fewer
    model_order: str = "full"
    #: what a user must know before trusting it: terms held fixed, parameters not determined
    warnings: list[str] = field(default_factory=list)

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
                                np.sqrt((r ** 2) @ (self.matrix_se ** 2)), {**self.params, **params},
                                self.model_order, list(self.warnings))

    def is_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.matrix)) and np.all(np.isfinite(self.offset_nT)))

    def value(self, key: str) -> np.ndarray:
        """The value of a named parameter as an array (KeyError naming what exists if absent)."""
        if key not in self.params:
            raise KeyError(f"{self.name}: no parameter {key!r} (has: {', '.join(self.params) or 'none'})")
        return np.asarray(self.params[key]["value"], dtype=float)


@dataclass
class ArrayCalibration:
    """Every probe's calibration in one common frame, with how it was obtained.

    diagnostics: free-form numbers a user needs to trust it (per probe scalar residual RMS before and
    after, condition numbers, coverage summary); see `scalar_residual_summary`.
    span: (t0_s, t1_s, n_samples) of the data the calibration came from.
    unit: the unit (and its probes' serial numbers) the calibration was made for, as far as known.
    """

    method: str
    align: str | None
    probes: list[ProbeCalibration]
    total_nT: float | None = None
    effects: list[str] = field(default_factory=list)
    effect_params: dict[str, Any] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    span: tuple[float, float, int] = (0.0, 0.0, 0)      # t0_s, t1_s, n_samples of the data it came from
    #: the unit it was made for: {"name": "grad1", "probes": {"s1": "<serial>", ...}} ({}: not said); the service
    #: refuses one made for another unit (fluxcal.service.wiring.identity)
    unit: dict[str, Any] = field(default_factory=dict)

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
        """(N, P, 3) raw -> (N, P, 3) corrected, all probes at once. A calibration with effect terms is refused: its
        effects need the samples' times and temperatures, which a field alone does not carry (apply_linear gives
        its linear part, knowingly; a fit's result corrects with the effects: FitResult.correct)."""
        if self.effects:
            raise DataError(f"this calibration holds effect terms ({', '.join(self.effects)}) that read more than the "
                            f"field (the samples' times, temperatures or logged columns): correct with the fit's result "
                            f"(result.correct(data)), or take its linear part knowingly with apply_linear(field_nT)")
        return self.apply_linear(field_nT)

    def apply_linear(self, field_nT: np.ndarray) -> np.ndarray:
        """(N, P, 3) raw -> (N, P, 3) corrected by the linear part alone (M (raw - o)), whatever effects it holds."""
        f = np.asarray(field_nT, dtype=float)
        if f.ndim != 3 or f.shape[1] != self.n_probes or f.shape[2] != 3:
            raise DataError(f"field_nT: expected shape (N, {self.n_probes}, 3) (samples, probes, axes), got {f.shape}")
        # b_k = M_k (raw_k - o_k), rounded as the service's pipeline rounds it, whatever the arrays' layout
        return apply_columns(matrix_columns(self.matrices()), f - self.offsets()[None])


def apply_columns(m: tuple[np.ndarray, np.ndarray, np.ndarray], d: np.ndarray) -> np.ndarray:
    """b[n, p, i] = Σ_j M[p, i, j] d[n, p, j], element by element in the order j = 0, 1, 2: the same rounding whatever
    N is and however the arrays lie in memory (a BLAS product or einsum may sum differently for other block sizes
    or strides, and replay must equal live, a loaded calibration the one in memory). m: matrix_columns(M)."""
    b = d[..., 0:1] * m[0]
    b += d[..., 1:2] * m[1]
    b += d[..., 2:3] * m[2]
    return b


def matrix_columns(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The columns of the matrices (P, 3, 3) as apply_columns multiplies them, (1, P, 3) each."""
    return m[None, :, :, 0], m[None, :, :, 1], m[None, :, :, 2]


def scalar_residual_summary(cal: ArrayCalibration, raw_nT: np.ndarray,
                            total_nT: float | np.ndarray) -> dict[str, dict[str, float]]:
    """Per probe RMS of |b| − F before (raw) and after calibration, in nT, for `diagnostics`."""
    raw = np.asarray(raw_nT, float)
    f = np.asarray(total_nT, float)
    f = f[:, None] if f.ndim == 1 else f
    before = np.sqrt(np.mean((np.linalg.norm(raw, axis=2) - f) ** 2, axis=0))
    after = np.sqrt(np.mean((np.linalg.norm(cal.apply(raw), axis=2) - f) ** 2, axis=0))
    return {p.name: {"before_nT": float(b), "after_nT": float(a)} for p, b, a in zip(cal.probes, before, after)}


# --- [FastRotation] eq. 11-12: the triangular model -------------------------------------------------


def triangular_matrix(nonorth_deg: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """M = (C A)⁻¹ of [FastRotation] eq. 12 from φ, θ, ψ (deg) and c_x, c_y, c_z.

    M = [[k_x, m k_y, g k_z], [0, k_y, n k_z], [0, 0, k_z]] with k_x = 1/(c_x cosφ cosθ),
    k_y = 1/(c_y cosψ), k_z = 1/c_z, m = −tanθ, n = −tanψ and
    g = (sinθ cosφ sinψ − sinφ cosψ) / (cosθ cosφ cosψ)   (the paper prints g with sinφ in place of
    cosφ sinψ in the first term and without cosψ below; this form is the exact inverse of C A).

    >>> m = triangular_matrix([3.56, -1.85, 2.27], [1.253, 1.175, 0.859])
    >>> a = np.array(triangular_params(m)[0])
    >>> bool(np.allclose(a, [3.56, -1.85, 2.27]))
    True
    """
    phi, theta, psi = np.radians(np.asarray(nonorth_deg, float))
    cx, cy, cz = np.asarray(scale, float)
    kx = 1.0 / (cx * np.cos(phi) * np.cos(theta))
    ky = 1.0 / (cy * np.cos(psi))
    kz = 1.0 / cz
    m = -np.tan(theta)
    n = -np.tan(psi)
    g = (np.sin(theta) * np.cos(phi) * np.sin(psi) - np.sin(phi) * np.cos(psi)) / (
        np.cos(theta) * np.cos(phi) * np.cos(psi))
    return np.array([[kx, m * ky, g * kz], [0.0, ky, n * kz], [0.0, 0.0, kz]])


def sensing_matrix(nonorth_deg: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """C A of [FastRotation] eq. 11 (raw = C A B_c + I): rows are the scaled unit sensing axes."""
    phi, theta, psi = np.radians(np.asarray(nonorth_deg, float))
    a = np.array([[np.cos(theta) * np.cos(phi), np.sin(theta) * np.cos(phi), np.sin(phi)],
                  [0.0, np.cos(psi), np.sin(psi)],
                  [0.0, 0.0, 1.0]])
    return np.diag(np.asarray(scale, float)) @ a


def triangular_params(matrix: np.ndarray) -> tuple[list[float], list[float]]:
    """(φ, θ, ψ in degrees, [c_x, c_y, c_z]) of an upper-triangular correction M ([FastRotation] eq. 11-12).

    Inverts `triangular_matrix` exactly: k = diag(M); m = M12/k_y, n = M23/k_z, g = M13/k_z;
    ψ = −atan n, θ = −atan m, tanφ = (sinθ sinψ − g cosθ cosψ)/cosψ; c_z = 1/k_z,
    c_y = 1/(k_y cosψ), c_x = 1/(k_x cosφ cosθ).
    """
    mat = np.asarray(matrix, float)
    if np.any(np.abs(np.tril(mat, -1)) > 1e-12 * np.abs(mat).max()) or np.any(np.diag(mat) <= 0):
        raise ValueError("triangular_params: expected an upper-triangular matrix with a positive diagonal")
    kx, ky, kz = np.diag(mat)
    m, n, g = mat[0, 1] / ky, mat[1, 2] / kz, mat[0, 2] / kz
    psi = -np.arctan(n)
    theta = -np.arctan(m)
    phi = np.arctan((np.sin(theta) * np.sin(psi) - g * np.cos(theta) * np.cos(psi)) / np.cos(psi))
    cz = 1.0 / kz
    cy = 1.0 / (ky * np.cos(psi))
    cx = 1.0 / (kx * np.cos(phi) * np.cos(theta))
    return np.degrees([phi, theta, psi]).tolist(), [float(cx), float(cy), float(cz)]


def scalar_rms(raw: np.ndarray, offset: np.ndarray, matrix: np.ndarray, total_nT) -> float:
    """RMS of |M (r − o)| − F over (N, 3) raw samples (F a number or (N,)), a chunk of rows at a time (hours of
    data: no (N, 3) temporaries)."""
    n, step = raw.shape[0], 65536
    f = np.broadcast_to(np.asarray(total_nT, float), (n,))
    sq = sum(float(np.sum((np.linalg.norm((raw[a:a + step] - offset) @ matrix.T, axis=1) - f[a:a + step]) ** 2))
             for a in range(0, n, step))
    return float(np.sqrt(sq / max(n, 1)))


def triangular_params_many(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """triangular_params of (M, 3, 3) upper-triangular matrices at once: angles (M, 3) deg, scales (M, 3);
    ValueError unless every one is upper-triangular with a positive diagonal."""
    mat = np.asarray(matrices, float)
    lower = np.abs(mat[:, [1, 2, 2], [0, 0, 1]])
    if np.any(lower > 1e-12 * np.abs(mat).max(axis=(1, 2))[:, None]) or np.any(mat[:, [0, 1, 2], [0, 1, 2]] <= 0):
        raise ValueError("triangular_params: expected upper-triangular matrices with a positive diagonal")
    kx, ky, kz = mat[:, 0, 0], mat[:, 1, 1], mat[:, 2, 2]
    m, n, g = mat[:, 0, 1] / ky, mat[:, 1, 2] / kz, mat[:, 0, 2] / kz
    psi = -np.arctan(n)
    theta = -np.arctan(m)
    phi = np.arctan((np.sin(theta) * np.sin(psi) - g * np.cos(theta) * np.cos(psi)) / np.cos(psi))
    scales = np.column_stack([1.0 / (kx * np.cos(phi) * np.cos(theta)), 1.0 / (ky * np.cos(psi)), 1.0 / kz])
    return np.degrees(np.column_stack([phi, theta, psi])), scales


def sensor_scale(matrix: np.ndarray) -> np.ndarray:
    """The sensor's scale factor per axis of a correction matrix M in any frame: the row norms of M⁻¹ (the raw
    output is M⁻¹ B + o, and row i of M⁻¹ is c_i times axis i's unit sensing direction, [FastRotation] eq. 11).

    >>> m = triangular_matrix([1.0, -2.0, 1.5], [1.02, 0.98, 1.01])
    >>> turn = np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])
    >>> sensor_scale(turn @ m).round(9).tolist()
    [1.02, 0.98, 1.01]
    """
    return np.linalg.norm(np.linalg.inv(np.asarray(matrix, float)), axis=1)


# --- [TwoFluxgate] Tables 1-2: non-orthogonality (unit columns) and column gains ----------------------


def unit_column_split(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, k): A = N diag(k)⁻¹ with the columns of N unit vectors ([TwoFluxgate] Tables 1-2).

    k are [TwoFluxgate]'s column gains (it calls them sensitivities): the raw output is X = diag(k) N⁻¹ B + E. They
    are not the sensor's scale factors (`sensor_scale`) unless the axes are orthogonal.
    """
    a = np.asarray(matrix, float)
    norms = np.linalg.norm(a, axis=0)
    return a / norms, 1.0 / norms
