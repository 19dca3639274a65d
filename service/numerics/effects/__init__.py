"""The catalogue of physical effect terms (CONTRACTS.md §2 `--effects`), one module per effect.

    temperature   offset and scale factor change with probe temperature      nT/degC, ppm/degC per axis
    eddy          fields induced by changing flux                            3x3 matrix on dB/dt, s
    lag           a probe sampled at another instant than probe 1            time offset, s
    nonlinearity  per-axis transfer non-linearity                            1/nT, 1/nT^2 per axis
    drift         slow change of the offsets or of the ambient field         nT/h, nT/h^2
    gradient      site gradient seen by probes off the rotation centre       G, nT/m (needs attitude)
    crossfield    an axis responds to the field across it                    1/nT per axis and pair
    hysteresis    perming: offset steps after a strong field or shock        nT per step and axis
    platform      Tolles-Lawson permanent and induced platform fields        nT, 3x3 per probe

Adding an effect is adding one module with one EffectTerm subclass and a line in EFFECTS.

>>> str(make_model(["temperature", "eddy"]))
'Baseline + Temperature + Eddy'
>>> make_model(["temprature"])
Traceback (most recent call last):
...
drivers.errors.ConfigError: --effects: 'temprature' is not an effect (allowed: temperature, eddy, lag, \
nonlinearity, drift, gradient, crossfield, hysteresis, platform)
"""

from __future__ import annotations

from typing import Iterable

from drivers.errors import ConfigError

from .base import Baseline, EffectData, EffectTerm, Model, ProbeView
from .crossfield import Crossfield
from .drift import Drift
from .eddy import Eddy
from .gradient import Gradient
from .hysteresis import Hysteresis
from .lag import Lag
from .nonlinearity import Nonlinearity
from .platform import Platform
from .temperature import Temperature

#: catalogue name -> term class, in the order candidates are listed
EFFECTS: dict[str, type[EffectTerm]] = {
    cls.name: cls for cls in (Temperature, Eddy, Lag, Nonlinearity, Drift, Gradient, Crossfield, Hysteresis,
                              Platform)
}


def make_term(name: str) -> EffectTerm:
    """One term by catalogue name; ConfigError names the allowed ones."""
    cls = EFFECTS.get(name)
    if cls is None:
        raise ConfigError(f"--effects: {name!r} is not an effect (allowed: {', '.join(EFFECTS)})")
    return cls()


def make_model(names: Iterable[str], *, baseline: bool = True) -> Model:
    """Baseline() + the named terms (baseline=False: the linear calibration is held fixed)."""
    terms = [make_term(n) for n in names]
    return Model(([Baseline()] if baseline else []) + terms)


__all__ = ["EFFECTS", "make_term", "make_model", "Baseline", "EffectData", "EffectTerm", "Model", "ProbeView",
           "Temperature", "Eddy", "Lag", "Nonlinearity", "Drift", "Gradient", "Crossfield", "Hysteresis",
           "Platform"]
