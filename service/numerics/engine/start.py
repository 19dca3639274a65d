"""Starting values of the fit engine: an ellipsoid per probe, aligned to probe 1, and the channel weights.
"""

from __future__ import annotations

import warnings

import numpy as np

from service.numerics.effects.base import EffectData, Model

from .linear import LinearCalibration
from .problem import Problem, channel_noise

#: floor of the per-channel noise used as weight, nT (the ADC step of the unit)
NOISE_FLOOR_NT = 1e-3


def _algebraic_ellipsoid(raw: np.ndarray, total_nT: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Offset and symmetric matrix from a least-squares quadric through the points (a start only).

    x^T Q x + b^T x = 1 (scaled coordinates); o = -Q^-1 b / 2; M = F sqrtm(Q / (1 + o^T Q o))."""
    scale = float(np.median(np.linalg.norm(raw - raw.mean(0), axis=1))) or 1.0
    c = raw.mean(0)
    x = (raw - c) / scale
    design = np.column_stack([x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2, 2 * x[:, 0] * x[:, 1],
                              2 * x[:, 0] * x[:, 2], 2 * x[:, 1] * x[:, 2], x])
    sol, *_ = np.linalg.lstsq(design, np.ones(x.shape[0]), rcond=None)
    q = np.array([[sol[0], sol[3], sol[4]], [sol[3], sol[1], sol[5]], [sol[4], sol[5], sol[2]]])
    ok = bool(np.all(np.linalg.eigvalsh(q) > 0))
    if ok:
        o = -0.5 * np.linalg.solve(q, sol[6:9])
        q = q / (1.0 + o @ q @ o)
        w, v = np.linalg.eigh(q)
        ok = bool(np.all(w > 0))
    if not ok:
        # turns about one axis (or too few directions): a plain centre and unit shape as the start
        o = np.zeros(3)
        m = np.eye(3)
    else:
        m = (v * np.sqrt(w)) @ v.T
    offset = c + scale * o
    mags = np.linalg.norm((raw - offset) @ m.T, axis=1)
    target = total_nT if total_nT is not None else float(np.median(np.linalg.norm(raw - offset, axis=1)))
    return offset, m * (target / float(np.median(mags)))


def initial_linear(data: EffectData, reference_nT: np.ndarray | float | None) -> LinearCalibration:
    """A starting linear calibration: an ellipsoid per probe (service.numerics.calib when present), then each
    probe regressed onto probe 1 (paper 000 eq. 10-16) for the alignment. Gauss-Newton refines it."""
    f_total = None if reference_nT is None else float(np.median(reference_nT))
    offs, mats = [], []
    try:
        from service.numerics.calib.ellipsoid import fit_ellipsoid  # the calibration core, when it exists
    except Exception:                                          # noqa: BLE001 - optional collaborator
        fit_ellipsoid = None
    for k in range(data.n_probes):
        raw = data.raw_nT[:, k, :]
        o = m = None
        if fit_ellipsoid is not None and reference_nT is not None:
            try:
                # refuses planar data (a single-axis turn): then our own start, which GN refines
                with warnings.catch_warnings(), np.errstate(all="ignore"):
                    warnings.simplefilter("ignore")
                    res = fit_ellipsoid(raw, reference_nT, name=data.probe_names[k])
                cal = getattr(res, "calibration", res)
                o = np.asarray(cal.offset_nT, dtype=np.float64).reshape(3)
                m = np.asarray(cal.matrix, dtype=np.float64).reshape(3, 3)
            except Exception:                                  # noqa: BLE001 - fall back to our own start
                o = m = None
        if o is None or not np.all(np.isfinite(m)):
            o, m = _algebraic_ellipsoid(raw, f_total)
        offs.append(o)
        mats.append(m)
    cal = LinearCalibration(np.array(offs), np.array(mats))
    vref = data.ref_vector_nT
    if data.n_probes > 1 or vref is not None:
        # align to the reference vector when there is one, else to probe 1
        v1 = vref if vref is not None else (data.raw_nT[:, 0, :] - cal.offset_nT[0]) @ cal.matrix[0].T
        for k in range(0 if vref is not None else 1, data.n_probes):
            vk = (data.raw_nT[:, k, :] - cal.offset_nT[k]) @ cal.matrix[k].T
            design = np.column_stack([vk, np.ones(vk.shape[0])])
            # v1 = A vk + b: regression of probe k onto probe 1
            sol, *_ = np.linalg.lstsq(design, v1, rcond=None)
            a = sol[:3].T
            cal.matrix[k] = a @ cal.matrix[k]
            # fold b into the offset: A M (raw - o) + b = A M (raw - o + (A M)^-1 b)
            cal.offset_nT[k] = cal.offset_nT[k] - np.linalg.solve(cal.matrix[k], sol[3])
    return cal


def start_weights(data: EffectData, linear: LinearCalibration, reference: np.ndarray) -> np.ndarray:
    """1 / noise per residual channel, the noise estimated at the start (model-independent)."""
    pr = Problem(data, Model([]), linear, reference, n_blocks=1)
    ev = pr.evaluate(pr.start_state(linear))
    noise = channel_noise(ev.channel_matrix())
    noise = np.where(np.isfinite(noise), np.maximum(noise, NOISE_FLOOR_NT), 1.0)
    return 1.0 / noise
