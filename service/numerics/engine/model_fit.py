"""A calibration with effect terms, fitted: `fit_with_effects`, the engine's public entry.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.numerics.effects.base import REF_PREFIX, Baseline, EffectData, Model

from .linear import LinearCalibration
from .problem import Problem, as_effect_data, reference_total, scaled_to
from .residuals import Channels
from .solve import FitResult, Parameter, fit_problem
from .start import initial_linear, start_weights
from .state import layout_slots


#: an effect the data show has a parameter at least this many standard errors from zero (EffectsFit.not_shown)
SHOWN_SIGMAS = 3.0


@dataclass
class EffectsFit:
    """A calibration with effect terms: the linear part (docs/contracts.md: corrected = matrix (raw - offset)
    before any effect term) plus every effect parameter with its standard error."""

    probe_names: list[str]
    effects: list[str]
    offset_nT: np.ndarray               # (P, 3)
    matrix: np.ndarray                  # (P, 3, 3)
    parameters: list[Parameter]
    offset_stderr_nT: np.ndarray        # (P, 3), NaN where undetermined
    rms_nT: float
    channel_rms_nT: dict[str, float]
    reference: str
    result: FitResult = field(repr=False)
    base_method: str = "ellipsoid"
    base_align: str | None = None
    total_nT: float | None = None

    def calibration(self) -> Any:
        """A fluxcal.service.numerics.calib.model.ArrayCalibration: the linear part with offset standard errors, the
        effect names and `effect_params` {effect: {name: {"value", "se", "unit"}}} (a term's constants with
        "fixed": true: held at their value, not fitted), plus the fit's
        RMS in `diagnostics`."""
        probes = [ProbeCalibration(n, self.offset_nT[k].copy(), self.matrix[k].copy(), self.offset_stderr_nT[k].copy())
                  for k, n in enumerate(self.probe_names)]
        effect_params: dict[str, Any] = {}
        for p in self.parameters:
            effect_params.setdefault(p.term, {})[p.name] = ({"value": p.value, "se": p.stderr, "unit": p.unit}
                                                            | ({"at_floor": p.at_floor} if p.at_floor else {}))
        for term, name, value, unit in self.constants():
            effect_params.setdefault(term, {})[name] = {"value": value, "se": None, "unit": unit, "fixed": True,
                                                        "note": "reference the parameters are defined against"}
        data = self.result.problem.data
        return ArrayCalibration(method=self.base_method, align=self.base_align, probes=probes, total_nT=self.total_nT,
                                effects=list(self.effects), effect_params=effect_params,
                                diagnostics={"rms_nT": self.rms_nT, "channel_rms_nT": dict(self.channel_rms_nT),
                                             "reference": self.reference},
                                span=(float(data.t_s[0]), float(data.t_s[-1]), int(data.n_samples)))

    def constants(self) -> list[tuple[str, str, float, str]]:
        """(effect, name, value, unit) of the references the effect parameters are defined against."""
        pr = self.result.problem
        out = []
        for t in pr.terms:
            for view in pr.views:
                for name, (value, unit) in t.constants(view).items():
                    out.append((t.name, name, float(value), unit))
        return out

    def not_shown(self, name: str) -> str:
        """Why the samples do not show effect `name` ("" where they do): `not_shown` of this fit's parameters."""
        return not_shown(self.parameters, name)

    def size_warnings(self) -> list[str]:
        """Per effect, its parameters the data do not determine, and those whose standard error exceeds their size
        (as calib.order.size_warnings says it of the offsets, scales and angles); first, a fit that stopped before
        it converged (its parameters printed ± errors as if they were the minimum's)."""
        out = []
        if not self.result.converged:
            out.append(f"the fit with {', '.join(self.effects)} stopped after {self.result.iterations} iterations, "
                       f"before it converged: its parameters are not the best these data give, nor their errors final")
        for term in self.effects:
            params = [p for p in self.parameters if p.term == term]
            idle = [p.name for p in params if p.stderr is None and not p.at_floor]
            held = [p for p in params if p.at_floor]
            wide = [p for p in params if p.stderr is not None and np.isfinite(p.stderr) and p.stderr > abs(p.value)]
            if idle:
                out.append(f"{term}: {len(idle)} of its {len(params)} parameters are not determined by these data (no "
                           f"standard error: their values are not measurements): {_some(idle)}")
            if held:
                out.append(f"{term}: {_some([p.name for p in held])} held at {held[0].value:g} {held[0].unit}, the "
                           f"lowest value it can take, where these data ask for less ({held[0].at_floor})")
            if wide:
                shown = [f"{p.name} = {p.value:.4g} ± {p.stderr:.2g}" for p in wide]
                out.append(f"{term}: the standard errors of {len(wide)} of its {len(params)} parameters exceed their "
                           f"size (these data do not determine them): {_some(shown)}")
        return out

    def effect_parameters(self) -> dict[str, dict[str, float | None]]:
        """{"temperature": {"s1.x nT/degC": value, ...}, ...} and the same with standard errors."""
        out: dict[str, dict[str, float | None]] = {}
        for p in self.parameters:
            out.setdefault(p.term, {})[p.name] = p.value
        return out

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: the sensors in the form of docs/contracts.md plus `effect_parameters` with errors."""
        sensors = [{"name": n, "offset_nT": self.offset_nT[k].tolist(), "matrix": self.matrix[k].tolist(),
                    "scalar_rms_nT": self.channel_rms_nT.get(f"{n}.scalar")}
                   for k, n in enumerate(self.probe_names)]
        return {"effects": list(self.effects), "sensors": sensors, "rms_nT": self.rms_nT,
                "reference": self.reference,
                "effect_parameters": [p.as_dict() | {"effect": p.term} for p in self.parameters],
                "effect_constants": [{"effect": e, "name": n, "value": v, "unit": u}
                                     for e, n, v, u in self.constants()]}

    def correct(self, data: Any) -> np.ndarray:
        """(N, P, 3) corrected field of other data with this calibration and its effects."""
        ed = as_effect_data(data, probe_names=self.probe_names)
        # the references of terms shared by the probes (kept on the data, not on a probe's view): keep them too
        fitted = self.result.problem.data
        if ed is not fitted:
            ed._cache.update({k: v for k, v in fitted._cache.items()
                              if isinstance(k, str) and k.startswith(REF_PREFIX)})
        lin = LinearCalibration(self.offset_nT, self.matrix)
        pr = Problem(ed, Model(self.result.model.effect_terms), lin, np.zeros(ed.n_samples), n_blocks=1,
                     rows=np.arange(ed.n_samples))
        for old, new in zip(self.result.problem.views, pr.views):
            # the references of the fit (temperature, time origin, step instants): keep them
            new.cache.update({k: v for k, v in old.cache.items() if k.startswith(REF_PREFIX)})
        pr.slots = layout_slots(pr.data, pr.terms, pr.views, pr.fit_linear)
        pr.n_params = pr.slots[-1].stop if pr.slots else 0
        st = pr.start_state(lin, self.result.state)
        ev = pr.evaluate(st)
        return np.stack(ev.v, axis=1)


def not_shown(parameters: Sequence[Parameter], name: str) -> str:
    """Why the samples do not show effect `name` ("" where they do), said after "do not show <name>: ": none of
    its parameters they determine lies SHOWN_SIGMAS standard errors from zero. An effect the data do not show only
    adds noise, and a drift is extrapolated (tens of Earth fields an hour, fitted to 106 s of a real board): the
    service refuses to add one, fit to give one, and diagnose to advise one. Parameters the data do not determine
    (no standard error: the solve moves them only along what the data fix) are said by EffectsFit.size_warnings."""
    params = [p for p in parameters if p.term == name]
    ratios = [abs(p.value) / p.stderr for p in params if p.stderr is not None and p.stderr > 0]
    if not params or (ratios and max(ratios) >= SHOWN_SIGMAS):
        return ""
    if not ratios:
        return f"none of its {len(params)} parameters is determined by them"
    return (f"none of its {len(params)} parameters is {SHOWN_SIGMAS:g} standard errors from zero (largest "
            f"|value| / standard error {max(ratios):.1f})")


def _some(items: list[str], n: int = 9) -> str:
    """The first n items, comma-separated, and how many more."""
    return ", ".join(items[:n]) + (f" and {len(items) - n} more" if len(items) > n else "")


def fit_with_effects(data: Any, effects: Sequence[str] | Model, base_calibration: Any = None, *,
                     total_nT: float | None = None, positions_m: np.ndarray | None = None,
                     fix_linear: bool = False, n_blocks: int = 8,
                     progress: Callable[[str], None] | None = None) -> tuple[EffectsFit, Channels]:
    """Fit the linear calibration (unless fix_linear) and the named effects; return the calibration with
    effect parameters and standard errors, and the residual channels.

    data: EffectData, LabData or SampleBlock. effects: catalogue names or a Model. base_calibration: the
    starting linear calibration (ArrayCalibration, LinearCalibration, `fit --json` dict) or None to start
    from an ellipsoid per probe aligned to probe 1."""
    from fluxcal.service.numerics.effects import make_model

    ed = as_effect_data(data, total_nT=total_nT, positions_m=positions_m)
    if isinstance(effects, Model):
        model = effects if (effects.has_baseline or fix_linear) else Model([Baseline()]) + effects
        if fix_linear:
            model = model.without_baseline()
    else:
        model = make_model(list(effects), baseline=not fix_linear)
    for t in model.effect_terms:
        why = t.why_unavailable(ed)
        if why:
            raise CalibrationRefused(f"effect {t.name!r} cannot be fitted to these data: {why}")
    if base_calibration is None:
        ref0 = ed.ref_total_nT if ed.ref_total_nT is not None else ed.total_nT
        linear = initial_linear(ed, ref0)
    else:
        linear = LinearCalibration.from_any(base_calibration, ed.n_probes)
    reference, kind = reference_total(ed, linear, held=fix_linear and base_calibration is not None)
    if kind == "estimated" and not fix_linear:
        linear = scaled_to(linear, ed, reference)
    weights = start_weights(ed, linear, reference)
    res = fit_model(ed, model, linear, reference, weights, n_blocks=n_blocks, progress=progress)
    out = effects_fit_from(res, kind)
    out.base_method = getattr(base_calibration, "method", None) or "ellipsoid"
    out.base_align = getattr(base_calibration, "align", None)
    out.total_nT = ed.total_nT if kind != "ref_total" else float(np.median(reference))
    return out, res.channels


def residual_hints(fit: FitResult) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Full-length scalar residual and offset sensitivity n^T M per probe (NaN off the fitted rows): what
    terms with `needs_residual` look for their regressors in."""
    pr = fit.problem
    n = pr.data.n_samples
    res, gain = [], []
    for k in range(pr.P):
        r = np.full(n, np.nan)
        r[pr.rows] = fit.channels.values[:, k]
        g = np.full((n, 3), np.nan)
        g[pr.rows] = fit.ev.nhat[k] @ fit.state.linear.matrix[k]
        res.append(r)
        gain.append(g)
    return res, gain


