"""Linear least-squares ellipsoid fit (000 eq. 5-9, 004 eq. 5-14).

A probe with offset o and matrix M sees raw samples r on the quadric

    (r − o)ᵀ A (r − o) = F²,   A = Mᵀ M.

In scaled coordinates u = r / s (every column of order one) this is linear in nine unknowns,

    uᵀ A' u + b'ᵀ u − γ δ = 1,   δ = (F² − F₀²) / s²,

with A' = A / K, b' = −2 A' o, K = F₀²/s² − oᵀ A o / s². The tenth column (δ) enters only
when the reference total field F varies enough to carry information. Fixing the right side to 1
removes the exact null direction that the ten-term form with a constant right side has (with a
steady field, Q(u) − F² is itself a solution of the homogeneous system). M is the upper-triangular
Cholesky factor of A (001's triangular model), o = −A'⁻¹ b' / 2, and A = A' F₀² / (s² (1 + oᵀA'o)).
F is the reference total field per sample (`ref_total`), a configured constant, or, when unknown,
the mean raw magnitude: then the scale of M is a convention, not a measurement, and the result
says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.errors import CalibrationRefused, DataError

from .coverage import check_excitation, coverage
from .model import ProbeCalibration

N_GEOMETRY = 9
N_PARAMS = 10


def quadric_design(u: np.ndarray, delta: np.ndarray | None = None) -> np.ndarray:
    """Rows [x², y², z², 2xy, 2xz, 2yz, x, y, z] (and −δ when given) of scaled samples u (N, 3)."""
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    cols = [x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z]
    if delta is not None:
        cols.append(-delta)
    return np.column_stack(cols)


def quadric_to_calibration(theta: np.ndarray, scale: float, f2_ref: float) -> tuple[np.ndarray, np.ndarray]:
    """(offset_nT, upper-triangular matrix) from the fitted coefficients (nine or ten).

    Raises numpy.linalg.LinAlgError if the quadric is not an ellipsoid."""
    a = np.array([[theta[0], theta[3], theta[4]],
                  [theta[3], theta[1], theta[5]],
                  [theta[4], theta[5], theta[2]]])
    o_u = -0.5 * np.linalg.solve(a, theta[6:9])
    # (u − o)ᵀ A' (u − o) = 1 + oᵀ A' o at F = F₀: rescale so the right side is F₀² / s²
    k = (f2_ref / scale ** 2) / (1.0 + o_u @ a @ o_u)
    if not np.isfinite(k) or k <= 0:
        raise np.linalg.LinAlgError("not an ellipsoid")
    lower = np.linalg.cholesky(a * k)       # raises LinAlgError unless positive definite
    return o_u * scale, lower.T


@dataclass
class EllipsoidFit:
    """Result of a batch ellipsoid fit, with what a user needs to trust it."""

    calibration: ProbeCalibration
    theta: np.ndarray
    theta_cov: np.ndarray
    scale: float
    condition: float
    residual_rms_nT: float
    total_known: bool


def _as_total(total_nT, n: int, raw: np.ndarray) -> tuple[np.ndarray, bool]:
    if total_nT is None:
        return np.full(n, float(np.mean(np.linalg.norm(raw, axis=1)))), False
    t = np.asarray(total_nT, dtype=float)
    if t.ndim == 0:
        t = np.full(n, float(t))
    if t.shape != (n,):
        raise DataError(f"total_nT: expected a number or {n} values, got shape {t.shape}")
    return t, True


def finite_rows(field_nT: np.ndarray, what: str = "field_nT") -> np.ndarray:
    """The data as float (N, 3); DataError naming the rows that hold NaN or inf."""
    f = np.asarray(field_nT, dtype=float)
    if f.ndim != 2 or f.shape[1] != 3:
        raise DataError(f"{what}: expected shape (N, 3), got {f.shape}")
    bad = np.flatnonzero(~np.isfinite(f).all(axis=1))
    if bad.size:
        more = f" and {bad.size - 10} more" if bad.size > 10 else ""
        raise DataError(f"{what}: rows {', '.join(map(str, bad[:10].tolist()))}{more} hold NaN or inf; "
                        f"remove them before fitting")
    return f


def fit_ellipsoid(field_nT: np.ndarray, total_nT=None, *, name: str = "s1",
                  max_condition: float = 1e7) -> EllipsoidFit:
    """Fit offset and upper-triangular matrix to (N, 3) raw samples of one probe.

    Refuses (CalibrationRefused) data that cannot determine an ellipsoid: too few samples, all in
    one plane (a single-axis turn), or a badly conditioned design; the message names the missing
    directions and the motion that would fill them.
    """
    raw = finite_rows(field_nT)
    n = raw.shape[0]
    if n < N_PARAMS:
        raise CalibrationRefused(f"{name}: {n} samples, an ellipsoid fit needs at least {N_PARAMS} "
                                 f"in several rotation planes")
    check_excitation(raw, name=name)
    f, known = _as_total(total_nT, n, raw)
    scale = float(np.median(np.linalg.norm(raw, axis=1)))
    f2_ref = float(np.mean(f ** 2))
    delta = (f ** 2 - f2_ref) / scale ** 2
    # the δ column only when F varies by more than ~1 nT rms: otherwise it carries no information
    use_delta = known and float(np.std(f)) > 1.0
    phi = quadric_design(raw / scale, delta if use_delta else None)
    y = np.ones(n)
    col = np.linalg.norm(phi, axis=0)
    phin = phi / col
    u, sv, vt = np.linalg.svd(phin, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if not np.isfinite(cond) or cond > max_condition:
        cov = coverage(raw)
        raise CalibrationRefused(f"{name}: the samples do not determine an ellipsoid (condition number "
                                 f"{cond:.3g}); {cov.reason or 'add rotations about other axes'}")
    theta_n = vt.T @ ((u.T @ y) / sv)
    theta = theta_n / col
    resid = y - phi @ theta
    dof = max(n - phi.shape[1], 1)
    sigma2 = float(resid @ resid) / dof
    # cov(θ) = σ² (ΦᵀΦ)⁻¹, through the SVD of the column-scaled design
    vs = vt.T / sv
    theta_cov = sigma2 * (vs @ vs.T) / np.outer(col, col)
    f2m = f2_ref
    try:
        offset, matrix = quadric_to_calibration(theta, scale, f2m)
    except np.linalg.LinAlgError:
        raise CalibrationRefused(f"{name}: the fitted quadric is not an ellipsoid; the data are not "
                                 f"one probe rotating in a steady field") from None
    o_se, m_se = _propagate(theta, theta_cov, scale, f2m)
    corr = (raw - offset) @ matrix.T
    rms = float(np.sqrt(np.mean((np.linalg.norm(corr, axis=1) - f) ** 2)))
    params = {"offset_nT": {"value": offset.tolist(), "se": o_se.tolist(), "unit": "nT"}}
    if not known:
        params["total_nT_assumed"] = {"value": float(f[0]), "se": None, "unit": "nT",
                                      "note": "total field unknown: the scale of the matrix is a convention"}
    cal = ProbeCalibration(name, offset, matrix, o_se, m_se, params)
    if not cal.is_finite():
        raise CalibrationRefused(f"{name}: the fit produced non-finite parameters")
    return EllipsoidFit(cal, theta, theta_cov, scale, cond, rms, known)


def _propagate(theta: np.ndarray, cov: np.ndarray, scale: float, f2m: float) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors of offset and matrix by a numerical Jacobian of θ -> (o, M)."""

    def flat(t: np.ndarray) -> np.ndarray:
        o, m = quadric_to_calibration(t, scale, f2m)
        return np.concatenate([o, m.ravel()])

    base = flat(theta)
    npar = theta.shape[0]
    jac = np.empty((12, npar))
    sd = np.sqrt(np.maximum(np.diag(cov), 0))
    for i in range(npar):
        h = sd[i] * 1e-2 if sd[i] > 0 else abs(theta[i]) * 1e-8 + 1e-12
        t = theta.copy()
        t[i] += h
        try:
            jac[:, i] = (flat(t) - base) / h
        except np.linalg.LinAlgError:
            return np.full(3, np.nan), np.full((3, 3), np.nan)
    c = jac @ cov @ jac.T
    se = np.sqrt(np.maximum(np.diag(c), 0))
    return se[:3], se[3:].reshape(3, 3)
