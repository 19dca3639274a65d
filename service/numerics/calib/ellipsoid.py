"""Linear least-squares ellipsoid fit ([TwoFluxgate] eq. 5-9, [TwoStep] eq. 5-14).

A probe with offset o and matrix M sees raw samples r on the quadric

    (r − o)ᵀ Q (r − o) = F²,   Q = Mᵀ M.

In centred, scaled coordinates u = (r − c) / s (c the samples' mean, s their median distance from
it, so every column is of order one) this is linear in nine unknowns,

    uᵀ A' u + b'ᵀ u − γ δ = 1,   δ = (F² − F₀²) / s²,

with A' = Q s² / κ, b' = −2 A' (o − c) / s, κ = F₀² − (o − c)ᵀ Q (o − c). Centring makes the fit
independent of where the origin is: a sensor whose hard-iron offset is several times the field puts
the origin outside its ellipsoid, where the uncentred form's constant changes sign (κ < 0) and its
conditioning collapses. Either sign of the fitted quadric is accepted (A' and κ flip together). The tenth column (δ) enters only when the
reference total field F varies enough to carry information. Fixing the right side to 1 removes the
exact null direction of the ten-term form with a constant right side ([TwoFluxgate] eq. 6 keeps nine terms
and the right side F², dropping oᵀQo; [FastRotation] eq. 15-16 keeps the constant column and the right side
F², and then V = (0, …, 0, F²) fits any data exactly). o = −A'⁻¹ b' s / 2 and Q follows from the
known F₀: κ (1 + uₒᵀA'uₒ) = F₀², uₒ = (o − c)/s.

Matrix convention: M is the upper-triangular Cholesky factor of Q ([FastRotation]'s triangular model, eq. 12):
only the rotation ambiguity of Q = MᵀM is fixed, by putting the corrected z axis along the
sensor's z winding and the corrected y axis in its y-z plane; the alignment step rotates each probe
into a common frame. `triangular_factor(q, "000")` gives [TwoFluxgate]'s own factor (eq. 8) instead.

Total field F: the reference per sample (`ref_total`), a configured constant, or — when unknown —
the field that gives M unit determinant (unit_volume_total). Then the scale of M is a convention, not a measurement (a fluxgate
ellipsoid alone cannot tell a 1 % larger field from 1 % larger sensitivities), and the result says
so in its params ("total_nT_assumed").

Refusals (CalibrationRefused) name what is missing and the motion that would fill it: fewer than
ten samples, all samples in one plane (a single-axis turn: the ten-term design has rank 5 of 10
there — the samples lie on one conic in one plane; at most 6 for any planar set — and a plane
section does not fix an ellipsoid), a badly conditioned design, or a quadric that
is not an ellipsoid. NaN/inf rows are a DataError naming the rows. No parameter is ever NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from drivers.errors import CalibrationRefused, DataError

from .excitation import (PLANARITY_MIN, band_problem, coverage_hint, excitation_problem,  # noqa: F401 (re-exported)
                         turn_problem)
from .model import ProbeCalibration, named, scalar_rms, triangular_params
from .order import (EXPANSIONS, FIXED, ORDERS, OrderChoice, block_normals, choose_order, expand, order_warnings,
                    sub_chunks, undetermined)

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


@dataclass
class EllipsoidFit:
    """Result of a batch ellipsoid fit, with what a user needs to trust it."""

    calibration: ProbeCalibration
    theta: np.ndarray            # fitted coefficients of the scaled quadric (nine, or ten with δ)
    theta_cov: np.ndarray        # their covariance, σ² (ΦᵀΦ)⁻¹
    scale: float                 # s, nT: u = (r − center) / s
    condition: float             # of the column-scaled design
    residual_rms_nT: float       # RMS of |M(r − o)| − F over the samples
    total_known: bool            # False: F was assumed (det M = 1), M's scale is a convention
    f2_ref: float = float("nan")     # F₀², nT²
    n_samples: int = 0
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))   # c, nT: u = (r − c) / s
    order: str = "full"          # the model order fitted (order.ORDERS)
    choice: OrderChoice | None = None    # the held-out comparison that chose it, if one did
    warnings: list[str] = field(default_factory=list)   # terms held fixed, parameters not determined


@dataclass(frozen=True)
class QuadricSolution:
    """The linear least-squares solution shared by `fit_ellipsoid` and `tmi.fit_tmi`."""

    theta: np.ndarray
    theta_cov: np.ndarray
    scale: float
    f2_ref: float
    condition: float
    total_nT: np.ndarray         # F per sample, nT
    total_known: bool
    center: np.ndarray           # c, nT: the samples' mean; u = (r − c) / scale
    order: str = "full"          # model order (order.ORDERS): the terms fitted; θ is always the nine (ten)
    choice: OrderChoice | None = None    # how the order was chosen, when it was


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


def _as_total(total_nT, n: int, raw: np.ndarray) -> tuple[np.ndarray, bool]:
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


# --- the shared least-squares solve ----------------------------------------------------------------


def solve_quadric(field_nT: np.ndarray, total_nT=None, *, name: str = "s1",
                  max_condition: float = MAX_CONDITION, min_samples: int = MIN_SAMPLES,
                  noise_nT: float | None = None, order: str = "full") -> QuadricSolution:
    """Least squares of uᵀA'u + b'ᵀu (− γδ) = 1 over (N, 3) raw samples; refuses what it cannot fix.

    order: "full" (nine terms), a reduced order of `order.ORDERS`, or "auto" (the held-out blocks
    choose, order.choose_order; "full" when there are too few samples to compare).
    noise_nT: the noise of |b| if known (e.g. from a recording at rest); the covariance then uses it
    instead of the residual variance, which is a poor estimate with few samples beyond the unknowns
    (ten samples leave one degree of freedom)."""
    raw = finite_rows(field_nT, f"{name}: field_nT")
    n = raw.shape[0]
    if n < min_samples:
        raise CalibrationRefused(f"{name}: {n} samples; the fit needs at least {min_samples}, spread over "
                                 f"turns about at least two axes")
    problem = excitation_problem(raw)
    if problem:
        raise CalibrationRefused(f"{name}: {problem}")
    f, known = _as_total(total_nT, n, raw)
    center, scale = normalise(raw)
    f2_ref = float(np.mean(f ** 2))
    delta = (f ** 2 - f2_ref) / scale ** 2
    # the δ column only when F varies by more than ~1 nT rms: otherwise it carries no information
    use_delta = known and float(np.std(f)) > 1.0
    def design(a: int, b: int) -> np.ndarray:
        return quadric_design((raw[a:b] - center) / scale)

    # one pass over the samples: the normal equations per time block (their sum is the whole design's);
    # everything after works on 9 x 9 matrices, and no more than one block's design is held at a time
    normals = block_normals(design, n)
    edges = normals[0]
    g9, r9 = sum(normals[1]), sum(normals[2])
    cond9 = gram_condition(g9)
    if not np.isfinite(cond9) or cond9 > max_condition:
        raise CalibrationRefused(f"{name}: the samples do not determine an ellipsoid (condition number "
                                 f"{cond9:.3g} > {max_condition:.3g}); {coverage_hint(raw)}")
    choice = None
    if order == "auto":
        choice = choose_order(normals, raw, f, known,
                              lambda t, f2: quadric_to_calibration(t, scale, f2, center))
        order = choice.order if choice is not None else "full"
    t = EXPANSIONS[order]
    g, r = t.T @ g9 @ t, t.T @ r9
    if use_delta:
        # the δ column: −δ against the geometric columns, itself, and the right side 1
        gd = t.T @ sum(design(c, d).T @ -delta[c:d] for a, b in zip(edges[:-1], edges[1:]) for c, d in sub_chunks(a, b))
        g = np.block([[g, gd[:, None]], [gd[None, :], np.array([[delta @ delta]])]])
        r = np.append(r, -delta.sum())
    # θ = (ΦᵀΦ)⁻¹ Φᵀ1 through the eigenvectors of the column-scaled normal matrix, never an explicit inverse
    col = np.sqrt(np.diag(g))
    lam, vec = np.linalg.eigh(g / np.outer(col, col))
    theta = (vec @ ((vec.T @ (r / col)) / lam)) / col
    if not known:
        # θ does not depend on F, only the scale of M does: the convention for an unknown field
        try:
            f = np.full(n, unit_volume_total(_nine(theta, order, use_delta), scale, center))
            f2_ref = float(f[0] ** 2)
        except np.linalg.LinAlgError:
            pass                     # not an ellipsoid: the caller refuses it
    # the residuals themselves (one product): from the normal equations, n − 2θᵀΦᵀ1 + θᵀΦᵀΦθ, a residual
    # variance of (2 × noise / F)² would be lost in the rounding of n
    sq = 0.0
    for a, b in (part for ends in zip(edges[:-1], edges[1:]) for part in sub_chunks(*ends)):
        resid = 1.0 - design(a, b) @ (t @ theta[:t.shape[1]])
        if use_delta:
            resid += delta[a:b] * theta[-1]
        sq += float(resid @ resid)
    dof = max(n - g.shape[0], 1)
    sigma2 = sq / dof
    if noise_nT is not None:
        # |M(r − o)| = F + ε makes the equation's residual 2 F ε / κ, κ = F₀² − oᵀQo
        try:
            _, _, kappa = quadric_matrix(_nine(theta, order, use_delta), scale, f2_ref, center)
            sigma2 = float(np.mean((2.0 * f * float(noise_nT) / kappa) ** 2))
        except np.linalg.LinAlgError:
            pass                     # not an ellipsoid: the caller refuses it
    # cov(θ) = σ² (ΦᵀΦ)⁻¹, through the same eigenvectors
    vs = vec / np.sqrt(lam)
    theta_cov = sigma2 * (vs @ vs.T) / np.outer(col, col)
    if order != "full":
        theta, theta_cov = expand(theta, theta_cov, order, extra=int(use_delta))
    return QuadricSolution(theta, theta_cov, scale, f2_ref, cond9, f, known, center, order, choice)


def _nine(theta: np.ndarray, order: str, use_delta: bool) -> np.ndarray:
    """The nine geometric terms of a fit of any order (the δ coefficient dropped)."""
    geo = theta[:-1] if use_delta else theta
    return geo if order == "full" else EXPANSIONS[order] @ geo


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
    sd = np.sqrt(np.maximum(np.diag(cov), 0))
    h = np.where(sd > 0, sd * 1e-2, np.abs(theta) * 1e-8 + 1e-12)
    points = np.vstack([theta, theta + np.diag(h)])
    try:
        vals = np.asarray(func(points), float)
    except (np.linalg.LinAlgError, ValueError):
        return None
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


def _propagate(theta: np.ndarray, cov: np.ndarray, scale: float, f2m: float,
               center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors of offset and matrix by a numerical Jacobian of θ -> (o, M)."""

    def flat(t: np.ndarray) -> np.ndarray:
        o, m = quadric_to_calibration(t, scale, f2m, center)
        return np.concatenate([o, m.ravel()])

    se = jacobian_se(flat, theta, cov)
    if se is None:
        return np.full(3, np.nan), np.full((3, 3), np.nan)
    return se[:3], se[3:].reshape(3, 3)


