"""Ambient: the field at the site changing in time, common to all probes, measured by the other probes.

    |corrected_k| -> |corrected_k| - g_k m_k(t),    m_k = the others' scalar residual, averaged, smoothed

Without a reference magnetometer the total field a probe is compared with is a constant, so a change of
the ambient field (geomagnetic activity, traffic, a slow drift of the site) stays in every probe's
scalar residual, and no sensor term should take it. The other probes of the array saw the same change at
the same instants: their mean scalar residual, smoothed over SMOOTH_S, is probe k's reference for it. g_k
(dimensionless, 1 for a change common to all) is fitted per probe. Because m_k is made of the *other*
probes' data at the same instants, a held-out block is predicted from data the fit never saw, as with a
logged reference: a probe's own noise or wander, which the others do not share, gives no gain. Needs two
probes at least, and no scalar reference (ref_total follows the ambient field already).

Applied as a correction along each probe's field direction, in the corrected frame, so the scalar
channels change by g_k m_k and the differences between probes barely at all (a uniform change cancels).
"""

from __future__ import annotations

import numpy as np

from .base import EffectData, EffectTerm, ProbeView

SMOOTH_S = 5.0


class Ambient(EffectTerm):
    """One gain per probe on the other probes' smoothed scalar residual (a change of the field common to all)."""

    name = "ambient"
    title = "Ambient"
    physical = "the field at the site changing in time, common to all probes, measured by the other probes"
    frame = "corrected"
    linear = False                 # along the field direction, which moves while the fit runs
    needs_residual = True
    #: diagnose calls it significant only where the probes' residuals are mostly shared: two independent
    #: slow wanders (1/f noise) regressed on each other give spurious gains of a few percent
    needs_common_mode = True
    separation = {
        "drift": "log a reference magnetometer: an ambient change is common to all probes, an offset drift is "
                 "each probe's own",
    }

    def why_unavailable(self, data: EffectData) -> str | None:
        if data.ref_total_nT is not None:
            return "the scalar reference (ref_total) follows the ambient field already"
        if data.n_probes < 2:
            return "a change of the ambient field shows only against other probes: it needs an array (or log ref_total)"
        return None

    def param_names(self, view: ProbeView) -> list[str]:
        return [f"{view.name}.ambient gain"]

    def _others(self, view: ProbeView) -> np.ndarray:
        """m_k (N,): the mean scalar residual of the other probes, smoothed; 0 where unknown."""
        key = "ambient:others"
        if key not in view.cache:
            hints = view.cache.get("residuals:all")
            r = view.model_residual
            if hints is None or r is None:
                view.cache[key] = np.zeros(view.data.n_samples)
            else:
                others = [h for j, h in enumerate(hints) if j != view.k]
                stack = np.stack(others) if others else np.zeros((1, view.data.n_samples))
                seen = np.isfinite(stack)
                # the mean over the others that are known at each instant (rows off the fit are NaN: 0 there)
                m = np.where(seen, stack, 0.0).sum(0) / np.maximum(seen.sum(0), 1)
                w = max(1, int(round(SMOOTH_S / view.data.dt_s)))
                from scipy.ndimage import uniform_filter1d      # here, not at import (a command's start)

                view.cache[key] = uniform_filter1d(m, size=w, mode="nearest")
        return view.cache[key]

    def _direction(self, view: ProbeView, v0: np.ndarray | None) -> np.ndarray:
        v = view.corrected_nT if v0 is None else v0
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def correction(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        return theta[0] * self._others(view)[:, None] * self._direction(view, v0)

    def jacobian(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        return (self._others(view)[:, None] * self._direction(view, v0))[:, :, None]
