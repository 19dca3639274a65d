"""The fit engine: a linear calibration plus effect terms fitted to the residual channels by Gauss-Newton.

Numerics only. The problem (problem.py: residual channels and their Jacobian, jacobian.py, accumulated
per time block), the state and its parameter slots (state.py), the solve (solve.py: steps, standard
errors, warm starts), starting values (start.py), and the public entry, `fit_with_effects`
(model_fit.py). The diagnosis (fluxcal.service.numerics.diagnose) uses the names exported here.
"""

from fluxcal.service.numerics.channels import channel_names
from fluxcal.service.numerics.noise import channel_noise

from .linear import LinearCalibration
from .model_fit import EffectsFit, fit_model, fit_with_effects, residual_hints
from .problem import Problem, as_effect_data, reference_total, scaled_to
from .residuals import Channels
from .solve import RANK_TOL, FitResult, Parameter, Warm, fit_problem, solve_normal, warm_from
from .start import initial_linear, start_weights

__all__ = ["Channels", "EffectsFit", "FitResult", "LinearCalibration", "Parameter", "Problem", "RANK_TOL", "Warm",
           "as_effect_data", "channel_names", "channel_noise", "fit_model", "fit_problem", "fit_with_effects",
           "initial_linear", "reference_total", "residual_hints", "scaled_to", "solve_normal", "start_weights", "warm_from"]
