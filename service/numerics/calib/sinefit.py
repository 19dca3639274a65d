"""Non-orthogonality of a three-axis probe from one turntable rotation by sine fits ([SineFit]).

Model ([SineFit] eq. 1): the probe's axes in the orthogonal frame O_XYZ (X along the x winding, Y in the
x-y winding plane, Z normal to it) give the raw output

    x = k_x B_X + o_x
    y = k_y (sinα B_X + cosα B_Y) + o_y
    z = k_z (cosβ sinγ B_X + sinβ sinγ B_Y + cosγ B_Z) + o_z

α: the y winding's tilt from Y in the X-Y plane; β: the azimuth of the z winding's projection on
the X-Y plane from X; γ: the z winding's tilt from Z. [SineFit] has k = 1 and o = 0; scales and offsets
are added here where one turn determines them.

A turn by θ about Z (the table's axis; right-handed about +z) in a field with a component
B_xy = B cos I in the turn plane and B_Z = B sin I along the axis (I: inclination of the field to
the plane) makes ([SineFit] eq. 3, 5)

    x = A_x sin(θ + θ_x0) + C_x,   A_x = k_x B_xy
    y = A_y sin(θ + θ_y0) + C_y,   A_y = k_y B_xy,   θ_y0 = θ_x0 + 90° − α
    z = A_z sin(θ + θ_z0) + C_z,   A_z = k_z B_xy sinγ,   θ_z0 = θ_x0 + β,   C_z = o_z + k_z B_Z cosγ

so each axis is a linear least-squares fit in [sin θ, cos θ, 1] (a sinθ + b cosθ + c: A = √(a²+b²),
θ0 = atan2(b, a)) and

    α = 90° − (θ_y0 − θ_x0)      (eq. 4)
    β = θ_z0 − θ_x0              (eq. 6)
    sinγ = A_z / A_x             (eq. 9 in least-squares form, with k_z = k_x)
    φ = arccos(cosβ sinγ)        (eq. 11: angle X-Z)
    η = arccos(sin(α + β) sinγ)  (eq. 12: angle Y-Z; cos(90° − α − β) = sin(α + β))

The correction is eq. 2 (B = S⁻¹ (raw − o) / k), computed as eq. 7 and 10:
    B_X = x',  B_Y = (y' − B_X sinα) / cosα,  B_Z = (z' − B_X cosβ sinγ − B_Y sinβ sinγ) / cosγ.

What one turn cannot separate, and what is assumed (each reported in params["assumed"]):
- k_z and sinγ enter z only as their product: k_z = k_x is assumed ([SineFit] has k = 1).
- o_z and the axial field: C_z = o_z + k_z B_Z cosγ. With the inclination known, B_Z = B_xy tan I
  fixes o_z; without it o_z = 0 is assumed ([SineFit]) and the inclination is estimated from C_z.
- the absolute scale k_x needs the total field B (and I, or o_z = 0); without B, k_x = 1 ([SineFit]):
  the output is in the x winding's units.
No total-field reference is needed ([SineFit]'s point); α and β need nothing but the phases.

When the table angle is not recorded, a constant rate is assumed and estimated from the data (one
frequency common to the three axes, refined on the total residual); the phase differences do not
depend on where θ = 0 is. If a given angle runs the other way (the field turning from +x towards
+y in the probe frame as θ grows), it is reversed and params["angle_reversed"] says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused

from .model import ProbeCalibration, named
from .quadric import finite_rows, jacobian_se

#: largest gap in table angle (mod 360°) a fit accepts: beyond it the sine and the constant blur
MAX_ANGLE_GAP_DEG = 120.0
MIN_SAMPLES = 8


@dataclass
class SineFit:
    """Result of `fit_sine_nonorthogonality`; angles in degrees with standard errors."""

    calibration: ProbeCalibration
    alpha_deg: float
    beta_deg: float
    gamma_deg: float
    phi_deg: float                  # angle between the x and z windings (eq. 11)
    eta_deg: float                  # angle between the y and z windings (eq. 12)
    se_deg: dict[str, float]        # standard errors of alpha, beta, gamma, phi, eta
    amplitude_nT: np.ndarray        # (3,) A per axis
    phase_deg: np.ndarray           # (3,) θ0 per axis
    mean_nT: np.ndarray             # (3,) C per axis
    axis_rms_nT: np.ndarray         # (3,) residual of each axis's sine fit (the noise)
    residual_rms_nT: float          # eq. 13: RMS of |corrected| − B (B given, else the mean |corrected|)
    inclination_deg: float          # given, or estimated from C_z with o_z = 0
    rate_rad_s: float | None        # estimated table rate when only time was given
    angle_reversed: bool
    assumed: list[str] = field(default_factory=list)


def _wrap_deg(a: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def _sine_design(theta_rad: np.ndarray) -> np.ndarray:
    return np.column_stack([np.sin(theta_rad), np.cos(theta_rad), np.ones_like(theta_rad)])


def _sine_lstsq(theta_rad: np.ndarray, field_nT: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients (3 axes × [a, b, c]), their covariances (3, 3, 3) and residual RMS per axis."""
    x = _sine_design(theta_rad)
    coef, *_ = np.linalg.lstsq(x, field_nT, rcond=None)          # (3 terms, 3 axes)
    resid = field_nT - x @ coef
    dof = max(field_nT.shape[0] - 3, 1)
    s2 = np.sum(resid ** 2, axis=0) / dof
    # cov = σ² (XᵀX)⁻¹ through the SVD of X (no explicit inverse of the normal matrix)
    _, sv, vt = np.linalg.svd(x, full_matrices=False)
    vs = vt.T / sv
    xtx_inv = vs @ vs.T
    cov = s2[:, None, None] * xtx_inv[None]
    return coef.T, cov, np.sqrt(np.mean(resid ** 2, axis=0))


