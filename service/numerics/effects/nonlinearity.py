"""Nonlinearity: per-axis transfer non-linearity of the probe.

    r_a = raw_a - offset_a = u_a + q_a u_a^2 + c_a u_a^3           (forward, per axis)
    raw_corrected_a = raw_a - (r_a - u_a(r_a))                     u solved exactly by Newton steps

Parameters per probe and axis: the quadratic coefficient q in 1/nT and the cubic c in 1/nT^2. The
inversion is exact (a first-order one, u = r - q r^2 - c r^3, would leave -2 q^2 u^3, which is
10 % of a typical c), so the fitted q and c are the physical ones. Non-linear in (q, c): the fitter
uses du/dq = -u^2 / D, du/dc = -u^3 / D, D = 1 + 2 q u + 3 c u^2.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .base import AXES, EffectTerm, ProbeView, axis_columns
from .span import ReadingSpan

#: the least slope dr/du = 1 + 2 q u + 3 c u^2 a sensor's transfer keeps over its readings (real fluxgates: within
#: 1e-3 of 1): below it the fitted q and c bend the transfer until it (nearly) folds back, no sensor's
MIN_SLOPE = 0.5


def invert(r: np.ndarray, q: np.ndarray, c: np.ndarray, iterations: int = 3) -> np.ndarray:
    """u with u + q u^2 + c u^3 = r, per axis (Newton from u = r, quadratic convergence: with |q r| and
    |c r^2| below 1e-2, three steps leave a relative error below 1e-12).

    >>> u = np.array([[50000.0, -30000.0, 1000.0]])
    >>> q, c = np.array([1e-7, -2e-7, 0.0]), np.array([2e-13, 1e-13, -3e-13])
    >>> bool(np.allclose(invert(u + q * u**2 + c * u**3, q, c), u, atol=1e-8))
    True
    """
    u = r.copy()
    for _ in range(iterations):
        f = u + q * u ** 2 + c * u ** 3 - r
        u = u - f / (1.0 + 2.0 * q * u + 3.0 * c * u ** 2)
    return u


class Nonlinearity(EffectTerm):
    """Quadratic (1/nT) and cubic (1/nT^2) transfer coefficients per probe and axis."""

    name = "nonlinearity"
    per_sample = True
    title = "Nonlinearity"
    physical = "per-axis transfer non-linearity"
    linear = False
    separation = {
        "crossfield": "vary the field magnitude (a scalar reference in a changing field, or coils): "
                      "a per-axis non-linearity follows each axis' own reading, a cross-field error the others'",
    }

    def param_names(self, view: ProbeView) -> list[str]:
        p = view.name
        return [f"{p}.{a} quadratic 1/nT" for a in AXES] + [f"{p}.{a} cubic 1/nT2" for a in AXES]

    def param_keys(self, view: ProbeView) -> list[tuple]:
        return [("quadratic", a) for a in range(3)] + [("cubic", a) for a in range(3)]

    def rules_out_over(self, parameters: Sequence[Any], span: ReadingSpan) -> str | None:
        """A transfer whose slope falls below MIN_SLOPE within the readings (a real log's compass held to a poor
        calibration: q = -2e-4 /nT over readings of +-20,000 nT, the response folded back on itself): the term bent
        itself to the data, it is not the sensor's. The slope is judged at the readings' ends and, for a cubic, at
        its turning point where that lies between them."""
        coef: dict[tuple[str, int], list[float]] = {}
        for p in parameters:
            if p.term == self.name and p.probe in span.probe_names and len(p.key) == 2:
                kind, axis = p.key
                coef.setdefault((p.probe, axis), [0.0, 0.0])[kind == "cubic"] = p.value
        for (probe, a), (q, c) in coef.items():
            k = span.probe_names.index(probe)
            lo, hi = float(span.low_nT[k, a]), float(span.high_nT[k, a])
            at = [lo, hi] + ([-q / (3 * c)] if c != 0 and lo < -q / (3 * c) < hi else [])
            slopes = [1 + 2 * q * u + 3 * c * u * u for u in at]
            worst = int(np.argmin(slopes))
            if slopes[worst] < MIN_SLOPE:
                how = "fold back" if slopes[worst] <= 0 else f"lose {1 - slopes[worst]:.0%} of its gain"
                return (f"{probe}'s {AXES[a]} transfer would {how} within its readings (slope {slopes[worst]:.2g} "
                        f"at {at[worst]:,.0f} nT about the offset; a sensor's stays near 1): the term bent itself "
                        f"to the data")
        return None

    def _u(self, view: ProbeView, theta: np.ndarray) -> np.ndarray:
        return invert(view.centred_nT, theta[:3], theta[3:])

    def correction(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        if not np.any(theta):
            return np.zeros((view.data.n_samples, 3))
        return view.centred_nT - self._u(view, theta)                   # r - u(r)

    def jacobian(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        u = self._u(view, theta) if np.any(theta) else view.centred_nT
        d = 1.0 + 2.0 * theta[:3] * u + 3.0 * theta[3:] * u ** 2
        # d(r - u)/dq = u^2 / D, d(r - u)/dc = u^3 / D
        return np.concatenate([axis_columns(u ** 2 / d), axis_columns(u ** 3 / d)], axis=2)
