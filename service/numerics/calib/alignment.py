"""Alignment of probes to each other or to the platform (`--align`, docs/calibration.md).

- regression ([TwoFluxgate] section 2.2, eq. 10-16): probe k's raw output X_k regressed onto the calibrated
  probe-1 output X = A_1 (X_1 − E_1): minimising ‖X − (A_k X_k − B_k)‖_F² over N samples gives,
  setting the derivatives in B_k and A_k to zero (eq. 15), the multivariate linear regression of
  eq. 16, one row of A_k (and of B_k) per axis. It calibrates probe k and its attitude relative to
  probe 1 in one step; E_k = A_k⁻¹ B_k. `align_regression`, `regression_calibration`.
- rotation ([FastRotation] section 3, eq. 3-10): each calibrated probe rotated onto the platform. The platform
  output is B0 = the mean of the probes' raw outputs (eq. 3), itself calibrated with the TMI
  method (`platform_calibration`); then per probe the x and y rows of T = Tα Tβ Tγ by least
  squares from N ≥ 3 samples (eq. 8-9; one turn is enough: three samples 120° apart about z are
  linearly independent) and heel α, pitch β, azimuth γ from them (eq. 10). `align_rotation`.
- `align_probes(..., "rotation")`, used by the service's pipeline on long windows, takes the
  constrained optimum instead (Kabsch/SVD onto the mean frame of the probes, iterated).
- pca ([TwoStep] section 3.2) lives in twostep.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused, DataError

from .excitation import PLANARITY_MIN, planarity
from .model import ProbeCalibration, named, sensor_scale


def _finite(a: np.ndarray, what: str, ndim: int = 2) -> np.ndarray:
    x = np.asarray(a, float)
    if x.ndim != ndim or x.shape[-1] != 3:
        raise DataError(f"{what}: expected shape {'(N, 3)' if ndim == 2 else '(N, P, 3)'}, got {x.shape}")
    bad = np.flatnonzero(~np.isfinite(x.reshape(x.shape[0], -1)).all(axis=1))
    if bad.size:
        raise DataError(f"{what}: rows {', '.join(map(str, bad[:10].tolist()))} hold NaN or inf; remove them")
    return x


# --- [TwoFluxgate] section 2.2: regression onto probe 1 ---------------------------------------------


#: beyond this many samples the regression is solved from its normal equations summed over chunks of rows
#: (hours of data: no (N, 4) design is built); below it, by lstsq of the whole design, as the live gate does
GRAM_ROWS = 1 << 20
_CHUNK = 1 << 18


def align_regression(ref_nT: np.ndarray, raw_nT: np.ndarray, *,
                     gram_rows: int = GRAM_ROWS) -> tuple[np.ndarray, np.ndarray]:
    """(A, c) minimising ‖B_ref − (A r + c)‖_F over samples ([TwoFluxgate] eq. 13-16).

    ref_nT: the calibrated reference probe's output (N, 3); raw_nT: the other probe's raw output.
    In the paper's symbols A = A_2 and c = −B_2 = −A_2 E_2. Needs the raw samples to span three
    directions (eq. 15: X_2 of full row rank), i.e. turns about at least two axes."""
    return _regression(ref_nT, raw_nT, gram_rows)[:2]


def _regression(ref_nT: np.ndarray, raw_nT: np.ndarray, gram_rows: int):
    """(A, c, XᵀX, per-axis residual sum of squares, residual (N, 3) or None) of the regression."""
    ref = _finite(ref_nT, "align_regression: ref_nT")
    raw = _finite(raw_nT, "align_regression: raw_nT")
    if ref.shape != raw.shape:
        raise DataError(f"align_regression: ref_nT {ref.shape} and raw_nT {raw.shape} differ in shape")
    if raw.shape[0] < 4:
        raise CalibrationRefused(f"regression alignment: {raw.shape[0]} samples; it needs at least 4 spanning "
                                 f"three directions (turns about at least two axes)")
    plan, normal = planarity(raw)
    if plan < PLANARITY_MIN:
        # one turn: [X_k, 1] has rank 3 (the plane's equation is a null combination), eq. 15 fails
        axis = "xyz"[int(np.argmax(np.abs(normal)))]
        others = [a for a in "xyz" if a != axis]
        raise CalibrationRefused(f"regression alignment: the samples do not span three directions (they lie in "
                                 f"one plane: a single-axis turn about {axis}); turn about the {others[0]} or "
                                 f"{others[1]} axis too")
    n = raw.shape[0]
    if n > gram_rows:
        return _regression_by_chunks(ref, raw)
    x = np.column_stack([raw, np.ones(n)])
    # scale the columns so the rank test does not see nT² against 1
    col = np.linalg.norm(x, axis=0)
    col[col == 0] = 1.0
    coef, _, rank, sv = np.linalg.lstsq(x / col, ref, rcond=None)
    if rank < 4 or sv[-1] < 1e-9 * sv[0]:
        raise CalibrationRefused(_NOT_SPANNED)
    coef = coef / col[:, None]
    a, c = coef[:3].T, coef[3]
    resid = ref - (raw @ a.T + c)
    return a, c, x.T @ x, (resid ** 2).sum(axis=0), resid


_NOT_SPANNED = "regression alignment: the samples do not span three directions; rotate about at least two axes"


def _regression_by_chunks(ref: np.ndarray, raw: np.ndarray):
    """The same regression from XᵀX and Xᵀ ref summed over chunks of rows, the columns scaled to unit norm as
    in lstsq's path (the rank test on the singular values of the scaled design: square roots of the scaled
    Gram's eigenvalues), then the residual's sums of squares in a second pass."""
    n = raw.shape[0]
    g, h = np.zeros((4, 4)), np.zeros((4, 3))
    for lo in range(0, n, _CHUNK):
        x = np.column_stack([raw[lo:lo + _CHUNK], np.ones(min(_CHUNK, n - lo))])
        g += x.T @ x
        h += x.T @ ref[lo:lo + _CHUNK]
    col = np.sqrt(np.diag(g))
    col[col == 0] = 1.0
    gs = g / np.outer(col, col)
    w = np.linalg.eigvalsh(gs)
    # the Gram's eigenvalues are the squared singular values, known to about 1e-16 of the largest: the test is
    # singular values below 1e-7 of the largest (lstsq's path resolves 1e-9)
    if w[0] <= 1e-14 * w[-1]:
        raise CalibrationRefused(_NOT_SPANNED)
    coef = np.linalg.solve(gs, h / col[:, None]) / col[:, None]
    a, c = coef[:3].T, coef[3]
    ss = np.zeros(3)
    for lo in range(0, n, _CHUNK):
        r = ref[lo:lo + _CHUNK] - (raw[lo:lo + _CHUNK] @ a.T + c)
        ss += (r ** 2).sum(axis=0)
    return a, c, g, ss, None


def regression_calibration(name: str, ref_nT: np.ndarray, raw_nT: np.ndarray, *,
                           gram_rows: int = GRAM_ROWS) -> ProbeCalibration:
    """Probe k as a ProbeCalibration in the reference probe's frame: M = A, o = −A⁻¹ c, with standard
    errors from the regression and the sensor's scale factor per axis (`scale`: the row norms of A⁻¹, as the
    ellipsoid fit's c_x, c_y, c_z; not [TwoFluxgate]'s column gains K of A = N K⁻¹, which differ from it where the axes
    are not orthogonal: by up to 1.3e-3 on configs/sim-gradiometer.toml's s2).

    The standard errors are those of the regression given the reference: errors of the reference
    probe's own calibration carry over one to one (an offset error δE_1 of probe 1 moves E_k by
    about A_k⁻¹ A_1 δE_1) and are not included here (`fluxcal fit` adds them:
    wiring/coloured_fit.py)."""
    a, c, xtx, ss, resid = _regression(ref_nT, raw_nT, gram_rows)
    offset = -np.linalg.solve(a, c)
    n = np.shape(raw_nT)[0]
    sigma2 = ss / max(n - 4, 1)                                # per output axis
    # cov of row i of [A | c] is σ_i² (XᵀX)⁻¹, X = [raw, 1]; rows independent
    xtx_inv = np.linalg.pinv(xtx)
    cov = np.kron(np.diag(sigma2), xtx_inv)                    # (12, 12), parameters row by row
    m_se = np.sqrt(np.outer(sigma2, np.diag(xtx_inv)[:3]))
    beta = np.column_stack([a, c]).ravel()

    def offset_of(b: np.ndarray) -> np.ndarray:
        bm = b.reshape(3, 4)
        return -np.linalg.solve(bm[:, :3], bm[:, 3])          # E = −A⁻¹ c

    jac = np.empty((3, 12))
    for j in range(12):
        h = 1e-6 * max(abs(beta[j]), 1e-3)
        bj = beta.copy()
        bj[j] += h
        jac[:, j] = (offset_of(bj) - offset) / h
    o_se = np.sqrt(np.maximum(np.diag(jac @ cov @ jac.T), 0))
    scale = sensor_scale(a)
    resid_rms = float(np.sqrt(np.mean(resid ** 2))) if resid is not None else float(np.sqrt(ss.sum() / (3 * n)))
    params = {"align": named(None, None, "", method="regression (000 eq. 10-16)"),
              "offset_nT": named(offset, o_se, "nT"),
              # no standard error: fluxcal fit widens the matrix's for coloured noise, which this would not follow
              "scale": named(scale, None, "", names=["c_x", "c_y", "c_z"],
                             note="the sensor's scale factor per axis: row norms of matrix^-1 (001 eq. 11's c)"),
              "vector_residual_rms_nT": named(resid_rms, None, "nT",
                                              note="RMS over the three axes of the corrected vector minus the "
                                                   "reference probe's (the vector residual against the aligned "
                                                   "reference)")}
    return ProbeCalibration(name, offset, a, o_se, m_se, params)


# --- [FastRotation] section 3: rotation onto the platform -------------------------------------------


def rotation_from_angles(alpha: float, beta: float, gamma: float) -> np.ndarray:
    """T = Tα Tβ Tγ of [FastRotation] eq. 4-5 (heel about x, pitch about y, azimuth about z; radians):
    platform = T · probe."""
    ca, sa, cb, sb, cg, sg = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta), np.cos(gamma), np.sin(gamma)
    ta = np.array([[1, 0, 0], [0, ca, sa], [0, -sa, ca]])
    tb = np.array([[cb, 0, -sb], [0, 1, 0], [sb, 0, cb]])
    tg = np.array([[cg, sg, 0], [-sg, cg, 0], [0, 0, 1]])
    return ta @ tb @ tg


def angles_from_rotation(r: np.ndarray) -> tuple[float, float, float]:
    """Heel α, pitch β, azimuth γ (rad) of R = Tα Tβ Tγ ([FastRotation] eq. 6, 10)."""
    beta = -np.arcsin(np.clip(r[0, 2], -1, 1))
    gamma = np.arctan2(r[0, 1], r[0, 0])
    alpha = np.arctan2(r[1, 2], r[2, 2])
    return float(alpha), float(beta), float(gamma)


def rotation_from_samples(platform_nT: np.ndarray, probe_nT: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float]]:
    """[FastRotation] eq. 8-10: V_x, V_y by least squares from N ≥ 3 samples, then α, β, γ and R = Tα Tβ Tγ.

    β = −arcsin V_x3, γ = atan2(V_x2, V_x1) (the paper's arctan(V_x2/V_x1) loses the quadrant
    beyond ±90°), α = arcsin(V_y3 / cos β)."""
    m = np.asarray(probe_nT, float)
    p = np.asarray(platform_nT, float)
    if m.shape[0] < 3:
        raise CalibrationRefused(f"rotation alignment needs at least 3 samples, got {m.shape[0]}")
    sv = np.linalg.svd(m, compute_uv=False)
    if sv[-1] < 1e-6 * sv[0]:
        raise CalibrationRefused("rotation alignment: the samples do not span three directions (eq. 8 needs "
                                 "rank 3); take samples at least ~30° apart on the turn")
    # eq. 9: V = (MᵀM)⁻¹ Mᵀ B, as a least-squares solve
    v = np.linalg.lstsq(m, p[:, :2], rcond=None)[0]
    vx, vy = v[:, 0], v[:, 1]
    beta = -np.arcsin(np.clip(vx[2], -1, 1))
    gamma = np.arctan2(vx[1], vx[0])
    alpha = np.arcsin(np.clip(vy[2] / np.cos(beta), -1, 1))
    return rotation_from_angles(alpha, beta, gamma), (float(alpha), float(beta), float(gamma))


def platform_output(raw_nT: np.ndarray) -> np.ndarray:
    """B0 of [FastRotation] eq. 3: the mean of the probes' outputs, (N, P, 3) -> (N, 3)."""
    return _finite(raw_nT, "platform_output: raw_nT", ndim=3).mean(axis=1)


