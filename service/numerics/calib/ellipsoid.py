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

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused

from .excitation import PLANARITY_MIN, coverage_hint, excitation_problem, turn_cone  # noqa: F401 (re-exported)
from .model import ProbeCalibration, named, scalar_rms, triangular_params, triangular_params_many
from .order import (
    EXPANSIONS,
    FIXED,
    ORDERS,
    OrderChoice,
    block_normals,
    choose_order,
    expand,
    order_warnings,
    sub_chunks,
    undetermined,
)
from .quadric import (
    MAX_CONDITION,
    MIN_SAMPLES,
    as_total,
    finite_rows,
    forward_steps,
    gram_condition,
    normalise,
    quadric_design,
    quadric_matrix,
    quadric_to_calibration,
    quadric_to_calibration_many,
    se_from_steps,
    unit_volume_total,
)


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
    f, known = as_total(total_nT, n, raw)
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
                              lambda t, f2: quadric_to_calibration_many(t, scale, f2, center))
        order = choice.order if choice is not None else "full"
    t = EXPANSIONS[order]
    g, r = t.T @ g9 @ t, t.T @ r9
    if use_delta:
        g, r = _with_delta_column(g, r, t, design, edges, delta)
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
    sq = _residual_sum_sq(design, edges, t, theta, delta if use_delta else None)
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


