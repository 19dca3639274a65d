"""Temperature: a probe's offset and scale factor follow its temperature.

    raw = u (1 + 1e-6 kappa_a dT) + offset + beta_a dT,   dT = T - T_ref, T_ref = mean(T) of the fit
    => raw_corrected_a = raw_a - beta_a dT - 1e-6 kappa_a dT (raw_a - offset_a)

Parameters per probe and axis: beta in nT/degC (offset) and kappa in ppm/degC (scale). The
reference temperature is the mean of the data; another reference only moves the linear part.
"""

from __future__ import annotations

import numpy as np

from .base import AXES, EffectData, EffectTerm, ProbeView, axis_columns


def why_no_temperature(data: EffectData) -> str | None:
    """Why these data cannot show a temperature effect, or None."""
    if not data.has_temperature():
        return "the data have no probe temperature (s<k>_temp columns)"
    if float(np.ptp(data.temperature(0))) < 1e-6:
        return "the probe temperature does not change in these data"
    return None


def borrowed_from(temp_C: np.ndarray, probe_names: list[str], k: int) -> str | None:
    """Whose temperature probe k takes (EffectData.temperature: the mean of the probes with one of their own; temp_C
    (N, P)), or None where it has its own."""
    own = [j for j in range(len(probe_names)) if np.isfinite(temp_C[:, j]).sum() >= 2]
    return None if k in own or not own else ", ".join(probe_names[j] for j in own)


def borrowed_notes(temp_C: np.ndarray, probe_names: list[str]) -> list[str]:
    """A probe without a temperature of its own takes the others' mean in every temperature term: said so by every
    command that fits one (diagnose always; fit with a temperature term, which said nothing and fitted s1's
    coefficient on s2's temperature as if it were s1's)."""
    notes = []
    for k, n in enumerate(probe_names):
        whose = borrowed_from(temp_C, probe_names, k)
        if whose is not None:
            notes.append(f"{n} has no temperature of its own: the temperature terms take the mean of {whose}'s "
                         f"(borrowed); a coefficient fitted for {n} is a coefficient on "
                         f"{'their' if ', ' in whose else 'its'} temperature")
    return notes


def reference_temperature(view: ProbeView, key: str) -> float:
    """The temperature coefficients are centred on: the mean of the data fitted, kept in the view under `key`
    (a `ref:` key), so applying the calibration to other data uses the same reference."""
    if key not in view.cache:
        view.cache[key] = float(np.mean(view.data.temperature(view.k)))
    return view.cache[key]


def temperature_columns(d_temp: np.ndarray, centred_nT: np.ndarray) -> np.ndarray:
    """(N, 3, 6) regressors of the offset (beta, nT/degC) and scale (kappa, ppm/degC) coefficients per axis for
    a temperature difference d_temp (N,) and the linear transfer output u = raw - offset (N, 3)."""
    d = d_temp[:, None]
    offset_cols = axis_columns(np.broadcast_to(d, centred_nT.shape))     # beta: nT per degC
    scale_cols = axis_columns(1e-6 * d * centred_nT)                     # kappa: 1e-6 dT (raw - o) per ppm/degC
    return np.concatenate([offset_cols, scale_cols], axis=2)


class Temperature(EffectTerm):
    """Offset (nT/degC) and scale-factor (ppm/degC) temperature coefficients per probe and axis."""

    name = "temperature"
    per_sample = True
    title = "Temperature"
    physical = "offset and scale factor change with probe temperature"
    separation = {
        "drift": "let the temperature go up and down (heat and cool) instead of a steady ramp: "
                 "a drift follows time, a temperature coefficient follows temperature",
    }

    def why_unavailable(self, data: EffectData) -> str | None:
        return why_no_temperature(data)

    def param_names(self, view: ProbeView) -> list[str]:
        p = view.name
        return [f"{p}.{a} nT/degC" for a in AXES] + [f"{p}.{a} ppm/degC" for a in AXES]

    def reference_C(self, view: ProbeView) -> float:
        return reference_temperature(view, "ref:temperature_C")

    def constants(self, view: ProbeView) -> dict[str, tuple[float, str]]:
        return {f"{view.name} reference temperature": (self.reference_C(view), "degC")}

    def columns(self, view: ProbeView) -> np.ndarray:
        return temperature_columns(view.data.temperature(view.k) - self.reference_C(view), view.centred_nT)
