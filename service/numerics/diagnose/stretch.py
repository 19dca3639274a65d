"""A gross disturbance in time (where.gross_stretch: a vehicle or a magnet passing, a knock) in a diagnosis: the
candidates significant only with it demoted, and what the advice says of it first, unless a term found explains it.
Numerics only."""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.effects import Model
from fluxcal.service.numerics.engine import fit_model, residual_hints

from .fits import heldout, try_candidate
from .result import Candidate
from .where import GROSS_RATIO, stretch_ratio


def demote_on_one_stretch(ed: Any, model: Model, cands: list[Candidate], cur: Any, stretch: dict[str, Any] | None,
                           reference: np.ndarray, weights: np.ndarray, n_blocks: int, tell: Any) -> list[str]:
    """A gross disturbance in time (a vehicle or a magnet passing, a knock) pulls the least-squares fit everywhere,
    and a flexible term that compensates for the pull can pass every block's test while following nothing real
    (Magneto's test file, a 47-s stretch 4,000 nT off: crossfield 'significant' at 21 %, 8 % without it). A
    significant candidate whose fit leaves the stretch the model leaves gross (where.gross_stretch) still gross is
    judged again with the stretch left out, and stays significant only if it still is (one that explains the
    stretch, as eddy a stretch of fast turning, is not asked). Returns a note when one was demoted."""
    if stretch is None:
        return []
    noise = 1.0 / weights
    demoted: list[str] = []
    lo, hi = stretch["t_start_s"], stretch["t_end_s"]
    rows = np.flatnonzero((ed.t_s < lo) | (ed.t_s > hi))
    sub, ref, base = ed.subset(rows), reference[rows], None
    for c in [c for c in cands if c.significant and c.fit is not None]:
        left = stretch_ratio(c.fit, noise, lo, hi)
        if not left >= GROSS_RATIO:
            continue                                  # it explains the stretch (or there is nothing to say)
        tell(0.96, f"trying {c.effect} without {lo:.1f}-{hi:.1f} s")
        base = base or fit_model(sub, model, cur.state.linear, ref, weights, n_blocks=n_blocks)
        again = try_candidate(sub, model, base, heldout(base), c.effect, ref, weights, residual_hints(base), n_blocks)
        if again.significant:
            continue
        c.refuse("rests on one stretch", f"rests on {lo:.1f}-{hi:.1f} s, which it leaves {left:.1f} x the rest's "
                                         f"residual: without that stretch its held-out gain is "
                                         f"{100 * again.gain:.1f} %")
        demoted.append(c.effect)
    if not demoted:
        return []
    return [f"{lo:.1f}-{hi:.1f} s: the residual there is {stretch['ratio']:.1f} x the rest's and no term follows it (a "
            f"disturbance in time: a vehicle or a magnet passing, a knock, a glitch); {' and '.join(demoted)} "
            f"{'was' if len(demoted) == 1 else 'were'} significant only with it"]


def explains_stretch(found: Any, stretch: dict[str, Any], noise_nT: float, cur: Any) -> bool:
    """Whether what discovery found leaves the gross stretch within GROSS_RATIO of the rest: then the stretch was its
    term's doing (a flap at the top of its swing, where a magnet's field grows fastest), no disturbance in time."""
    if found is None or not found.claimed or found.fit is None:
        return False
    noise = np.asarray(cur.problem.weights, float) ** -1
    return stretch_ratio(found.fit, noise, stretch["t_start_s"], stretch["t_end_s"]) < GROSS_RATIO


def stretch_advice(stretch: dict[str, Any], advice: str | None) -> str:
    """The gross stretch no term follows, first: its pull on the least-squares fit spreads over the whole record and
    colours what the rest of the residual seems to follow."""
    lo, hi = stretch["t_start_s"], stretch["t_end_s"]
    return (f"first {lo:.1f}-{hi:.1f} s, where the residual is {stretch['ratio']:.1f} x the rest's: a disturbance in time "
            f"(a vehicle or a magnet passing, a knock, a glitch) pulls the fit over the whole record; judge the rest "
            f"without it (--skip {lo:.1f}-{hi:.1f})" + (f"; then: {advice}" if advice else ""))
