"""Model versus measurement: residual channels, where the model fails, and which effect is missing.

`diagnose(data, effects=...)` fits the model (the linear calibration plus the named effects) and
reports (CONTRACTS.md §3):

- channels: each probe's scalar residual |corrected| - total field and, for arrays, each component
  of each aligned probe minus probe 1; rms_nT over all of them; noise_nT, the noise floor of the same
  channels from their second differences (std / sqrt(6), robust; independent of the model);
- where: how much of each channel's residual variance an observable explains (adjusted R^2 of a
  small basis in time, temperature, angular rate, orientation, heading, field magnitude, extra
  columns; for frequency the excess power of the strongest band), strongest first; and the worst
  time segments;
- candidates: every catalogue effect not in the model, fitted in addition. Judged on K contiguous
  time blocks (never shuffled samples): each block predicted by the fit to the others. A candidate
  is significant when the nested-model F-test gives p < P_SIGNIFICANT, the pooled held-out gain is
  positive, and the mean over blocks of ln(MSE without / MSE with) is at least GAIN_SIGMAS standard
  errors (block to block) above zero. Two candidates are reported indistinguishable when their
  held-out errors agree (per-block log ratios within GAIN_SIGMAS standard errors, or held-out MSEs
  within a factor exp(GAIN_TOLERANCE)) and each one's fitted correction is at least COLLINEAR_R2 explained
  by the other's regressors; a candidate whose regressors the model already spans is
  indistinguishable from that part of the model (e.g. a site gradient under turns about one axis
  looks like an offset). Each such entry says what motion or data would separate them.

Numerics only: no file I/O (service.wiring.commands.diagnose and service.io.report do that).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from scipy import stats

from drivers.errors import CalibrationRefused, FluxcalError

from service.numerics.effects import EFFECTS, Baseline, Model, make_model, make_term
from service.numerics.effects.base import EffectData, EffectTerm
from service.numerics.engine import (RANK_TOL, FitResult, LinearCalibration, Parameter, Problem, Warm, as_effect_data,
                                      fit_model, fit_problem, initial_linear, reference_total, residual_hints,
                                      solve_normal, start_weights, warm_from)

P_SIGNIFICANT = 1e-3
GAIN_SIGMAS = 2.0
GAIN_TOLERANCE = 0.10
COLLINEAR_R2 = 0.90
ABSORBED = 0.01            # largest unexplained fraction of a candidate's regressors for "absorbed"
N_BLOCKS = 8
CANDIDATE_ITERATIONS = 4
PARAMETER_LINES = 18
WHERE_MAX_ROWS = 20000

Progress = Callable[[float, str], None]


@dataclass
class Candidate:
    """One catalogue effect tried on top of the model."""

    effect: str
    rms_nT: float                         # in-sample RMS over all channels with the effect added
    heldout_rms_nT: float                 # RMS of the blocks each predicted by the others
    significant: bool = False
    testable: bool = True
    reason: str | None = None             # why not testable, or a note
    gain: float = 0.0                     # held-out gain, fraction of the model's held-out weighted MSE
    log_ratio: float = 0.0                # mean over blocks of ln(MSE without / MSE with), held out
    log_ratio_se: float = 0.0             # its standard error from the block-to-block spread
    p_value: float = 1.0                  # nested-model F-test on all the data
    bic_delta: float = 0.0                # BIC with - BIC without (negative favours the effect)
    n_params: int = 0                     # parameters the data determine
    indistinguishable_from: list[str] = field(default_factory=list)
    separate_by: str | None = None
    parameters: list[Parameter] = field(default_factory=list)
    block_log_ratio: np.ndarray | None = field(default=None, repr=False)
    fit: FitResult | None = field(default=None, repr=False)

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"effect": self.effect, "rms_nT": _num(self.rms_nT), "significant": self.significant,
                             "heldout_rms_nT": _num(self.heldout_rms_nT), "heldout_gain": _num(self.gain),
                             "heldout_log_ratio": _num(self.log_ratio),
                             "heldout_log_ratio_se": _num(self.log_ratio_se), "p_value": _num(self.p_value),
                             "bic_delta": _num(self.bic_delta), "n_params": self.n_params,
                             "testable": self.testable}
        if self.indistinguishable_from:
            d["indistinguishable_from"] = list(self.indistinguishable_from)
        if self.separate_by:
            d["separate_by"] = self.separate_by
        if self.reason:
            d["reason"] = self.reason
        if self.parameters:
            d["parameters"] = [{"name": p.name, "value": _num(p.value), "stderr": _num(p.stderr)}
                               for p in self.parameters]
        return d


@dataclass
class Diagnosis:
    """Everything `fluxcal diagnose` reports; `as_dict()` is the CONTRACTS §3 JSON."""

    effects: list[str]
    model: str
    linear: str                           # "refit" or "fixed"
    reference: str                        # "ref_total", "config" or "estimated"
    rms_nT: float
    noise_nT: float
    channel_names: list[str]
    channel_rms_nT: np.ndarray
    channel_noise_nT: np.ndarray
    where: list[dict[str, Any]]
    candidates: list[Candidate]
    worst_segments: list[dict[str, Any]]
    n_samples: int
    duration_s: float
    heldout_rms_nT: float
    notes: list[str]
    fit: FitResult = field(repr=False)
    linear_refit_rms_nT: float | None = None
    parameters: list[Parameter] = field(default_factory=list)

    @property
    def best(self) -> Candidate | None:
        """The first significant candidate, if any."""
        return next((c for c in self.candidates if c.significant), None)

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "effects": list(self.effects),
            "rms_nT": _num(self.rms_nT),
            "noise_nT": _num(self.noise_nT),
            "channels": [{"name": n, "rms_nT": _num(r), "noise_nT": _num(s)}
                         for n, r, s in zip(self.channel_names, self.channel_rms_nT, self.channel_noise_nT)],
            "where": [{k: _num(v) if isinstance(v, float) else v for k, v in w.items()} for w in self.where],
            "candidates": [c.as_dict() for c in self.candidates],
            "worst_segments": self.worst_segments,
            "model": self.model,
            "linear": self.linear,
            "reference": self.reference,
            "n_samples": self.n_samples,
            "duration_s": _num(self.duration_s),
            "heldout_rms_nT": _num(self.heldout_rms_nT),
            "parameters": [{"name": p.name, "value": _num(p.value), "stderr": _num(p.stderr)}
                           for p in self.parameters],
            "notes": list(self.notes),
        }
        if self.linear_refit_rms_nT is not None:
            d["linear_refit_rms_nT"] = _num(self.linear_refit_rms_nT)
        return d


def _num(x: Any) -> Any:
    """JSON-safe float (None for NaN/inf)."""
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


# --- held-out statistics --------------------------------------------------------------------------------------

@dataclass
class _Heldout:
    sse_w: np.ndarray
    sse: np.ndarray
    n: np.ndarray

    @property
    def rms_nT(self) -> float:
        return float(np.sqrt(self.sse.sum() / self.n.sum()))

    @property
    def mse_w(self) -> np.ndarray:
        return self.sse_w / self.n


def _heldout(fit: FitResult) -> _Heldout:
    return _Heldout(*fit.heldout())


def _compare(base: FitResult, base_ho: _Heldout, cand: FitResult, cand_ho: _Heldout) -> dict[str, Any]:
    """Held-out gain, its per-block log ratio (paired by block), F-test and BIC of cand against base.

    The held-out test uses lr_b = ln(MSE_base,b / MSE_cand,b): scale-free, so one block whose error
    is large (an end block predicted by extrapolation) does not swamp the spread of the others."""
    gain = 1.0 - float(cand_ho.sse_w.sum() / base_ho.sse_w.sum()) if base_ho.sse_w.sum() > 0 else 0.0
    lr_b = np.log(np.maximum(base_ho.mse_w, 1e-300) / np.maximum(cand_ho.mse_w, 1e-300))
    k = lr_b.size
    lr = float(lr_b.mean())
    lr_se = float(lr_b.std(ddof=1) / np.sqrt(k)) if k > 1 else float("inf")
    n = base.n_rows
    dp = max(cand.rank - base.rank, 1)
    rss0, rss1 = base.rss_w, cand.rss_w
    dof = max(n - cand.rank, 1)
    if rss1 > 0 and rss0 > rss1:
        f = ((rss0 - rss1) / dp) / (rss1 / dof)
        p = float(stats.f.sf(f, dp, dof))
    else:
        p = 1.0
    bic0 = n * np.log(rss0 / n) + base.rank * np.log(n)
    bic1 = n * np.log(max(rss1, 1e-300) / n) + cand.rank * np.log(n)
    return {"gain": gain, "lr": lr, "lr_se": lr_se, "lr_b": lr_b, "p": p, "bic": float(bic1 - bic0),
            "dp": cand.rank - base.rank}


# --- absorbed and collinear -----------------------------------------------------------------------------------

def _slot_indices(pr: Problem, pred: Callable[[Any], bool]) -> np.ndarray:
    idx = [np.arange(s.start, s.stop) for s in pr.slots if pred(s)]
    return np.concatenate(idx) if idx else np.zeros(0, int)


def _unexplained(a: np.ndarray, cand: np.ndarray, by: np.ndarray) -> float:
    """Largest fraction of a candidate column's weighted energy outside the span of columns `by`."""
    diag = np.diag(a)
    if cand.size:
        # a column these motions hardly excite (1e-4 of the term's strongest, e.g. G_yy under a turn
        # about z) has nothing to explain
        cand = cand[diag[cand] > 1e-4 * max(float(diag[cand].max()), 1e-300)]
    if cand.size == 0:
        return 0.0
    d = np.sqrt(np.clip(diag, 1e-300, None))
    a_s = a / np.outer(d, d)
    acc = a_s[np.ix_(cand, cand)]
    if by.size == 0:
        return 1.0
    abb, abc = a_s[np.ix_(by, by)], a_s[np.ix_(by, cand)]
    lam, vec = np.linalg.eigh(abb)
    keep = lam > RANK_TOL * max(lam[-1], 1e-300)
    proj = vec[:, keep].T @ abc
    explained = np.einsum("ij,ij->j", proj, proj / lam[keep][:, None])   # diag(A_cb A_bb^+ A_bc)
    frac = 1.0 - explained / np.clip(np.diag(acc), 1e-300, None)
    return float(np.max(frac))