def platform_calibration(raw_nT: np.ndarray, total_nT, *, name: str = "platform") -> ProbeCalibration:
    """[FastRotation] section 2: B0 (eq. 3) treated as a virtual probe with its own offset, scale factors and
    non-orthogonality, calibrated with the TMI method; its corrected output is the platform frame."""
    from .tmi import fit_tmi

    return fit_tmi(platform_output(raw_nT), total_nT, name=name)


@dataclass
class RotationAlignment:
    """[FastRotation] section 3 for P probes: platform = rotations[k] · corrected_k."""

    rotations: np.ndarray        # (P, 3, 3)
    angles_rad: np.ndarray       # (P, 3) heel α, pitch β, azimuth γ
    angles_se_rad: np.ndarray    # (P, 3), NaN with exactly 3 samples (no residual to estimate noise)
    reference_nT: np.ndarray     # (n, 3) the platform output used
    samples: np.ndarray          # indices of the samples used

    @property
    def angles_deg(self) -> np.ndarray:
        return np.degrees(self.angles_rad)

    def apply(self, probes: list[ProbeCalibration]) -> list[ProbeCalibration]:
        """Each probe's calibration expressed in the platform frame (M' = T M)."""
        out = []
        for p, r, a, s in zip(probes, self.rotations, self.angles_deg, np.degrees(self.angles_se_rad)):
            out.append(p.rotated(r, misalign_deg=named(a, s, "deg", names=["heel", "pitch", "azimuth"],
                                                       note="001 eq. 5: platform = Tα Tβ Tγ probe")))
        return out