def fit_ellipsoid(field_nT: np.ndarray, total_nT=None, *, name: str = "s1",
                  max_condition: float = MAX_CONDITION, noise_nT: float | None = None,
                  order: str = "auto", errors: str = "time") -> EllipsoidFit:
    """Fit offset and upper-triangular matrix to (N, 3) raw samples of one probe.

    total_nT: the reference total field per sample (N,), a constant, or None (unknown: the mean raw
    field of unit_volume_total is assumed and the scale of the matrix is a convention).
    order: "auto" fits only what the samples determine (order.py: the held-out blocks choose, then
    an order whose offsets or scales the standard errors do not determine gives way to the next
    smaller one); "full", "axes" or "sphere" fit that order. What an order holds fixed, and any
    parameter whose standard error exceeds its size, is said in `warnings`.
    Refuses (CalibrationRefused) data that cannot determine even the offsets: too few samples, all in
    one plane (a single-axis turn), field directions within a narrow cone about one axis (a turn with
    some wobble) where the model's misfit would move the offset along the axis by more than a percent of
    the field (excitation.band_problem), a badly conditioned design, or offsets whose standard errors
    are a tenth of the field; the message names the missing directions and the motion that would fill them.
    noise_nT: the noise of |b| if known; standard errors then use it (see `solve_quadric`).
    errors: "time" (samples in time order): where the residual differs between stretches of time beyond its
    noise (1/f noise, a misfit following the motion) the errors are at least those of leaving one stretch out
    (misfit.add_time_spread); "white": the white-noise errors alone, for a caller that adds its own (`fluxcal
    fit`'s coloured-noise and direction errors). theta_cov stays the white-noise one either way.
    """
    if order != "auto" and order not in ORDERS:
        raise ValueError(f"order: {order!r} is not allowed (allowed: auto, {', '.join(ORDERS)})")
    if errors not in ("time", "white"):
        raise ValueError(f"errors: {errors!r} is not allowed (allowed: time, white)")
    raw = np.asarray(field_nT, float)
    sol = solve_quadric(field_nT, total_nT, name=name, max_condition=max_condition, noise_nT=noise_nT, order=order)
    fit, missing = _fit_result(sol, raw, name)
    choice = sol.choice
    while order == "auto" and missing and sol.order != ORDERS[-1]:
        sol = solve_quadric(field_nT, total_nT, name=name, max_condition=max_condition, noise_nT=noise_nT,
                            order=ORDERS[ORDERS.index(sol.order) + 1])
        fit, missing = _fit_result(sol, raw, name)
    problem = turn_problem(raw, fit.calibration.offset_nT, fit.calibration.matrix,
                           residual_rms=fit.residual_rms_nT, field=float(np.sqrt(fit.f2_ref)))
    if problem:
        raise CalibrationRefused(f"{name}: {problem}")
    if any(m.startswith("offset") for m in missing):
        se = ", ".join(f"{v:.3g}" for v in fit.calibration.offset_se_nT)
        raise CalibrationRefused(f"{name}: the samples do not determine even the offsets (standard errors {se} nT "
                                 f"against a field of {float(np.sqrt(fit.f2_ref)):.6g} nT); "
                                 f"{coverage_hint(raw, fit.calibration.offset_nT)}")
    bias = []
    if order == "auto" and sol.order != "full":
        from .misfit import add_order_bias        # a reduced order's offsets can differ from the full model's
        bias = add_order_bias(fit, lambda: _fit_result(solve_quadric(field_nT, total_nT, name=name, order="full",
                                                                     max_condition=max_condition, noise_nT=noise_nT),
                                                       raw, name)[0], name)
    fit.order = sol.order
    fit.choice = choice
    if errors == "time":
        from .misfit import add_time_spread      # (solve_quadric refused rows holding NaN)
        bias += add_time_spread(fit.calibration, fit.order, raw, total_nT, name)
    fit.warnings = order_warnings(fit.calibration, fit.order, missing, choice) + bias
    fit.calibration.model_order = sol.order
    fit.calibration.warnings = list(fit.warnings)
    return fit


