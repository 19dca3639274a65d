"""A discovered group read back as physics (discover.py step 4): its parameters with standard errors (the robust,
1/f-aware ones, with the white-noise correlations), a matrix split into scale, non-orthogonality and rotation, an
offset and scale into its two parts, a wave's amplitudes, a loop's steps; one sentence a user reads. Numerics only.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import AXES
from fluxcal.service.numerics.effects.temperature import borrowed_from
from fluxcal.service.numerics.engine import FitResult, Parameter
from fluxcal.service.numerics.jsonsafe import finite_or_none as _num
from fluxcal.service.numerics.jsonsafe import json_safe as _plain

from .library import SHAPE_KINDS, Group
from .result import P_SIGNIFICANT
from .shape_reading import law_parameters, read_law, read_shape


@dataclass
class FoundGroup:
    """A discovered group read back as physics: its parameters with standard errors and what they say."""

    group: Group
    term: str                                   # the engine's name for it in the fit
    parameters: list[Parameter]
    reading: str                                # one sentence of physics
    parts: dict[str, Any] = field(default_factory=dict)

    @property
    def observable(self) -> str:
        return self.group.feature.observable

    def as_dict(self) -> dict[str, Any]:
        g, f = self.group, self.group.feature
        return {"probe": None if g.common else g.probe_name, "kind": g.kind, "feature": f.name,
                "observable": f.observable, "how": f.how, "frame": g.frame, "per_sample": g.per_sample,
                "borrowed": f.borrowed, "reading": self.reading, "parts": _plain(self.parts),
                "parameters": [{"name": p.name, "value": _num(p.value), "stderr": _num(p.stderr)}
                               for p in self.parameters]}



# --- reading a group back as physics --------------------------------------------------------------------

def _wald(values: np.ndarray, cov: np.ndarray) -> float:
    lam, vec = np.linalg.eigh(cov)
    keep = lam > 1e-12 * max(float(lam[-1]), 1e-300)
    z = vec[:, keep].T @ values
    return float(np.sum(z * z / lam[keep]))


@functools.cache
def _wald_critical() -> float:
    """The threshold of a part's Wald statistic: the chi-square quantile of P_SIGNIFICANT on 3 degrees of freedom
    (scipy.stats imported here, not at a command's start)."""
    from scipy import stats

    return stats.chi2.isf(P_SIGNIFICANT, 3)


def covariance(fit: FitResult, term: str) -> tuple[np.ndarray, np.ndarray]:
    """(values, covariance) of a term's parameters: the correlations of the normal matrix's inverse, with each
    parameter's own robust (1/f-aware) standard error on the diagonal, as the fitted parameters state it (scaled by
    the median ratio of the two instead, a reading's errors (40, 28, 58) stood beside the parameters' (40, 36, 55))."""
    pr = fit.problem
    idx = np.concatenate([np.arange(s.start, s.stop) for s in pr.slots if s.term is not None and s.term.name == term])
    a = fit.a_blocks.sum(0)
    d = np.sqrt(np.clip(np.diag(a), 1e-300, None))
    lam, vec = np.linalg.eigh(a / np.outer(d, d))
    keep = lam > 1e-7 * lam[-1]
    inv = (vec[:, keep] / lam[keep]) @ vec[:, keep].T / np.outer(d, d)
    s2 = fit.rss_w / max(fit.n_rows - fit.rank, 1)
    cov = inv[np.ix_(idx, idx)] * s2
    white = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    robust = np.where(fit.undetermined[idx], white, np.maximum(fit.robust_stderr[idx], white))
    return fit.values[idx], cov / np.outer(white, white) * np.outer(robust, robust)


#: a matrix that follows x, split into its physical parts: scale and non-orthogonality in the probe's frame (its
#: own axes), rotation in the aligned (platform) frame (its alignment to the others)
MATRIX_PARTS = ("rotation", "scale", "non-orthogonality")
#: a part is named beside the largest only where it is at least this share of it (a probe's own non-orthogonality
#: turns a pure rotation of the platform frame into small scale and non-orthogonality parts in its own)
PART_SHARE = 0.2


def matrix_parts(values: np.ndarray, cov: np.ndarray, m: np.ndarray) -> dict[str, Any]:
    """A raw-frame matrix K (9 values, ppm per unit: raw_corrected = raw - 1e-6 x K u) in parts with standard errors
    and their joint Wald statistic: scale (diagonal) and non-orthogonality (symmetric off-diagonal, xy xz yz) of K
    in the probe's frame; rotation (about x y z) of K' = M K M^-1, the same matrix in the aligned frame."""
    k = values.reshape(3, 3)
    jac = np.kron(m, np.linalg.inv(m).T)                        # vec(M K M^-1) = (M kron M^-T) vec(K), row-major
    kc = m @ k @ np.linalg.inv(m)
    out: dict[str, Any] = {"matrix_probe_frame": k.tolist(), "matrix_platform_frame": kc.tolist()}
    for part in MATRIX_PARTS:
        t = np.zeros((3, 9))
        if part == "scale":
            for r in range(3):
                t[r, 4 * r] = 1.0
        elif part == "non-orthogonality":
            for r, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
                t[r, 3 * i + j] = t[r, 3 * j + i] = 0.5
        else:
            for r, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):     # [theta]x: theta_x = A_zy, ...
                t[r, 3 * i + j], t[r, 3 * j + i] = 0.5, -0.5
            t = t @ jac
        v, c = t @ values, t @ cov @ t.T
        wald = _wald(v, c)
        out[part] = {"values": v.tolist(), "stderr": np.sqrt(np.clip(np.diag(c), 0.0, None)).tolist(), "wald": wald,
                     "significant": bool(wald >= _wald_critical()),
                     "frame": "platform" if part == "rotation" else "probe"}
    return out


