"""The catalogue of physical effect terms (`--effects`, docs/effects.md), one module per effect.

    temperature   offset and scale factor change with probe temperature      nT/degC, ppm/degC per axis
    thermal       the same, on a core temperature lagging the logged one     nT/degC, ppm/degC per axis, s
    eddy          fields induced by changing flux                            3x3 matrix on dB/dt, s
    lag           a probe sampled at another instant than probe 1            time offset, s
    nonlinearity  per-axis transfer non-linearity                            1/nT, 1/nT^2 per axis
    drift         slow change of the offsets or of the ambient field         nT/h, nT/h^2
    gradient      site gradient seen by probes off the rotation centre       G, nT/m (needs attitude)
    crossfield    an axis responds to the field across it                    1/nT per axis and pair
    hysteresis    perming: offset steps after a strong field or shock        nT per step and axis
    platform      Tolles-Lawson permanent and induced platform fields        nT, 3x3 per probe
    column        the field of a logged quantity (current, voltage, ...)    nT per unit, per unit/s, per axis
    ambient       the site's field changing, measured by the other probes    gain per probe

Adding an effect to the catalogue is adding one module with one EffectTerm subclass and a line in
EFFECTS. A user adds one without editing the package: `register_effect(cls)` (what `--effects
file.py:ClassName` and the `fluxcal.effects` entry-point group do, docs/effects.md); `known_effects()`
is the catalogue and the registered ones together.

>>> str(make_model(["temperature", "eddy"]))
'Baseline + Temperature + Eddy'
>>> make_model(["temprature"])
Traceback (most recent call last):
...
fluxcal.drivers.errors.ConfigError: --effects: 'temprature' is not an effect (allowed: temperature, thermal, eddy, \
lag, nonlinearity, drift, gradient, crossfield, hysteresis, platform, column, ambient; or file.py:ClassName for \
one of your own)
"""

from __future__ import annotations

from typing import Iterable

from fluxcal.drivers.errors import ConfigError

from .ambient import Ambient
from .base import Baseline, EffectData, EffectTerm, Model, ProbeView
from .column import Column
from .crossfield import Crossfield
from .drift import Drift
from .eddy import Eddy
from .gradient import Gradient
from .guard import guarded
from .hysteresis import Hysteresis
from .lag import Lag
from .nonlinearity import Nonlinearity
from .platform import Platform
from .temperature import Temperature
from .thermal import ThermalLag

#: catalogue name -> term class, in the order candidates are listed
EFFECTS: dict[str, type[EffectTerm]] = {
    cls.name: cls for cls in (Temperature, ThermalLag, Eddy, Lag, Nonlinearity, Drift, Gradient, Crossfield,
                              Hysteresis, Platform, Column, Ambient)
}


#: effects registered by the user (name -> class), beside the catalogue
_REGISTERED: dict[str, type[EffectTerm]] = {}
#: where each registered effect came from (file.py:Class, or its module), for the messages
_ORIGIN: dict[str, str] = {}

_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyz0123456789_-")


def known_effects() -> dict[str, type[EffectTerm]]:
    """The catalogue, then the effects the user registered, in that order."""
    return {**EFFECTS, **_REGISTERED}


def effect_spec(name: str) -> str:
    """How to name an effect on the command line: a registered one as it was given (file.py:Class,
    package.module:Class), so that advice naming it can be run as written; the catalogue's by name."""
    origin = _ORIGIN.get(name, "")
    return origin if ":" in origin else name


