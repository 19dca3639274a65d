"""A diagnosis as text for the terminal.
"""

from __future__ import annotations

from typing import Any

from fluxcal.service.numerics.effects import effect_spec
from fluxcal.service.numerics.engine.model_fit import not_shown

from .result import GAIN_SIGMAS, MIN_GAIN, P_SIGNIFICANT, Candidate, Diagnosis

PARAMETER_LINES = 18


DECIDES = (f"    the held-out columns decide: SIGNIFICANT needs a held-out gain of at least {100 * MIN_GAIN:g} %, "
           f"{GAIN_SIGMAS:g} standard errors\n    (block to block) above zero, p < {P_SIGNIFICANT:g}, and parameters "
           f"beyond their own errors;\n    p-value and dBIC assume white noise and alone decide nothing")


def verdict_word(c: Candidate, weak: dict | None = None) -> str:
    """The verdict column: SIGNIFICANT, or "no" with the figure that refused it ("undecided" where the held-out test
    is weak and nothing else refused it)."""
    if c.significant:
        return "SIGNIFICANT"
    if c.refusal:
        return f"no: {c.refusal}"
    if weak and c.n_params > 0:
        return "undecided: the held-out test is weak here"
    if c.n_params <= 0:
        return "no: nothing determined"
    if c.gain <= 0:
        return "no: held-out error rises"
    if c.gain < MIN_GAIN:
        return f"no: gain < {100 * MIN_GAIN:g} %"
    if c.log_ratio <= GAIN_SIGMAS * c.log_ratio_se:
        return f"no: held-out gain < {GAIN_SIGMAS:g} SE"
    return f"no: p >= {P_SIGNIFICANT:g}"


def reference_words(reference: str) -> str:
    """The total field a diagnosis compared with, in words: 'estimated from the data', 'from the ref_total column'."""
    return {"estimated": "estimated from the data", "ref_total": "from the ref_total column",
            "config": "from the configuration"}.get(reference, f"from {reference}")


def summary_text(d: Diagnosis, data_name: str = "") -> str:
    """A readable summary of a Diagnosis for the terminal."""
    lines = []
    head = f"fluxcal diagnose {data_name}".rstrip()
    lines.append(head)
    lines.append(f"  model: {d.model}   (linear part {d.linear}; total field {reference_words(d.reference)})")
    lines.append(f"  {d.n_samples} samples over {d.duration_s:.1f} s" + (
        "" if d.n_fitted is None else f"; the residuals over the {d.n_fitted} away from the record's ends and its "
                                      f"gaps in time (the rows every candidate's terms are fitted on)"))
    ratio = d.rms_nT / d.noise_nT if d.noise_nT > 0 else float("inf")
    lines.append(f"  residual RMS {d.rms_nT:.3f} nT against a noise floor of {d.noise_nT:.3f} nT "
                 f"({ratio:.2f} x noise); held-out {d.heldout_rms_nT:.3f} nT")
    if d.linear_refit_rms_nT is not None:
        lines.append(f"  refitting the linear part would give {d.linear_refit_rms_nT:.3f} nT"
                     + (" in-sample, but these data do not determine that refit" if d.linear_refit_refused else ""))
    lines.append("")
    lines.append("  channel              rms nT   noise nT")
    for n, r, s in zip(d.channel_names, d.channel_rms_nT, d.channel_noise_nT):
        lines.append(f"  {n:<18} {r:9.3f} {s:10.3f}")
    if d.parameters:
        lines.append("")
        lines.append("  fitted effect parameters (value +- standard error):")
        for p in d.parameters[:PARAMETER_LINES]:
            se = (f"at its floor: {p.at_floor}" if p.at_floor else "undetermined by these data" if p.stderr is None
                  else f"+- {p.stderr:.4g}")
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
    frame_lines = frames_text(d.frames)
    if frame_lines:
        lines.append("  per axis (rms nT) in each frame; % of the excess a vector fixed in the platform explains:")
        lines += frame_lines
    if d.worst_segments:
        seg = ", ".join(f"{s['t_start_s']:.1f}-{s['t_end_s']:.1f} s ({s['rms_nT']:.2f} nT)"
                        for s in d.worst_segments)
        lines.append(f"  worst segments: {seg}")
    lines.append("")
    lines.append("  candidate effects (blocked held-out test):")
    lines.append(DECIDES)
    if d.heldout_weak:              # a SIGNIFICANT effect also stands beyond its parameters' errors: said so, one story
        either = ("the gains alone decide nothing, and an effect called SIGNIFICANT below also stands beyond its "
                  "parameters' own errors" if any(c.significant for c in d.candidates)
                  else "the gains are not a verdict")
        lines.append(f"    the held-out test is weak here: {d.heldout_weak['reason']}: {either}")
    lines.append("    effect         rms if added  held-out   gain     p-value   dBIC       verdict")
    for c in d.candidates:
        if not c.testable:
            lines.append(f"    {c.effect:<14} {'-':>12}  {'-':>8}   {'-':>6}   {'-':>8}  {'-':>9}   not testable: {c.reason}")
            continue
        verdict = verdict_word(c, d.heldout_weak)
        gain = gain_text(c.gain, d.heldout_weak)
        lines.append(f"    {c.effect:<14} {c.rms_nT:10.3f} nT {c.heldout_rms_nT:8.3f}   {gain}  "
                     f"{c.p_value:9.2g}  {c.bic_delta:9.1f}   {verdict}")
    lines += _alike_lines(d)
    lines += discovery_lines(d)
    lines.append("")
    lines += verdict_lines(d)
    for n in d.notes:
        lines.append(f"  note: {n}")
    return "\n".join(lines)


