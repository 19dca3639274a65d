"""Gradient: the site's field gradient seen by probes off the rotation centre.

A probe at r_k (platform frame) on a platform with attitude R (platform -> NED) sees

    B_k = R^T (B0 + G R r_k)      =>   corrected_k -= R^T G R r_k

with G symmetric and traceless (a source-free field; 5 parameters in nT/m, NED, shared by all
probes; G_zz = -G_xx - G_yy). The scalar reference sits at the platform origin. The term needs the
attitude in the data (heel_deg/pitch_deg/azimuth_deg or q_w..q_z columns, e.g. from a turntable
controller) and the probe positions (--config). Under turns about a single axis (z) the gradient seen
in one probe's scalar channel is a first harmonic of the turn: G_xx and G_xy then act like offsets,
G_xz and G_yz like the matrix's xz and yz entries, and G_yy does not show at all.
"""

from __future__ import annotations

import numpy as np

from .base import EffectData, EffectTerm

_NAMES = ("xx", "yy", "xy", "xz", "yz")


def gradient_basis() -> np.ndarray:
    """(5, 3, 3) symmetric traceless basis: G = sum_m g_m E_m.

    >>> b = gradient_basis(); [float(np.trace(e)) for e in b], bool(np.allclose(b, np.swapaxes(b, 1, 2)))
    ([0.0, 0.0, 0.0, 0.0, 0.0], True)
    """
    e = np.zeros((5, 3, 3))
    e[0, 0, 0], e[0, 2, 2] = 1.0, -1.0
    e[1, 1, 1], e[1, 2, 2] = 1.0, -1.0
    for m, (i, j) in zip((2, 3, 4), ((0, 1), (0, 2), (1, 2))):
        e[m, i, j] = e[m, j, i] = 1.0
    return e


class Gradient(EffectTerm):
    """A uniform site gradient G (nT/m, symmetric traceless, NED) shared by all probes."""

    name = "gradient"
    title = "Gradient"
    physical = "field gradient at the test site, seen by probes off the rotation centre"
    frame = "corrected"
    separation = {
        "baseline": "turn about a second axis (or tumble): under turns about one axis a site gradient looks "
                    "like probe offsets and matrix terms",
        "offset": "turn about a second axis (or tumble): under turns about one axis a site gradient looks "
                  "like a probe offset",
    }

    def why_unavailable(self, data: EffectData) -> str | None:
        # everything missing said at once: advice that unlocks only the next blocker sends a user round twice
        attitude = ("the platform attitude in the data (columns heel_deg, pitch_deg, azimuth_deg or q_w, q_x, q_y, q_z)"
                    if data.attitude() is None else "")
        if data.positions_m is None:
            return "needs the probe positions (--config with [[probes]] position_m)" + (f" and {attitude}"
                                                                                       if attitude else "")
        if not np.any(data.positions_m):
            return "every probe sits at the rotation centre: a site gradient does not show"
        return f"needs {attitude}" if attitude else None

    def shared_names(self, data: EffectData) -> list[str]:
        return [f"gradient G{n} nT/m" for n in _NAMES]

    def shared_vcolumns(self, data: EffectData, k: int) -> np.ndarray | None:
        key = ("gradient", k)
        if key not in data._cache:
            r = data.attitude()                                         # (N, 3, 3)
            r_earth = r @ data.positions_m[k]                           # R r_k, NED (N, 3)
            basis = gradient_basis()
            # psi_m = R^T E_m R r_k
            g_earth = np.einsum("mij,nj->nim", basis, r_earth)          # (N, 3, 5)
            data._cache[key] = np.einsum("nji,njm->nim", r, g_earth)
        return data._cache[key]