def mean_frame_reference(corrected: list[np.ndarray]) -> np.ndarray:
    """The platform output when only corrected probe outputs are known: every probe rotated onto
    probe 1 (Kabsch), the mean orientation of the probes (the rotation closest to the mean of those
    rotations), and the mean of the probes expressed in it."""
    c0 = corrected[0]
    rots = [kabsch(c0, c) for c in corrected]                # c0 ≈ R_k c_k
    u, _, vt = np.linalg.svd(sum(rots))
    mean_rot = u @ vt                                         # polar factor of Σ R_k
    return np.mean([c @ (mean_rot.T @ r).T for c, r in zip(corrected, rots)], axis=0)


def align_rotation(corrected: list[np.ndarray], reference_nT: np.ndarray | None = None, *,
                   samples: np.ndarray | None = None) -> RotationAlignment:
    """[FastRotation] section 3: the rotation of each calibrated probe onto the platform, from N ≥ 3 samples.

    corrected: per probe (N, 3), each in its own orthogonal frame (after fit_tmi / fit_ellipsoid).
    reference_nT: the platform output (N, 3) — in [FastRotation] the calibrated B0,
      `platform_calibration(raw, F).apply(platform_output(raw))`. None: the mean frame of the
      probes (`mean_frame_reference`), for when the raw outputs are not at hand.
    samples: which samples to use (e.g. three 120° apart on one turn); default all.
    """
    cs = [_finite(c, f"align_rotation: corrected[{k}]") for k, c in enumerate(corrected)]
    n = cs[0].shape[0]
    if any(c.shape != (n, 3) for c in cs):
        raise DataError("align_rotation: every probe needs the same samples (N, 3)")
    idx = np.arange(n) if samples is None else np.asarray(samples, dtype=int)
    cs = [c[idx] for c in cs]
    if reference_nT is None:
        ref = mean_frame_reference(cs)
    else:
        ref = _finite(reference_nT, "align_rotation: reference_nT")[idx]
    rots, angles, ses = [], [], []
    for c in cs:
        r, abg = rotation_from_samples(ref, c)
        rots.append(r)
        angles.append(abg)
        ses.append(_angle_se(ref, c, abg))
    return RotationAlignment(np.array(rots), np.array(angles), np.array(ses), ref, idx)


