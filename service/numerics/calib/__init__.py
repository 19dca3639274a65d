"""Calibration numerics: pure numpy/scipy, no I/O.

model (ProbeCalibration, ArrayCalibration, the [FastRotation] triangular and [TwoFluxgate] unit-column
parameterisations), ellipsoid ([TwoFluxgate], [TwoStep] step 1), tmi ([FastRotation] section 4), sinefit
([SineFit]), twostep ([TwoStep]), rls (the online estimator), alignment ([TwoFluxgate] regression,
[FastRotation] rotation), tensor ([FastRotation]), coverage (what users need to trust a fit). The papers'
keys are defined in docs/references.md. The calibration file is read and written in fluxcal.service.io.calfile.
"""

from .alignment import (
                        RotationAlignment,
                        align_probes,
                        align_regression,
                        align_rotation,
                        platform_calibration,
                        platform_output,
                        regression_calibration,
                        rotation_from_angles,
                        rotation_from_samples,
)
from .ellipsoid import EllipsoidFit, fit_ellipsoid
from .model import (
                        ArrayCalibration,
                        ProbeCalibration,
                        sensor_scale,
                        triangular_matrix,
                        triangular_params,
                        unit_column_split,
)
from .quadric import triangular_factor
from .tensor import (
                        center_field,
                        cross_positions,
                        differences,
                        invariants,
                        measured_components,
                        tensor_from_cross,
                        tensor_from_positions,
)
from .tmi import TmiFit, fit_tmi, fit_tmi_full

__all__ = [
    "ArrayCalibration", "ProbeCalibration", "sensor_scale", "triangular_matrix", "triangular_params",
    "unit_column_split",
    "EllipsoidFit", "fit_ellipsoid", "triangular_factor",
    "TmiFit", "fit_tmi", "fit_tmi_full",
    "RotationAlignment", "align_probes", "align_regression", "align_rotation", "platform_calibration",
    "platform_output", "regression_calibration", "rotation_from_angles", "rotation_from_samples",
    "center_field", "cross_positions", "differences", "invariants", "measured_components",
    "tensor_from_cross", "tensor_from_positions",
]