def _absorbed_by(cand: FitResult, term: str) -> list[str] | None:
    """The smallest part of the model that spans the candidate's regressors: ['offset'], ['baseline'],
    [an effect in the model], or None."""
    return _absorbed_in(cand.problem, cand.a_blocks.sum(0), term)


def _absorbed_in(pr: Problem, a: np.ndarray, term: str) -> list[str] | None:
    """As _absorbed_by, from a normal matrix `a` of problem pr."""
    c_idx = _slot_indices(pr, lambda s: s.term is not None and s.term.name == term)
    if c_idx.size == 0:
        return None
    tests: list[tuple[list[str], np.ndarray]] = []
    if pr.fit_linear:
        tests.append((["offset"], _slot_indices(pr, lambda s: s.kind == "offset")))
        tests.append((["baseline"], _slot_indices(pr, lambda s: s.kind in ("offset", "matrix"))))
    for t in pr.terms:
        if t.name == term:
            continue
        tests.append(([t.name], _slot_indices(
            pr, lambda s, _n=t.name: s.kind in ("offset", "matrix") or (s.term is not None and s.term.name == _n))))
    for names, idx in tests:
        if idx.size and _unexplained(a, c_idx, idx) < ABSORBED:
            return names
    return None


def _explained_by(target: Candidate, other: Candidate) -> float:
    """Partial R^2: the part of target's fitted correction that other's regressors explain beyond the model."""
    ft, fo = target.fit, other.fit
    pr_t = ft.problem
    t_idx = _slot_indices(pr_t, lambda s: s.term is not None and s.term.name == target.effect)
    delta = np.zeros(pr_t.n_params)
    delta[t_idx] = ft.values[t_idx]
    f = pr_t.apply(ft.jac, ft.ev, delta)                          # the target's correction, (M, C)
    pr_o = fo.problem
    _, g_b = pr_o.assemble(fo.jac, fo.ev, residual=f)
    g = g_b.sum(0)
    a = fo.a_blocks.sum(0)
    energy = float(np.sum((f * pr_o.weights) ** 2))
    if energy <= 0:
        return 1.0
    d_all, *_ = solve_normal(a, g)
    e_all = float(-g @ d_all)
    m_idx = _slot_indices(pr_o, lambda s: s.term is None or s.term.name != other.effect)
    if m_idx.size:
        d_m, *_ = solve_normal(a[np.ix_(m_idx, m_idx)], g[m_idx])
        e_m = float(-g[m_idx] @ d_m)
    else:
        e_m = 0.0
    rest = energy - e_m
    return 1.0 if rest <= 1e-12 * energy else float(np.clip((e_all - e_m) / rest, 0.0, 1.0))


