"""Column: the field of something the recording logs, coupled into each probe axis.

    raw_corrected_a = raw_a - sum_c (alpha_ca x_c + rho_ca dx_c/dt)

x_c: every auxiliary column of the data that is an observable and changes (extra CSV columns, MCAP
channels: a heater or motor current, a battery voltage, a reference magnetometer's components), each
centred on its mean. alpha in nT per unit of the column and rho in nT per (unit/s) per probe and axis:
a current beside a probe adds a field fixed in the probe's frame, and switching it induces one that
follows its rate. Columns with gaps (NaN) are interpolated in time.
"""

from __future__ import annotations

import numpy as np

from .base import AXES, EffectData, EffectTerm, ProbeView, axis_columns


def column_values(data: EffectData, name: str) -> np.ndarray | None:
    """(N,) a logged column's values, gaps (NaN) filled by interpolation in time; None with fewer than two values."""
    v = np.asarray(data.extras[name], dtype=np.float64)
    ok = np.isfinite(v)
    if ok.sum() < 2:
        return None
    return v if ok.all() else np.interp(data.t_s, data.t_s[ok], v[ok])


def usable_columns(data: EffectData) -> dict[str, np.ndarray]:
    """Observable extra columns that change, gaps filled by interpolation (column_values), centred on their means."""
    out = {}
    for name in data.observables():
        v = column_values(data, name)
        if v is None or float(np.ptp(v)) <= 1e-12 * max(1.0, float(np.max(np.abs(v)))):
            continue
        out[name] = v - v.mean()
    return out


class Column(EffectTerm):
    """Per probe and axis: nT per unit of each logged column, and nT per unit/s of its rate."""

    name = "column"
    title = "Column"
    physical = "the field of something the recording logs (a current, a voltage, a reference), per axis"

    def why_unavailable(self, data: EffectData) -> str | None:
        if usable_columns(data):
            return None
        logged = sorted(data.observables())
        if logged:                            # logged, but constant: say which, never ask to log what is logged
            return (f"the auxiliary column(s) the data carry ({', '.join(logged)}) do not change over the record: "
                    f"nothing to fit against (a current that reads 0 throughout is not measured: check its sensor)")
        reference = "" if data.ref_total_nT is not None else ", a reference magnetometer"   # never what is logged
        return ("the data carry no auxiliary column that changes (extra CSV columns, MCAP channels: log the "
                f"heater or motor currents{reference})")

    def _cols(self, view: ProbeView) -> dict[str, np.ndarray]:
        key = "column:values"
        if key not in view.cache:
            view.cache[key] = usable_columns(view.data)
        return view.cache[key]

    def param_names(self, view: ProbeView) -> list[str]:
        # the rate's coefficient is in nT per (unit of the column per second): "nT per (battery_current_a/s)"
        return [f"{view.name}.{a} nT per {f'({c}/s)' if rate else c}" for c in self._cols(view) for rate in (False, True)
                for a in AXES]

    def columns(self, view: ProbeView) -> np.ndarray:
        t = view.data.t_s
        parts = []
        for v in self._cols(view).values():
            for x in (v, np.gradient(v, t)):
                parts.append(axis_columns(np.repeat(x[:, None], 3, axis=1)))
        return np.concatenate(parts, axis=2)
