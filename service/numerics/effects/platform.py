"""Platform: the Tolles-Lawson permanent and induced fields of the platform a probe sits on.

    corrected = v0 - p - A v0,      v0 = matrix (raw - offset - raw-frame effects)

p (nT, 3 per probe) is the platform's permanent field at the probe; A (3x3 per probe, dimensionless)
its field induced by the ambient field. (The eddy-current part of Tolles-Lawson is the `eddy` term.)
While the linear calibration is fitted to the same data, p and A cannot be told from the probe's
offset and matrix: the term is meant for data taken on the platform with a calibration from the lab
held fixed (`diagnose --calibration CAL.json`).
"""

from __future__ import annotations

import numpy as np

from .base import AXES, EffectTerm, ProbeView


class Platform(EffectTerm):
    """Permanent (nT) and induced (3x3) platform fields per probe, in the corrected frame."""

    name = "platform"
    title = "Platform"
    physical = "permanent and induced magnetic fields of the platform (Tolles-Lawson)"
    frame = "corrected"
    linear = False          # the induced part acts on v0, which moves while the fit runs
    separation = {
        "baseline": "hold a calibration made off the platform fixed (diagnose --calibration CAL.json): with the "
                    "probe calibration refitted, platform fields are indistinguishable from offsets and matrix",
    }

    def param_names(self, view: ProbeView) -> list[str]:
        p = view.name
        return ([f"{p}.platform permanent {a} nT" for a in AXES]
                + [f"{p}.platform induced[{a}{b}]" for a in AXES for b in AXES])

    def _columns(self, view: ProbeView, v0: np.ndarray | None) -> np.ndarray:
        v = view.corrected_nT if v0 is None else v0
        n = v.shape[0]
        cols = np.zeros((n, 3, 12))
        idx = np.arange(3)
        cols[:, idx, idx] = 1.0                                        # permanent: e_a
        for a in range(3):                                             # induced: A[a, b] v0_b on axis a
            cols[:, a, 3 + 3 * a:6 + 3 * a] = v
        return cols

    def correction(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        v = view.corrected_nT if v0 is None else v0
        return theta[:3] + v @ theta[3:].reshape(3, 3).T                  # p + A v0

    def jacobian(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        return self._columns(view, v0)
