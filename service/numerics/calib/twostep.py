"""The equivalent two-step calibration ([TwoStep]): ellipsoid, then PCA of three single-axis turns.

Model ([TwoStep] eq. 1-3): h_s = M h_b + b with the SVD view M = U D V: the body frame is turned by the
orthogonal V into an "equivalent sensor frame", stretched by D = diag(d) and turned by U, then
shifted by b. The correction (eq. 4) is ĥ_b = V̂⁻¹ D̂⁻¹ Û⁻¹ (h_s − b̂).

Step 1, equivalent sensor frame (eq. 5-14): the ellipsoid fit gives b̂ and the quadric
E = M⁻ᵀ M⁻¹ (here scaled so |ĥ| equals the total field F, [TwoStep] sets k = 1: the scale does not
matter for heading); E = U_E D_E U_Eᵀ (eq. 12) gives Û = U_E (eq. 13), d̂ = 1/√d_E (eq. 14).
U_E's columns are chosen with det Û = +1, so that V is a rotation when M keeps the handedness
([TwoStep] notes V is orthogonal "not necessarily a rotation": that is exactly this sign choice, and
the right-handed cross products of the orthogonality correction need a rotation).

Step 2, equivalent misalignment (eq. 15-18): ĥ_c = D̂⁻¹ Ûᵀ (h_s − b̂) = V h_b (eq. 15-16). During a
turn about body axis i the component h_b,i stays constant, so the centred ĥ_c of the turn lie in a
plane whose normal is V_i: the eigenvector P3 of the smallest eigenvalue of their scatter matrix
(eq. 17). Two corrections:
- sign (3.2.1): P3 and −P3 are both eigenvectors. Assuming h_s,i and h_b,i have the same sign
  (M nearly diagonal, and the turn made with |h_s,i| ≫ 0, i.e. the field well off the plane of
  the turn), V̂_i is flipped when mean(P3ᵀ ĥ_c) and mean(h_s,i) differ in sign.
- orthogonality (3.2.2): the variance contribution α_i = λ3 / (λ1 + λ2 + λ3) grades each column
  (lower is better); the best column is kept, the worst is the right-handed cross product of the
  other two, the middle one the cross product of the new pair (eq. 18 for α_z < α_x < α_y:
  V_cz = V_z, V_cy = V_z × V_x, V_cx = V_cy × V_z), each normalised.

`align_pca` is the same step 2 for an array (`--align pca`, [TwoStep] section 3.2): every probe, already
calibrated in its own orthogonal frame, is turned onto the platform frame that the three turns
define.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused, DataError

from .ellipsoid import fit_ellipsoid
from .model import ProbeCalibration, named
from .quadric import finite_rows

_AXIS = "xyz"
#: the turn's axial raw component must be at least this share of |h_s| for the sign assumption
SIGN_MIN_SHARE = 0.2
MIN_TURN_SAMPLES = 3


@dataclass
class PcaAxes:
    """Step 2's result: V̂ with its columns' grades and what was corrected."""

    v: np.ndarray                    # (3, 3) columns V̂_x, V̂_y, V̂_z (after the corrections asked for)
    v_pca: np.ndarray                # (3, 3) the eigenvectors as the eigensolver returned them
    contribution: np.ndarray         # (3,) α_i = λ3 / Σλ of each turn
    flipped: list[bool]              # sign correction flipped column i
    sign_share: np.ndarray           # (3,) |mean h_s,i| / mean |h_s| of each turn (the sign assumption's margin)
    order: list[int] = field(default_factory=list)     # columns best to worst (orthogonality correction)

    @property
    def non_orthogonality_deg(self) -> float:
        """Largest departure of a pair of V̂ columns from 90°."""
        u = self.v / np.linalg.norm(self.v, axis=0)
        g = u.T @ u
        return float(np.degrees(np.max(np.abs(np.arcsin(np.clip(g[np.triu_indices(3, 1)], -1, 1))))))


@dataclass
class TwoStepFit:
    """Result of `fit_two_step_full`."""

    calibration: ProbeCalibration    # corrected = matrix (raw − offset) in the body frame
    u: np.ndarray                    # Û (eq. 13), det +1
    d: np.ndarray                    # d̂ (eq. 14): semi-axes of the measured ellipsoid per unit field
    offset_nT: np.ndarray            # b̂ (eq. 9)
    pca: PcaAxes                     # V̂ and how it was obtained
    equivalent_matrix: np.ndarray    # D̂⁻¹ Ûᵀ: raw − b̂ -> equivalent sensor frame (eq. 15)

    @property
    def v(self) -> np.ndarray:
        return self.pca.v


def _right_handed_cross(a: int, b: int, va: np.ndarray, vb: np.ndarray) -> tuple[int, np.ndarray]:
    """The third axis c from axes a, b by the right-hand rule: e_a × e_b = ±e_c."""
    c = 3 - a - b
    sign = 1.0 if (a, b, c) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0
    w = sign * np.cross(va, vb)
    return c, w / np.linalg.norm(w)


def orthogonality_correction(v: np.ndarray, contribution: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """[TwoStep] eq. 18 for any order of the variance contributions: keep the best column, rebuild the worst
    from the other two, then the middle from the new pair; returns (V̂_c, columns best to worst)."""
    order = [int(i) for i in np.argsort(contribution)]
    best, mid, worst = order
    vb = v[:, best] / np.linalg.norm(v[:, best])
    out = np.empty((3, 3))
    out[:, best] = vb
    _, out[:, worst] = _right_handed_cross(best, mid, vb, v[:, mid])
    _, out[:, mid] = _right_handed_cross(worst, best, out[:, worst], vb)
    return out, order


def pca_axes(turns_c: Sequence[np.ndarray], turns_raw: Sequence[np.ndarray], *, sign_correction: bool = True,
             orth_correction: bool = True) -> PcaAxes:
    """V̂ from three turns (about body x, y, z) of data in the equivalent frame (eq. 17) and the same
    turns' raw output less the fitted offset (for the sign correction)."""
    if len(turns_c) != 3 or len(turns_raw) != 3:
        raise ValueError(f"expected three turns (about x, y, z), got {len(turns_c)}")
    v_pca = np.empty((3, 3))
    v = np.empty((3, 3))
    contribution = np.empty(3)
    share = np.empty(3)
    flipped = []
    for i, (hc, hs) in enumerate(zip(turns_c, turns_raw)):
        hc = np.asarray(hc, float)
        centred = hc - hc.mean(axis=0)
        # C = Σ h̃ h̃ᵀ = P diag(λ) Pᵀ (eq. 17); eigh gives λ ascending, so P3 is column 0
        lam, p = np.linalg.eigh(centred.T @ centred)
        p3 = p[:, 0]
        v_pca[:, i] = p3
        contribution[i] = lam[0] / lam.sum() if lam.sum() > 0 else 1.0
        hs = np.asarray(hs, float)
        axial_raw = float(np.mean(hs[:, i]))
        share[i] = abs(axial_raw) / float(np.mean(np.linalg.norm(hs, axis=1)))
        flip = False
        if sign_correction:
            # 3.2.1: ĥ_b,i = V̂_iᵀ ĥ_c must have the sign of h_s,i
            flip = float(np.mean(hc @ p3)) * axial_raw < 0
        v[:, i] = -p3 if flip else p3
        flipped.append(flip)
    order: list[int] = []
    if orth_correction:
        v, order = orthogonality_correction(v, contribution)
    return PcaAxes(v, v_pca, contribution, flipped, share, order)