def _largest_gap_deg(theta_rad: np.ndarray) -> float:
    a = np.sort(np.mod(np.degrees(theta_rad), 360.0))
    gaps = np.diff(np.concatenate([a, [a[0] + 360.0]]))
    return float(gaps.max())


def _trajectory_angle(field_nT: np.ndarray) -> np.ndarray:
    """ψ = atan2(x − x̄, y − ȳ) unwrapped: grows with θ in [SineFit]'s convention (x = sin, y = cos)."""
    c = 0.5 * (field_nT.min(axis=0) + field_nT.max(axis=0))
    return np.unwrap(np.arctan2(field_nT[:, 0] - c[0], field_nT[:, 1] - c[1]))


def estimate_rate(t_s: np.ndarray, field_nT: np.ndarray) -> float:
    """Table rate (rad/s, constant) common to the three axes: a first guess from the slope of the x-y
    trajectory angle, refined by minimising the summed residual of the three sine fits."""
    t = np.asarray(t_s, float)
    psi = _trajectory_angle(field_nT)
    tc = t - t.mean()
    w0 = float(tc @ (psi - psi.mean()) / (tc @ tc))

    def rss(w: float) -> float:
        x = _sine_design(w * t)
        coef, *_ = np.linalg.lstsq(x, field_nT, rcond=None)
        return float(np.sum((field_nT - x @ coef) ** 2))

    from scipy.optimize import minimize_scalar          # here, not at import (a command's start)

    # the first guess is biased by the skew of y (α) by at most a few percent
    res = minimize_scalar(rss, bounds=(0.9 * w0, 1.1 * w0) if w0 > 0 else (1.1 * w0, 0.9 * w0),
                          method="bounded", options={"xatol": abs(w0) * 1e-10})
    return float(res.x)


