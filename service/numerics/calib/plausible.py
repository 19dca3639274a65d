"""Whether a calibration could belong to this unit and to physics, before anything uses it.

One check for every way a calibration enters the running service: the `apply` command, the persisted
calibration reloaded at start, and `calibration.initial`. A calibration that fails is refused whole,
naming the check, the probe and the figure; nothing of it is applied or persisted.

The checks, in order (the first that fails is said):

    probe names    the file's probes are this unit's, in this unit's order (entries matched by name,
                   never by position: a file with two probes' entries swapped is refused)
    finite         every offset and matrix entry is a finite number
    offset         |offset| within `max_offset_nT` on every axis (a fluxgate's range is ~1e5 nT)
    mirror         det(matrix) > 0: a correction cannot turn a right-handed sensor frame into a left-handed one
    condition      cond(matrix) within `max_condition` (a real correction is within a few percent of a rotation)
    scale          every singular value of the matrix within [1/max_scale, max_scale]: the sensor's scale
                   factors near 1 (the correction's gain is their inverse)
    total field    total_nT, when given, within [min_total_nT, max_total_nT]
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fluxcal.drivers.errors import DataError


@dataclass(frozen=True)
class CalibrationLimits:
    """What a calibration may be and still be applied (the configuration's [calibration] keys)."""

    max_offset_nT: float = 1e6
    max_condition: float = 10.0
    max_scale: float = 2.0
    min_total_nT: float = 1000.0
    max_total_nT: float = 200000.0


class ImplausibleCalibration(DataError):
    """A calibration that cannot be this unit's or is physically absurd; `check` names the check failed."""

    def __init__(self, check: str, message: str) -> None:
        super().__init__(f"fails the {check} check: {message}")
        self.check = check


def matrix_problem(m: np.ndarray, limits: CalibrationLimits = CalibrationLimits(),
                   keys: bool = True) -> tuple[str, str] | None:
    """(check, why) for a correction matrix no sensor has (a mirror, a condition or a scale beyond the limits), or
    None. The fits ask it too: data that do not determine the shape can return one (keys: name the configuration
    keys that set the limits)."""
    sign, logdet = np.linalg.slogdet(m)
    if not sign > 0:
        return "mirror", (f"the matrix's determinant is {sign * np.exp(logdet):.4g}: a correction that mirrors (or "
                          f"flattens) the sensor frame")
    sv = np.linalg.svd(m, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    if not cond <= limits.max_condition:
        return "condition", (f"the matrix's condition number is {cond:.4g} (at most {limits.max_condition:.4g}"
                             + (": calibration.max_condition)" if keys else ")"))
    lo, hi = 1.0 / limits.max_scale, limits.max_scale
    if not (sv[-1] >= lo and sv[0] <= hi):                         # (max_scale inf: the level not judged)
        return "scale", (f"the matrix scales the field by {sv[-1]:.4g} to {sv[0]:.4g} (allowed {lo:.4g} to {hi:.4g}"
                         + (": calibration.max_scale" if keys else "") + "): the sensor's scale factors must be near 1")
    return None


def check_calibration(cal, probe_names: Sequence[str], limits: CalibrationLimits = CalibrationLimits()) -> None:
    """Raise ImplausibleCalibration naming the first check `cal` (an ArrayCalibration) fails; None if it passes."""
    names = [p.name for p in cal.probes]
    unit = list(probe_names)
    if names != unit:
        if sorted(names) == sorted(unit):
            raise ImplausibleCalibration("probe names", f"its probes come in the order {', '.join(names)}; this "
                                         f"unit's are {', '.join(unit)} (entries are matched by name, never by "
                                         f"position: write them in the unit's order)")
        raise ImplausibleCalibration("probe names", f"its probes are {', '.join(names) or 'none'}; this unit's are "
                                     f"{', '.join(unit)}: a calibration of another unit")
    for p in cal.probes:
        o = np.asarray(p.offset_nT, dtype=float)
        m = np.asarray(p.matrix, dtype=float)
        if o.shape != (3,) or m.shape != (3, 3) or not (np.isfinite(o).all() and np.isfinite(m).all()):
            raise ImplausibleCalibration("finite", f"{p.name}: the offset and matrix must be 3 and 3x3 finite numbers")
        worst = float(np.max(np.abs(o)))
        if not worst <= limits.max_offset_nT:
            raise ImplausibleCalibration("offset", f"{p.name}: an offset of {worst:.4g} nT (at most "
                                         f"{limits.max_offset_nT:.4g} nT: calibration.max_offset_nT)")
        problem = matrix_problem(m, limits)
        if problem is not None:
            raise ImplausibleCalibration(problem[0], f"{p.name}: {problem[1]}")
    total = cal.total_nT
    if total is not None and not (limits.min_total_nT <= total <= limits.max_total_nT):
        raise ImplausibleCalibration("total field", f"total_nT {total:.4g} (allowed {limits.min_total_nT:.4g} to "
                                     f"{limits.max_total_nT:.4g} nT: calibration.min_total_nT, max_total_nT)")