def scale_parts(values: np.ndarray, cov: np.ndarray) -> dict[str, Any]:
    """A scale group's 6 values (offset nT, scale ppm per unit, per axis of the probe) in its two parts with standard
    errors and their joint Wald statistic."""
    out: dict[str, Any] = {}
    for part, sl in (("offset", slice(0, 3)), ("scale", slice(3, 6))):
        v, c = values[sl], cov[sl, sl]
        wald = _wald(v, c)
        out[part] = {"values": v.tolist(), "stderr": np.sqrt(np.clip(np.diag(c), 0.0, None)).tolist(), "wald": wald,
                     "significant": bool(wald >= _wald_critical()), "frame": "probe"}
    return out


def read_group(g: Group, term: str, params: list[Parameter], fit: FitResult) -> FoundGroup:
    """A group's parameters as physics, in the probe's and the aligned (platform) frame, with standard errors."""
    values, cov = covariance(fit, term)
    f = g.feature
    who = "a field common to all probes" if g.common else g.probe_name
    src = _source(f)
    parts: dict[str, Any] = {}
    if g.kind in ("offset", "common offset"):
        se = np.sqrt(np.diag(cov))
        vec = values if g.common else fit.state.linear.matrix[g.probe] @ values
        parts["vector"] = {"probe_frame" if not g.common else "platform_frame": values.tolist(),
                           "stderr": se.tolist(), "platform_frame": vec.tolist()}
        unit = f"nT{f.per}"
        head = (f"{who}'s offset follows {src}" if not g.common else
                f"{who} follows {src} (it shows in the scalar channels and cancels in the differences)")
        reading = (f"{head}: ({', '.join(f'{v:.3g}' for v in values)}) +- ({', '.join(f'{s:.2g}' for s in se)}) "
                   f"{unit} on the {'platform' if g.common else 'probe'}'s x, y, z axes")
    elif g.kind == "scale":
        parts.update(scale_parts(values, cov))
        off, sc = parts["offset"], parts["scale"]
        if sc["significant"] or (not off["significant"] and sc["wald"] >= off["wald"]):
            v, se = np.asarray(sc["values"]), np.asarray(sc["stderr"])
            i = int(np.argmax(np.abs(v)))
            reading = (f"{g.probe_name}'s scale factors follow {src}: scale {v[i]:.3g} +- {se[i]:.2g} ppm{f.per} of "
                       f"the probe's {AXES[i]} ({', '.join(f'{x:.3g}' for x in v)} ppm{f.per} on x, y, z), its offset "
                       f"({', '.join(f'{x:.3g}' for x in off['values'])}) +- "
                       f"({', '.join(f'{x:.2g}' for x in off['stderr'])}) nT{f.per}")
        else:
            reading = (f"{g.probe_name}'s offset follows {src} (its scale factors within their errors): "
                       f"({', '.join(f'{x:.3g}' for x in off['values'])}) +- "
                       f"({', '.join(f'{x:.2g}' for x in off['stderr'])}) nT{f.per} on the probe's x, y, z axes")
    elif g.kind == "matrix":
        reading = _read_matrix(g, values, cov, fit, src, parts)
    elif g.kind in ("wave", "common wave"):
        c, s = values[:3], values[3:]
        if not g.common:
            m = fit.state.linear.matrix[g.probe]
            c, s = m @ c, m @ s
        amp = np.sqrt(c ** 2 + s ** 2)
        parts["amplitude_platform_frame_nT"] = amp.tolist()
        se = np.sqrt(np.diag(cov))
        parts["stderr_nT"] = se.tolist()
        at = (f"at the phase of {f.observable} ({f.recipe.get('unit')}, its time integral)" if f.how == "phase"
              else f"periodic at {f.recipe['hz']:.4g} Hz (a line of the residual that no logged column's motion makes)")
        head = f"a field {at} on {who}" if not g.common else f"a field common to all probes {at}"
        reading = (f"{head}: amplitudes ({', '.join(f'{x:.3g}' for x in amp)}) nT on the platform's x, y, z axes "
                   f"(+- {float(np.median(se)):.2g} nT each cosine and sine part)"
                   + (" (it shows in the scalar channels and cancels in the differences)" if g.common else ""))
    elif g.kind in SHAPE_KINDS:
        reading, more = read_shape(g, values, cov, fit, src)
        parts.update(more)
    else:                                                              # loop
        se = np.sqrt(np.diag(cov))
        parts["step_nT"] = values.tolist()
        parts["stderr_nT"] = se.tolist()
        data = fit.problem.data
        n = int(f.recipe.get("window_samples", data.window_samples))    # the data's own where not refined
        span = window_span_s(data.t_s, n)
        parts.update(rate_window_samples=n, rate_window_span_s=span)
        over = f"; the rate over {n} samples, {span:.2g} s"
        reading = (f"{g.probe_name}'s offset follows the sign of each axis' rate of change (a core's loop, "
                   f"hysteresis{over}): +-({', '.join(f'{v:.3g}' for v in values)}) +- "
                   f"({', '.join(f'{s:.2g}' for s in se)}) nT on the probe's x, y, z axes as the field along it rises "
                   f"or falls")
    return FoundGroup(g, term, params, reading, parts)


