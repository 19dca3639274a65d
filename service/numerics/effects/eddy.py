"""Eddy: fields induced in the probe (or the platform nearby) by a changing flux, proportional to dB/dt.

    raw = u + E du/dt + offset   =>   raw_corrected = raw - E d(raw)/dt

Parameters per probe: the 3x3 matrix E in seconds, in the probe's raw frame (for a probe with a
nearly orthogonal, unit-scale transfer this is the sensor-frame matrix). d(raw)/dt is a
Savitzky-Golay derivative of the data. Only the anisotropic part of E shows in a probe's own scalar
channel (an isotropic E acts like a time shift, which keeps |B|); arrays see all of it in the
differential channels, against probe 1.
"""

from __future__ import annotations

import numpy as np

from .base import AXES, EffectTerm, ProbeView


class Eddy(EffectTerm):
    """A 3x3 matrix (s) on dB/dt per probe."""

    name = "eddy"
    title = "Eddy"
    physical = "fields induced in the probe or platform by changing flux"
    separation = {
        "lag": "rotate at two different rates (or one much faster): a lag only delays the signal and keeps "
               "|B|, an eddy field adds to it and grows with the rate; turns about each axis also separate "
               "an anisotropic eddy matrix from a lag",
    }

    def param_names(self, view: ProbeView) -> list[str]:
        return [f"{view.name}.eddy[{a}{b}] s" for a in AXES for b in AXES]

    def columns(self, view: ProbeView) -> np.ndarray:
        rate = view.data.rate(view.k)                                  # (N, 3) nT/s
        n = rate.shape[0]
        cols = np.zeros((n, 3, 9))
        for a in range(3):                                             # E[a, b] acts on axis a with dB_b/dt
            cols[:, a, 3 * a:3 * a + 3] = rate
        return cols