def _table_angle(theta_rad: np.ndarray | None, t_s: np.ndarray | None, raw: np.ndarray,
                 name: str) -> tuple[np.ndarray, float | None, bool]:
    """The table angle per sample (given, or estimated at a constant rate), turned to advance with the x-y
    trajectory: (θ in rad, the estimated rate or None, whether a given angle was reversed). Refuses a turn
    that leaves a gap larger than MAX_ANGLE_GAP_DEG."""
    n = raw.shape[0]
    rate = None
    if theta_rad is None:
        t = np.arange(n, dtype=float) if t_s is None else np.asarray(t_s, float)
        rate = estimate_rate(t, raw)
        theta = rate * (t - t[0])
    else:
        theta = np.asarray(theta_rad, float).reshape(-1)
        if theta.shape[0] != n:
            raise ValueError(f"theta_rad: expected {n} angles, got {theta.shape[0]}")
    reversed_ = False
    if theta_rad is not None:
        # the x-y trajectory must advance with θ ([SineFit] eq. 3: x ∝ sin, y ∝ cos); a table angle read the
        # other way round would turn α and β into −α and −β
        psi = _trajectory_angle(raw)
        if np.polyfit(theta, psi, 1)[0] < 0:
            theta, reversed_ = -theta, True
    gap = _largest_gap_deg(theta)
    if gap > MAX_ANGLE_GAP_DEG:
        raise CalibrationRefused(f"{name}: the table angles leave a gap of {gap:.0f}° (at most "
                                 f"{MAX_ANGLE_GAP_DEG:.0f}° allowed): turn the table through one full turn")
    return theta, rate, reversed_


def _assumptions(total_nT: float | None, inclination_deg: float | None) -> list[str]:
    """What one turn cannot separate and the fit therefore assumes, given what is known."""
    assumed = ["k_z = k_x (z scale and sinγ enter only as their product)"]
    if inclination_deg is None:
        assumed.append("o_z = 0 (the z offset and the axial field B_Z enter only as their sum)")
    if total_nT is None:
        assumed.append("k_x = 1 (no total field given: the output is in the x winding's units)")
    return assumed


def _sine_physics(q: np.ndarray, total_nT: float | None, inclination_deg: float | None) -> dict[str, np.ndarray]:
    """The angles, offset, scales, correction matrix and inclination from the nine sine coefficients
    q = [a_x, b_x, c_x, a_y, b_y, c_y, a_z, b_z, c_z] (eq. 4, 6, 9, 11, 12 and 2 / 7 / 10)."""
    c = q.reshape(3, 3)
    amp = np.hypot(c[:, 0], c[:, 1])                         # A = √(a² + b²)
    ph = np.degrees(np.arctan2(c[:, 1], c[:, 0]))            # a sinθ + b cosθ = A sin(θ + θ0)
    alpha = _wrap_deg(90.0 - (ph[1] - ph[0]))                # eq. 4
    beta = _wrap_deg(ph[2] - ph[0])                          # eq. 6
    sin_g = amp[2] / amp[0]                                  # eq. 9, least-squares form
    gamma = np.degrees(np.arcsin(np.clip(sin_g, -1.0, 1.0)))
    a_r, b_r, g_r = np.radians([alpha, beta, gamma])
    phi = np.degrees(np.arccos(np.cos(b_r) * np.sin(g_r)))            # eq. 11
    eta = np.degrees(np.arccos(np.sin(a_r + b_r) * np.sin(g_r)))      # eq. 12
    # C_z = o_z + k_x B_Z cosγ, in x-winding units: k_x B_Z = A_x tan I
    if inclination_deg is not None:
        incl = float(inclination_deg)
        kbz = amp[0] * np.tan(np.radians(incl))
        o_z = c[2, 2] - kbz * np.cos(g_r)
    else:
        o_z = 0.0
        kbz = c[2, 2] / np.cos(g_r)
        incl = np.degrees(np.arctan2(kbz, amp[0]))
    if total_nT is None:
        k_x = 1.0
    elif inclination_deg is not None:
        k_x = amp[0] / (float(total_nT) * np.cos(np.radians(incl)))  # A_x = k_x B cos I
    else:
        k_x = np.hypot(amp[0], kbz) / float(total_nT)               # |(A_x, k_x B_Z)| = k_x B
    k_y = k_x * amp[1] / amp[0]
    offset = np.array([c[0, 2], c[1, 2], o_z])
    # eq. 2 / 7 / 10: M = (K S)⁻¹, lower-triangular
    sa, ca, sb, cb, sg, cg = np.sin(a_r), np.cos(a_r), np.sin(b_r), np.cos(b_r), np.sin(g_r), np.cos(g_r)
    s = np.array([[1.0, 0.0, 0.0], [sa, ca, 0.0], [cb * sg, sb * sg, cg]])
    m = np.linalg.solve(np.diag([k_x, k_y, k_x]) @ s, np.eye(3))
    return {"angles": np.array([alpha, beta, gamma, phi, eta]), "offset": offset,
            "scale": np.array([k_x, k_y, k_x]), "matrix": m, "incl": np.array([incl]),
            "amp": amp, "phase": ph}


