"""Effects of your own (docs/effects.md): the contract a class meets, and what it may use.

>>> from fluxcal.effects import EffectTerm, register_effect, known_effects
>>> "temperature" in known_effects()
True
"""

from fluxcal.service.numerics.effects import EffectTerm, known_effects, register_effect, unregister_effect
from fluxcal.service.numerics.effects.base import EffectData, ProbeView, axis_columns
from fluxcal.service.numerics.effects.thermal import low_pass

__all__ = ["EffectData", "EffectTerm", "ProbeView", "axis_columns", "known_effects", "low_pass", "register_effect",
           "unregister_effect"]
