"""Lag: a probe sampled at a different instant than the reference probe (probe 1).

    raw_k(t) = true_k(t + tau_k)   =>   raw_corrected_k(t) = raw_k(t) - [s_k(t) - s_k(t - tau_k)]

with s_k the Savitzky-Golay smoothed output, interpolated between samples by a cubic Hermite spline
through s and its derivative (linear interpolation would leave dt^2/8 d2s/dt2, a few tenths of a
nT at 100 Hz and 30 deg/s) (the shift moves the motion, never the noise, so a
half-sample shift cannot pass for a gain by smoothing noise). Non-linear in tau: the fitter uses
d/dtau = ds/dt (t - tau). Parameters: one time offset per probe after the first, in seconds,
relative to probe 1. A time shift keeps |B| in a uniform field, so a lag shows only against
another probe; probe 1's own lag against the acquisition clock shows only against a vector
reference (ref_x, ref_y, ref_z columns), and then every probe has one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.interpolate import CubicHermiteSpline

from .base import EffectData, EffectTerm, ProbeView


def shifted(values: np.ndarray, t_s: np.ndarray, shift_s: float) -> np.ndarray:
    """(N, c) values at t - shift_s by linear interpolation (held at the ends).

    >>> t = np.arange(5.0)
    >>> shifted(np.stack([t, 2 * t], axis=1), t, 0.5)[1:3].tolist()
    [[0.5, 1.0], [1.5, 3.0]]
    """
    tq = t_s - shift_s
    return np.stack([np.interp(tq, t_s, values[:, c]) for c in range(values.shape[1])], axis=1)


class Lag(EffectTerm):
    """A sampling-time offset (s) of each probe relative to probe 1."""

    name = "lag"
    title = "Lag"
    physical = "a probe sampled at a different instant than the reference probe"
    linear = False
    separation = {
        "eddy": "rotate at two different rates (or one much faster): a lag only delays the signal and keeps "
                "|B|, an eddy field adds to it and grows with the rate",
    }

    def why_unavailable(self, data: EffectData) -> str | None:
        if data.n_probes < 2 and data.ref_vector_nT is None:
            return ("a lag keeps |B| and shows only against another probe: it needs an array "
                    "(or a vector reference)")
        return None

    def param_names(self, view: ProbeView) -> list[str]:
        if view.k == 0 and view.data.ref_vector_nT is None:
            return []
        return [f"{view.name}.lag s"]

    def _spline(self, view: ProbeView) -> CubicHermiteSpline:
        key = "lag:spline"
        if key not in view.cache:
            from scipy.interpolate import CubicHermiteSpline      # here, not at import (a command's start)

            view.cache[key] = CubicHermiteSpline(view.data.t_s, view.data.smooth(view.k),
                                                 view.data.rate(view.k), axis=0, extrapolate=False)
        return view.cache[key]

    def _at(self, view: ProbeView, tau: float, nu: int) -> np.ndarray:
        """s (nu=0) or ds/dt (nu=1) at t - tau, held at the ends."""
        t = view.data.t_s
        tq = np.clip(t - tau, t[0], t[-1])
        return self._spline(view)(tq, nu)

    def correction(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        if theta.size == 0 or theta[0] == 0.0:
            return np.zeros((view.data.n_samples, 3))
        # c(tau) = s(t) - s(t - tau)
        return view.data.smooth(view.k) - self._at(view, float(theta[0]), 0)

    def jacobian(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        if theta.size == 0:
            return np.zeros((view.data.n_samples, 3, 0))
        # dc/dtau = ds/dt (t - tau)
        if theta[0] == 0.0:
            return view.data.rate(view.k)[:, :, None]
        return self._at(view, float(theta[0]), 1)[:, :, None]
