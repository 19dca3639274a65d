"""Model versus measurement: residual channels, where the model fails, and which effect is missing.

`diagnose(data, effects=...)` fits the model (the linear calibration plus the named effects) and
reports (docs/contracts.md):

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

Numerics only: no file I/O (fluxcal.service.wiring.commands.diagnose and fluxcal.service.io.report do that).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.service.numerics.effects import Baseline, Model, known_effects, make_model, make_term
from fluxcal.service.numerics.effects.temperature import borrowed_notes
from fluxcal.service.numerics.engine import (
    LinearCalibration,
    as_effect_data,
    fit_model,
    initial_linear,
    reference_total,
    residual_hints,
    scaled_to,
    start_weights,
)
from fluxcal.service.numerics.usable import refuse_stuck, temperature_notes

from .beyond import at_floor, beyond_catalogue
from .fits import heldout, try_candidate
from .frames import frame_summary, frames
from .result import N_BLOCKS, P_SIGNIFICANT, Candidate, Diagnosis, Progress
from .signature import (
    FLOOR_FACTOR,
    FOLLOWS,
    SHARED,
    Carried,
    channels_above,
    describe,
    signature,
    verdict,
)
from .stretch import demote_on_one_stretch, explains_stretch, stretch_advice
from .verdict import demote_nested, mark_indistinguishable, rank
from .weak import heldout_weakness
from .where import gross_stretch, where_it_fails, worst_segments


def diagnose(data: Any, *, effects: Sequence[str] = (), calibration: Any = None, fix_linear: bool | None = None,
             candidates: Sequence[str] | None = None, total_nT: float | None = None,
             positions_m: np.ndarray | None = None, n_blocks: int = N_BLOCKS,
             progress: Progress | None = None, check_linear: Callable[[Any], None] | None = None,
             discover: bool | None = None) -> Diagnosis:
    """Compare the model (linear calibration + `effects`) with the data; find what fails and what is missing.

    calibration: a linear calibration to hold fixed (the model compared is then exactly that
    calibration plus the effects); None refits the linear part. fix_linear overrides that choice.
    check_linear(linear): asked of the refitted linear part before any candidate (a refusal costs the first fit
    only); where the calibration is held, of the refit made for comparison (a refusal is then said in the advice).
    discover: look for the missing term in the library beyond the catalogue (discover.py): None (the default) where
    the catalogue leaves an excess (_excess_left), True always, False never."""
    tell = progress if progress is not None else (lambda frac, msg: None)
    ed = as_effect_data(data, total_nT=total_nT, positions_m=positions_m)
    notes = _data_notes(ed)
    fixed = (calibration is not None) if fix_linear is None else bool(fix_linear)
    tell(0.0, "linear calibration")
    linear, reference, ref_kind, weights, model = _start(ed, calibration, fixed, effects, notes)

    # 1. the model as it stands
    tell(0.05, f"fitting {model}")
    cur = fit_model(ed, model, linear, reference, weights, n_blocks=n_blocks)
    if check_linear is not None and not fixed:
        check_linear(cur.state.linear)
    cur_ho = heldout(cur)
    if not cur.converged:
        notes.append(f"the model fit stopped after {cur.iterations} iterations without converging")
    linear_refit = refit_refused = None
    if fixed:                               # what refitting the calibration held would give, for comparison
        tell(0.1, "linear refit for comparison")
        refit = fit_model(ed, Model([Baseline()]) + model, linear, reference, weights, n_blocks=n_blocks)
        linear_refit, refit_refused = refit.rms_nT, _refused(check_linear, refit.state.linear)

    # 2. the candidates: each effect not in the model, fitted beside it and judged on held-out blocks (fits.py)
    names = list(candidates) if candidates is not None else [n for n in known_effects() if n not in model]
    cands = _try_each(ed, model, cur, cur_ho, names, reference, weights, n_blocks, tell)

    # 3. where the model fails: what the residual follows (where.py), and the signature of that residual
    tell(0.87, "where it fails")
    noise = 1.0 / weights
    noise_nT = float(np.sqrt(np.mean(noise ** 2)))
    where, sig_cur, frames_cur = _where(ed, cur, noise)

    # 4. the verdict over the candidates: which are indistinguishable, which keep their gain beside the
    # others, and their order (verdict.py)
    tell(0.9, "comparing candidates")
    cands, stretch = _compare(ed, model, cur, cands, sig_cur, reference, weights, n_blocks, tell, notes)

    # 5. the verdict in kinds, per channel as well as over all, and what is left described (signature.py)
    best = next((c for c in cands if c.significant and c.fit is not None), None)
    carried = Carried.of(ed)
    left_where, above, held_above = _left(ed, best, cur, cur_ho, where, noise)
    told = verdict(cur.rms_nT, noise_nT, best, _what_is_left(ed, best, sig_cur, noise, noise_nT, left_where, above),
                   carried, above)

    # 6. beyond the catalogue: the library of terms the data allow (discover.py), where the catalogue leaves an excess:
    # a channel above its floor, a family of them, or a residual that still follows what the data carry
    found = None
    if discover or (discover is None and (held_above or _excess_left(told, best.fit if best is not None else cur, noise,
                                                                      left_where))):
        tell(0.93, "discovery beyond the catalogue")
        found, told, cands = beyond_catalogue(ed, model, cur, cur_ho, cands, told, sig_cur, carried, reference,
                                               weights, n_blocks, noise, noise_nT, tell)
        best = next((c for c in cands if c.significant and c.fit is not None), None)

    weak = _weakness(cur, cur_ho, best, found)
    _last_advice(told, notes, cur, best, found, weak, cands, (linear_refit, refit_refused), noise_nT, stretch,
                 carried)
    notes += _coloured_noise_notes(sig_cur.get("spectral_slope"), model.effects, ed.duration_s)

    tell(1.0, "done")
    return Diagnosis(effects=model.effects, model=str(model), linear="fixed" if fixed else "refit",
                     reference=ref_kind, rms_nT=cur.rms_nT, noise_nT=noise_nT, verdict=told,
                     channel_names=list(cur.channels.names), channel_rms_nT=cur.channels.rms_nT,
                     channel_noise_nT=noise, linear_refit_refused=refit_refused,
                     where=where, candidates=cands, worst_segments=worst_segments(cur), n_samples=ed.n_samples,
                     duration_s=ed.duration_s, heldout_rms_nT=cur_ho.rms_nT, notes=notes, fit=cur,
                     linear_refit_rms_nT=linear_refit, parameters=cur.parameters(), frames=frames_cur,
                     discovery=found, heldout_weak=weak)


def _data_notes(ed: Any) -> list[str]:
    """What the data left out or lack that every figure depends on: saturated rows, invalid or borrowed temperatures."""
    notes: list[str] = []
    if ed.dropped_rows:
        notes += ed.dropped_notes or [f"{ed.dropped_rows} samples with a saturated axis (NaN) left out"]
    notes += temperature_notes(ed.temp_C, ed.probe_names)        # the temperature terms are among those tested
    return notes + borrowed_notes(ed.temp_C, ed.probe_names)


def _where(ed, fit, noise: np.ndarray) -> tuple[list, dict, Any]:
    """What the residual of `fit` follows (where.py), its signature with the frames it stands still in."""
    where = where_it_fails(ed, fit, noise)
    sig = signature(fit, noise, where)
    fr = frames(ed, fit, noise)
    sig["frames"] = frame_summary(fr)
    return where, sig, fr


def _compare(ed, model, cur, cands: list[Candidate], sig_cur: dict, reference, weights, n_blocks: int, tell,
             notes: list[str]) -> tuple[list[Candidate], Any]:
    """The candidates against each other (verdict.py): which are indistinguishable or nested, which need a common
    mode, which rest on one stretch of time, which keep their gain beside the best; ranked. Also the worst stretch."""
    mark_indistinguishable(cands)
    demote_nested(cands)
    _demote_without_common_mode(cands, sig_cur.get("shared_fraction"))
    cands = rank(cands)
    stretch = gross_stretch(cur, 1.0 / weights)
    notes += demote_on_one_stretch(ed, model, cands, cur, stretch, reference, weights, n_blocks, tell)
    cands = rank(cands)
    _beyond_the_best(ed, model, cands, reference, weights, n_blocks, tell)
    return rank(cands), stretch


def _what_is_left(ed, best, sig_cur: dict, noise: np.ndarray, noise_nT: float, where: list[dict],
                  above: list[dict]) -> dict:
    """The signature of what the best candidate leaves (the model's own without one; nothing where every channel is
    at its floor)."""
    if best is None:
        return sig_cur
    if best.rms_nT > FLOOR_FACTOR * noise_nT or above:
        left = signature(best.fit, noise, where)
        left["frames"] = frame_summary(frames(ed, best.fit, noise))
        return left
    return {}


def _left(ed: Any, best: Candidate | None, cur: Any, cur_ho: Any, where: list[dict],
          noise: np.ndarray) -> tuple[list[dict], list[dict], list[dict]]:
    """(what the residual of the best model found follows (where.py), the channels it leaves above their own floor
    (signature.channels_above: held out and in the fit, for the verdict; held out alone, for discovery))."""
    fit, held, left_where = cur, cur_ho.channel_rms_nT, where
    if best is not None:
        fit, left_where = best.fit, where_it_fails(ed, best.fit, noise)
        held = best.heldout_channels_nT if best.heldout_channels_nT is not None else best.fit.channels.rms_nT
    return (left_where, channels_above(fit, held, noise, left_where),
            channels_above(fit, held, noise, held_out_only=True))


def _excess_left(told: dict[str, Any], fit: Any, noise: np.ndarray, where: list[dict]) -> bool:
    """Whether the catalogue's best model leaves an excess discovery should look at: a channel above its floor (the
    verdict unexplained or partly explained), a family of channels DISCOVER_EXCESS times its floor, or a residual that
    still follows something the data carry."""
    return (told["kind"] in ("unexplained", "partly explained") or family_excess(fit, noise) >= DISCOVER_EXCESS
            or follows_observable(where))


#: observables a residual may follow that discovery's library builds from (time, a band, orientation and heading are
#: no cause it can take: the catalogue's drift, lines, the linear calibration and platform have them)
NOT_DISCOVERABLE = ("time", "frequency", "orientation", "heading")


def follows_observable(where: list[dict]) -> bool:
    """Whether a residual still follows something the data carry that discovery's library builds from, with a share
    of FOLLOWS or more (a coil's current that `column` took in part: 0.58 of s1's scalar residual left)."""
    return any(w["strength"] >= FOLLOWS and w["observable"] not in NOT_DISCOVERABLE for w in where)


def _start(ed: Any, calibration: Any, fixed: bool, effects: Sequence[str], notes: list[str]):
    """The linear part the model starts from (the calibration held, or one fitted), the reference total field and
    what it is, the channels' weights and the model; an effect the data cannot take refused, and a probe that did
    not measure (usable.refuse_stuck), a calibration held or not."""
    refuse_stuck(ed.raw_nT, ed.probe_names)
    if calibration is not None:
        linear = LinearCalibration.from_any(calibration, ed.n_probes)
    else:
        ref0 = ed.ref_total_nT if ed.ref_total_nT is not None else ed.total_nT
        linear = initial_linear(ed, ref0)
    reference, ref_kind = reference_total(ed, linear, held=fixed)
    if ref_kind == "estimated" and not fixed:
        linear = scaled_to(linear, ed, reference)
    if ref_kind == "estimated":
        how = ("the field the calibration held assumed (its total_nT_assumed)" if fixed and linear.assumed_total_nT
               else f"the median |corrected| of {ed.probe_names[0]} by the calibration held" if fixed else
               f"as fit assumes it: the calibrated sphere has the volume of {ed.probe_names[0]}'s raw ellipsoid")
        notes.append(f"no ref_total and no total field in --config: the total field is estimated, "
                     f"{float(reference[0]):,.1f} nT, {how} (an overall scale error cannot be seen)")
    weights = start_weights(ed, linear, reference)
    model = make_model(list(effects), baseline=not fixed)
    for t in model.effect_terms:
        why = t.why_unavailable(ed)
        if why:
            raise CalibrationRefused(f"effect {t.name!r} cannot be fitted to these data: {why}")
    return linear, reference, ref_kind, weights, model


def _try_each(ed, model, cur, cur_ho, names: list[str], reference, weights, n_blocks: int, tell) -> list[Candidate]:
    """Each named effect fitted beside the model and judged on held-out blocks (fits.try_candidate)."""
    hints = residual_hints(cur)
    cands: list[Candidate] = []
    for i, name in enumerate(names):
        tell(0.15 + 0.7 * i / max(len(names), 1), f"trying {name}")
        cands.append(try_candidate(ed, model, cur, cur_ho, name, reference, weights, hints, n_blocks))
    return cands


def _refused(check_linear: Callable[[Any], None] | None, linear: Any) -> str | None:
    """Why `check_linear` refuses the linear part `linear` (None: it takes it, or there is no check)."""
    if check_linear is None:
        return None
    try:
        check_linear(linear)
    except CalibrationRefused as e:
        return getattr(e, "problem", None) or str(e)     # what is not determined, without the refusal's way out
    return None


def _weakness(cur: Any, cur_ho: Any, best: Candidate | None, found: Any) -> dict[str, Any] | None:
    """Whether the held-out test can judge these data (weak.py), asked of the best model found: a missing effect that
    changes in time makes the model's own held-out error large against its in-sample one, which the effect, once
    added, takes away (a tutorial's temperature effect: 1.38 without it, 1.00 with it, called SIGNIFICANT under 'the
    gains are not a verdict')."""
    if found is not None and found.claimed and found.fit is not None:
        return heldout_weakness(found.fit, found.heldout_rms_nT)
    if best is not None:
        return heldout_weakness(best.fit, best.heldout_rms_nT)
    return heldout_weakness(cur, cur_ho.rms_nT)


def _last_advice(told: dict, notes: list[str], cur, best, found, weak, cands, refit: tuple, noise_nT: float,
                 stretch, carried: Carried) -> None:
    """What the verdict and the notes say last: a weak held-out test, a fit stopped early, a calibration held that is
    off (refit: the residual of the linear part refitted, and why these data do not determine it, or None), a
    disturbance in time."""
    linear_refit, refit_refused = refit
    if weak is None and found is not None and found.claimed and (at_floor(found, noise_nT)
                                                                  or told.get("rest") == "flicker"):
        # one story: what discovery found takes every channel to its floor, so the headline says so (it said
        # "unexplained" above a finding that explained it); `left` stays what the catalogue leaves, which it takes,
        # without the frames' guesses at what moves it (a field of the site, or each probe's noise): the finding says
        told.update(kind="explained beyond the catalogue", rms_nT=found.rms_nT, channels_above=[],
                    left=describe({**(told.get("signature") or {}), "frames": None,
                                   "channels_above": told.get("channels_above") or []}, carried)[0])
    if told.get("kind") != "explained beyond the catalogue":
        told.pop("rest", None)              # said with that headline only (the held-out test weak: it stays unjudged)
    if weak is not None:
        notes.append(f"the held-out test is weak here: {weak['reason']}; {weak['advice']}")
        if found is not None and found.claimed:
            told["advice"] += f"; but the held-out test is weak here ({weak['reason']}): {weak['advice']}"
        elif told["kind"] == "unexplained":
            told["advice"] = _weak_advice(weak, cands, told.get("advice"))
    if best is not None and not best.fit.converged:     # candidates stop early (conservative for the gain)
        notes.append(f"{best.effect}'s fit stopped after {best.fit.iterations} iterations, not converged: its "
                     f"parameters and residual are not final (its gain is understated); `--effects {best.effect}` fits "
                     f"it with more iterations")
    if linear_refit is not None and best is not None and best.rms_nT >= (1.0 - LINEAR_REFIT_MARGIN) * linear_refit:
        told["linear_refit_nT"] = linear_refit       # refitting the calibration held explains as much: one to the data
    if (linear_refit is not None and best is None and told["kind"] == "unexplained"
            and linear_refit < (1.0 - 0.1) * cur.rms_nT):
        told["advice"] = (f"the calibration held is off: refitting its linear part alone brings the residual from "
                          f"{cur.rms_nT:.3f} to {linear_refit:.3f} nT "
                          + ("(diagnose without --calibration, or fit again)" if refit_refused is None else
                             f"in-sample, but these data do not determine that refit ({refit_refused}): a calibration "
                             f"of the same sensor from a fuller turn, held here, would tell")
                          + (f"; then: {told['advice']}" if told.get("advice") and
                             linear_refit > FLOOR_FACTOR * noise_nT else ""))
    if stretch is not None and told["kind"] == "unexplained" and not explains_stretch(found, stretch, noise_nT, cur):
        told["advice"] = stretch_advice(stretch, told.get("advice"))


#: discovery runs by itself where the catalogue leaves an excess: the verdict unexplained or partly explained, or a
#: family of channels (the scalar channels, or the differences) this many times its floor (a field common to the
#: probes shows in the scalar channels alone; over all channels it is diluted under the verdict's 1.3)
DISCOVER_EXCESS = 1.15


def family_excess(fit: Any, noise: np.ndarray) -> float:
    """The largest RMS over noise floor of a family of channels: the scalar channels, the differences, the
    differences to a reference vector (each pooled)."""
    pr = fit.problem
    rms = fit.channels.rms_nT
    fams: dict[str, list[int]] = {}
    for c in range(len(rms)):
        fams.setdefault(pr.channel_probe(c)[0], []).append(c)
    return max(float(np.sqrt(np.mean(rms[c] ** 2) / np.mean(noise[c] ** 2))) for c in fams.values())


#: with the linear part held fixed, the best candidate is said to be no better than a refit of the linear part when
#: it brings the residual less than this far (relative) below the refit's
LINEAR_REFIT_MARGIN = 0.005


def _coloured_noise_notes(slope: float | None, effects: Sequence[str], duration_s: float) -> list[str]:
    """What a coloured residual (its spectral slope) means for the standard errors: the block jackknife
    (engine/solve.py), and for every effect a power-law model of the noise spectrum extended to the record's
    own periods (engine/coloured.py), the larger of the two."""
    if slope is None or slope > -0.5:
        return []
    out = [f"the residual is coloured (spectrum ~ f^{slope:.1f} across the band above its floor): standard errors come from the block jackknife "
           f"over time blocks, not from white-noise formulas, and each effect's from a power law fitted to each "
           f"probe's noise spectrum where that is larger"]
    if effects:
        out.append(f"a wander of the noise at periods as long as the record ({duration_s:.0f} s) looks like a drift, "
                   f"a step or any slow effect; their standard errors come from that power law, extended to those "
                   f"periods as fitted where the residual keeps that power there, else as flicker (1/f) noise: a "
                   f"noise that steepens only below what the record shows (a random walk of the offsets slower "
                   f"than it) would make them too small")
    return out


def _beyond_the_best(ed: Any, model: Model, cands: list[Candidate], reference: np.ndarray, weights: np.ndarray,
                     n_blocks: int, tell: Any) -> None:
    """A strong missing effect leaks into the others: each is fitted beside the model without it, and soaks
    up a part of it. So every other significant candidate is tried again beside the model and the best
    one, and stays significant only for what it adds beyond it (two effects at once keep both)."""
    best = next((c for c in cands if c.significant and c.fit is not None), None)
    if best is None:
        return
    others = [c for c in cands if c is not best and c.significant and best.effect not in c.indistinguishable_from]
    if not others:
        return
    with_best = model + make_term(best.effect)
    ho = heldout(best.fit)
    hints = residual_hints(best.fit)
    for c in others:
        tell(0.95, f"trying {c.effect} beside {best.effect}")
        again = try_candidate(ed, with_best, best.fit, ho, c.effect, reference, weights, hints, n_blocks)
        if not again.significant:
            c.refuse(f"nothing beyond {best.effect}", f"nothing beyond {best.effect}: beside it, {c.effect}'s held-out "
                                                      f"gain is {100 * again.gain:.1f} %")


def _weak_advice(weak: dict[str, Any], cands: list[Candidate], advice: str | None) -> str:
    """Unexplained on data whose held-out test is weak: say so, what would decide, and which candidate explains most
    in-sample (undecided, not named as the cause)."""
    tried = [c for c in cands if c.testable and c.fit is not None and c.n_params > 0 and c.p_value < P_SIGNIFICANT]
    top = min(tried, key=lambda c: c.bic_delta, default=None)
    said = (f"the held-out test cannot decide on these data ({weak['reason']}); "
            + (f"in-sample, {top.effect} explains most (residual {top.rms_nT:.3f} nT, dBIC {top.bic_delta:.0f}), "
               f"undecided; " if top is not None else "")
            + weak["advice"])
    return said + (f"; then: {advice}" if advice else "")


def _demote_without_common_mode(cands: list[Candidate], shared: float | None) -> None:
    """A term for a change common to all probes (ambient) counts only where the residual is mostly shared."""
    for c in cands:
        cls = known_effects().get(c.effect)
        if c.significant and getattr(cls, "needs_common_mode", False) and (shared is None or shared < SHARED):
            c.refuse("not common to the probes", f"no change common to the probes: "
                                                 f"{0 if shared is None else 100 * shared:.0f} % of the residual's "
                                                 f"excess is shared (a change of the site's field would be common to "
                                                 f"all)")