def _separation(a: str, b: str) -> str:
    ta = EFFECTS.get(a)
    tb = EFFECTS.get(b)
    for t, other in ((ta, b), (tb, a)):
        if t is not None and other in t.separation:
            return t.separation[other]
    return (f"vary what each depends on independently ({_depends(a)} against {_depends(b)}), "
            f"or record more of the motion that excites them")


def _depends(name: str) -> str:
    return {"temperature": "temperature", "eddy": "rotation rate", "lag": "rotation rate",
            "nonlinearity": "field per axis", "drift": "time", "gradient": "attitude and position",
            "crossfield": "field across each axis", "hysteresis": "field history", "platform": "attitude",
            "offset": "attitude", "baseline": "attitude"}.get(name, name)


# --- where it fails ---------------------------------------------------------------------------------------------

def _legendre(x: np.ndarray, deg: int) -> np.ndarray:
    lo, hi = float(np.min(x)), float(np.max(x))
    z = np.zeros_like(x) if hi <= lo else 2.0 * (x - lo) / (hi - lo) - 1.0
    return np.polynomial.legendre.legvander(z, deg)[:, 1:]


def _r2(y: np.ndarray, cols: np.ndarray) -> float:
    """Adjusted R^2 of y on [1, cols], clipped to [0, 1]."""
    n = y.size
    x = np.column_stack([np.ones(n), cols])
    ok = np.all(np.isfinite(x), axis=1) & np.isfinite(y)
    x, yy = x[ok], y[ok]
    n, q = yy.size, x.shape[1] - 1
    if n <= q + 2:
        return 0.0
    sd = x.std(0)
    sd[0] = 1.0
    sd[sd == 0] = 1.0
    beta, *_ = np.linalg.lstsq(x / sd, yy, rcond=None)
    resid = yy - (x / sd) @ beta
    sst = float(np.sum((yy - yy.mean()) ** 2))
    if sst <= 0:
        return 0.0
    r2 = 1.0 - (float(resid @ resid) / (n - q - 1)) / (sst / (n - 1))
    return float(np.clip(r2, 0.0, 1.0))


