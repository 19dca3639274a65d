"""The algebra of the ellipsoid fit, shared by the batch fit, the online estimator and the error estimates: the
quadric's design and its solution turned into a calibration, the data and total field checked, Jacobian-propagated
standard errors, and the triangular factor of a positive definite matrix."""

from __future__ import annotations

from typing import Callable

import numpy as np

from fluxcal.drivers.errors import DataError

N_GEOMETRY = 9
N_PARAMS = 10
MIN_SAMPLES = 10
#: condition number of the column-scaled design above which a fit is refused. Measured: offset
#: standard errors ≈ 0.04 × condition × noise for 200 samples (a ±20° wobble about one axis: 5e3,
#: SE 170 nT at 1 nT noise; three full turns or 10 well spread attitudes: 2-5)
MAX_CONDITION = 1e3




def quadric_design(u: np.ndarray, delta: np.ndarray | None = None) -> np.ndarray:
    """Rows [x², y², z², 2xy, 2xz, 2yz, x, y, z] (and −δ when given) of scaled samples u (…, 3): (…, 9 or 10)."""
    x, y, z = u[..., 0], u[..., 1], u[..., 2]
    cols = [x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z]
    if delta is not None:
        cols.append(-delta)
    return np.stack(cols, axis=-1)


def algebraic_ellipsoid(raw: np.ndarray, total_nT: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A starting offset and symmetric matrix, never a refusal: the least-squares quadric uᵀQu + bᵀu = 1
    through the centred, scaled samples (`normalise`, `quadric_design`), o = −Q⁻¹b/2, M = √(Q / (1 + oᵀQo));
    where that is no ellipsoid (one turn, too few directions) the samples' mean and a unit shape. M is
    scaled so the median |M(r − o)| is total_nT (or the median |r − o|). The fit engine refines it."""
    center, scale = normalise(raw)
    sol, *_ = np.linalg.lstsq(quadric_design((raw - center) / scale), np.ones(raw.shape[0]), rcond=None)
    q = np.array([[sol[0], sol[3], sol[4]], [sol[3], sol[1], sol[5]], [sol[4], sol[5], sol[2]]])
    ok = bool(np.all(np.linalg.eigvalsh(q) > 0))
    if ok:
        o = -0.5 * np.linalg.solve(q, sol[6:9])
        q = q / (1.0 + o @ q @ o)
        w, v = np.linalg.eigh(q)
        ok = bool(np.all(w > 0))
    if ok:
        m = (v * np.sqrt(w)) @ v.T
    else:
        o, m = np.zeros(3), np.eye(3)
    offset = center + scale * o
    mags = np.linalg.norm((raw - offset) @ m.T, axis=1)
    target = total_nT if total_nT is not None else float(np.median(np.linalg.norm(raw - offset, axis=1)))
    return offset, m * (target / float(np.median(mags)))


def normalise(raw: np.ndarray) -> tuple[np.ndarray, float]:
    """(c, s): the samples' mean and their median distance from it, so that u = (r − c) / s is of order
    one whatever the origin and unit of r (the fit's answer then moves with r and nothing else)."""
    center = raw.mean(axis=0)                              # distances a chunk at a time: no (N, 3) temporary
    d = np.concatenate([np.linalg.norm(raw[a:a + 65536] - center, axis=1) for a in range(0, raw.shape[0], 65536)])
    return center, float(np.median(d)) or 1.0


def quadric_to_calibration(theta: np.ndarray, scale: float, f2_ref: float,
                           center: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(offset_nT, upper-triangular matrix) from the fitted coefficients (nine or ten) of the quadric
    in u = (r − center) / scale (center 0 when not given).

    Raises numpy.linalg.LinAlgError if the quadric is not an ellipsoid."""
    a = np.array([[theta[0], theta[3], theta[4]],
                  [theta[3], theta[1], theta[5]],
                  [theta[4], theta[5], theta[2]]])
    o_u = -0.5 * np.linalg.solve(a, theta[6:9])
    # (u − o)ᵀ A' (u − o) = 1 + oᵀ A' o at F = F₀: rescale so the right side is F₀² / s². An origin
    # outside the ellipsoid makes both A' and 1 + oᵀA'o negative: k A' is the same quadric either way
    k = (f2_ref / scale ** 2) / (1.0 + o_u @ a @ o_u)
    if not np.isfinite(k) or k == 0:
        raise np.linalg.LinAlgError("not an ellipsoid")
    lower = np.linalg.cholesky(a * k)       # raises LinAlgError unless positive definite
    offset = o_u * scale if center is None else np.asarray(center, float) + o_u * scale
    return offset, lower.T


def quadric_to_calibration_many(theta: np.ndarray, scale: float, f2_ref: float,
                                center: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """quadric_to_calibration of M coefficient vectors (M, k) at once: offsets (M, 3), matrices (M, 3, 3).
    Raises numpy.linalg.LinAlgError if any of them is not an ellipsoid."""
    t = np.asarray(theta, float)
    a = t[:, [0, 3, 4, 3, 1, 5, 4, 5, 2]].reshape(-1, 3, 3)
    o_u = -0.5 * np.linalg.solve(a, t[:, 6:9, None])[..., 0]
    k = (f2_ref / scale ** 2) / (1.0 + np.einsum("mi,mij,mj->m", o_u, a, o_u))
    if not np.all(np.isfinite(k)) or np.any(k == 0):
        raise np.linalg.LinAlgError("not an ellipsoid")
    lower = np.linalg.cholesky(a * k[:, None, None])
    offset = o_u * scale if center is None else np.asarray(center, float) + o_u * scale
    return offset, lower.transpose(0, 2, 1)


def unit_volume_total(theta: np.ndarray, scale: float, center: np.ndarray | None = None) -> float:
    """The total field, nT, that gives the fitted quadric a matrix of determinant 1: the calibrated sphere
    has the volume of the raw ellipsoid. The convention when the field is unknown; it depends on the
    ellipsoid alone, not on where the samples lie on it (a mean magnitude would) nor on the origin."""
    return float(np.linalg.det(quadric_to_calibration(theta, scale, 1.0, center)[1]) ** (-1.0 / 3.0))


def quadric_matrix(theta: np.ndarray, scale: float, f2_ref: float,
                   center: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """(Q, o in nT, κ in nT²) of the fitted quadric: |M(r − o)|² = F₀² with Q = MᵀM (dimensionless),
    i.e. in d = r − c: dᵀQd − 2(o − c)ᵀQd + (o − c)ᵀQ(o − c) = F₀², which is the fitted (right side 1)
    form times κ = F₀² − (o − c)ᵀQ(o − c).

    Raises numpy.linalg.LinAlgError if the quadric is not an ellipsoid."""
    offset, m = quadric_to_calibration(theta, scale, f2_ref, center)
    q = m.T @ m
    oc = offset if center is None else offset - np.asarray(center, float)
    return q, offset, float(f2_ref - oc @ q @ oc)


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


def as_total(total_nT, n: int, raw: np.ndarray) -> tuple[np.ndarray, bool]:
    if total_nT is None:
        return np.full(n, float(np.mean(np.linalg.norm(raw, axis=1)))), False
    t = np.asarray(total_nT, dtype=float)
    if t.ndim == 0:
        t = np.full(n, float(t))
    if t.shape != (n,):
        raise DataError(f"total_nT: expected a number or {n} values, got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t) | (t <= 0))
    if bad.size:
        raise DataError(f"total_nT: rows {', '.join(map(str, bad[:10].tolist()))} are not a positive finite "
                        f"field; remove them before fitting")
    return t, True


def gram_condition(gram: np.ndarray) -> float:
    """Condition number of a design after column scaling, from its normal matrix ΦᵀΦ (inf when a column
    is empty or the rank short): the same number as an SVD of the design, to ~1e-12 relative below the
    refusal limit (the squared condition stays far from double precision), at a fraction of the cost."""
    norms = np.sqrt(np.diag(gram))
    if np.any(norms == 0):
        return float("inf")
    ev = np.linalg.eigvalsh(gram / np.outer(norms, norms))
    return float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")


def jacobian_se_many(func: Callable[[np.ndarray], np.ndarray], theta: np.ndarray,
                     cov: np.ndarray) -> np.ndarray | None:
    """jacobian_se for a func that maps many θ (M, k) to their values (M, n) in one call: θ and its k
    forward steps evaluated together (None if func fails at any of them)."""
    h, points = forward_steps(theta, cov)
    try:
        vals = np.asarray(func(points), float)
    except (np.linalg.LinAlgError, ValueError):
        return None
    return se_from_steps(vals, h, cov)


def forward_steps(theta: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(h, points) of the forward-difference Jacobian: steps of 1 % of each θ's own standard error, and θ
    (row 0) with its k forward steps (rows 1..k)."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0))
    h = np.where(sd > 0, sd * 1e-2, np.abs(theta) * 1e-8 + 1e-12)
    return h, np.vstack([theta, theta + np.diag(h)])


def se_from_steps(vals: np.ndarray, h: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Standard errors of a function from its values (k + 1, n) at `forward_steps`' points."""
    jac = ((vals[1:] - vals[0]) / h[:, None]).T
    c = jac @ cov @ jac.T
    return np.sqrt(np.maximum(np.diag(c), 0))


def jacobian_se(func: Callable[[np.ndarray], np.ndarray], theta: np.ndarray,
                cov: np.ndarray) -> np.ndarray | None:
    """Standard errors of func(θ) by a forward-difference Jacobian, steps of 1 % of each θ's own
    standard error (None if func fails near θ, e.g. the quadric stops being an ellipsoid; a failure at θ
    itself raises): jacobian_se_many with func taken one θ at a time."""
    base = np.asarray(func(theta), float)
    return jacobian_se_many(lambda pts: np.stack([base] + [np.asarray(func(t), float) for t in pts[1:]]),
                            theta, cov)



def triangular_factor(q: np.ndarray, pattern: str = "upper") -> np.ndarray:
    """A factor A of a positive definite Q (AᵀA = Q) with its rotation fixed by a zero pattern.

    "upper": upper-triangular, positive diagonal ([FastRotation]'s triangular model; what `fit_ellipsoid` gives).
    "000":   [[a11, a12, 0], [0, a22, 0], [a31, a32, a33]] of [TwoFluxgate] eq. 8:
             a33 = √Q33, a32 = Q23/a33, a31 = Q13/a33, a11 = √(Q11 − a31²),
             a12 = (Q12 − a31 a32)/a11 (the paper prints a31 on the left), a22 = √(Q22 − a12² − a32²).
    Raises numpy.linalg.LinAlgError unless Q is positive definite.
    """
    q = np.asarray(q, float)
    if pattern == "upper":
        return np.linalg.cholesky(q).T
    if pattern != "000":
        raise ValueError(f"pattern: {pattern!r} is not allowed (allowed: 'upper', '000')")
    np.linalg.cholesky(q)            # positive definite, or LinAlgError
    a33 = np.sqrt(q[2, 2])
    a32 = q[1, 2] / a33
    a31 = q[0, 2] / a33
    a11 = np.sqrt(q[0, 0] - a31 ** 2)
    a12 = (q[0, 1] - a31 * a32) / a11
    a22 = np.sqrt(q[1, 1] - a12 ** 2 - a32 ** 2)
    return np.array([[a11, a12, 0.0], [0.0, a22, 0.0], [a31, a32, a33]])
