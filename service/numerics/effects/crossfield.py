"""Crossfield: a probe axis responds to the field across it (the fluxgate cross-field effect).

    raw_a - o_a = u_a + sum_{b<c} x_{a,bc} u_b u_c
    => raw_corrected_a = raw_a - sum_{b<c} x_{a,bc} (raw_b - o_b)(raw_c - o_c)

Parameters per probe: for each axis a, three coefficients on the products xy, xz, yz, in 1/nT.
Together with the squares of `nonlinearity` they make the full second-order transfer. In a scalar
channel x_{x,yz}, x_{y,xz} and x_{z,xy} all multiply the monomial u_x u_y u_z, so only their sum
shows; the differences of an array do not separate them either (probe 1's own coefficients trade
against probe k's). Their standard errors say so.
"""

from __future__ import annotations

import numpy as np

from .base import AXES, EffectTerm, ProbeView

_PAIRS = ((0, 1), (0, 2), (1, 2))


class Crossfield(EffectTerm):
    """Bilinear cross-axis coefficients (1/nT) per probe and axis."""

    name = "crossfield"
    title = "Crossfield"
    physical = "an axis' output depends on the field across it"
    separation = {
        "nonlinearity": "vary the field magnitude (a scalar reference in a changing field, or coils): "
                        "a per-axis non-linearity follows each axis' own reading, a cross-field error the others'",
    }

    def param_names(self, view: ProbeView) -> list[str]:
        return [f"{view.name}.{AXES[a]} cross {AXES[b]}{AXES[c]} 1/nT" for a in range(3) for b, c in _PAIRS]

    def columns(self, view: ProbeView) -> np.ndarray:
        u = view.centred_nT
        prods = np.stack([u[:, b] * u[:, c] for b, c in _PAIRS], axis=1)   # (N, 3)
        cols = np.zeros((u.shape[0], 3, 9))
        for a in range(3):
            cols[:, a, 3 * a:3 * a + 3] = prods
        return cols