def observables(data: EffectData, fit: FitResult, rows: np.ndarray) -> dict[str, Any]:
    """Observable bases at the given rows (indices into the full data): name -> per-channel function."""
    pr = fit.problem
    full_rows = pr.rows[rows]
    t = data.t_s[full_rows]
    out: dict[str, Any] = {"time": lambda c: _legendre(t, 4)}
    if data.has_temperature() and float(np.ptp(data.temperature(0))) > 1e-6:
        temps = [data.temperature(k)[full_rows] for k in range(data.n_probes)]

        def temp_basis(c: int) -> np.ndarray:
            kind, k = pr.channel_probe(c)
            ks = [k, 0] if kind == "diff" else [k]
            cols = []
            for k in ks:
                cols += [temps[k], temps[k] ** 2]
            return np.column_stack(cols)
        out["temperature"] = temp_basis
    # angular rate from probe 1: omega_perp = |b x db/dt| / |b|^2 (rad/s); and the rate's direction
    s1 = data.smooth(0)[full_rows]
    r1 = data.rate(0)[full_rows]
    b2 = np.sum(s1 ** 2, axis=1)
    omega = np.linalg.norm(np.cross(s1, r1), axis=1) / b2
    rate_dir = r1 / np.sqrt(b2)[:, None]
    out["angular rate"] = lambda c: np.column_stack([omega, omega ** 2, rate_dir])
    us = [fit.ev.nhat[k][rows] for k in range(pr.P)]

    def probe_u(c: int) -> np.ndarray:
        kind, k = pr.channel_probe(c)
        return us[0] if kind == "diff" else us[k]

    def orient(c: int) -> np.ndarray:
        u = probe_u(c)
        return np.column_stack([u, u[:, 0] ** 2 - u[:, 2] ** 2, u[:, 1] ** 2 - u[:, 2] ** 2,
                                u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2]])
    out["orientation"] = orient

    def heading(c: int) -> np.ndarray:
        u = probe_u(c)
        psi = np.arctan2(u[:, 1], u[:, 0])
        return np.column_stack([f(k * psi) for k in (1, 2, 3) for f in (np.cos, np.sin)])
    out["heading"] = heading
    if data.ref_total_nT is not None and float(np.ptp(data.ref_total_nT)) > 1.0:
        f = data.ref_total_nT[full_rows]
        out["field magnitude"] = lambda c: np.column_stack([f, f ** 2])
    for name, vals in data.observables().items():
        v = vals[full_rows]
        if float(np.ptp(v)) > 0:
            out[name] = lambda c, _v=v: np.column_stack([_v, _v ** 2])
    return out


