"""Each candidate effect fitted beside the model and judged on held-out time blocks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from fluxcal.drivers.errors import FluxcalError
from fluxcal.service.numerics.effects import Model, known_effects, make_term
from fluxcal.service.numerics.effects.base import EffectData, EffectTerm
from fluxcal.service.numerics.effects.hysteresis import no_step_reason
from fluxcal.service.numerics.effects.span import ReadingSpan
from fluxcal.service.numerics.engine import (
    RANK_TOL,
    FitResult,
    Problem,
    Warm,
    fit_problem,
    warm_from,
)

from .result import ABSORBED, CANDIDATE_ITERATIONS, GAIN_SIGMAS, MIN_GAIN, P_SIGNIFICANT, Candidate


@dataclass
class Heldout:
    """The held-out residual of a fit, per time block: weighted and unweighted sums of squares, value counts, and
    per block and channel the unweighted sum of squares (K, C)."""

    sse_w: np.ndarray
    sse: np.ndarray
    n: np.ndarray
    sse_channels: np.ndarray

    @property
    def rms_nT(self) -> float:
        return float(np.sqrt(self.sse.sum() / self.n.sum()))

    @property
    def channel_rms_nT(self) -> np.ndarray:
        """(C,) each channel's held-out RMS, nT."""
        rows = self.n.sum() / max(self.sse_channels.shape[1], 1)
        return np.sqrt(self.sse_channels.sum(0) / max(rows, 1.0))

    @property
    def mse_w(self) -> np.ndarray:
        return self.sse_w / self.n


def heldout(fit: FitResult) -> Heldout:
    return Heldout(*fit.heldout())


def _compare(base: FitResult, base_ho: Heldout, cand: FitResult, cand_ho: Heldout) -> dict[str, Any]:
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
        from scipy import stats                         # here, not at import (a command's start)

        f = ((rss0 - rss1) / dp) / (rss1 / dof)
        p = float(stats.f.sf(f, dp, dof))
    else:
        p = 1.0
    bic0 = n * np.log(rss0 / n) + base.rank * np.log(n)
    bic1 = n * np.log(max(rss1, 1e-300) / n) + cand.rank * np.log(n)
    return {"gain": gain, "lr": lr, "lr_se": lr_se, "lr_b": lr_b, "p": p, "bic": float(bic1 - bic0),
            "dp": cand.rank - base.rank}


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


def _separation(a: str, b: str) -> str:
    known = known_effects()
    ta, tb = known.get(a), known.get(b)
    for t, other in ((ta, b), (tb, a)):
        if t is not None and other in t.separation:
            return t.separation[other]
    return (f"vary what each depends on independently ({_depends(a)} against {_depends(b)}), "
            f"or record more of the motion that excites them")


def _depends(name: str) -> str:
    return {"temperature": "temperature", "thermal": "temperature, delayed", "eddy": "rotation rate", "lag": "rotation rate",
            "nonlinearity": "field per axis", "drift": "time", "gradient": "attitude and position",
            "crossfield": "field across each axis", "hysteresis": "field history", "platform": "attitude", "column": "a logged column", "ambient": "the other probes",
            "offset": "attitude", "baseline": "attitude"}.get(name, name)


