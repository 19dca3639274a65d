"""Platform: the Tolles-Lawson permanent and induced fields of the platform a probe sits on.

    corrected = v0 - p - A v0,      v0 = matrix (raw - offset - raw-frame effects)

p (nT, 3 per probe) is the platform's permanent field at the probe; A (3x3 per probe, dimensionless)
its field induced by the ambient field. (The eddy-current part of Tolles-Lawson is the `eddy` term.)
While the linear calibration is fitted to the same data, p and A cannot be told from the probe's
offset and matrix: the term is meant for data taken on the platform with a calibration from the lab
held fixed (`diagnose --calibration CAL.json`).

A platform's induced field is a small fraction of the ambient field (an aircraft's, 1e-4 to 1e-2 of it). With A = I
and |p| the total field the term fits any data exactly, noise included: it cancels the measured field and puts a
constant vector of the field's size in its place. On a real flight log whose held calibration was poor (27 % of the
field RMS) the fit went there (A's diagonal 0.95-0.99, a residual of 19 nT under a noise floor of 296 nT); an induced
matrix whose largest singular value reaches MAX_INDUCED is ruled out as no platform's.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .base import AXES, EffectTerm, ProbeView

#: the largest induced field, as a fraction of the ambient field, a platform's term may take (rules_out)
MAX_INDUCED = 0.5


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

    def rules_out(self, parameters: Sequence[Any]) -> str | None:
        """An induced matrix whose largest singular value reaches MAX_INDUCED: the term replaced the measured field
        (module docstring), not a platform's field beside it."""
        induced: dict[str, np.ndarray] = {}
        for p in parameters:
            if p.term == self.name and p.key[:1] == ("induced",):
                induced.setdefault(p.probe, np.zeros((3, 3)))[p.key[1], p.key[2]] = p.value
        for probe, a in induced.items():
            size = float(np.linalg.norm(a, 2))
            if not size < MAX_INDUCED:
                left = float(np.linalg.svd(np.eye(3) - a, compute_uv=False).min())
                return (f"{probe}'s induced field would be {size:.2f} of the ambient field (a platform's is a small "
                        f"fraction of it): the fit cancels the measured field (what is left of it along one "
                        f"direction: {left:.2g} of it) and puts a constant vector in its place, which fits any data")
        return None

    def param_names(self, view: ProbeView) -> list[str]:
        p = view.name
        return ([f"{p}.platform permanent {a} nT" for a in AXES]
                + [f"{p}.platform induced[{a}{b}]" for a in AXES for b in AXES])

    def param_keys(self, view: ProbeView) -> list[tuple]:
        return [("permanent", a) for a in range(3)] + [("induced", a, b) for a in range(3) for b in range(3)]

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