def _angle_se(ref: np.ndarray, probe: np.ndarray, abg: tuple[float, float, float]) -> np.ndarray:
    """Standard errors of (α, β, γ) from the residuals of eq. 8 (NaN with three samples)."""
    n = probe.shape[0]
    if n <= 3:
        return np.full(3, np.nan)
    alpha, beta, gamma = abg
    r = rotation_from_angles(alpha, beta, gamma)
    resid = ref - probe @ r.T
    sigma2 = float((resid ** 2).sum() / (3 * n - 3))
    # linearised: a small rotation ω of the probe frame changes T c by T (ω × c); its information
    # is Σ ‖T [c]×‖² ~ Σ (|c|² I − c cᵀ); the angles are ω in the (heel, pitch, azimuth) axes
    info = np.zeros((3, 3))
    for c in probe:
        cx = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
        info += cx.T @ cx
    # d(α, β, γ)/dω: numerically, through the angles of T exp([ω]×)
    jac = np.empty((3, 3))
    h = 1e-7
    for i in range(3):
        w = np.zeros(3)
        w[i] = h
        wx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        jac[:, i] = (np.array(angles_from_rotation(r @ (np.eye(3) + wx))) - np.array(abg)) / h
    cov = jac @ (sigma2 * np.linalg.pinv(info)) @ jac.T
    return np.sqrt(np.maximum(np.diag(cov), 0))