def try_candidate(ed: EffectData, model: Model, cur: FitResult, cur_ho: Heldout, name: str,
                   reference: np.ndarray, weights: np.ndarray, hints, n_blocks: int) -> Candidate:
    untestable = Candidate(effect=name, rms_nT=cur.rms_nT, heldout_rms_nT=cur_ho.rms_nT, testable=False)
    term: EffectTerm = make_term(name)
    why = term.why_unavailable(ed)
    if why:
        untestable.reason = why
        return untestable
    try:
        # the model's terms keep the references they were fitted with (perming step instants, temperature
        # and time origins): a candidate is tried beside the model as it is, not beside a model whose steps
        # are looked for again in a residual they were already taken from
        pr = Problem(ed, model + term, cur.state.linear, reference, weights=weights, n_blocks=n_blocks,
                     hints=hints, refs=[v.cache for v in cur.problem.views])
        if pr.term_size(name) == 0:
            untestable.reason = no_step_reason(pr.views) if name == "hysteresis" else "nothing to fit in these data"
            return untestable
        start, warm, ev0, jac0 = _warm_start(pr, cur)
        if warm is not None:
            # the model's normal equations at this very point are known: only the candidate's rows were
            # assembled; see first whether the model already spans them (then there is nothing to fit)
            absorbed = _absorbed_in(pr, warm.a_blocks.sum(0), name)
            if absorbed:
                same = Candidate(effect=name, rms_nT=cur.rms_nT, heldout_rms_nT=cur_ho.rms_nT,
                                 indistinguishable_from=absorbed, separate_by=_separation(name, absorbed[0]),
                                 reason=f"the model's {absorbed[0]} spans its regressors in these data",
                                 refusal=f"the model's {absorbed[0]} spans it")
                return same
        fit = _fit_from(pr, start, warm, ev0, jac0)
    except (FluxcalError, np.linalg.LinAlgError, ValueError) as e:
        untestable.reason = f"fit failed: {e}"
        return untestable
    ho = heldout(fit)
    if term.chooses_in_residual and hints is not None:
        ho = crossfit_heldout(ed, model, cur, cur_ho, name, reference, weights, hints, n_blocks)
    cmp = _compare(cur, cur_ho, fit, ho)
    c = Candidate(effect=name, rms_nT=fit.rms_nT, heldout_rms_nT=ho.rms_nT, gain=cmp["gain"],
                  log_ratio=cmp["lr"], log_ratio_se=cmp["lr_se"], p_value=cmp["p"], bic_delta=cmp["bic"],
                  n_params=int(cmp["dp"]), block_log_ratio=cmp["lr_b"], fit=fit, heldout_channels_nT=ho.channel_rms_nT)
    c.significant = bool(c.p_value < P_SIGNIFICANT and c.gain >= MIN_GAIN and c.log_ratio > GAIN_SIGMAS * c.log_ratio_se
                         and c.n_params > 0)
    floor = float(np.sqrt(np.mean((1.0 / np.asarray(weights, float)) ** 2)))
    if c.significant and not cur.rms_nT > floor:   # nothing left to explain: a held-out gain there is no evidence
        c.refuse("the model is at its noise floor",
                 f"the model's residual ({cur.rms_nT:.3g} nT) is not above its noise floor ({floor:.3g} nT): nothing "
                 f"is left for an effect to explain, and a held-out error "
                 f"({cur_ho.rms_nT:.3g} nT{' below the in-sample one' if cur_ho.rms_nT < cur.rms_nT else ''}) is "
                 f"no evidence for one")
    wald = _beyond_errors(c.parameters) if c.significant else None
    if wald:                       # the gain is the noise's slow wander: its parameters are within their errors
        c.refuse("within its errors of zero", wald)
    ruled_out = ((term.rules_out(c.parameters)
                  or term.rules_out_over(c.parameters, ReadingSpan.of(ed, fit.state.linear.offset_nT)))
                 if c.significant else None)
    if ruled_out:                  # a shape the effect's physics does not take (perming that came back)
        c.refuse("its physics rules it out", ruled_out)
    absorbed = _absorbed_by(fit, name)
    if absorbed:
        c.indistinguishable_from = absorbed
        c.separate_by = _separation(name, absorbed[0])
        c.refuse(f"the model's {absorbed[0]} spans it", f"the model's {absorbed[0]} spans its regressors in these data")
    return c


def _beyond_errors(parameters, p_level: float = P_SIGNIFICANT) -> str | None:
    """None where the candidate's determined parameters, with their standard errors (which take the residual's
    power law where it is coloured), stand beyond zero: jointly (sum of (value / error)^2 above the chi-square
    quantile of p = P_SIGNIFICANT) or one alone (|value / error| above the normal quantile of p = P_SIGNIFICANT / k,
    two-sided: an effect on one axis of one probe among k parameters); else why not. Under 1/f noise a polynomial
    in time, or a term of a slow rate, predicts held-out blocks from their neighbours' wander: 3 of 16 simulated
    worlds without any effect (300 s at 5 nT/sqrt(Hz)) had drift significant on the held-out test alone, with
    parameters at most 1.7-2.6 of their errors (sum 10-17 over 12); effects found had sums of 48-700, or one
    parameter at 4 of its errors."""
    z = np.array([p.value / p.stderr for p in parameters if p.stderr is not None and np.isfinite(p.stderr)
                  and p.stderr > 0 and np.isfinite(p.value)])
    if not z.size:
        return None
    from scipy import stats                             # here, not at import (a command's start)

    wald, crit = float(np.sum(z ** 2)), float(stats.chi2.isf(p_level, z.size))
    one, one_crit = float(np.max(np.abs(z))), float(stats.norm.isf(p_level / (2 * z.size)))
    if wald >= crit or one >= one_crit:
        return None
    return (f"its {z.size} parameters are within their errors of zero (sum of (value / error)^2 {wald:.1f}, below "
            f"{crit:.1f}; the largest {one:.1f} errors, below {one_crit:.1f}; p < {p_level:.2g}): the held-out gain "
            f"follows the noise's slow wander, not this effect")