def _band_excess(y: np.ndarray, dt: float, noise: float) -> tuple[float, str]:
    """Strongest frequency band of a residual above its white-noise floor: (fraction of variance, band)."""
    n = y.size
    if n < 64:
        return 0.0, ""
    y = y - y.mean()
    spec = np.abs(np.fft.rfft(y)) ** 2 / n                  # periodogram, E = variance for white noise
    freq = np.fft.rfftfreq(n, dt)
    total = float(np.sum(y ** 2) / n)
    if total <= 0:
        return 0.0, ""
    edges = np.geomspace(freq[1], freq[-1] * 1.0001, 13)
    best, band = 0.0, ""
    for a, b in zip(edges[:-1], edges[1:]):                  # 12 bands
        m = (freq >= a) & (freq < b)
        if not m.any():
            continue
        # share of the mean square: (2/n) sum spec; white noise of variance s^2 has E[spec] = s^2
        excess = (2.0 / n) * (float(spec[m].sum()) - noise ** 2 * int(m.sum()))
        frac = excess / total
        if frac > best:
            best, band = frac, f"{a:.3g}-{b:.3g} Hz"
    return float(np.clip(best, 0.0, 1.0)), band


def where_it_fails(data: EffectData, fit: FitResult, noise_nT: np.ndarray, *, top: int = 30,
                   min_strength: float = 0.05) -> list[dict[str, Any]]:
    """(channel, observable, strength) sorted strongest first; strength = explained variance fraction."""
    pr = fit.problem
    m = pr.M
    stride = max(1, m // WHERE_MAX_ROWS)
    rows = np.arange(0, m, stride)
    obs = observables(data, fit, rows)
    vals = fit.channels.values
    out = []
    for c, name in enumerate(fit.channels.names):
        y = vals[rows, c]
        for oname, basis in obs.items():
            s = _r2(y, basis(c))
            if s >= min_strength:
                out.append({"channel": name, "observable": oname, "strength": s})
        s, band = _band_excess(vals[:, c], data.dt_s, float(noise_nT[c]))
        if s >= min_strength:
            out.append({"channel": name, "observable": "frequency", "strength": s, "band": band})
    out.sort(key=lambda d: -d["strength"])
    return out[:top]


def worst_segments(fit: FitResult, *, n_segments: int = 20, top: int = 3) -> list[dict[str, Any]]:
    """The time segments with the largest RMS over all channels."""
    vals, t = fit.channels.values, fit.channels.t_s
    edges = np.linspace(0, vals.shape[0], n_segments + 1).round().astype(int)
    segs = []
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        per = np.sqrt(np.mean(vals[a:b] ** 2, axis=0))
        c = int(np.argmax(per))
        segs.append({"t_start_s": float(t[a]), "t_end_s": float(t[b - 1]),
                     "rms_nT": float(np.sqrt(np.mean(vals[a:b] ** 2))),
                     "worst_channel": fit.channels.names[c], "worst_channel_rms_nT": float(per[c])})
    segs.sort(key=lambda d: -d["rms_nT"])
    return segs[:top]


# --- the diagnosis ----------------------------------------------------------------------------------------------

def diagnose(data: Any, *, effects: Sequence[str] = (), calibration: Any = None, fix_linear: bool | None = None,
             candidates: Sequence[str] | None = None, total_nT: float | None = None,
             positions_m: np.ndarray | None = None, n_blocks: int = N_BLOCKS,
             progress: Progress | None = None) -> Diagnosis:
    """Compare the model (linear calibration + `effects`) with the data; find what fails and what is missing.

    calibration: a linear calibration to hold fixed (the model compared is then exactly that
    calibration plus the effects); None refits the linear part. fix_linear overrides that choice."""
    def tell(frac: float, msg: str) -> None:
        if progress is not None:
            progress(frac, msg)

    ed = as_effect_data(data, total_nT=total_nT, positions_m=positions_m)
    notes: list[str] = []
    if ed.dropped_rows:
        notes.append(f"{ed.dropped_rows} samples with a saturated axis (NaN) left out")
    fixed = (calibration is not None) if fix_linear is None else bool(fix_linear)
    tell(0.0, "linear calibration")
    if calibration is not None:
        linear = LinearCalibration.from_any(calibration, ed.n_probes)
    else:
        ref0 = ed.ref_total_nT if ed.ref_total_nT is not None else ed.total_nT
        linear = initial_linear(ed, ref0)
    reference, ref_kind = reference_total(ed, linear)
    if ref_kind == "estimated":
        notes.append("no ref_total and no total field in --config: the total field is estimated "
                     "(an overall scale error cannot be seen)")
    weights = start_weights(ed, linear, reference)
    model = make_model(list(effects), baseline=not fixed)
    for t in model.effect_terms:
        why = t.why_unavailable(ed)
        if why:
            raise CalibrationRefused(f"effect {t.name!r} cannot be fitted to these data: {why}")

    tell(0.05, f"fitting {model}")
    cur = fit_model(ed, model, linear, reference, weights, n_blocks=n_blocks)
    cur_ho = _heldout(cur)
    if not cur.converged:
        notes.append(f"the model fit stopped after {cur.iterations} iterations without converging")

    linear_refit = None
    if fixed:
        tell(0.1, "linear refit for comparison")
        linear_refit = fit_model(ed, Model([Baseline()]) + model, linear, reference, weights,
                                 n_blocks=n_blocks).rms_nT

    names = list(candidates) if candidates is not None else [n for n in EFFECTS if n not in model]
    hints = residual_hints(cur)
    cands: list[Candidate] = []
    for i, name in enumerate(names):
        tell(0.15 + 0.7 * i / max(len(names), 1), f"trying {name}")
        cands.append(_try_candidate(ed, model, cur, cur_ho, name, reference, weights, hints, n_blocks))

    tell(0.87, "comparing candidates")
    _mark_indistinguishable(cands)
    cands = _rank(cands)

    tell(0.92, "where it fails")
    noise = 1.0 / weights
    where = where_it_fails(ed, cur, noise)
    tell(1.0, "done")
    ch_rms = cur.channels.rms_nT
    return Diagnosis(effects=model.effects, model=str(model), linear="fixed" if fixed else "refit",
                     reference=ref_kind, rms_nT=cur.rms_nT, noise_nT=float(np.sqrt(np.mean(noise ** 2))),
                     channel_names=list(cur.channels.names), channel_rms_nT=ch_rms, channel_noise_nT=noise,
                     where=where, candidates=cands, worst_segments=worst_segments(cur), n_samples=ed.n_samples,
                     duration_s=ed.duration_s, heldout_rms_nT=cur_ho.rms_nT, notes=notes, fit=cur,
                     linear_refit_rms_nT=linear_refit, parameters=cur.parameters())


def _try_candidate(ed: EffectData, model: Model, cur: FitResult, cur_ho: _Heldout, name: str,
                   reference: np.ndarray, weights: np.ndarray, hints, n_blocks: int) -> Candidate:
    untestable = Candidate(effect=name, rms_nT=cur.rms_nT, heldout_rms_nT=cur_ho.rms_nT, testable=False)
    term: EffectTerm = make_term(name)
    why = term.why_unavailable(ed)
    if why:
        untestable.reason = why
        return untestable
    try:
        pr = Problem(ed, model + term, cur.state.linear, reference, weights=weights, n_blocks=n_blocks,
                     hints=hints)
        if pr.term_size(name) == 0:
            untestable.reason = ("no perming step stands out of the noise in the residual" if name == "hysteresis"
                                 else "nothing to fit in these data")
            return untestable
        start = pr.start_state(cur.state.linear, cur.state)
        warm = warm_from(cur, pr)
        if warm is not None:
            # the model's normal equations at this very point are known: assemble only the candidate's rows,
            # and see first whether the model already spans them (then there is nothing to fit)
            ev0 = pr.evaluate(start)
            jac0 = pr.jacobian(start, ev0)
            a_c, g_c = pr.assemble(jac0, ev0, only=~warm.known)
            both = warm.known[:, None] & warm.known[None, :]
            a_c[:, both] = warm.a_blocks[:, both]
            g_c[:, warm.known] = warm.g_blocks[:, warm.known]
            absorbed = _absorbed_in(pr, a_c.sum(0), name)
            if absorbed:
                same = Candidate(effect=name, rms_nT=cur.rms_nT, heldout_rms_nT=cur_ho.rms_nT,
                                 indistinguishable_from=absorbed, separate_by=_separation(name, absorbed[0]),
                                 reason=f"the model's {absorbed[0]} spans its regressors in these data")
                return same
            warm = Warm(a_c, g_c, np.ones(pr.n_params, bool))
        # at most CANDIDATE_ITERATIONS: a fit stopped early overstates its RSS, so its gain is understated
        # (conservative); in practice one or two steps converge and only flat directions creep on
        fit = (fit_problem(pr, start, warm=warm, max_iter=CANDIDATE_ITERATIONS, ev0=ev0, jac0=jac0)
               if warm is not None else fit_problem(pr, start, max_iter=CANDIDATE_ITERATIONS))
    except (FluxcalError, np.linalg.LinAlgError, ValueError) as e:
        untestable.reason = f"fit failed: {e}"
        return untestable
    ho = _heldout(fit)
    cmp = _compare(cur, cur_ho, fit, ho)
    c = Candidate(effect=name, rms_nT=fit.rms_nT, heldout_rms_nT=ho.rms_nT, gain=cmp["gain"],
                  log_ratio=cmp["lr"], log_ratio_se=cmp["lr_se"], p_value=cmp["p"], bic_delta=cmp["bic"],
                  n_params=int(cmp["dp"]), parameters=[p for p in fit.parameters() if p.term == name],
                  block_log_ratio=cmp["lr_b"], fit=fit)
    c.significant = bool(c.p_value < P_SIGNIFICANT and c.gain > 0 and c.log_ratio > GAIN_SIGMAS * c.log_ratio_se
                         and c.n_params > 0)
    absorbed = _absorbed_by(fit, name)
    if absorbed:
        c.indistinguishable_from = absorbed
        c.separate_by = _separation(name, absorbed[0])
        c.significant = False
        c.reason = f"the model's {absorbed[0]} spans its regressors in these data"
    return c


def _mark_indistinguishable(cands: list[Candidate]) -> None:
    live = [c for c in cands if c.testable and c.fit is not None and c.gain > 0 and c.block_log_ratio is not None]
    for i, a in enumerate(live):
        for b in live[i + 1:]:
            if not (a.significant or b.significant):
                continue
            diff = a.block_log_ratio - b.block_log_ratio             # ln(MSE_b / MSE_a) per block
            se = float(diff.std(ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else float("inf")
            # equal within their uncertainty (block to block), or practically equal (held-out MSE within
            # GAIN_TOLERANCE); a fraction-of-MSE gain would hide 1.2 against 1.8 nT behind 92 % against 82 %
            overall = abs(np.log(a.heldout_rms_nT ** 2 / b.heldout_rms_nT ** 2))
            close = abs(float(diff.mean())) <= GAIN_SIGMAS * se or overall <= GAIN_TOLERANCE
            if not close:
                continue
            if _explained_by(a, b) < COLLINEAR_R2 or _explained_by(b, a) < COLLINEAR_R2:
                continue
            for x, y in ((a, b), (b, a)):
                if y.effect not in x.indistinguishable_from:
                    x.indistinguishable_from.append(y.effect)
                    x.separate_by = _separation(x.effect, y.effect)


def _rank(cands: list[Candidate]) -> list[Candidate]:
    """Significant first, then by held-out gain (those the linear calibration spans last); among
    indistinguishable ones the simpler first."""
    absorbed = {"offset", "baseline"}
    order = sorted(cands, key=lambda c: (not c.significant, not c.testable,
                                         bool(absorbed & set(c.indistinguishable_from)), -c.gain))
    for _ in range(len(order)):
        moved = False
        for i in range(len(order) - 1):
            a, b = order[i], order[i + 1]
            if (b.effect in a.indistinguishable_from and a.significant == b.significant
                    and b.n_params < a.n_params):
                order[i], order[i + 1] = b, a
                moved = True
        if not moved:
            break
    return order


# --- the text summary ----------------------------------------------------------------------------------------

def summary_text(d: Diagnosis, data_name: str = "") -> str:
    """A readable summary of a Diagnosis for the terminal."""
    lines = []
    head = f"fluxcal diagnose {data_name}".rstrip()
    lines.append(head)
    lines.append(f"  model: {d.model}   (linear part {d.linear}; total field from {d.reference})")
    lines.append(f"  {d.n_samples} samples over {d.duration_s:.1f} s")
    ratio = d.rms_nT / d.noise_nT if d.noise_nT > 0 else float("inf")
    lines.append(f"  residual RMS {d.rms_nT:.3f} nT against a noise floor of {d.noise_nT:.3f} nT "
                 f"({ratio:.2f} x noise); held-out {d.heldout_rms_nT:.3f} nT")
    if d.linear_refit_rms_nT is not None:
        lines.append(f"  refitting the linear part would give {d.linear_refit_rms_nT:.3f} nT")
    lines.append("")
    lines.append("  channel              rms nT   noise nT")
    for n, r, s in zip(d.channel_names, d.channel_rms_nT, d.channel_noise_nT):
        lines.append(f"  {n:<18} {r:9.3f} {s:10.3f}")
    if d.parameters:
        lines.append("")
        lines.append("  fitted effect parameters (value +- standard error):")
        for p in d.parameters[:PARAMETER_LINES]:
            se = "undetermined by these data" if p.stderr is None else f"+- {p.stderr:.4g}"
            lines.append(f"    {p.name:<30} {p.value:12.5g} {se}")
        if len(d.parameters) > PARAMETER_LINES:
            lines.append(f"    ... {len(d.parameters) - PARAMETER_LINES} more in --json")
    lines.append("")
    lines.append("  where it fails (explained variance of the residual):")
    if not d.where:
        lines.append("    no observable explains the residual")
    for w in d.where[:8]:
        band = f" ({w['band']})" if w.get("band") else ""
        lines.append(f"    {w['channel']:<18} {w['observable'] + band:<28} {w['strength']:.2f}")
    if d.worst_segments:
        seg = ", ".join(f"{s['t_start_s']:.1f}-{s['t_end_s']:.1f} s ({s['rms_nT']:.2f} nT)"
                        for s in d.worst_segments)
        lines.append(f"  worst segments: {seg}")
    lines.append("")
    lines.append("  candidate effects (blocked held-out test):")
    lines.append("    effect         rms if added  held-out   gain     p-value   dBIC       verdict")
    for c in d.candidates:
        if not c.testable:
            lines.append(f"    {c.effect:<14} {'-':>12}  {'-':>8}   {'-':>6}   {'-':>8}  {'-':>9}   not testable: {c.reason}")
            continue
        verdict = "SIGNIFICANT" if c.significant else "no"
        lines.append(f"    {c.effect:<14} {c.rms_nT:10.3f} nT {c.heldout_rms_nT:8.3f}   {100 * c.gain:5.1f}%  "
                     f"{c.p_value:9.2g}  {c.bic_delta:9.1f}   {verdict}")
    told: set[frozenset] = set()
    for c in d.candidates:
        for other in c.indistinguishable_from:
            key = frozenset((c.effect, other))
            if key in told:
                continue
            told.add(key)
            if other in ("offset", "baseline") or other in d.effects:
                what = "the probe offsets" if other == "offset" else (
                    "the linear calibration" if other == "baseline" else f"the {other} term already in the model")
                lines.append(f"  {c.effect} cannot be told apart from {what} with these data: {c.separate_by}.")
            else:
                lines.append(f"  {c.effect} and {other} are indistinguishable with these data (equal held-out gain, "
                             f"collinear regressors): {c.separate_by}.")
    best = d.best
    lines.append("")
    if best is None:
        lines.append("  no missing effect is significant: the model explains the data down to the noise"
                     if ratio < 1.2 else "  no catalogue effect explains the rest of the residual significantly")
    else:
        lines.append(f"  most likely missing: {best.effect} (RMS {d.rms_nT:.3f} -> {best.rms_nT:.3f} nT); "
                     f"try: --effects {','.join(d.effects + [best.effect])}")
    for n in d.notes:
        lines.append(f"  note: {n}")
    return "\n".join(lines)


__all__ = ["diagnose", "Diagnosis", "Candidate", "summary_text", "where_it_fails", "worst_segments",
           "P_SIGNIFICANT", "GAIN_SIGMAS"]