# --- the service's alignment of long windows --------------------------------------------------------


def kabsch(ref_nT: np.ndarray, vec_nT: np.ndarray) -> np.ndarray:
    """The rotation R minimising Σ‖ref − R vec‖² (proper, det +1)."""
    h = np.asarray(vec_nT, float).T @ np.asarray(ref_nT, float)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def align_probes(probes: list[ProbeCalibration], raw_nT: np.ndarray, method: str = "rotation",
                 iterations: int = 3) -> list[ProbeCalibration]:
    """Express every probe in one common frame, using (N, P, 3) raw samples seen together.

    rotation: onto the probes' mean frame ([FastRotation]'s platform); regression: onto probe 1 ([TwoFluxgate]).
    """
    raw = np.asarray(raw_nT, float)
    ok = np.isfinite(raw).all(axis=(1, 2))
    if not ok.all():
        raw = raw[ok]                                 # a copy only when some sample must go (hours of data)
    if raw.shape[0] < 3:
        raise CalibrationRefused("alignment needs at least 3 samples seen by every probe")
    if method == "regression":
        ref = probes[0].apply(raw[:, 0])
        return [probes[0]] + [regression_calibration(p.name, ref, raw[:, k]) for k, p in enumerate(probes[1:], 1)]
    if method != "rotation":
        raise ValueError(f"align: {method!r} is not allowed here (allowed: 'rotation', 'regression')")
    corr = np.stack([p.apply(raw[:, k]) for k, p in enumerate(probes)], axis=1)   # (N, P, 3)
    rots = [np.eye(3) for _ in probes]
    for _ in range(iterations):
        aligned = np.stack([corr[:, k] @ rots[k].T for k in range(len(probes))], axis=1)
        mean = aligned.mean(axis=1)
        rots = [kabsch(mean, corr[:, k]) for k in range(len(probes))]
    # fix the common frame to the mean orientation of the probes (rotations average to identity)
    u, _, vt = np.linalg.svd(sum(rots))
    r_mean = u @ vt
    out = []
    for p, r in zip(probes, rots):
        rk = r_mean.T @ r
        a, b, g = angles_from_rotation(rk)
        out.append(p.rotated(rk, misalign_deg=named(np.degrees([a, b, g]), None,
                                                    "deg (heel, pitch, azimuth of 001 eq. 5)")))
    return out