def register_effect(cls: object, origin: str = "") -> str:
    """Add a user's effect class (an EffectTerm subclass with a `name`) beside the catalogue; returns its name.
    ConfigError says what is wrong with it (origin: where it came from, for the message)."""
    where = f"{origin}: " if origin else ""
    cls = getattr(cls, "user_class", cls)               # a registered (guarded) class given again: the user's own
    if not (isinstance(cls, type) and issubclass(cls, EffectTerm)) or cls in (EffectTerm, Baseline):
        raise ConfigError(f"--effects: {where}{cls!r} is not an effect (allowed: a subclass of "
                          f"fluxcal.service.numerics.effects.EffectTerm; docs/effects.md)")
    name = getattr(cls, "name", "")
    if not name or not set(name) <= _NAME_CHARS or not name[0].isalpha():
        raise ConfigError(f"--effects: {where}{cls.__name__}.name = {name!r} is not allowed (allowed: a lower-case "
                          f"name of letters, digits, _ and -, starting with a letter)")
    taken = known_effects().get(name)
    if taken is not None and getattr(taken, "user_class", taken) is cls:
        return name                                         # the same class again
    if taken is not None:
        raise ConfigError(f"--effects: {where}{cls.__name__}.name = {name!r} is taken by "
                          f"{_ORIGIN.get(name, taken.__module__ + '.' + taken.__name__)} (allowed: a name not in "
                          f"{', '.join(known_effects())})")
    beside = getattr(cls, "beside", ())
    unknown = [b for b in beside if not isinstance(b, str) or b not in known_effects()] if isinstance(
        beside, (tuple, list)) else [beside]
    if unknown:
        raise ConfigError(f"--effects: {where}{cls.__name__}.beside = {beside!r} is not allowed (allowed: a tuple of "
                          f"effect names: {', '.join(known_effects())})")
    linear = cls.columns is not EffectTerm.columns
    nonlinear = cls.correction is not EffectTerm.correction and cls.jacobian is not EffectTerm.jacobian
    if not (linear or nonlinear or cls.shared_names is not EffectTerm.shared_names):
        raise ConfigError(f"--effects: {where}{cls.__name__} defines neither columns() (a linear term) nor "
                          f"correction() and jacobian() (a non-linear one); docs/effects.md")
    _REGISTERED[name] = guarded(cls, origin)            # what it raises or returns wrong is said (guard.py)
    _ORIGIN[name] = origin or f"{cls.__module__}.{cls.__name__}"
    return name


def unregister_effect(name: str) -> None:
    """Take a user's effect out of the registry (a notebook's cell defines its class again after an edit: register
    the new one after this). ConfigError for a catalogue effect or one not registered.

    >>> class Once(EffectTerm):
    ...     name = "once"
    ...     def param_names(self, view):
    ...         return []
    ...     def columns(self, view):
    ...         return None
    >>> register_effect(Once), "once" in known_effects()
    ('once', True)
    >>> unregister_effect("once"); "once" in known_effects()
    False
    """
    if name not in _REGISTERED:
        why = "a catalogue effect" if name in EFFECTS else "not registered"
        raise ConfigError(f"unregister_effect: {name!r} is {why} (registered: {', '.join(_REGISTERED) or 'none'})")
    del _REGISTERED[name]
    _ORIGIN.pop(name, None)


def make_term(name: str) -> EffectTerm:
    """One term by name (catalogue or registered); ConfigError names the allowed ones."""
    cls = known_effects().get(name)
    if cls is None:
        raise ConfigError(f"--effects: {name!r} is not an effect (allowed: {', '.join(known_effects())}; or "
                          f"file.py:ClassName for one of your own)")
    return cls()


def make_model(names: Iterable[str], *, baseline: bool = True) -> Model:
    """Baseline() + the named terms (baseline=False: the linear calibration is held fixed)."""
    terms = [make_term(n) for n in names]
    return Model(([Baseline()] if baseline else []) + terms)


__all__ = ["EFFECTS", "known_effects", "effect_spec", "register_effect", "unregister_effect", "make_term", "make_model", "Baseline", "EffectData", "EffectTerm", "Model", "ProbeView",
           "Temperature", "ThermalLag", "Eddy", "Lag", "Nonlinearity", "Drift", "Gradient", "Crossfield", "Hysteresis",
           "Platform", "Column", "Ambient"]
