"""The laws a discovered shape is read back as (discover.py, after the claim): once the library's splines of an
observable x are claimed, the smooth function they found is tried as one fixed direction per probe times one
function of x that every probe carrying it shares (rank one: one source seen at several probes), first as a free
spline and then as each of a few laws a physicist would try first:

    polynomial      (x - x0)^2                            a quadratic about its vertex x0
    cubic           z + b2 z^2 + b3 z^3, z = (x - r) / w   a polynomial of degree 3
    distance power  ((c - r) / (c - x))^n                 a source whose distance, c - x in x's unit, closes or
                                                          opens as x moves (a magnet on a flap or a servo arm)
    exponential     exp((x - r) / s)                      a leakage, a thermistor, a supply's exponential load
    saturation      tanh(x / s)                           a coil or a core that saturates as its drive grows
    shifted sat.    tanh((x - x0) / s)                    the same about a level x0 of the observable

each less its value at the reference r (the observable's mean, or zero where the data span it), so that the offsets
keep the constant. Every form is fitted by the engine beside the model and the other groups found (shared
parameters in the aligned frame: the amplitude vector of each probe in nT, the law's own in x's unit), judged on the
held-out blocks, and the smallest whose held-out error the others do not beat by the held-out rule is chosen (the
number of parameters breaks ties). Numerics only.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from fluxcal.service.numerics.effects.base import AXES, EffectData, EffectTerm

from .shapes import basis_of

#: each law as the code of a function law(x, p, ref, span) -> (f, df/dp): f is the law less its value at the reference
#: ref (span: the observable's range, for a scaled variable). One text serves the fit here and the effect module
#: diagnose writes (write_effect.py), so that the two can never differ.
LAW_CODE = {
    "polynomial": """def law(x, p, ref, span):
    \"\"\"(x - x0)^2 less its value at ref; p = (x0,).\"\"\"
    x0 = p[0]
    return (x - x0) ** 2 - (ref - x0) ** 2, (-2.0 * (x - x0) + 2.0 * (ref - x0))[:, None]
""",
    "cubic": """def law(x, p, ref, span):
    \"\"\"z + b2 z^2 + b3 z^3, z = (x - ref) / span; p = (b2, b3).\"\"\"
    z = (x - ref) / span
    return z + p[0] * z ** 2 + p[1] * z ** 3, np.column_stack([z ** 2, z ** 3])
""",
    "distance power": """def law(x, p, ref, span):
    \"\"\"((c - ref) / (c - x))^n less one: the field of a source at a distance c - x (in x's unit) as its power n;
    p = (c, n).\"\"\"
    c, n = p
    ratio = np.clip((c - ref) / np.where(np.abs(c - x) < 1e-12, 1e-12, c - x), 1e-9, None)
    power = ratio ** n
    return power - 1.0, np.column_stack([n * power * (1.0 / (c - ref) - 1.0 / (c - x)), power * np.log(ratio)])
""",
    "exponential": """def law(x, p, ref, span):
    \"\"\"exp((x - ref) / s) less one; p = (s,).\"\"\"
    s = p[0]
    e = np.exp(np.clip((x - ref) / s, -50.0, 50.0))
    return e - 1.0, (-e * (x - ref) / s ** 2)[:, None]
""",
    "saturation": """def law(x, p, ref, span):
    \"\"\"tanh(x / s) less its value at ref; p = (s,).\"\"\"
    s = p[0]
    t, t0 = np.tanh(x / s), np.tanh(ref / s)
    return t - t0, (-(1.0 - t ** 2) * x / s ** 2 + (1.0 - t0 ** 2) * ref / s ** 2)[:, None]
""",
    "shifted saturation": """def law(x, p, ref, span):
    \"\"\"tanh((x - x0) / s) less its value at ref; p = (x0, s).\"\"\"
    x0, s = p
    t, t0 = np.tanh((x - x0) / s), np.tanh((ref - x0) / s)
    d, d0 = 1.0 - t ** 2, 1.0 - t0 ** 2
    return t - t0, np.column_stack([-d / s + d0 / s, -d * (x - x0) / s ** 2 + d0 * (ref - x0) / s ** 2])