def _fit_result(sol: QuadricSolution, raw: np.ndarray, name: str) -> tuple[EllipsoidFit, list[str]]:
    """The calibration, its named parameters and standard errors, and what they leave undetermined."""
    theta, cov, scale, f2m, center = sol.theta, sol.theta_cov, sol.scale, sol.f2_ref, sol.center
    try:
        offset, matrix = quadric_to_calibration(theta, scale, f2m, center)
    except np.linalg.LinAlgError:
        raise CalibrationRefused(f"{name}: the fitted quadric is not an ellipsoid; the directions seen do not "
                                 f"determine one (or the field changed while the probe turned); "
                                 f"{coverage_hint(raw)}") from None
    o_se, m_se = _propagate(theta, cov, scale, f2m, center)
    rms = scalar_rms(raw, offset, matrix, sol.total_nT)

    def physical(t: np.ndarray) -> np.ndarray:
        angles, c = triangular_params(quadric_to_calibration(t, scale, f2m, center)[1])
        return np.concatenate([angles, c])

    phys = physical(theta)
    phys_se = jacobian_se(physical, theta, cov)
    phys_se = np.full(6, np.nan) if phys_se is None else phys_se
    params = {"offset_nT": named(offset, o_se, "nT"),
              "nonorth_deg": named(phys[:3], phys_se[:3], "deg", names=["phi", "theta", "psi"],
                                   note="001 eq. 11: x axis tilt out of the y-z plane (phi), in it (theta), "
                                        "y axis tilt towards z (psi)"),
              "scale": named(phys[3:], phys_se[3:], "", names=["c_x", "c_y", "c_z"]),
              "residual_rms_nT": named(rms, None, "nT"),
              "condition": named(sol.condition, None, ""),
              "samples": named(raw.shape[0], None, "")}
    if "nonorth_deg" in FIXED[sol.order]:
        params["nonorth_deg"].update(se=None, note="not determined by these samples: fixed at 0")
    if not sol.total_known:
        params["total_nT_assumed"] = named(float(sol.total_nT[0]), None, "nT",
                                           note="total field unknown: the field that gives the matrix determinant 1 "
                                                "(the calibrated sphere has the raw ellipsoid's volume) was assumed, "
                                                "so the scale of the matrix (and the scale factors) is a convention")
        params["scale"]["note"] = "relative to the assumed total field"
    cal = ProbeCalibration(name, offset, matrix, o_se, m_se, params)
    if not cal.is_finite():
        raise CalibrationRefused(f"{name}: the fit produced non-finite parameters")
    fit = EllipsoidFit(cal, theta, cov, scale, sol.condition, rms, sol.total_known, f2m, raw.shape[0], center)
    return fit, undetermined(offset, o_se, phys[3:], phys_se[3:], float(np.sqrt(f2m)))


# --- the factor conventions ------------------------------------------------------------------------


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