def _read_matrix(g: Group, values: np.ndarray, cov: np.ndarray, fit: FitResult, src: str,
                 parts: dict[str, Any]) -> str:
    """A matrix group's reading: its significant parts (matrix_parts), the largest first; `parts` filled in."""
    f = g.feature
    parts.update(matrix_parts(values, cov, fit.state.linear.matrix[g.probe]))
    named = {p: parts[p] for p in MATRIX_PARTS}
    big = max(float(np.max(np.abs(named[p]["values"]))) for p in MATRIX_PARTS)
    sig = [p for p in sorted(MATRIX_PARTS, key=lambda p: -named[p]["wald"]) if named[p]["significant"]
           and float(np.max(np.abs(named[p]["values"]))) >= PART_SHARE * big] or \
        [max(named, key=lambda p: named[p]["wald"])]
    bits = []
    for p in sig:
        v, se = np.asarray(named[p]["values"]), np.asarray(named[p]["stderr"])
        u, frame = ("µrad", "platform") if p == "rotation" else ("ppm", "probe")
        about = {"rotation": "about", "scale": "of", "non-orthogonality": "between"}[p]
        labels = ("xy", "xz", "yz") if p == "non-orthogonality" else AXES
        i = int(np.argmax(np.abs(v)))
        bits.append(f"{p} {v[i]:.3g} +- {se[i]:.2g} {u}{f.per} {about} the {frame}'s {labels[i]} "
                    f"({', '.join(f'{x:.3g}' for x in v)} {u}{f.per} on {', '.join(labels)})")
    what = ("alignment to the others" if sig[0] == "rotation" and fit.problem.P > 1 else
            "scale factors" if sig == ["scale"] else "matrix")
    reading = f"{g.probe_name}'s {what} follow{'s' if what != 'scale factors' else ''} {src}: " + "; ".join(bits)
    return reading


