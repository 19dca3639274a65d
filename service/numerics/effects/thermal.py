"""Thermal lag: offset and scale follow the core's temperature, which lags the logged one.

    T_c = first-order low-pass of the logged temperature T with time constant tau (dT_c/dt = (T - T_c) / tau)
    raw = u (1 + 1e-6 kappa_a dT_c) + offset + beta_a dT_c,   dT_c = T_c - T_ref, T_ref = mean(T) of the fit
    => raw_corrected_a = raw_a - beta_a dT_c - 1e-6 kappa_a dT_c (raw_a - offset_a)

A sensor's temperature is logged at its housing or board; the core heats and cools later. The
`temperature` term, fitted to such data, sees the right coefficient delayed and leaves the delay in
the residual. Parameters per probe: beta in nT/degC and kappa in ppm/degC per axis, and tau in s.
Non-linear in tau: tau is fitted with the rest, its standard error from the same normal equations.
It starts at the best of TAU_STEPS time constants from zero to a third of the record (tau_grid), each with its
coefficients and the offsets solved against the residual of the model without the term (TAU_START_S without
one): a start, not a choice, since the fit moves tau on and counts it among the parameters. From a few fixed
taus (0, 10, 30 ... 600 s) with the offset coefficients alone, a 4000-sample record whose core lags by 5 s or
not at all stopped unconverged, or at a wrong tau, in 11 of 24 (12 seeds); tau cannot go below zero (floors).
"""

from __future__ import annotations

import numpy as np

from .base import AXES, EffectData, EffectTerm, ProbeView
from .temperature import reference_temperature, temperature_columns, why_no_temperature

TAU_START_S = 60.0
TAU_STEPS = 16


def tau_grid(dt_s: float, duration_s: float) -> np.ndarray:
    """Zero and TAU_STEPS - 1 time constants spaced evenly in log from two samples to a third of the record.

    >>> tau_grid(0.01, 40.0)[[0, 1, -1]].round(3).tolist()
    [0.0, 0.02, 13.333]
    """
    top = max(duration_s / 3.0, 4.0 * dt_s)
    return np.concatenate([[0.0], np.geomspace(2.0 * dt_s, top, TAU_STEPS - 1)])


def low_pass(t_s: np.ndarray, values: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order low-pass of values(t) with time constant tau, starting at values[0] (a core in balance
    with its housing when the record starts). On the median sample interval (samples in gaps are
    interpolated, then read back at t): one lfilter pass, no loop over samples."""
    if tau_s <= 0:
        return values.copy()
    from scipy.signal import lfilter                    # here, not at import (a command's start)

    dt = float(np.median(np.diff(t_s)))
    grid = np.arange(t_s[0], t_s[-1] + 0.5 * dt, dt)
    uniform = grid.size == t_s.size and np.allclose(grid, t_s, rtol=0, atol=0.05 * dt)
    x = values if uniform else np.interp(grid, t_s, values)
    a = np.exp(-dt / tau_s)
    # the trapezoidal input of a ramp between samples: y[n] = a y[n-1] + (1 - a) (x[n] + x[n-1]) / 2
    y, _ = lfilter([0.5 * (1 - a), 0.5 * (1 - a)], [1.0, -a], x, zi=[a * x[0] + 0.5 * (1 - a) * x[0]])
    return y if uniform else np.interp(t_s, grid, y)


class ThermalLag(EffectTerm):
    """Temperature coefficients (nT/degC, ppm/degC per axis) on a core temperature lagging by tau (s)."""

    name = "thermal"
    title = "Thermal lag"
    physical = "offset and scale follow the core temperature, which lags the logged one by a time constant"
    linear = False
    needs_residual = True           # for tau's start only
    nests = ("temperature",)        # tau = 0 is the temperature term: thermal must beat it to count
    floors = {6: (0.0, "a core cannot lag its housing by less than nothing; at 0 s the term is the temperature "
                       "term")}
    separation = {
        "temperature": "heat and cool faster than the core can follow (a step, or swings of a few minutes): "
                       "a lag delays the response, a plain coefficient does not",
        "drift": "let the temperature go up and down instead of a steady ramp: a lagged temperature follows "
                 "it, a drift follows time",
    }

    def why_unavailable(self, data: EffectData) -> str | None:
        return why_no_temperature(data)

    def param_names(self, view: ProbeView) -> list[str]:
        p = view.name
        return [f"{p}.{a} nT/degC" for a in AXES] + [f"{p}.{a} ppm/degC" for a in AXES] + [f"{p}.thermal lag s"]

    def start_values(self, view: ProbeView) -> np.ndarray:
        start = np.zeros(7)
        start[6] = self._tau_start(view)
        return start

    def _tau_start(self, view: ProbeView) -> float:
        key = "thermal:tau_start"
        if key not in view.cache:
            r, g = view.model_residual, view.model_gain
            best = TAU_START_S
            if r is not None and g is not None:
                ok = np.isfinite(r) & np.all(np.isfinite(g), axis=1)
                taus = tau_grid(view.data.dt_s, view.data.duration_s)
                # the linear part moves with the coefficients: its offsets (g) and matrix (n_i v_j) solved beside them
                v = view.corrected_nT[ok]
                n = g[ok] @ np.linalg.inv(view.matrix)
                linear = np.concatenate([g[ok], (n[:, :, None] * v[:, None, :]).reshape(-1, 9)], axis=1)
                rss = []
                for tau in taus:                           # each one small least-squares solve of 18 columns
                    cols = temperature_columns(self._core(view, tau), view.centred_nT)
                    x = np.concatenate([np.einsum("na,nac->nc", g[ok], cols[ok]), linear], axis=1)
                    coef, *_ = np.linalg.lstsq(x, r[ok], rcond=None)
                    rss.append(float(np.sum((r[ok] - x @ coef) ** 2)))
                best = float(taus[int(np.argmin(rss))])
            view.cache[key] = best
        return view.cache[key]

    def reference_C(self, view: ProbeView) -> float:
        return reference_temperature(view, "ref:thermal_C")

    def constants(self, view: ProbeView) -> dict[str, tuple[float, str]]:
        return {f"{view.name} reference temperature": (self.reference_C(view), "degC")}

    def _core(self, view: ProbeView, tau: float) -> np.ndarray:
        """dT_c (N,) at tau, cached for the last few values of tau."""
        tau = max(float(tau), 0.0)
        cache = view.cache.setdefault("thermal:core", {})
        if tau not in cache:
            if len(cache) > 6:
                cache.pop(next(iter(cache)))
            cache[tau] = low_pass(view.data.t_s, view.data.temperature(view.k), tau) - self.reference_C(view)
        return cache[tau]

    def _parts(self, view: ProbeView, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3, 6) columns of beta and kappa at theta's tau, and (N, 3) their d/d dT_c."""
        u = view.centred_nT
        return temperature_columns(self._core(view, theta[6]), u), theta[:3] + 1e-6 * theta[3:6] * u

    def correction(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        cols, _ = self._parts(view, theta)
        return cols @ theta[:6]

    def jacobian(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        cols, per_degree = self._parts(view, theta)
        tau = max(float(theta[6]), 1e-3)
        h = 0.01 * tau
        d_core_d_tau = (self._core(view, tau + h) - self._core(view, tau - h)) / (2 * h)
        return np.concatenate([cols, (per_degree * d_core_d_tau[:, None])[:, :, None]], axis=2)