def _with_delta_column(g: np.ndarray, r: np.ndarray, t: np.ndarray, design, edges: np.ndarray,
                       delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations (g, r) of the expanded order `t` with the δ column added: −δ against the geometric
    columns, itself, and the right side 1 (`design(a, b)`: the nine-term design of samples a..b)."""
    gd = t.T @ sum(design(c, d).T @ -delta[c:d] for a, b in zip(edges[:-1], edges[1:]) for c, d in sub_chunks(a, b))
    g = np.block([[g, gd[:, None]], [gd[None, :], np.array([[delta @ delta]])]])
    return g, np.append(r, -delta.sum())


def _residual_sum_sq(design, edges: np.ndarray, t: np.ndarray, theta: np.ndarray, delta: np.ndarray | None) -> float:
    """The sum of the squared residuals 1 − Φθ (+ δ θ_δ when `delta` is given), a part of the samples at a time.
    The residuals themselves (one product): from the normal equations, n − 2θᵀΦᵀ1 + θᵀΦᵀΦθ, a residual
    variance of (2 × noise / F)² would be lost in the rounding of n."""
    sq = 0.0
    for a, b in (part for ends in zip(edges[:-1], edges[1:]) for part in sub_chunks(*ends)):
        resid = 1.0 - design(a, b) @ (t @ theta[:t.shape[1]])
        if delta is not None:
            resid += delta[a:b] * theta[-1]
        sq += float(resid @ resid)
    return sq


def _nine(theta: np.ndarray, order: str, use_delta: bool) -> np.ndarray:
    """The nine geometric terms of a fit of any order (the δ coefficient dropped)."""
    geo = theta[:-1] if use_delta else theta
    return geo if order == "full" else EXPANSIONS[order] @ geo


def _propagate(theta: np.ndarray, cov: np.ndarray, scale: float, f2m: float, center: np.ndarray,
               base: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Standard errors of offset and matrix (NaN where the quadric stops being an ellipsoid near θ) and of the
    six physical parameters (None there, or where a step's matrix has no triangular parameters), by forward
    differences of θ -> (o, M) (quadric.jacobian_se's steps; `base`: (o, M) at θ), each step's calibration
    worked out once for both."""
    h, points = forward_steps(theta, cov)
    try:
        offsets, matrices = quadric_to_calibration_many(points[1:], scale, f2m, center)
    except (np.linalg.LinAlgError, ValueError):
        return np.full(3, np.nan), np.full((3, 3), np.nan), None
    offsets, matrices = np.concatenate([base[0][None], offsets]), np.concatenate([base[1][None], matrices])
    se = se_from_steps(np.concatenate([offsets, matrices.reshape(-1, 9)], axis=1), h, cov)
    try:
        angles, scales = triangular_params_many(matrices)
    except (np.linalg.LinAlgError, ValueError):
        return se[:3], se[3:].reshape(3, 3), None
    return se[:3], se[3:].reshape(3, 3), se_from_steps(np.concatenate([angles, scales], axis=1), h, cov)


def fit_ellipsoid(field_nT: np.ndarray, total_nT=None, *, name: str = "s1",
                  max_condition: float = MAX_CONDITION, noise_nT: float | None = None,
                  order: str = "auto", errors: str = "time", core: EllipsoidCore | None = None) -> EllipsoidFit:
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
    the field (excitation.cone_of), a badly conditioned design, or offsets whose standard errors
    are a tenth of the field; the message names the missing directions and the motion that would fill them.
    noise_nT: the noise of |b| if known; standard errors then use it (see `solve_quadric`).
    errors: "time" (samples in time order): where the residual differs between stretches of time beyond its
    noise (1/f noise, a misfit following the motion) the errors are at least those of leaving one stretch out
    (misfit.add_time_spread); "white": the white-noise errors alone, for a caller that adds its own (`fluxcal
    fit`'s coloured-noise and direction errors). theta_cov stays the white-noise one either way.
    core: ellipsoid_core of the same samples, reference and order already made (the determinacy gate's), not redone.
    """
    if order != "auto" and order not in ORDERS:
        raise ValueError(f"order: {order!r} is not allowed (allowed: auto, {', '.join(ORDERS)})")
    if errors not in ("time", "white"):
        raise ValueError(f"errors: {errors!r} is not allowed (allowed: time, white)")
    raw = np.asarray(field_nT, float)
    if core is None:
        core = ellipsoid_core(field_nT, total_nT, name=name, max_condition=max_condition, noise_nT=noise_nT,
                              order=order)
    problem = core.problem()
    if problem:
        raise CalibrationRefused(f"{name}: {problem}")
    fit, sol, missing, choice = core.fit, core.solution, core.missing, core.fit.choice
    bias = []
    if order == "auto" and sol.order != "full":
        from .misfit import add_order_bias  # a reduced order's offsets can differ from the full model's
        bias = add_order_bias(fit, lambda: _fit_result(solve_quadric(field_nT, total_nT, name=name, order="full",
                                                                     max_condition=max_condition, noise_nT=noise_nT),
                                                       raw, name)[0], name)
    fit.order = sol.order
    fit.choice = choice
    if errors == "time":
        from .misfit import add_time_spread  # (solve_quadric refused rows holding NaN)
        bias += add_time_spread(fit.calibration, fit.order, raw, total_nT, name)
    fit.warnings = order_warnings(fit.calibration, fit.order, missing, choice) + bias
    fit.calibration.model_order = sol.order
    fit.calibration.warnings = list(fit.warnings)
    return fit


@dataclass
class EllipsoidCore:
    """The ellipsoid fit of order `auto` (or as asked) before any refusal of what it leaves undetermined: the fit,
    its solution, what its standard errors leave undetermined, and the cone its directions lie in. What
    fit_ellipsoid refuses on, and the determinacy gate (determinacy.judge) reads its figures from."""

    fit: EllipsoidFit
    solution: QuadricSolution
    missing: list[str]
    cone: object = None                  # excitation.Cone of the fitted directions (None: fewer than three samples)
    raw: np.ndarray | None = None

    def problem(self) -> str:
        """Why the fit does not determine the offsets ("" where it does): one cone of directions, or offsets whose
        standard errors are a tenth of the field; with what would help."""
        if self.cone is not None and self.cone.problem:
            return self.cone.problem
        if any(m.startswith("offset") for m in self.missing):
            fit = self.fit
            se = ", ".join(f"{v:.3g}" for v in fit.calibration.offset_se_nT)
            return (f"the samples do not determine even the offsets (standard errors {se} nT against a field of "
                    f"{float(np.sqrt(fit.f2_ref)):.6g} nT); {coverage_hint(self.raw, fit.calibration.offset_nT)}")
        return ""


def ellipsoid_core(field_nT: np.ndarray, total_nT=None, *, name: str = "s1", max_condition: float = MAX_CONDITION,
                   noise_nT: float | None = None, order: str = "auto") -> EllipsoidCore:
    """The fit of fit_ellipsoid up to its refusals of what the samples leave undetermined (EllipsoidCore); the
    refusals of the solve itself (too few samples, one plane, conditioning, not an ellipsoid) are raised."""
    raw = np.asarray(field_nT, float)
    sol = solve_quadric(field_nT, total_nT, name=name, max_condition=max_condition, noise_nT=noise_nT, order=order)
    fit, missing = _fit_result(sol, raw, name)
    choice = sol.choice
    while order == "auto" and missing and sol.order != ORDERS[-1]:
        sol = solve_quadric(field_nT, total_nT, name=name, max_condition=max_condition, noise_nT=noise_nT,
                            order=ORDERS[ORDERS.index(sol.order) + 1])
        fit, missing = _fit_result(sol, raw, name)
    fit.choice, fit.order = choice, sol.order
    cone = turn_cone(raw, fit.calibration.offset_nT, fit.calibration.matrix, residual_rms=fit.residual_rms_nT,
                     field=float(np.sqrt(fit.f2_ref)))
    return EllipsoidCore(fit, sol, missing, cone, raw)


def assumed_total(raw_nT: np.ndarray) -> float | None:
    """The total field, nT, a fit with none given assumes for these (N, 3) samples (their rows with a NaN left out): the
    one at which the calibrated sphere has the raw ellipsoid's volume (unit_volume_total) of the judge's fit
    (ellipsoid_core, order auto), as `fit` reports it (total_nT_assumed); None where the samples fit no ellipsoid."""
    raw = np.asarray(raw_nT, float)
    raw = raw[np.isfinite(raw).all(axis=1)]
    try:
        return float(np.sqrt(ellipsoid_core(raw).fit.f2_ref))
    except (CalibrationRefused, np.linalg.LinAlgError, ValueError):
        return None


def _fit_result(sol: QuadricSolution, raw: np.ndarray, name: str) -> tuple[EllipsoidFit, list[str]]:
    """The calibration, its named parameters and standard errors, and what they leave undetermined."""
    theta, cov, scale, f2m, center = sol.theta, sol.theta_cov, sol.scale, sol.f2_ref, sol.center
    try:
        offset, matrix = quadric_to_calibration(theta, scale, f2m, center)
    except np.linalg.LinAlgError:
        raise CalibrationRefused(f"{name}: the fitted quadric is not an ellipsoid; the directions seen do not "
                                 f"determine one (or the field changed while the probe turned); "
                                 f"{coverage_hint(raw)}") from None
    phys = np.concatenate(triangular_params(matrix))
    o_se, m_se, phys_se = _propagate(theta, cov, scale, f2m, center, (offset, matrix))
    rms = scalar_rms(raw, offset, matrix, sol.total_nT)
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