def _alike_lines(d: Diagnosis) -> list[str]:
    """The candidates the held-out blocks do not tell apart: from the model's own terms, from each other, or from each
    other where a later check does (then said as that)."""
    out: list[str] = []
    told: set[frozenset] = set()
    by = {c.effect: c for c in d.candidates}
    for c in d.candidates:
        for other in c.indistinguishable_from:
            key = frozenset((c.effect, other))
            if key in told:
                continue
            told.add(key)
            if other in ("offset", "baseline") or other in d.effects:
                what = "the probe offsets" if other == "offset" else (
                    "the linear calibration" if other == "baseline" else f"the {other} term already in the model")
                out.append(f"  {c.effect} cannot be told apart from {what} with these data: {c.separate_by}.")
            elif (o := by.get(other)) is not None and o.significant != c.significant and (o.refusal or c.refusal):
                # one story: the held-out blocks do not tell them apart, a later check did; said as that
                kept, refused = (c, o) if c.significant else (o, c)
                out.append(f"  {c.effect} and {other} predict the held-out blocks alike (equal held-out gain, "
                           f"collinear regressors); {refused.effect} is refused ({refused.refusal}), {kept.effect} is "
                           f"not: {c.separate_by}.")
            elif o is not None and not o.significant and not c.significant and o.refusal and c.refusal:
                # neither is kept: how to tell them apart is no advice for these data (both refused beside a finding)
                out.append(f"  {c.effect} and {other} are indistinguishable with these data (equal held-out gain, "
                           f"collinear regressors), and neither is kept ({c.effect}: {c.refusal}; {other}: "
                           f"{o.refusal}).")
            else:
                out.append(f"  {c.effect} and {other} are indistinguishable with these data (equal held-out gain, "
                           f"collinear regressors): {c.separate_by}.")
    return out


def gain_text(gain: float, weak: dict | None = None) -> str:
    """The gain column, 6 characters: a percentage; 'weak' where the held-out test cannot judge the data; below
    -100 % (the held-out error more than doubled: an extrapolation, whose size says nothing) '<-100%'."""
    if weak:
        return "  weak"
    if gain < -1.0:
        return "<-100%"
    return f"{100 * gain:5.1f}%"


def discovery_lines(d: Diagnosis) -> list[str]:
    """What discovery tried beyond the catalogue, and each group it found read as physics."""
    f = getattr(d, "discovery", None)
    if f is None:
        return []
    out = ["", f"  beyond the catalogue (discovery: {f.tried} groups of {f.tried_params} parameters built from what "
               f"the data carry, chosen inside training blocks):"]
    for hz, (col, how) in getattr(f, "harmonics", {}).items():
        out.append(f"    the residual's line at {hz:.4g} Hz is {col}'s motion ({how}): {col}'s shapes take it, never a "
                   f"wave of its own")
    if not f.claimed:
        out.append(f"    nothing claimed: {f.reason}")
        return out
    for g in f.groups:
        out.append(f"    {g.reading}")
    for form in getattr(f, "forms", []):
        tried = "; ".join(f"{t['form']} {t['parameters']}, {t['heldout_rms_nT']:.4g}" for t in form["forms"])
        alike = form.get("alike") or []
        out.append(f"    the shape of {form['observable']} kept as {form['chosen']}, the smallest that no other form "
                   f"predicts better on the held-out blocks (form, parameters, held-out nT: {tried})"
                   + (f"; they do not tell it from {' or '.join(alike)}: its parameters are those of this form, not a "
                      f"law these data single out" if alike else ""))
    out.append(f"    with {'it' if len(f.groups) == 1 else 'them'}: residual {f.rms_nT:.3f} nT, held-out "
               f"{f.heldout_rms_nT:.3f} nT (from {f.base_heldout_rms_nT:.3f}) against a {f.floor_nT:.3f} nT floor; "
               f"the search itself, every choice made without the block it predicts, takes {100 * f.cv_gain:.1f} % "
               f"of the held-out sum of squares, "
               f"{f.cv_log_ratio / f.cv_log_ratio_se if f.cv_log_ratio_se > 0 else float('inf'):.1f} standard errors")
    return out


