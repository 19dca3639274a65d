"""The verdict over the candidates: which are indistinguishable from each other, and their order.
"""

from __future__ import annotations

import numpy as np

from fluxcal.service.numerics.effects import known_effects
from fluxcal.service.numerics.engine import (
    solve_normal,
)

from .fits import _separation, _slot_indices
from .result import COLLINEAR_R2, GAIN_SIGMAS, GAIN_TOLERANCE, MIN_GAIN, Candidate


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


def mark_indistinguishable(cands: list[Candidate]) -> None:
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


def demote_nested(cands: list[Candidate]) -> None:
    """A candidate that contains another (thermal holds temperature at tau = 0) is significant only where it
    beats the one it contains on the held-out blocks, by the same rule as a candidate beats the model: the
    extra parameters must earn their keep. Whatever the verdict on the one it contains, so long as that was
    fitted: a gain judged the noise's wander in temperature (its parameters within their errors of zero) was
    called SIGNIFICANT in thermal, which predicted the held-out blocks worse (2.383 against 2.259 nT) on a fit
    that had not converged (grad1-hidden-effect with `fit`'s calibration held)."""
    by = {c.effect: c for c in cands}
    for c in cands:
        cls = known_effects().get(c.effect)
        for inner in getattr(cls, "nests", ()):
            b = by.get(inner)
            if not (c.significant and b is not None and b.testable and b.block_log_ratio is not None
                    and c.block_log_ratio is not None):
                continue
            diff = c.block_log_ratio - b.block_log_ratio            # ln(MSE with b / MSE with c) per block
            se = float(diff.std(ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else float("inf")
            gain = 1.0 - (c.heldout_rms_nT / b.heldout_rms_nT) ** 2 if b.heldout_rms_nT > 0 else 0.0
            if not (gain >= MIN_GAIN and float(diff.mean()) > GAIN_SIGMAS * se):
                c.refuse(f"not better than {inner}", f"no better than {inner}, which it contains, on the held-out "
                                                     f"blocks ({c.heldout_rms_nT:.3f} against "
                                                     f"{b.heldout_rms_nT:.3f} nT)")


def rank(cands: list[Candidate]) -> list[Candidate]:
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
