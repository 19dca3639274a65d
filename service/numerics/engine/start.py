"""Starting values of the fit engine: an ellipsoid per probe, aligned to probe 1, and the channel weights.
"""

from __future__ import annotations

import warnings

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.quadric import algebraic_ellipsoid
from fluxcal.service.numerics.effects.base import EffectData, Model
from fluxcal.service.numerics.noise import channel_noise
from fluxcal.service.numerics.usable import refuse_stuck

from .linear import LinearCalibration
from .problem import Problem

#: floor of the per-channel noise used as weight, nT (the ADC step of the unit)
NOISE_FLOOR_NT = 1e-3


def initial_linear(data: EffectData, reference_nT: np.ndarray | float | None) -> LinearCalibration:
    """A starting linear calibration: an ellipsoid per probe (fluxcal.service.numerics.calib.ellipsoid), then each
    probe regressed onto probe 1 ([TwoFluxgate] eq. 10-16) for the alignment. Gauss-Newton refines it."""
    f_total = None if reference_nT is None else float(np.median(reference_nT))
    refuse_stuck(data.raw_nT, data.probe_names)
    offs, mats = [], []
    for k in range(data.n_probes):
        raw = data.raw_nT[:, k, :]
        o = m = None
        if reference_nT is not None:
            try:
                # refuses planar data (a single-axis turn): then our own start, which GN refines
                with warnings.catch_warnings(), np.errstate(all="ignore"):
                    warnings.simplefilter("ignore")
                    res = fit_ellipsoid(raw, reference_nT, name=data.probe_names[k], errors="white")
                cal = getattr(res, "calibration", res)
                o = np.asarray(cal.offset_nT, dtype=np.float64).reshape(3)
                m = np.asarray(cal.matrix, dtype=np.float64).reshape(3, 3)
            except (CalibrationRefused, np.linalg.LinAlgError):   # planar data: our own start, GN refines it
                o = m = None
        if o is None or not np.all(np.isfinite(m)):
            o, m = algebraic_ellipsoid(raw, f_total)
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