def verdict_lines(d: Diagnosis) -> list[str]:
    """The verdict: at the floor, explained by X, partly explained by X, or unexplained, with what is left."""
    v = d.verdict
    best = d.best
    if v is None:                                   # a Diagnosis made by hand, without a verdict
        return ["  no missing effect is significant" if best is None else f"  most likely missing: {best.effect}"]
    # as the command line takes them: a user's effect as the file.py:Class it was given as
    # only what the data show: fit refuses an effect they do not (model_fit.not_shown), so the advice leaves it out
    unshown = {e: why for e in d.effects if (why := not_shown(d.parameters, e))}
    kept = [e for e in d.effects if e not in unshown] + ([] if best is None else [best.effect])
    try_it = "" if best is None else f"; try: --effects {','.join(map(effect_spec, kept))}"
    left = ", and the advice leaves it out" if try_it else ""
    said = [f"  {e}: these data do not show it ({why}): fit refuses it{left}" for e, why in unshown.items()]
    return said + _verdict_lines(d, v, best, try_it)


def _verdict_lines(d: Diagnosis, v: dict[str, Any], best: Candidate | None, try_it: str) -> list[str]:
    """verdict_lines once the advice is formed."""
    if v["kind"] == "at the floor":
        return ["  no missing effect is significant: the model explains the data down to the noise"]
    alike = []
    if v.get("linear_refit_nT") is not None and best is not None:
        alike = [f"  or the calibration held is off: refitting its linear part alone gives "
                 f"{v['linear_refit_nT']:.3f} nT as well, and these data cannot tell the two apart"
                 + (" (a field the platform carries is one only if the calibration was made off the platform, e.g. "
                    "on a turntable before mounting; a calibration learned in place already holds it)"
                    if best.effect == "platform" else "")]
    if v["kind"] == "explained":
        return [f"  explained by {best.effect}: adding it brings the residual from {d.rms_nT:.3f} to "
                f"{best.rms_nT:.3f} nT, the noise floor is {d.noise_nT:.3f} nT{try_it}"] + alike
    if v["kind"] == "explained beyond the catalogue":
        head = (f"what discovery found takes the residual ({d.rms_nT:.3f} nT) to its {d.noise_nT:.3f} nT floor, and "
                f"no catalogue effect adds to it" if best is None else
                f"{best.effect} brings the residual from {d.rms_nT:.3f} to {best.rms_nT:.3f} nT, and what discovery "
                f"found beside it takes it to its {d.noise_nT:.3f} nT floor")
        if v.get("rest") == "flicker":      # what the finding leaves is the probes' own slow noise, above white
            head = (f"what discovery found{'' if best is None else f' beside {best.effect}'} takes the residual "
                    f"({d.rms_nT:.3f} nT) to {v['rms_nT']:.3f} nT; the rest is each probe's own slow noise (flicker, "
                    f"spectrum about 1/f) above its {d.noise_nT:.3f} nT white floor, not a missing effect")
        else:
            head += "; every channel is within its own floor"
        return ([f"  explained beyond the catalogue: {head}"]
                + ([f"  what the catalogue leaves: {v['left']}"] if v.get("left") else [])
                + [f"  what explains it: {v['advice']}"] + alike)
    if v["kind"] == "partly explained":
        head = (f"  partly explained by {best.effect}: adding it brings the residual from {d.rms_nT:.3f} to "
                f"{best.rms_nT:.3f} nT against a {d.noise_nT:.3f} nT floor{try_it}")
    elif d.heldout_weak is not None:        # no more than the data determine: nothing found, and nothing ruled out
        head = (f"  unexplained: the held-out test cannot judge these data, so no catalogue effect is found "
                f"significant and none is ruled out ({d.rms_nT:.3f} nT against a {d.noise_nT:.3f} nT floor)")
    else:
        head = (f"  unexplained: no catalogue effect explains the rest of the residual significantly "
                f"({d.rms_nT:.3f} nT against a {d.noise_nT:.3f} nT floor)")
    out = [head] + alike
    if v.get("left"):
        out.append(f"  what is left: {v['left']}")
    if v.get("advice"):
        out.append(f"  what would explain it: {v['advice']}")
    return out


def frames_text(entries: list[dict]) -> list[str]:
    """The frames table (frames.py): one line per channel group with something above its floor."""
    out = []
    for e in entries or []:
        cells = []
        for frame in ("platform", "probe", "earth"):
            f = e.get(frame)
            if f is None or e["platform"]["fixed_share"] is None or (frame != "platform" and "rms_nT" not in f):
                continue
            axes = f.get("rms_nT")
            rms = (" " + " ".join(f"{a[0]} {v:.2f}" for a, v in axes.items())) if axes else ""
            share = f" {100 * f['fixed_share']:.0f} % fixed" if frame == "platform" else ""
            cells.append(f"{frame}{share}{rms}")
        if cells:
            out.append(f"    {e['channels']:<18} " + "; ".join(cells))
    return out
