"""Discovery beside the catalogue's best effect, and the verdict said again with what it found (diagnostics.diagnose's
step 6): the catalogue's significant effects judged again beside the groups found, kept only where they still add, and
the story told of the model with both."""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.effects import Model
from fluxcal.service.numerics.engine import residual_hints

from .discover import beside
from .discover import discover as find_terms
from .fits import heldout, try_candidate
from .frames import frame_summary, frames
from .result import Candidate
from .signature import (
    CHANNEL_FACTOR,
    FLOOR_FACTOR,
    Carried,
    channels_above,
    describe,
    rest_is_flicker,
    signature,
    verdict,
)
from .verdict import rank
from .where import where_it_fails


def at_floor(found: Any, noise_nT: float) -> bool:
    """Whether the terms discovery claims explain the data down to their noise, as the catalogue's "explained" asks:
    the held-out error within FLOOR_FACTOR of the floor, every channel within CHANNEL_FACTOR of its own in the fit."""
    fit = found.fit
    if fit is None or found.heldout_rms_nT is None or found.heldout_rms_nT > FLOOR_FACTOR * noise_nT:
        return False
    noise = 1.0 / fit.problem.weights
    return bool(np.all(fit.channels.rms_nT <= CHANNEL_FACTOR * noise))


def beyond_catalogue(ed: Any, model: Model, cur: Any, cur_ho: Any, cands: list[Candidate], told: dict[str, Any],
                      sig_cur: dict[str, Any], carried: Carried, reference: np.ndarray, weights: np.ndarray,
                      n_blocks: int, noise: np.ndarray, noise_nT: float, tell: Any) -> tuple[Any, dict, list]:
    """Discovery beside the model and the catalogue's best effect (if any); where it claims, the catalogue's best
    judged again beside the groups found (kept only where it still adds, as two catalogue effects are), and the
    verdict said again with the finding as its advice. Returns (the Discovery, the verdict, the candidates)."""
    best = next((c for c in cands if c.significant and c.fit is not None), None)
    base = best.fit if best is not None else cur
    found = find_terms(ed, base, heldout(base) if best is not None else cur_ho, reference, weights, n_blocks,
                       noise_nT, progress=lambda msg: tell(0.95, msg))
    if not found.claimed and best is not None and best.effect == "column":
        found = _instead_of_column(ed, best, cur, cur_ho, reference, weights, n_blocks, noise_nT, tell) or found
    if not found.claimed:
        return found, told, cands
    if best is not None:
        tell(0.97, f"{best.effect} beside what discovery found")
        alone = beside(found, ed, cur, cur_ho, reference, weights, n_blocks)
        if alone.claimed:
            again = try_candidate(ed, alone.fit.model, alone.fit, heldout(alone.fit), best.effect, reference, weights,
                                  residual_hints(alone.fit), n_blocks)
            if not again.significant:
                best.refuse("nothing beyond the discovered", f"nothing beyond what discovery found: beside it, "
                                                             f"{best.effect}'s held-out gain is "
                                                             f"{100 * again.gain:.1f} %")
                found = alone
                cands = rank(cands)
                best = next((c for c in cands if c.significant and c.fit is not None), None)
    base = best.fit if best is not None else cur
    base_where = where_it_fails(ed, base, noise)
    sig0 = sig_cur if best is None else signature(base, noise, base_where)
    sig0.setdefault("frames", frame_summary(frames(ed, base, noise)))
    if best is None or best.heldout_channels_nT is None:
        above = channels_above(base, (heldout(base) if best is not None else cur_ho).channel_rms_nT, noise, base_where)
    else:
        above = channels_above(base, best.heldout_channels_nT, noise, base_where)
    again_told = verdict(cur.rms_nT, noise_nT, best, sig0, carried, above)
    if again_told["kind"] in ("at the floor", "explained"):
        # the verdict is over all channels together; a family of them was not at its floor
        again_told.update(kind="unexplained" if best is None else "partly explained", left=describe(sig0, carried)[0],
                          advice=None, signature=sig0)
    if told.get("linear_refit_nT") is not None:
        again_told["linear_refit_nT"] = told["linear_refit_nT"]
    # beside the finding: what the residual with the groups found still follows (from the residual without them,
    # it named the very column the groups follow)
    sig_found = (signature(found.fit, noise, where_it_fails(ed, found.fit, noise))
                 if not at_floor(found, noise_nT) else None)
    beside_it = describe(sig_found, carried)[1] if sig_found is not None else None
    again_told["advice"] = found.sentence() + (f"; beside it: {beside_it}" if beside_it else "")
    if sig_found is not None and rest_is_flicker(sig_found, carried):
        again_told["rest"] = "flicker"       # what the finding leaves is the probes' own slow noise: no missing effect
    return found, again_told, cands


def _instead_of_column(ed: Any, best: Candidate, cur: Any, cur_ho: Any, reference: np.ndarray, weights: np.ndarray,
                       n_blocks: int, noise_nT: float, tell: Any) -> Any:
    """Discovery beside the model without the catalogue's `column`, where beside it discovery found nothing: `column`
    takes every logged column and its rate on every axis (30 parameters a probe for five columns), which discovery's
    library holds one group at a time; where the groups it finds predict the held-out blocks at least as well with
    fewer parameters, they are what the data show (a flap's field on an hour-long board that wanders: `column` left
    1.15 times the untouched board's held-out error, the flap's own offset 1.08). The Discovery, or None."""
    tell(0.96, "discovery beside the model without column")
    alone = find_terms(ed, cur, cur_ho, reference, weights, n_blocks, noise_nT, progress=lambda msg: tell(0.96, msg))
    if not alone.claimed:
        return None
    ours, theirs = heldout(alone.fit), heldout(best.fit)
    fewer = alone.fit.rank - cur.rank < best.fit.rank - cur.rank
    return alone if fewer and ours.sse_w.sum() <= theirs.sse_w.sum() else None