#: a probe aligned by regression whose scalar residual is this many times its own ellipsoid's: the reference's
#: errors came with it (clean simulated arrays: 1.000-1.006; a flap's magnet at the reference, 0.15 of it: 1.24)
BORROWED_RATIO = 1.1


def scalar_rms(offset_nT: np.ndarray, matrix: np.ndarray, raw_nT: np.ndarray, total_nT: np.ndarray | None) -> float:
    """RMS of |M (raw - o)| - F (F: the total field per sample; None: the magnitude's own mean)."""
    mag = np.linalg.norm((raw_nT - offset_nT) @ np.asarray(matrix).T, axis=1)
    ok = np.isfinite(mag) if total_nT is None else np.isfinite(mag) & np.isfinite(total_nT)
    ref = float(np.mean(mag[ok])) if total_nT is None else total_nT[ok]
    return float(np.sqrt(np.mean((mag[ok] - ref) ** 2)))


def borrowed_errors(aligned: list[ProbeCalibration], own: list[tuple[np.ndarray, np.ndarray] | None],
                    raw_nT: np.ndarray, total_nT: np.ndarray | None) -> dict[int, str]:
    """Per probe aligned by regression onto probe 1: where its scalar residual is BORROWED_RATIO times or more what
    its own ellipsoid (offset, matrix in `own`) leaves, why and what keeps it. The regression makes the probe follow
    probe 1's corrected vector, so what probe 1's calibration lacks (an effect at probe 1 only) comes with it: a
    simulated servo's magnet at the reference gave a clean probe 10.7 nT where its own fit left 0.50."""
    ref = aligned[0]
    ref_rms = scalar_rms(ref.offset_nT, ref.matrix, raw_nT[:, 0], total_nT)
    out = {}
    for k in range(1, len(aligned)):
        if own[k] is None:
            continue
        mine = scalar_rms(*own[k], raw_nT[:, k], total_nT)
        now = scalar_rms(aligned[k].offset_nT, aligned[k].matrix, raw_nT[:, k], total_nT)
        if mine > 0 and now >= BORROWED_RATIO * mine:
            p, r = aligned[k].name, ref.name
            out[k] = (f"{p}: aligned to {r} by regression, its scalar residual is {now:.3f} nT where its own "
                       f"ellipsoid leaves {mine:.3f} ({now / mine:.2f} times): the regression makes {p} follow "
                       f"{r}, and what {r}'s calibration lacks comes with it ({r}'s own scalar residual "
                       f"{ref_rms:.3f} nT); "
                       f"--align rotation keeps {p}'s own calibration and only turns it into {r}'s frame")
    return out