def _source(f: Any) -> str:
    """What a feature is, in words: 's2_temp', 'heater_A through a first-order lag of 60 s', 'the time'."""
    base = {"time": "time", "ref_total": "the total field (ref_total)",
            "angular rate": "the angular rate"}.get(f.observable, f.observable)
    if f.borrowed:
        base = f"{base} (borrowed: {f.name.split('(', 1)[-1].rstrip(')')})"
    if f.how == "low-passed":
        return f"{base} through a first-order lag of {f.recipe['low_pass_s']:g} s (low-passed)"
    return base


def window_span_s(t_s: np.ndarray, n: int) -> float:
    """The time n consecutive samples span at the median: on a uniform time base (n - 1) intervals, on a bursty one
    several times what the median interval says (77 samples of a hand-turned board, 3.3 ms apart at the median in
    bursts with longer pauses, span 1.0 s).

    >>> t = np.concatenate([i * 0.06 + np.arange(8) * 0.0025 for i in range(200)])
    >>> round(window_span_s(np.arange(100) * 0.02, 13), 3), round(window_span_s(t, 101), 2)
    (0.24, 0.73)
    """
    t = np.asarray(t_s, float)
    n = int(min(max(n, 2), t.size))
    return float(np.median(t[n - 1:] - t[:t.size - n + 1]))


def read_law_group(term: Any, fit: FitResult) -> FoundGroup:
    """A law term (laws.LawTerm) as a found group of kind "law": its reading, and in its feature's recipe everything
    the written effect needs to make it again (the law, its reference, the probes, the fitted values)."""
    from .library import Feature

    data = fit.problem.data
    values, _, _ = law_parameters(term, fit)
    r = term.recipe
    name = r.get("of", r.get("column", r["source"]))                 # "heater_A low-passed 37 s", "s2_temp"
    obs = {"temperature": f"{r.get('probe_name', data.probe_names[r.get('probe', 0)])}_temp", "column": r.get("column"),
           "ref_total": "ref_total"}.get(r["source"], r["source"])
    names = [data.probe_names[k] for k in term.probes]
    recipe = {**r, "law": term.law.name if term.law else None, "reference": term.ctx, "probes": names,
              "values": [float(v) for v in values], "unit": term.unit, "fixed": term.fixed}
    feature = Feature(name, obs, term.unit, "law", recipe, np.zeros(data.n_samples), per_sample=term.per_sample)
    group = Group("law", term.probes[0] if len(term.probes) == 1 else None, ", ".join(names), feature)
    _, cov = covariance(fit, term.name)
    how = "low-passed" if "low_pass_s" in r else "value"              # a law of the observable through its lag
    # a probe's temperature taken from the others is said as theirs (it was said as its own column, empty)
    borrowed = (borrowed_from(data.temp_C, data.probe_names, int(r.get("probe", 0)))
                if r["source"] == "temperature" else None)
    said = name if borrowed is None or "of" in r else f"{name} (the mean of {borrowed}'s)"   # "of": a feature's name
    reading, parts = read_law(term, fit, _source(Feature(said, obs, term.unit, how, r, np.zeros(1), borrowed=borrowed)),
                              cov)
    params = [p for p in fit.parameters() if p.term == term.name]
    return FoundGroup(group, term.name, params, reading, parts)