def _equivalent_frame(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Û, d̂) of eq. 12-14 from E = Q = MᵀM (the fitted quadric of the correction matrix)."""
    d_e, u_e = np.linalg.eigh(q)                      # E = U_E D_E U_Eᵀ (eq. 12)
    if np.linalg.det(u_e) < 0:
        u_e[:, 2] = -u_e[:, 2]                        # both signs are eigenvectors: keep det Û = +1
    return u_e, 1.0 / np.sqrt(d_e)                   # Û = U_E (eq. 13), d̂ = 1/√d_E (eq. 14)


def _check_turns(rotations: Sequence[np.ndarray], name: str) -> list[np.ndarray]:
    if len(rotations) != 3:
        raise DataError(f"{name}: two-step needs three single-axis turns (about x, y, z), got {len(rotations)}")
    turns = [finite_rows(t, f"{name}: turn about {_AXIS[i]}") for i, t in enumerate(rotations)]
    for i, t in enumerate(turns):
        if t.shape[0] < MIN_TURN_SAMPLES:
            raise CalibrationRefused(f"{name}: the turn about {_AXIS[i]} has {t.shape[0]} samples; PCA needs at "
                                     f"least {MIN_TURN_SAMPLES} spread over the turn")
    return turns


def fit_two_step_full(rotations: Sequence[np.ndarray], *, extra_nT: np.ndarray | None = None,
                      total_nT: float | None = None, sign_correction: bool = True, orth_correction: bool = True,
                      name: str = "s1") -> TwoStepFit:
    """[TwoStep]: step 1 (ellipsoid) on every sample, step 2 (PCA) on the three turns.

    rotations: three (N_i, 3) raw arrays, turns about the body x, y and z axes, each made with the
      field well off the turn plane (|h_s,i| ≫ 0: [TwoStep] section 3.2.1).
    extra_nT: (K, 3) further raw samples for step 1 only (e.g. tilted sweeps).
    total_nT: the total field (scales the result to nT; [TwoStep] leaves it free, heading does not need it).
    """
    turns = _check_turns(rotations, name)
    step1 = np.concatenate(turns + ([finite_rows(extra_nT, f"{name}: extra_nT")] if extra_nT is not None else []))
    # the white-noise errors: step 1's rows are turns grouped by axis, not in time order, so stretches of them are
    # no stretches of time (misfit.add_time_spread)
    fit = fit_ellipsoid(step1, total_nT, name=name, errors="white")
    ell = fit.calibration
    q = ell.matrix.T @ ell.matrix                     # E = M⁻ᵀ M⁻¹ of [TwoStep] (eq. 10), scaled to |ĥ| = F
    u, d = _equivalent_frame(q)
    b = ell.offset_nT
    equiv = (u / d).T                                 # D̂⁻¹ Ûᵀ
    turns_c = [(t - b) @ equiv.T for t in turns]      # ĥ_c = D̂⁻¹ Ûᵀ (h_s − b̂)  (eq. 15)
    # the sign test reads each turn's axial component about the fitted offset: about the origin a hard-iron
    # offset larger than the field would decide it
    pca = pca_axes(turns_c, [t - b for t in turns], sign_correction=sign_correction, orth_correction=orth_correction)
    # ĥ_b = V̂⁻¹ ĥ_c  (eq. 4): a solve, V̂ need not be orthogonal without the correction
    matrix = np.linalg.solve(pca.v, equiv)
    # the ellipsoid's offset errors carry over; the matrix's, turned into the body frame, to first order
    rot = matrix @ np.linalg.solve(ell.matrix, np.eye(3))
    m_se = np.sqrt((rot ** 2) @ (ell.matrix_se ** 2))
    params = {
        "offset_nT": named(b, ell.offset_se_nT, "nT"),
        "equivalent_semi_axes": named(d, None, "", note="004 eq. 14: d of D (per unit field)"),
        "equivalent_rotation_U": named(u, None, "", note="004 eq. 13"),
        "equivalent_misalignment_V": named(pca.v, None, "",
                                           note="004 eq. 16-18: columns are the body axes in the equivalent frame"),
        "pca_variance_contribution": named(pca.contribution, None, "", names=["x", "y", "z"],
                                           note="lambda3 / sum(lambda) of each turn: lower is a cleaner turn"),
        "pca_sign_flipped": [bool(f) for f in pca.flipped],
        "pca_sign_share": named(pca.sign_share, None, "", names=["x", "y", "z"],
                                note="|mean axial raw component| / |h_s| of each turn: the sign assumption's margin"),
        "v_non_orthogonality_deg": named(
            PcaAxes(pca.v_pca, pca.v_pca, pca.contribution, [], pca.sign_share).non_orthogonality_deg, None, "deg",
            note="of the PCA columns before the orthogonality correction"),
        "sign_correction": bool(sign_correction),
        "orth_correction": bool(orth_correction),
        "residual_rms_nT": named(fit.residual_rms_nT, None, "nT"),
        "condition": named(fit.condition, None, ""),
        "samples": named(step1.shape[0], None, ""),
    }
    weak = [_AXIS[i] for i in range(3) if pca.sign_share[i] < SIGN_MIN_SHARE]
    if weak and sign_correction:
        params["sign_warning"] = (f"turn(s) about {', '.join(weak)}: the field lies nearly in the turn plane, so "
                                  f"the sign of the axial component is not reliable (004 3.2.1: make the turn with "
                                  f"the field close to the turn axis)")
    if not fit.total_known:
        params["total_nT_assumed"] = ell.params.get("total_nT_assumed")
    cal = ProbeCalibration(name, b, matrix, ell.offset_se_nT, m_se, params)
    if not cal.is_finite():
        raise CalibrationRefused(f"{name}: the two-step calibration produced non-finite parameters")
    return TwoStepFit(cal, u, d, b, pca, equiv)


def fit_two_step(rotations: Sequence[np.ndarray], *, extra_nT: np.ndarray | None = None,
                 total_nT: float | None = None, sign_correction: bool = True, orth_correction: bool = True,
                 name: str = "s1") -> ProbeCalibration:
    """`--method two-step`: the ProbeCalibration of `fit_two_step_full` (V̂ is in its params)."""
    return fit_two_step_full(rotations, extra_nT=extra_nT, total_nT=total_nT, sign_correction=sign_correction,
                             orth_correction=orth_correction, name=name).calibration


def align_pca(probes: Sequence[ProbeCalibration], field_nT: np.ndarray, turn: np.ndarray, *,
              sign_correction: bool = True, orth_correction: bool = True) -> list[ProbeCalibration]:
    """`--align pca` ([TwoStep] section 3.2): turn every calibrated probe onto the platform frame that three
    single-axis turns of the platform define.

    probes: each probe's calibration in its own orthogonal frame; field_nT: (N, P, 3) raw;
    turn: (N,) 0, 1, 2 for samples of the turns about the platform x, y, z (anything else: not used).
    Probe k becomes M'_k = V̂_kᵀ M_k (V̂_k: the platform axes seen in probe k's corrected frame).
    """
    f = np.asarray(field_nT, float)
    turn = np.asarray(turn)
    if f.ndim != 3 or f.shape[1] != len(probes) or f.shape[2] != 3:
        raise DataError(f"field_nT: expected shape (N, {len(probes)}, 3), got {f.shape}")
    if turn.shape != (f.shape[0],):
        raise DataError(f"turn: expected {f.shape[0]} labels, got shape {turn.shape}")
    out = []
    for k, p in enumerate(probes):
        raw_turns = []
        for i in range(3):
            rows = f[turn == i, k]
            rows = rows[np.isfinite(rows).all(axis=1)]
            if rows.shape[0] < MIN_TURN_SAMPLES:
                raise CalibrationRefused(f"{p.name}: align pca needs a turn about the platform {_AXIS[i]} axis "
                                         f"(turn = {i}) with at least {MIN_TURN_SAMPLES} samples, got {rows.shape[0]}")
            raw_turns.append(rows)
        corrected = [p.apply(r) for r in raw_turns]
        ax = pca_axes(corrected, raw_turns, sign_correction=sign_correction, orth_correction=orth_correction)
        # platform coordinates = V̂⁻¹ (probe's corrected frame); V̂ orthogonal after the correction
        rot = np.linalg.solve(ax.v, np.eye(3))
        out.append(p.rotated(rot, misalign_pca={
            "value": ax.v.tolist(), "se": None, "unit": "",
            "note": "004 3.2: columns are the platform axes in the probe's corrected frame",
            "variance_contribution": ax.contribution.tolist(), "sign_flipped": [bool(x) for x in ax.flipped]}))
    return out
