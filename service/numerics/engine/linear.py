"""The linear part of a calibration as the fit engine holds it: corrected = matrix (raw - offset), per probe.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError


@dataclass
class LinearCalibration:
    """Per probe: corrected = matrix (raw - offset_nT), in the common frame (probe 1's)."""

    offset_nT: np.ndarray      # (P, 3)
    matrix: np.ndarray         # (P, 3, 3)
    #: the total field the calibration was made for where it was made without one (its first probe's
    #: total_nT_assumed: `fit` of an estimated field), nT; None otherwise
    assumed_total_nT: float | None = None

    def copy(self) -> "LinearCalibration":
        return LinearCalibration(self.offset_nT.copy(), self.matrix.copy(), self.assumed_total_nT)

    @classmethod
    def from_any(cls, cal: Any, n_probes: int) -> "LinearCalibration":
        """From an ArrayCalibration (fluxcal.service.numerics.calib.model), a list of ProbeCalibration, a `fit --json`
        dict (docs/contracts.md: sensors with offset_nT and matrix), or a LinearCalibration."""
        if isinstance(cal, LinearCalibration):
            return cal.copy()
        probes = None
        if isinstance(cal, dict):
            probes = cal.get("sensors") or cal.get("probes")
        else:
            for attr in ("probes", "sensors", "calibrations"):
                if hasattr(cal, attr):
                    probes = getattr(cal, attr)
                    break
            if probes is None and isinstance(cal, (list, tuple)):
                probes = cal
        if probes is None:
            raise DataError(f"calibration: cannot read offsets and matrices from a {type(cal).__name__}")
        probes = list(probes)
        if len(probes) != n_probes:
            raise DataError(f"calibration: it has {len(probes)} probes, the data have {n_probes}")
        off, mat = [], []
        assumed = _assumed_total(probes[0]) if probes else None
        for p in probes:
            get = p.get if isinstance(p, dict) else (lambda k, _p=p: getattr(_p, k, None))
            o, m = get("offset_nT"), get("matrix")
            if o is None or m is None:
                raise DataError("calibration: a probe entry lacks offset_nT or matrix")
            off.append(np.asarray(o, dtype=np.float64).reshape(3))
            mat.append(np.asarray(m, dtype=np.float64).reshape(3, 3))
        return cls(np.array(off), np.array(mat), assumed)


def _assumed_total(probe: Any) -> float | None:
    """A probe calibration's total_nT_assumed (its params, object or `fit --json` dict), nT, or None."""
    params = probe.get("params") if isinstance(probe, dict) else getattr(probe, "params", None)
    value = params.get("total_nT_assumed") if isinstance(params, dict) else None
    value = value.get("value") if isinstance(value, dict) else None
    return float(value) if isinstance(value, (int, float)) and np.isfinite(value) and value > 0 else None
