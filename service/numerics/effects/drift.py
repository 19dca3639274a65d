"""Drift: slow change of the probe offsets, or of the ambient field, over time.

    raw_corrected_a = raw_a - sum_j d_aj p_j(t)              per probe and axis (offset drift)
    F(t)            = F_reference + sum_j f_j p_j(t)         shared, only without a measured ref_total

with p_1 = h, p_2 = h^2 - mean(h^2), h = (t - t_mid) / 3600 in hours: a smooth function of time.
Parameters: nT/h and nT/h^2 per probe and axis; an ambient drift (nT/h, nT/h^2) when the total
field comes from the configuration or is estimated (a measured ref_total already follows it).
"""

from __future__ import annotations

import numpy as np

from fluxcal.drivers.errors import ConfigError

from .base import AXES, EffectData, EffectTerm, ProbeView, axis_columns


def _basis(data: EffectData, degree: int, t_mid_s: float | None = None,
           means: list[float] | None = None) -> tuple[np.ndarray, float, list[float]]:
    """(N, degree) centred powers of time in hours, the centre time and the means removed (the
    references, so the same basis can be rebuilt on other data)."""
    t = data.t_s
    t_mid = 0.5 * (t[0] + t[-1]) if t_mid_s is None else t_mid_s
    h = (t - t_mid) / 3600.0
    cols = [h]
    used = []
    for d in range(2, degree + 1):
        p = h ** d
        m = float(p.mean()) if means is None else means[d - 2]
        used.append(m)
        cols.append(p - m)
    return np.stack(cols, axis=1), float(t_mid), used


_UNITS = {1: "nT/h", 2: "nT/h2", 3: "nT/h3"}


class Drift(EffectTerm):
    """Offset drift per probe and axis, plus ambient drift without a scalar reference."""

    name = "drift"
    per_sample = True
    title = "Drift"
    physical = "slow change of the ambient field or of the offsets over time"
    separation = {
        "temperature": "let the temperature go up and down (heat and cool) instead of a steady ramp: "
                       "a drift follows time, a temperature coefficient follows temperature",
        "hysteresis": "record longer: a drift changes smoothly, a perming step jumps once",
    }

    def __init__(self, *, degree: int = 2) -> None:
        if degree not in _UNITS:
            raise ConfigError(f"drift degree: {degree!r} is not allowed (allowed: 1, 2, 3)")
        self.degree = degree

    def settings(self) -> dict:
        return {"degree": self.degree}

    def param_names(self, view: ProbeView) -> list[str]:
        return [f"{view.name}.{a} drift {_UNITS[d]}" for d in range(1, self.degree + 1) for a in AXES]

    def constants(self, view: ProbeView) -> dict[str, tuple[float, str]]:
        self.columns(view)
        return {f"{view.name} drift time origin": (view.cache["ref:drift_t_mid_s"], "s")}

    def columns(self, view: ProbeView) -> np.ndarray:
        # the time origin and centring of the fitted data, kept in the view for other data
        b, t_mid, means = _basis(view.data, self.degree, view.cache.get("ref:drift_t_mid_s"),
                                 view.cache.get("ref:drift_means"))
        view.cache["ref:drift_t_mid_s"], view.cache["ref:drift_means"] = t_mid, means
        return np.concatenate([axis_columns(np.repeat(b[:, d:d + 1], 3, axis=1)) for d in range(self.degree)],
                              axis=2)

    def shared_names(self, data: EffectData) -> list[str]:
        if data.ref_total_nT is not None:
            return []
        return [f"ambient drift {_UNITS[d]}" for d in range(1, self.degree + 1)]

    def shared_scolumns(self, data: EffectData) -> np.ndarray | None:
        if data.ref_total_nT is not None:
            return None
        return _basis(data, self.degree)[0]