def fit_model(data: EffectData, model: Model, linear: LinearCalibration, reference: np.ndarray,
              weights: np.ndarray, *, n_blocks: int = 8, progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit a model from a linear start. Terms that find their regressors in a residual (perming steps)
    get the residual of the model without them: two stages."""
    hints = None
    if any(t.needs_residual for t in model.effect_terms):
        first = Model([t for t in model if not t.needs_residual])
        pr0 = Problem(data, first, linear, reference, weights=weights, n_blocks=n_blocks)
        fit0 = fit_problem(pr0, pr0.start_state(linear), progress=progress)
        hints = residual_hints(fit0)
        pr = Problem(data, model, fit0.state.linear, reference, weights=weights, n_blocks=n_blocks, hints=hints)
        return fit_problem(pr, pr.start_state(fit0.state.linear, fit0.state), progress=progress)
    pr = Problem(data, model, linear, reference, weights=weights, n_blocks=n_blocks)
    return fit_problem(pr, pr.start_state(linear), progress=progress)


def effects_fit_from(res: FitResult, reference_kind: str) -> EffectsFit:
    pr = res.problem
    off_se = np.full((pr.P, 3), np.nan)
    for s in pr.slots:
        if s.kind == "offset":
            se = res.robust_stderr[s.start:s.stop].copy()
            se[res.undetermined[s.start:s.stop]] = np.nan
            off_se[s.k] = se
    rms = res.channels.rms_nT
    return EffectsFit(probe_names=list(pr.data.probe_names), effects=pr.model.effects,
                      offset_nT=res.state.linear.offset_nT.copy(), matrix=res.state.linear.matrix.copy(),
                      parameters=res.parameters(), offset_stderr_nT=off_se, rms_nT=res.rms_nT,
                      channel_rms_nT={n: float(rms[i]) for i, n in enumerate(res.channels.names)},
                      reference=reference_kind, result=res)