def crossfit_heldout(ed: EffectData, model: Model, cur: FitResult, cur_ho: Heldout, name: str,
                     reference: np.ndarray, weights: np.ndarray, hints, n_blocks: int) -> Heldout:
    """The held-out errors of a term that chooses its regressors in the residual (perming step instants): for
    each block, the regressors are found again in the residual with that block left out, the term fitted with
    them, and the block predicted by the fit to the others. Found in the whole residual, the steps would be
    chosen on the very samples they are judged on, and any smooth change left there would pass for steps
    that predict well. A block with no step found outside it is predicted as the model predicts it. (Terms
    that only start from the residual, thermal's tau, or take another probe's residual at the same instant as
    their regressor, ambient, choose nothing there.)"""
    from fluxcal.service.numerics.effects.hysteresis import BARRIER

    pr0 = cur.problem
    sse_w, sse, cnt, per_channel = cur_ho.sse_w.copy(), cur_ho.sse.copy(), cur_ho.n.copy(), cur_ho.sse_channels.copy()
    for b, sl in enumerate(pr0.blocks):
        rows = pr0.rows[sl]
        masked = [r.copy() for r in hints[0]]
        for r in masked:
            r[rows] = np.nan
        # searched on each side of the block, not across it (a smooth change across a hole looks like a step)
        span = (float(ed.t_s[rows[0]]), float(ed.t_s[rows[-1]]))
        refs = [{**v.cache, BARRIER: span} for v in pr0.views]
        pr = Problem(ed, model + make_term(name), cur.state.linear, reference, weights=weights, n_blocks=n_blocks,
                     hints=(masked, hints[1]), refs=refs)
        if pr.term_size(name) == 0 or len(pr.blocks) != len(pr0.blocks):
            continue
        try:
            f = _fit_beside(pr, cur)
        except (FluxcalError, np.linalg.LinAlgError, ValueError):
            continue
        h = heldout(f)
        sse_w[b], sse[b], cnt[b], per_channel[b] = h.sse_w[b], h.sse[b], h.n[b], h.sse_channels[b]
    return Heldout(sse_w, sse, cnt, per_channel)


def _warm_start(pr: Problem, cur: FitResult) -> tuple[Any, Warm | None, Any, Any]:
    """(start, warm, ev0, jac0) of a candidate problem from the model's fit: the model's normal equations
    reused and only the candidate's rows assembled (warm None when the layouts differ)."""
    start = pr.start_state(cur.state.linear, cur.state)
    warm = warm_from(cur, pr)
    if warm is None:
        return start, None, None, None
    ev0 = pr.evaluate(start)
    jac0 = pr.jacobian(start, ev0)
    a_c, g_c = pr.assemble(jac0, ev0, only=~warm.known)
    both = warm.known[:, None] & warm.known[None, :]
    a_c[:, both] = warm.a_blocks[:, both]
    g_c[:, warm.known] = warm.g_blocks[:, warm.known]
    return start, Warm(a_c, g_c, np.ones(pr.n_params, bool)), ev0, jac0


def _fit_from(pr: Problem, start: Any, warm: Warm | None, ev0: Any, jac0: Any) -> FitResult:
    """At most CANDIDATE_ITERATIONS: a fit stopped early overstates its RSS, so its gain is understated
    (conservative); in practice one or two steps converge and only flat directions creep on."""
    if warm is None:
        return fit_problem(pr, start, max_iter=CANDIDATE_ITERATIONS)
    return fit_problem(pr, start, warm=warm, max_iter=CANDIDATE_ITERATIONS, ev0=ev0, jac0=jac0)


def _fit_beside(pr: Problem, cur: FitResult) -> FitResult:
    """A candidate problem fitted from the model's fit."""
    return _fit_from(pr, *_warm_start(pr, cur))
