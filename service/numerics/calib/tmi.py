"""Ten-parameter linear calibration against a scalar (TMI) reference, [FastRotation] section 4.

The probe model ([FastRotation] eq. 11-12): raw B_r = C A B_c + I, corrected B_c = M (B_r − I) with
M = [[k_x, m k_y, g k_z], [0, k_y, n k_z], [0, 0, k_z]] upper-triangular. Then (eq. 13)

    |B_c|² = k_x² (B_x + k_m B_y + k_g B_z − i_1)² + k_y² (B_y + k_n B_z − i_2)² + k_z² (B_z − i_3)²

with (transformation I) k_m = m k_y/k_x, k_g = g k_z/k_x, k_n = n k_z/k_y, i_1 = i_x + k_m i_y + k_g i_z,
i_2 = i_y + k_n i_z, i_3 = i_z, and (transformation II) R1 = k_x², R2 = −2 i_1 k_x², R3 = k_y²,
R4 = −2 i_2 k_y², R5 = k_z², R6 = −2 i_3 k_z², R7 = i_1² k_x² + i_2² k_y² + i_3² k_z², which makes
|B_c|² = F² linear in the ten coefficients (eq. 14-15)

    V = [R2, R2 k_m + R4, R2 k_g + R4 k_n + R6, R1, R1 k_m² + R3, R1 k_g² + R3 k_n² + R5,
         2 R1 k_m, 2 R1 k_g, 2 (R1 k_m k_g + R3 k_n), R7]
    on  [B_x, B_y, B_z, B_x², B_y², B_z², B_x B_y, B_x B_z, B_y B_z, 1].

Two things in the paper do not hold as printed, and this module does what they intend:
- eq. 16 solves the ten columns against a right side F² that is constant in a steady field; the
  constant column then fits any data exactly with V = (0, …, 0, F²), and with noise the least
  squares returns that trivial V. We eliminate R7 instead: divide by κ = F² − R7 and solve the
  nine remaining columns against a right side 1 (ellipsoid.solve_quadric; a tenth column −δ
  enters when the reference F varies), then R7 = F₀² − κ with κ fixed by the centre of the fitted
  quadric. This is the same least-squares problem, without its null direction.
- R7 is printed as |B|² − Σ(k i)²; with eq. 15 as written the constant's coefficient is +Σ(k i)².
- g is printed as (sinθ sinφ cosφ − sinφ cosψ)/(cosθ cosφ); the exact inverse of C A gives
  (sinθ cosφ sinψ − sinφ cosψ)/(cosθ cosφ cosψ) (model.triangular_matrix).

Ten samples are the minimum, and they must not be coplanar: the first ten samples of one turn about
z (as [FastRotation] section 5.1 uses) lie on one conic in one plane in every probe frame and the ten-column
design has rank 5 (noise lifts the five null singular values only to ~1e-5 of the largest);
such data are refused with the motion that would help.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused

from .ellipsoid import solve_quadric
from .model import ProbeCalibration, named, triangular_params
from .quadric import MAX_CONDITION, MIN_SAMPLES, jacobian_se, quadric_matrix

#: names of the ten coefficients of eq. 15, in order
V_TERMS = ("Bx", "By", "Bz", "Bx2", "By2", "Bz2", "BxBy", "BxBz", "ByBz", "1")


@dataclass
class TmiFit:
    """Everything [FastRotation] section 4 computes, with standard errors."""

    calibration: ProbeCalibration
    v: np.ndarray                  # (10,) eq. 15 coefficients, nT units (V·[B terms] = F²)
    v_se: np.ndarray
    nonorth_deg: np.ndarray        # φ, θ, ψ
    nonorth_se_deg: np.ndarray
    scale: np.ndarray              # c_x, c_y, c_z
    scale_se: np.ndarray
    offset_nT: np.ndarray          # i_x, i_y, i_z
    offset_se_nT: np.ndarray
    condition: float
    residual_rms_nT: float
    n_samples: int


def v_design(field_nT: np.ndarray) -> np.ndarray:
    """Rows [B_x, B_y, B_z, B_x², B_y², B_z², B_x B_y, B_x B_z, B_y B_z, 1] of eq. 15 (N, 10)."""
    b = np.asarray(field_nT, float)
    x, y, z = b[:, 0], b[:, 1], b[:, 2]
    return np.column_stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z, np.ones_like(x)])


def v_from_quadric(theta: np.ndarray, scale: float, f2_ref: float, center: np.ndarray | None = None) -> np.ndarray:
    """The eq. 15 vector V (nT units) of the fitted quadric uᵀA'u + b'ᵀu = 1, u = (B − c)/s.

    In raw coordinates the quadric is |M(B − o)|² = F₀²: BᵀQB − 2(Qo)ᵀB + oᵀQo = F₀², so
    V_quad = Q (cross terms doubled), V_lin = −2 Q o and V_const = oᵀQo (the paper's R7).
    """
    q, o, _ = quadric_matrix(theta, scale, f2_ref, center)
    lin = -2.0 * q @ o
    return np.array([lin[0], lin[1], lin[2], q[0, 0], q[1, 1], q[2, 2],
                     2 * q[0, 1], 2 * q[0, 2], 2 * q[1, 2], float(o @ q @ o)])


def transformation_ii_inverse(v: np.ndarray) -> dict[str, float]:
    """R1…R7 and k_m, k_g, k_n from V (inverse of eq. 14's substitution, exact)."""
    r1 = v[3]
    km = v[6] / (2 * r1)
    kg = v[7] / (2 * r1)
    r3 = v[4] - r1 * km ** 2
    kn = (v[8] / 2 - r1 * km * kg) / r3
    r5 = v[5] - r1 * kg ** 2 - r3 * kn ** 2
    r2 = v[0]
    r4 = v[1] - r2 * km
    r6 = v[2] - r2 * kg - r4 * kn
    return {"R1": r1, "R2": r2, "R3": r3, "R4": r4, "R5": r5, "R6": r6, "R7": v[9], "km": km, "kg": kg, "kn": kn}


def transformation_i_inverse(r: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """(M, I) of eq. 12 from R1…R6, k_m, k_g, k_n (inverse of transformation I, exact).

    Raises ValueError when R1, R3 or R5 is not positive (the quadric is not an ellipsoid)."""
    if min(r["R1"], r["R3"], r["R5"]) <= 0:
        raise ValueError("not an ellipsoid: a squared scale k² came out non-positive")
    kx, ky, kz = np.sqrt(r["R1"]), np.sqrt(r["R3"]), np.sqrt(r["R5"])
    i1 = -r["R2"] / (2 * r["R1"])
    i2 = -r["R4"] / (2 * r["R3"])
    i3 = -r["R6"] / (2 * r["R5"])
    iz = i3
    iy = i2 - r["kn"] * iz
    ix = i1 - r["km"] * iy - r["kg"] * iz
    m = r["km"] * kx / ky
    g = r["kg"] * kx / kz
    n = r["kn"] * ky / kz
    mat = np.array([[kx, m * ky, g * kz], [0.0, ky, n * kz], [0.0, 0.0, kz]])
    return mat, np.array([ix, iy, iz])


def v_from_parameters(matrix: np.ndarray, offset_nT: np.ndarray) -> np.ndarray:
    """Forward transformations I and II (eq. 13-15): V from M (eq. 12 form) and I."""
    kx, ky, kz = np.diag(matrix)
    m, g, n = matrix[0, 1] / ky, matrix[0, 2] / kz, matrix[1, 2] / kz
    ix, iy, iz = offset_nT
    km, kg, kn = m * ky / kx, g * kz / kx, n * kz / ky
    i1, i2, i3 = ix + km * iy + kg * iz, iy + kn * iz, iz
    r1, r2, r3, r4, r5, r6 = kx ** 2, -2 * i1 * kx ** 2, ky ** 2, -2 * i2 * ky ** 2, kz ** 2, -2 * i3 * kz ** 2
    r7 = i1 ** 2 * kx ** 2 + i2 ** 2 * ky ** 2 + i3 ** 2 * kz ** 2
    return np.array([r2, r2 * km + r4, r2 * kg + r4 * kn + r6, r1, r1 * km ** 2 + r3,
                     r1 * kg ** 2 + r3 * kn ** 2 + r5, 2 * r1 * km, 2 * r1 * kg, 2 * (r1 * km * kg + r3 * kn), r7])


def _chain(theta: np.ndarray, scale: float, f2_ref: float, center: np.ndarray) -> np.ndarray:
    """θ -> [φ, θ, ψ (deg), c_x, c_y, c_z, i_x, i_y, i_z, M (9), V (10)]: the paper's whole route."""
    v = v_from_quadric(theta, scale, f2_ref, center)
    mat, offset = transformation_i_inverse(transformation_ii_inverse(v))
    angles, c = triangular_params(mat)
    return np.concatenate([angles, c, offset, mat.ravel(), v])


def fit_tmi_full(field_nT: np.ndarray, total_nT, *, name: str = "s1",
                 max_condition: float = MAX_CONDITION, noise_nT: float | None = None) -> TmiFit:
    """[FastRotation] section 4 on (N ≥ 10, 3) raw samples of one probe and the scalar reference F (N,) or F.

    noise_nT: the noise of |b| if known; standard errors then use it rather than the residuals
    (ten samples leave a single degree of freedom to estimate the noise from)."""
    if total_nT is None:
        raise CalibrationRefused(f"{name}: tmi needs a scalar reference of the total field "
                                 f"(a ref_total column or a configured total_nT)")
    sol = solve_quadric(field_nT, total_nT, name=name, max_condition=max_condition, min_samples=MIN_SAMPLES,
                        noise_nT=noise_nT)
    raw = np.asarray(field_nT, float)
    try:
        out = _chain(sol.theta, sol.scale, sol.f2_ref, sol.center)
    except (np.linalg.LinAlgError, ValueError):
        raise CalibrationRefused(f"{name}: the fitted quadric is not an ellipsoid; the directions seen do "
                                 f"not determine one (or the field changed while the probe turned)") from None
    se = jacobian_se(lambda t: _chain(t, sol.scale, sol.f2_ref, sol.center), sol.theta, sol.theta_cov)
    se = np.full(out.size, np.nan) if se is None else se
    angles, c, offset, mat, v = out[:3], out[3:6], out[6:9], out[9:18].reshape(3, 3), out[18:]
    corr = (raw - offset) @ mat.T
    rms = float(np.sqrt(np.mean((np.linalg.norm(corr, axis=1) - sol.total_nT) ** 2)))
    params = {"offset_nT": named(offset, se[6:9], "nT", names=["i_x", "i_y", "i_z"]),
              "nonorth_deg": named(angles, se[:3], "deg", names=["phi", "theta", "psi"],
                                   note="001 eq. 11: x axis tilt out of the y-z plane (phi), in it (theta), "
                                        "y axis tilt towards z (psi)"),
              "scale": named(c, se[3:6], "", names=["c_x", "c_y", "c_z"]),
              "v": named(v, se[18:], "nT^(2-k)", names=list(V_TERMS), note="001 eq. 15 coefficients"),
              "residual_rms_nT": named(rms, None, "nT"),
              "condition": named(sol.condition, None, ""),
              "samples": named(raw.shape[0], None, "")}
    cal = ProbeCalibration(name, offset, mat, se[6:9], se[9:18].reshape(3, 3), params)
    if not cal.is_finite():
        raise CalibrationRefused(f"{name}: the fit produced non-finite parameters")
    return TmiFit(cal, v, se[18:], angles, se[:3], c, se[3:6], offset, se[6:9], sol.condition, rms, raw.shape[0])


def fit_tmi(field_nT: np.ndarray, total_nT, *, name: str = "s1",
            max_condition: float = MAX_CONDITION, noise_nT: float | None = None) -> ProbeCalibration:
    """[FastRotation] section 4: the probe's calibration in its own triangular frame, with named parameters
    nonorth_deg (φ, θ, ψ), scale (c_x, c_y, c_z), offset_nT (i_x, i_y, i_z) and their standard errors."""
    return fit_tmi_full(field_nT, total_nT, name=name, max_condition=max_condition, noise_nT=noise_nT).calibration
