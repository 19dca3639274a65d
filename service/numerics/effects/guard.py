"""A user's effect class, guarded: what its methods raise or return wrong is said as a ConfigError that names the
effect, where it came from and what is wrong, never a traceback from deep in a fit (a written effect given data
without its column raised KeyError('heater_A') from the engine; columns of the wrong shape, a parameter count that
is not the columns', NaN columns: each a traceback). diagnose takes the error as the candidate's "fit failed",
fit and a model named on the command line stop with it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.drivers.errors import ConfigError, FluxcalError

from .base import EffectTerm

#: the frames an effect may act in
FRAMES = ("raw", "corrected")


def _said(who: str, method: str, call) -> Any:
    try:
        return call()
    except FluxcalError:
        raise
    except Exception as e:                              # noqa: BLE001 - the user's code: say what it raised
        raise ConfigError(f"{who}: {method}() raised {type(e).__name__}: {e}") from None


def _array(who: str, method: str, out: Any, shape: tuple[int, ...]) -> np.ndarray:
    if not isinstance(out, np.ndarray) or out.shape != shape:
        got = out.shape if isinstance(out, np.ndarray) else type(out).__name__
        raise ConfigError(f"{who}: {method}() returned {got} where {shape} is asked (N samples, 3 axes"
                          f"{', m parameters' if len(shape) == 3 else ''}; docs/effects.md)")
    if not np.all(np.isfinite(out)):
        bad = int(np.count_nonzero(~np.isfinite(out)))
        raise ConfigError(f"{who}: {method}() returned {bad:,} NaN or infinite value(s): the effect must give a "
                          f"number for every sample (fill gaps in what it follows, as `column` does)")
    return out


def guarded(cls: type[EffectTerm], origin: str) -> type[EffectTerm]:
    """A subclass of the user's `cls` whose columns, correction, jacobian and shared columns are checked (shape,
    parameter count, finite) and whose failures are said (module doc). Its `user_class` is `cls`."""
    if getattr(cls, "frame", "raw") not in FRAMES:
        raise ConfigError(f"--effects: {origin}: {cls.__name__}.frame = {cls.frame!r} is not allowed (allowed: "
                          f"{', '.join(FRAMES)})")
    who = f"effect {cls.name!r} ({origin or cls.__module__ + '.' + cls.__name__})"

    def m(self, view) -> int:
        return len(_said(who, "param_names", lambda: cls.param_names(self, view)))

    def columns(self, view):
        out = _said(who, "columns", lambda: cls.columns(self, view))
        return _array(who, "columns", out, (view.data.n_samples, 3, m(self, view)))

    def correction(self, view, theta, v0=None):
        out = _said(who, "correction", lambda: cls.correction(self, view, theta, v0))
        return _array(who, "correction", out, (view.data.n_samples, 3))

    def jacobian(self, view, theta, v0=None):
        out = _said(who, "jacobian", lambda: cls.jacobian(self, view, theta, v0))
        return _array(who, "jacobian", out, (view.data.n_samples, 3, m(self, view)))

    def why_unavailable(self, data):
        return _said(who, "why_unavailable", lambda: cls.why_unavailable(self, data))

    def shared(self, data) -> int:
        return len(_said(who, "shared_names", lambda: cls.shared_names(self, data)))

    def shared_vcolumns(self, data, k):
        out = _said(who, "shared_vcolumns", lambda: cls.shared_vcolumns(self, data, k))
        return None if out is None else _array(who, "shared_vcolumns", out, (data.n_samples, 3, shared(self, data)))

    def shared_vcorrection(self, data, k, theta):
        out = _said(who, "shared_vcorrection", lambda: cls.shared_vcorrection(self, data, k, theta))
        return None if out is None else _array(who, "shared_vcorrection", out, (data.n_samples, 3))

    def shared_vjacobian(self, data, k, theta):
        out = _said(who, "shared_vjacobian", lambda: cls.shared_vjacobian(self, data, k, theta))
        return None if out is None else _array(who, "shared_vjacobian", out, (data.n_samples, 3, shared(self, data)))

    def shared_scolumns(self, data):
        out = _said(who, "shared_scolumns", lambda: cls.shared_scolumns(self, data))
        return None if out is None else _array(who, "shared_scolumns", out, (data.n_samples, shared(self, data)))

    body: dict[str, Any] = {"user_class": cls, "__doc__": cls.__doc__, "__module__": cls.__module__,
                            "why_unavailable": why_unavailable}
    if cls.columns is not EffectTerm.columns:
        body["columns"] = columns
    if cls.correction is not EffectTerm.correction:
        body["correction"] = correction
    if cls.jacobian is not EffectTerm.jacobian:
        body["jacobian"] = jacobian
    if cls.shared_vcolumns is not EffectTerm.shared_vcolumns:
        body["shared_vcolumns"] = shared_vcolumns
    if cls.shared_scolumns is not EffectTerm.shared_scolumns:
        body["shared_scolumns"] = shared_scolumns
    if cls.shared_vcorrection is not EffectTerm.shared_vcorrection:
        body["shared_vcorrection"] = shared_vcorrection
    if cls.shared_vjacobian is not EffectTerm.shared_vjacobian:
        body["shared_vjacobian"] = shared_vjacobian
    return type(cls.__name__, (cls,), body)
