"""Calibration numerics: pure numpy/scipy, no I/O.

model (ProbeCalibration, ArrayCalibration), ellipsoid (000, 004 step 1), tmi (001 section 4),
sinefit (003), twostep (004), rls (the online estimator), alignment (000, 001), tensor (001),
coverage (what users need to trust a fit), calfile (the versioned calibration file).
"""

from .model import ArrayCalibration, ProbeCalibration

__all__ = ["ArrayCalibration", "ProbeCalibration"]
