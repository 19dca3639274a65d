"""The fit engine: a linear calibration plus effect terms fitted to the residual channels by Gauss-Newton.

Numerics only: the problem (residual channels and their Jacobian, accumulated per time block), the
solver (steps, standard errors, warm starts), and the starting values.
"""

from .fit import EffectsFit, FitResult, LinearCalibration, Parameter, fit_with_effects  # noqa: F401