#: the parts of `_sine_physics` whose standard errors are propagated, in this order
_SE_KEYS = ("angles", "offset", "scale", "matrix", "incl")


def _physics_with_se(p: np.ndarray, cov: np.ndarray, total_nT: float | None,
                     inclination_deg: float | None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """`_sine_physics` at the coefficients p and the standard errors of its `_SE_KEYS` parts, propagated from
    the coefficients' covariance cov (9, 9) through the Jacobian (NaN where it cannot be taken)."""
    def flat(q: np.ndarray) -> np.ndarray:
        d = _sine_physics(q, total_nT, inclination_deg)
        return np.concatenate([np.ravel(d[k]) for k in _SE_KEYS])

    est = _sine_physics(p, total_nT, inclination_deg)
    se = jacobian_se(flat, p, cov)
    if se is None:
        se = np.full(flat(p).size, np.nan)
    i = 0
    se_parts = {}
    for k in _SE_KEYS:
        size = np.size(est[k])
        se_parts[k] = se[i:i + size].reshape(np.shape(est[k]))
        i += size
    return est, se_parts


def _block_covariance(cov_axes: np.ndarray) -> np.ndarray:
    """The (9, 9) covariance of the nine coefficients from the three axes' (3, 3) ones (the axes independent)."""
    cov = np.zeros((9, 9))
    for k in range(3):
        cov[3 * k:3 * k + 3, 3 * k:3 * k + 3] = cov_axes[k]
    return cov


def _residual_rms(raw: np.ndarray, offset: np.ndarray, matrix: np.ndarray, total_nT: float | None) -> float:
    """Eq. 13: RMS of |corrected| − B (B given, else the mean |corrected|)."""
    corr = (raw - offset) @ matrix.T
    mag = np.linalg.norm(corr, axis=1)
    ref = float(total_nT) if total_nT is not None else float(np.mean(mag))
    return float(np.sqrt(np.mean((mag - ref) ** 2)))


_ANGLE_NAMES = ["alpha", "beta", "gamma", "phi", "eta"]


def _sine_params(est: dict, se_parts: dict, coef: np.ndarray, cov_axes: np.ndarray, axis_rms: np.ndarray,
                 resid: float, n: int, inclination_deg: float | None, assumed: list[str]) -> dict:
    """The calibration's params: the fitted quantities named with their units and standard errors."""
    angles, angles_se = est["angles"], se_parts["angles"]
    return {
        "nonorth_deg": named(angles[:3], angles_se[:3], "deg", names=_ANGLE_NAMES[:3],
                             note="003 eq. 1: y winding tilt in the x-y plane (alpha), azimuth (beta) and tilt "
                                  "from the normal (gamma) of the z winding"),
        "axis_angles_deg": named(angles[3:], angles_se[3:], "deg", names=["phi_xz", "eta_yz"],
                                 note="003 eq. 11-12: angles between the x and z, y and z windings"),
        "offset_nT": named(est["offset"], se_parts["offset"], "nT"),
        "scale": named(est["scale"], se_parts["scale"], "", names=["k_x", "k_y", "k_z"]),
        "inclination_deg": named(est["incl"][0], se_parts["incl"][0] if inclination_deg is None else 0.0, "deg",
                                 note="given" if inclination_deg is not None else "estimated with o_z = 0"),
        "sine_amplitude_nT": named(est["amp"], None, "nT"),
        "sine_phase_deg": named(est["phase"], None, "deg"),
        "sine_mean_nT": named(coef[:, 2], np.sqrt(cov_axes[:, 2, 2]), "nT"),
        "axis_rms_nT": named(axis_rms, None, "nT"),
        "residual_rms_nT": named(resid, None, "nT"),
        "samples": named(n, None, ""),
        "assumed": assumed,
    }


def fit_sine_nonorthogonality(theta_rad: np.ndarray | None, field_nT: np.ndarray, *,
                              t_s: np.ndarray | None = None, total_nT: float | None = None,
                              inclination_deg: float | None = None, name: str = "s1") -> SineFit:
    """[SineFit]: α, β, γ (and offsets, relative scale) from (N, 3) raw samples of one turn about the probe z.

    theta_rad: the table angle per sample (right-handed about the probe's +z); None: estimated at a
      constant rate from `t_s` (or from the sample index if `t_s` is None, i.e. uniform sampling).
    total_nT: the total field B, if known: fixes the absolute scale k_x.
    inclination_deg: the field's inclination to the turn plane (the geomagnetic dip for a level
      table), if known: fixes the z offset; otherwise o_z = 0 is assumed and I is estimated.
    Refuses (CalibrationRefused) fewer than 8 samples or a turn leaving a gap larger than 120°.
    """
    raw = finite_rows(field_nT, f"{name}: field_nT")
    n = raw.shape[0]
    if n < MIN_SAMPLES:
        raise CalibrationRefused(f"{name}: {n} samples; the sine fit needs at least {MIN_SAMPLES} spread over "
                                 f"one full turn of the table")
    theta, rate, reversed_ = _table_angle(theta_rad, t_s, raw, name)
    coef, cov_axes, axis_rms = _sine_lstsq(theta, raw)
    p = coef.reshape(-1)                                         # [a_x, b_x, c_x, a_y, b_y, c_y, a_z, b_z, c_z]
    assumed = _assumptions(total_nT, inclination_deg)
    est, se_parts = _physics_with_se(p, _block_covariance(cov_axes), total_nT, inclination_deg)
    angles, angles_se = est["angles"], se_parts["angles"]
    offset, matrix = est["offset"], est["matrix"]
    resid = _residual_rms(raw, offset, matrix, total_nT)
    params = _sine_params(est, se_parts, coef, cov_axes, axis_rms, resid, n, inclination_deg, assumed)
    if rate is not None:
        params["rate_rad_s"] = named(rate, None, "rad/s", note="estimated (table angle not given)")
    if reversed_:
        params["angle_reversed"] = True
    cal = ProbeCalibration(name, offset, matrix, se_parts["offset"], se_parts["matrix"], params)
    if not cal.is_finite():
        raise CalibrationRefused(f"{name}: the sine fit produced non-finite parameters (is the table turning "
                                 f"about the probe's z axis?)")
    return SineFit(calibration=cal, alpha_deg=float(angles[0]), beta_deg=float(angles[1]),
                   gamma_deg=float(angles[2]), phi_deg=float(angles[3]), eta_deg=float(angles[4]),
                   se_deg=dict(zip(_ANGLE_NAMES, map(float, angles_se))), amplitude_nT=est["amp"],
                   phase_deg=est["phase"], mean_nT=coef[:, 2].copy(), axis_rms_nT=axis_rms,
                   residual_rms_nT=resid, inclination_deg=float(est["incl"][0]), rate_rad_s=rate,
                   angle_reversed=reversed_, assumed=assumed)


def fit_sinefit(theta_rad: np.ndarray | None, field_nT: np.ndarray, *, inclination_deg: float | None = None,
                total_nT: float | None = None, t_s: np.ndarray | None = None, name: str = "s1") -> ProbeCalibration:
    """`--method sinefit`: the ProbeCalibration of `fit_sine_nonorthogonality`."""
    return fit_sine_nonorthogonality(theta_rad, field_nT, t_s=t_s, total_nT=total_nT,
                                     inclination_deg=inclination_deg, name=name).calibration