""",
}


def _compiled(code: str, value_only: bool = False) -> Callable:
    """The law of `code`; value_only: the same text returning f alone (its return's first item: the fit's residual,
    taken hundreds of times a start, needs no df/dp, which was half a law's time), the very same arithmetic for f."""
    tree = ast.parse(code)
    if value_only:
        for node in ast.walk(tree):
            if isinstance(node, ast.Return) and isinstance(node.value, ast.Tuple):
                node.value = node.value.elts[0]
    space: dict[str, Any] = {"np": np}
    exec(compile(tree, "<law>", "exec"), space)           # noqa: S102 - this module's own constant text
    return space["law"]


@dataclass(frozen=True)
class Law:
    """One law: its parameters' names and units (the observable's unit is 'x'), its code (LAW_CODE), where its fit
    starts, and what it means."""

    name: str
    params: tuple[str, ...]
    units: tuple[str, ...]
    starts: Callable[[np.ndarray, dict], list[np.ndarray]]
    physics: str

    @property
    def code(self) -> str:
        return LAW_CODE[self.name]

    def both(self, x: np.ndarray, p: np.ndarray, ctx: dict) -> tuple[np.ndarray, np.ndarray]:
        """(f, df/dp) at x: the law less its value at the reference."""
        with np.errstate(all="ignore"):                  # a step far out: infinite, which the fit refuses
            return _LAWS_RUN[self.name](np.asarray(x, float), np.asarray(p, float), ctx["ref"], _span(ctx))

    def f(self, x: np.ndarray, p: np.ndarray, ctx: dict) -> np.ndarray:
        """The law less its value at the reference, without its derivative."""
        with np.errstate(all="ignore"):
            return _LAWS_VALUE[self.name](np.asarray(x, float), np.asarray(p, float), ctx["ref"], _span(ctx))


def _span(ctx: dict) -> float:
    return max(ctx["hi"] - ctx["lo"], 1e-12)


def _distance_starts(x: np.ndarray, ctx: dict) -> list[np.ndarray]:
    w = _span(ctx)
    out = []
    for side in (1.0, -1.0):
        edge = ctx["hi"] if side > 0 else ctx["lo"]
        for gap in (0.1, 0.4, 1.5, 5.0):
            for n in (1.0, 2.0, 3.0):
                out.append(np.array([edge + side * gap * w, n]))
    return out


_LAWS_RUN = {name: _compiled(code) for name, code in LAW_CODE.items()}
_LAWS_VALUE = {name: _compiled(code, value_only=True) for name, code in LAW_CODE.items()}
LAWS: tuple[Law, ...] = (
    Law("polynomial", ("x0",), ("x",),
        lambda x, c: [np.array([v]) for v in np.linspace(c["lo"] - _span(c), c["hi"] + _span(c), 7)],
        "a quadratic about its vertex"),
    Law("cubic", ("b2", "b3"), ("", ""), lambda x, c: [np.zeros(2)], "a polynomial of degree 3"),
    Law("distance power", ("c", "n"), ("x", ""), _distance_starts, "a source whose distance follows the observable"),
    Law("exponential", ("s",), ("x",),
        lambda x, c: [np.array([s * _span(c) * k]) for s in (1.0, -1.0) for k in (0.15, 0.4, 1.0, 3.0)],
        "an exponential"),
    Law("saturation", ("s",), ("x",),
        lambda x, c: [np.array([k * max(abs(c["lo"]), abs(c["hi"]), 1e-12)]) for k in (0.1, 0.3, 1.0, 3.0)],
        "a saturation about zero of the observable (a coil's current, a core's drive)"),
    Law("shifted saturation", ("x0", "s"), ("x", "x"),
        lambda x, c: [np.array([x0, s * _span(c)]) for x0 in np.linspace(c["lo"], c["hi"], 5)
                      for s in (0.1, 0.3, 1.0)],
        "a saturation about x0"),
)
LAW_NAMES = tuple(law.name for law in LAWS)


def law_named(name: str) -> Law:
    return next(law for law in LAWS if law.name == name)


def context(x: np.ndarray) -> dict[str, float]:
    """The observable's range and the reference the laws are taken against: zero where the data span it (a flap's
    angle), else the mean, to two significant figures (written into the effect)."""
    lo, hi = float(np.min(x)), float(np.max(x))
    ref = 0.0 if lo <= 0.0 <= hi else float(f"{float(np.mean(x)):.2g}")
    return {"lo": lo, "hi": hi, "ref": ref}


def start_law(law: Law, x: np.ndarray, y: np.ndarray, ctx: dict) -> tuple[np.ndarray, float, float] | None:
    """The law's parameters that best take the shape y(x) (one direction's values at the samples) with a free
    amplitude and constant (variable projection from several starts): (p, amplitude, relative misfit), or None."""
    best = None
    yc = y - y.mean()
    scale = float(np.sqrt(np.mean(yc ** 2))) or 1.0

    def resid(p: np.ndarray) -> np.ndarray:
        f = law.f(x, p, ctx)
        if not np.all(np.isfinite(f)) or float(np.max(np.abs(f))) > 1e100:
            return np.full(x.size, 1e3)
        f = f - f.mean()
        den = float(f @ f)
        if not np.isfinite(den) or den <= 0:
            return np.full(x.size, 1e3)
        return (yc - f * float(f @ yc) / den) / scale
    from scipy.optimize import least_squares            # here, not at import (a command's start)

    for p0 in law.starts(x, ctx):
        try:
            r = least_squares(resid, p0, method="lm", max_nfev=200 * (p0.size + 1))
        except (ValueError, FloatingPointError):
            continue
        if not np.all(np.isfinite(r.x)):
            continue
        cost = float(np.mean(r.fun ** 2))
        if best is None or cost < best[2]:
            f = law.f(x, r.x, ctx)
            f = f - f.mean()
            best = (r.x, float(f @ yc) / max(float(f @ f), 1e-300), cost)
    if best is not None and law.name in ("saturation", "shifted saturation") and best[0][-1] < 0:
        # tanh is odd: a tanh(x / s) is -a tanh(x / -s); the width is said positive, the field takes the sign
        p = best[0].copy()
        p[-1] = -p[-1]                                    # (x0 of the shifted one stays)
        best = (p, -best[1], best[2])
    return best


class LawTerm(EffectTerm):
    """A shape of an observable as one fixed field per probe times one function of the observable the probes share:
    a law (LAWS) or a free spline (law None: a spline's coefficients, the largest held at one). Shared parameters,
    corrected (aligned) frame: each probe's field in nT, then the law's."""

    linear = False
    frame = "corrected"
    title = "Discovered law"
    physical = "a field that follows a smooth function of what the data carry"

    def __init__(self, law: Law | None, recipe: dict[str, Any], ctx: dict, probes: list[int], index: int,
                 start: np.ndarray, unit: str, fixed: int | None = None) -> None:
        self.law = law
        self.recipe = recipe
        self.ctx = ctx
        self.probes = list(probes)
        self.name = f"discovered-law-{index + 1}"                   # type: ignore[misc]
        self.title = f"{recipe.get('column', recipe['source'])} {law.name if law else 'shape'}"  # type: ignore[misc]
        self.start = np.asarray(start, float)
        self.unit = unit
        self.fixed = fixed                                          # a free spline: its coefficient held at one
        self.per_sample = recipe.get("source") != "angular rate"     # type: ignore[misc]
        #: the other laws the held-out blocks do not tell from this one (forms.choose_forms): its parameters are then
        #: the form's, not a law these data single out, and its reading says so
        self.alike: list[str] = []

    @property
    def n_law(self) -> int:
        return self.start.size - 3 * len(self.probes)

    def shared_names(self, data: EffectData) -> list[str]:
        obs = self.recipe.get("column") or self.recipe.get("of") or self.recipe["source"]
        names = [f"{data.probe_names[k]}.{obs} field {a} nT" for k in self.probes for a in AXES]
        if self.law is None:
            m = self.n_law + 1
            return names + [f"{obs} shape b{j + 1}" for j in range(m) if j != self.fixed]
        units = [self.unit if u == "x" else u for u in self.law.units]
        return names + [f"{obs} {p}{' ' + u if u else ''}" for p, u in zip(self.law.params, units)]

    def shared_start_values(self, data: EffectData) -> np.ndarray:
        return self.start.copy()

    def _x(self, data: EffectData) -> np.ndarray:
        from .shape_reading import observable_values

        key = ("law x", self.recipe.get("column"), self.recipe["source"], self.recipe.get("probe"))
        if key not in data._cache:
            data._cache[key] = observable_values(data, self.recipe)
        return data._cache[key]

    def _basis(self, data: EffectData) -> np.ndarray:
        key = ("law basis", self.name)
        if key not in data._cache:
            data._cache[key] = basis_of(self.recipe, self._x(data))
        return data._cache[key]

    def function(self, data: EffectData, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(f (N,), df/dp (N, q)) of the shared function at the samples, at the law's parameters p."""
        if self.law is not None:
            return self.function_at(self._x(data), p)
        return self._spline(self._basis(data), p)

    def function_at(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As function, at values x of the observable."""
        if self.law is not None:
            return self.law.both(x, p, self.ctx)
        return self._spline(basis_of(self.recipe, x), p)

    def _spline(self, phi: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        free = [j for j in range(phi.shape[1]) if j != self.fixed]
        return phi[:, self.fixed] + phi[:, free] @ p, phi[:, free]

    def shared_vcorrection(self, data: EffectData, k: int, theta: np.ndarray) -> np.ndarray | None:
        if k not in self.probes:
            return None
        i = self.probes.index(k)
        f, _ = self.function(data, theta[3 * len(self.probes):])
        return np.outer(f, theta[3 * i:3 * i + 3])

    def shared_vjacobian(self, data: EffectData, k: int, theta: np.ndarray) -> np.ndarray | None:
        if k not in self.probes:
            return None
        i, n_amp = self.probes.index(k), 3 * len(self.probes)
        f, df = self.function(data, theta[n_amp:])
        out = np.zeros((data.n_samples, 3, theta.size))
        idx = np.arange(3)
        out[:, idx, 3 * i + idx] = f[:, None]
        out[:, :, n_amp:] = df[:, None, :] * theta[3 * i:3 * i + 3][None, :, None]
        return out
