"""Drift: slow change of the probe offsets, or of the ambient field, over time.

    raw_corrected_a = raw_a - sum_j d_aj p_j(t)              per probe and axis (offset drift)
    F(t)            = F_reference + sum_j f_j p_j(t)         shared, only without a measured ref_total

with p_1 = h, p_2 = h^2 - mean(h^2), h = (t - t_mid) / 3600 in hours: a smooth function of time.
Parameters: nT/h and nT/h^2 per probe and axis; an ambient drift (nT/h, nT/h^2) when the total
field comes from the configuration or is estimated (a measured ref_total already follows it).
"""

from __future__ import annotations

import numpy as np

from drivers.errors import ConfigError

from .base import AXES, EffectData, EffectTerm, ProbeView, axis_columns


def _basis(data: EffectData, degree: int) -> np.ndarray:
    """(N, degree) centred powers of time in hours."""
    t = data.t_s
    h = (t - 0.5 * (t[0] + t[-1])) / 3600.0
    cols = [h]
    for d in range(2, degree + 1):
        p = h ** d
        cols.append(p - p.mean())
    return np.stack(cols, axis=1)


_UNITS = {1: "nT/h", 2: "nT/h2", 3: "nT/h3"}


class Drift(EffectTerm):
    """Offset drift per probe and axis, plus ambient drift without a scalar reference."""

    name = "drift"
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

    def columns(self, view: ProbeView) -> np.ndarray:
        b = _basis(view.data, self.degree)
        return np.concatenate([axis_columns(np.repeat(b[:, d:d + 1], 3, axis=1)) for d in range(self.degree)],
                              axis=2)

    def shared_names(self, data: EffectData) -> list[str]:
        if data.ref_total_nT is not None:
            return []
        return [f"ambient drift {_UNITS[d]}" for d in range(1, self.degree + 1)]

    def shared_scolumns(self, data: EffectData) -> np.ndarray | None:
        if data.ref_total_nT is not None:
            return None
        return _basis(data, self.degree)
