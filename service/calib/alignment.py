"""Alignment of probes to each other or to the platform (CONTRACTS `--align`).

- regression (000 section 2.2, eq. 10-16): probe k's raw output mapped onto the calibrated
  probe 1 by multivariate linear regression, B1 ≈ A_k r_k + c_k; this calibrates probe k and its
  attitude relative to probe 1 in one step, minimising the Frobenius norm of the difference.
- rotation (001 section 3, eq. 4-10): each calibrated probe rotated onto the platform frame.
  `rotation_from_samples` is 001's own solve (lstsq of the x and y rows, angles by eq. 10, from
  ≥ 3 samples); `align_probes(..., "rotation")` uses the constrained optimum (Kabsch/SVD) onto
  the mean of the probes, iterated: the platform is the probes' mean frame.
- pca (004 section 3.2) lives in twostep.py.
"""

from __future__ import annotations

import numpy as np

from drivers.errors import CalibrationRefused

from .model import ProbeCalibration


def align_regression(ref_nT: np.ndarray, raw_nT: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, c) minimising ‖B_ref − (A r + c)‖_F over samples (000 eq. 10-16)."""
    ref = np.asarray(ref_nT, float)
    raw = np.asarray(raw_nT, float)
    x = np.column_stack([raw, np.ones(raw.shape[0])])
    coef, _, rank, _ = np.linalg.lstsq(x, ref, rcond=None)
    if rank < 4:
        raise CalibrationRefused("regression alignment: the samples do not span three directions; "
                                 "rotate about at least two axes")
    return coef[:3].T, coef[3]


def regression_calibration(name: str, ref_nT: np.ndarray, raw_nT: np.ndarray) -> ProbeCalibration:
    """Probe k as a ProbeCalibration in probe 1's frame: M = A, o = −A⁻¹ c."""
    a, c = align_regression(ref_nT, raw_nT)
    offset = -np.linalg.solve(a, c)
    return ProbeCalibration(name, offset, a, params={"align": {"value": "regression", "se": None, "unit": ""}})


def kabsch(ref_nT: np.ndarray, vec_nT: np.ndarray) -> np.ndarray:
    """The rotation R minimising Σ‖ref − R vec‖² (proper, det +1)."""
    h = np.asarray(vec_nT, float).T @ np.asarray(ref_nT, float)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def angles_from_rotation(r: np.ndarray) -> tuple[float, float, float]:
    """Heel α, pitch β, azimuth γ (rad) of R = Tα Tβ Tγ (001 eq. 5, 10)."""
    beta = -np.arcsin(np.clip(r[0, 2], -1, 1))
    gamma = np.arctan2(r[0, 1], r[0, 0])
    alpha = np.arctan2(r[1, 2], r[2, 2])
    return float(alpha), float(beta), float(gamma)


def rotation_from_angles(alpha: float, beta: float, gamma: float) -> np.ndarray:
    """Tα Tβ Tγ of 001 eq. 4-5."""
    ca, sa, cb, sb, cg, sg = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta), np.cos(gamma), np.sin(gamma)
    ta = np.array([[1, 0, 0], [0, ca, sa], [0, -sa, ca]])
    tb = np.array([[cb, 0, -sb], [0, 1, 0], [sb, 0, cb]])
    tg = np.array([[cg, sg, 0], [-sg, cg, 0], [0, 0, 1]])
    return ta @ tb @ tg


def rotation_from_samples(platform_nT: np.ndarray, probe_nT: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float]]:
    """001 eq. 8-10: V_x, V_y by least squares from N ≥ 3 samples, then α, β, γ and R = Tα Tβ Tγ."""
    m = np.asarray(probe_nT, float)
    p = np.asarray(platform_nT, float)
    if m.shape[0] < 3:
        raise CalibrationRefused(f"rotation alignment needs at least 3 samples, got {m.shape[0]}")
    vx = np.linalg.lstsq(m, p[:, 0], rcond=None)[0]
    vy = np.linalg.lstsq(m, p[:, 1], rcond=None)[0]
    beta = -np.arcsin(np.clip(vx[2], -1, 1))
    gamma = np.arctan2(vx[1], vx[0])
    alpha = np.arcsin(np.clip(vy[2] / np.cos(beta), -1, 1))
    return rotation_from_angles(alpha, beta, gamma), (float(alpha), float(beta), float(gamma))


def align_probes(probes: list[ProbeCalibration], raw_nT: np.ndarray, method: str = "rotation",
                 iterations: int = 3) -> list[ProbeCalibration]:
    """Express every probe in one common frame, using (N, P, 3) raw samples seen together.

    rotation: onto the probes' mean frame (001's platform); regression: onto probe 1 (000).
    """
    raw = np.asarray(raw_nT, float)
    ok = np.isfinite(raw).all(axis=(1, 2))
    raw = raw[ok]
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
        out.append(p.rotated(rk, misalign_deg={"value": np.degrees([a, b, g]).tolist(), "se": None,
                                               "unit": "deg (heel, pitch, azimuth of 001 eq. 5)"}))
    return out
