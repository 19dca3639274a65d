"""Nonlinearity: per-axis transfer non-linearity of the probe.

    raw_a - offset_a = u_a + q_a u_a^2 + c_a u_a^3
    => raw_corrected_a = raw_a - q_a (raw_a - o_a)^2 - c_a (raw_a - o_a)^3      (first order in q, c)

Parameters per probe and axis: the quadratic coefficient q in 1/nT and the cubic c in 1/nT^2.
"""

from __future__ import annotations

import numpy as np

from .base import AXES, EffectTerm, ProbeView, axis_columns


class Nonlinearity(EffectTerm):
    """Quadratic (1/nT) and cubic (1/nT^2) transfer coefficients per probe and axis."""

    name = "nonlinearity"
    title = "Nonlinearity"
    physical = "per-axis transfer non-linearity"
    separation = {
        "crossfield": "vary the field magnitude (a scalar reference in a changing field, or coils): "
                      "a per-axis non-linearity follows each axis' own reading, a cross-field error the others'",
    }

    def param_names(self, view: ProbeView) -> list[str]:
        p = view.name
        return [f"{p}.{a} quadratic 1/nT" for a in AXES] + [f"{p}.{a} cubic 1/nT2" for a in AXES]

    def columns(self, view: ProbeView) -> np.ndarray:
        u = view.centred_nT
        return np.concatenate([axis_columns(u ** 2), axis_columns(u ** 3)], axis=2)
