"""`fluxcal fit DATA`: a calibration from lab data, as a readable summary, JSON, or a calibration file."""

from __future__ import annotations

import argparse
import sys
from argparse import Namespace
from dataclasses import dataclass, field, replace
from itertools import islice
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError, FluxcalError
from fluxcal.service.io.calfile import save_calibration
from fluxcal.service.io.recordings.labdata import LabData, keep_every
from fluxcal.service.numerics.diagnose.text import reference_words
from fluxcal.service.numerics.effects.temperature import borrowed_notes
from fluxcal.service.numerics.usable import temperature_notes, usable_samples
from fluxcal.service.wiring.coloured_fit import coloured_offsets, direction_offsets
from fluxcal.service.wiring.commands.notes import check_output_file, check_output_folder
from fluxcal.service.wiring.commands.options import (
    ALIGNS,
    CONFIG_HELP,
    DATA_HELP,
    EFFECT_SPECS,
    EFFECTS_HELP,
    METHODS,
    PATH,
    CommandHelp,
    data_options,
    effect_names,
    fleet_help,
    fleet_options,
)
from fluxcal.service.wiring.fitting import (
    NONLINEAR_PROBE_SAMPLES,
    channel_sums,
    contract_json,
    fit_array,
    iter_residual_channels,
    judge_data,
    rms,
    rms_all,
    uncalibrated_rms,
)
from fluxcal.service.wiring.identity import recording_identity
from fluxcal.service.wiring.prepare import FROM_RECORDING, Prepared
from fluxcal.service.wiring.result import Note, Result, Said, print_result, stderr_say
from fluxcal.service.wiring.scale_notes import data_scale_notes

HELP = CommandHelp("fit a calibration to lab data (CSV, MCAP, a PX4 or ArduPilot log, a ROS 2 bag)",
                   "  fluxcal fit grad.csv --out cal.json\n  fluxcal fit board.csv --site 46.52,6.63,400 --json\n"
                   "  fluxcal fit grad.csv --effects temperature,drift")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA", nargs="+", help=DATA_HELP + fleet_help("--out and --report"))
    p.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    p.add_argument("--method", default="ellipsoid", metavar="M", choices=METHODS,
                   help=f"calibration method (allowed: {', '.join(METHODS)}; default: %(default)s)")
    p.add_argument("--align", default=None, metavar="A", choices=ALIGNS,
                   help=f"how the probes of an array are brought to one frame (allowed: {', '.join(ALIGNS)}; "
                        f"default: regression for arrays)")
    p.add_argument("--effects", type=effect_names, default=[], metavar="E,..", help=EFFECTS_HELP)
    data_options(p)
    p.add_argument("--out", metavar="CAL.json", help="write the calibration file here (default: none)")
    p.add_argument("--json", action="store_true", help="print JSON (docs/contracts.md) instead of the summary")
    fleet_options(p)
    p.add_argument("--report", metavar="DIR",
                   help="also write an HTML report of the calibration here (plots: matplotlib)")


def _progress(msg: str) -> None:
    if sys.stderr.isatty():
        print(f"\r\033[K{msg}", end="", file=sys.stderr, flush=True)


@dataclass
class FitOptions:
    """What `fit` is asked to do with one recording (the command line's options, or a fleet's)."""

    method: str = "ellipsoid"
    align: str | None = None
    effects: list[str] = field(default_factory=list, metadata=EFFECT_SPECS)
    config: str | None = field(default=None, metadata=PATH)
    site: str | None = None
    skip: list[tuple[float, float]] | None = None
    topics: dict[str, str | None] | None = None   # another ecosystem's log: what becomes what
    mags: tuple[int, ...] | None = None
    out: str | None = field(default=None, metadata=PATH)  # the calibration file to write
    report: str | None = field(default=None, metadata=PATH)  # the folder of an HTML report


@dataclass
class FitResult(Result):
    """A fitted calibration: the JSON contract (docs/contracts.md) and the summary a person reads."""

    contract: dict[str, Any] = field(default_factory=dict)
    summary: str = ""
    report: str | None = None             # the report written, if any
    #: the calibration fitted (fluxcal.service.numerics.calib.model.ArrayCalibration): save(), apply() ... in Python
    calibration: Any = field(default=None, repr=False)
    #: the fit with its effects (engine.EffectsFit), where effects were fitted: `correct` applies them
    effects_fit: Any = field(default=None, repr=False)

    def correct(self, data: Any) -> np.ndarray:
        """(N, P, 3) the field of `data` (what fluxcal.read gives, a LabData or a SampleBlock) corrected by this
        calibration with its effects, which read the samples' times, temperatures or logged columns (calibration.apply
        has the field alone, and refuses a calibration with effects)."""
        lab = getattr(data, "lab", data)
        if self.effects_fit is not None:
            return self.effects_fit.correct(lab)
        return self.calibration.apply(getattr(lab, "block", lab).field_nT)

    def as_dict(self) -> dict[str, Any]:
        return self.contract

    def text(self) -> str:
        return self.summary

    @property
    def warnings(self) -> list[Note]:
        """The warnings `fluxcal fit` says: those said as the data were read and fitted, then the fit's own (coverage,
        standard errors, what reading left out, a temperature borrowed), as its JSON's `warnings` holds them."""
        said = super().warnings
        texts = {n.text for n in said}
        return said + [Note("fit", w, "warning") for w in self.contract.get("warnings", []) if w not in texts]

    @property
    def rms_nT(self) -> float | None:
        """The residual RMS over every channel after the calibration, nT."""
        return self.contract.get("rms_nT")

    def rows(self) -> list[dict[str, Any]]:
        """Each fitted parameter with its standard error: every probe's offset and matrix, then the effects'."""
        out = []
        for s in self.contract.get("sensors", []):
            for a, (v, e) in enumerate(zip(s["offset_nT"], s.get("offset_se_nT") or [None] * 3)):
                out.append({"probe": s["name"], "parameter": f"offset {'xyz'[a]}", "value": v, "stderr": e,
                            "unit": "nT"})
            se = s.get("matrix_se") or [[None] * 3] * 3
            for i in range(3):
                for j in range(3):
                    out.append({"probe": s["name"], "parameter": f"matrix [{'xyz'[i]}{'xyz'[j]}]",
                                "value": s["matrix"][i][j], "stderr": se[i][j], "unit": ""})
        for effect, params in (self.contract.get("effect_params") or {}).items():
            for name, p in params.items():
                out.append({"probe": None, "parameter": name, "value": p.get("value"), "stderr": p.get("se"),
                            "unit": p.get("unit", ""), "effect": effect})
        return out


def main(args: Namespace) -> int:
    """The command line: the result as text, or JSON (--json); the notes said on stderr as they came."""
    result = execute(args.data, options(args), Said("fit", stderr_say("fit")))
    print_result(result, args.json)
    if args.json and result.report:
        print(f"fluxcal fit: report written to {result.report}", file=sys.stderr)
    return result.status


def options(args: Namespace) -> FitOptions:
    return FitOptions(method=args.method, align=args.align, effects=list(args.effects), config=args.config,
                      site=args.site, skip=args.skip, topics=args.topics, mags=args.mags, out=args.out,
                      report=args.report)


def execute(source: str, opts: FitOptions, said: Said) -> FitResult:
    """`fluxcal fit SOURCE`: the Python API's fit (fluxcal.service.wiring.api), with the command line's options."""
    from fluxcal.service.wiring import api

    return api.fit(source, method=opts.method, align=opts.align, effects=opts.effects, out=opts.out,
                   report=opts.report, said=said, config=opts.config, site=opts.site, skip=opts.skip,
                   topics=opts.topics, mags=opts.mags)


def checked(opts: FitOptions, source: str | None) -> FitOptions:
    """The options with the effects known (installed ones loaded, a user's file.py:Class registered) and the outputs
    checked, before any work (source: the input, which no output may be)."""
    from fluxcal.service.wiring.user_effects import load_installed_effects, resolve_effects

    load_installed_effects()
    opts = replace(opts, effects=resolve_effects(opts.effects))
    if opts.out:
        check_output_file(opts.out, example="cal.json", not_this=source)
    if opts.report:
        check_output_folder(opts.report, "--report")
    return opts


def run(prep: Prepared, opts: FitOptions, said: Said) -> FitResult:
    """The calibration of the prepared data (and its files, when asked): figures and notes as data."""
    data, source = prep.data, prep.source
    data, left_out = usable_data(data, uses_temperature=bool({"temperature", "thermal"} & set(opts.effects)))
    known_total = prep.total_nT
    judged = judge_data(data, known_total, prep.total_source or "")    # the one determinacy gate, before any fit
    cal, total = fit_array(data, method=opts.method, align=opts.align, configured_total_nT=known_total,
                           positions_m=prep.positions_m, progress=_progress, judged=judged)
    if prep.site is not None or prep.track is not None:    # the site's field, or the model along the track
        total.source = prep.total_source
    # data in µT (or counts) fit without complaint; said here, before anything is reported in "nT"
    scale = data_scale_notes(said, prep, data, judged)     # as diagnose and inspect say it
    if opts.effects:
        ef, cal, channels, rows, report_data, thinned, effect_sizes = _with_effects(data, cal, opts.effects, prep)
    else:
        ef, rows, report_data, thinned, effect_sizes = None, None, data, None, []
        # each channel's sum of squares is enough, taken over chunks of rows (hours of data); the report bins
        # the scalar residuals over direction and needs those whole (not the 3 (P - 1) differences)
        channels = channel_sums(data, cal, total)
        if opts.report:
            channels.update(islice(iter_residual_channels(data, cal, total), data.block.n_probes))   # scalars first
    if sys.stderr.isatty():
        print("\r\033[K", end="", file=sys.stderr)
    before = uncalibrated_rms(data, total)
    refuse_worse(cal, channels, before, total.source)
    cal.diagnostics.update({"rms_before_nT": dict(before),
                            "rms_after_nT": {k: rms(v) for k, v in channels.items()},
                            "total_field": total.source})
    # coloured noise first: it changes the offsets' errors, which the warnings below compare with the offsets
    coloured = coloured_warnings(coloured_offsets(data, cal, total)) if not opts.effects else []
    coloured += direction_offsets(data, cal, total) if not opts.effects else []
    coverages = [j.coverage for j in judged]             # about the gate's centre: the figures every command shows
    warnings = (left_out + calibration_warnings(cal, coverages) + effect_sizes + ([thinned] if thinned else [])
                + coloured)
    warnings += [prep.config_warning] if prep.config_warning else []
    warnings += [prep.part_of_run] if prep.part_of_run else []
    warnings = scale + warnings
    # what reading the file lost or left out (a logger's holds, a gap, a cut message), said as it came: in the JSON
    # too, where a program reads it (nothing left out silently)
    warnings = said.lost_in_reading(besides=warnings) + warnings
    cal.diagnostics["warnings"] = warnings
    cal.unit = recording_identity(data.metadata)          # the unit a service recording says it was made by
    out = FitResult("fit", source, effects_fit=ef)
    if opts.out:
        save_calibration(cal, opts.out)
        out.written.append(opts.out)
    result = contract_json(cal, channels, data.probe_names, coverages, warnings)
    result["determinacy"] = [j.as_dict() for j in judged]
    if prep.origin == FROM_RECORDING:
        result["configuration"] = "recording"               # the total field and positions it stores were used
    if prep.site is not None:
        result["site"] = prep.site.as_dict()
    text = ([f"site field: {prep.site.summary()}"] if prep.site is not None else [])
    text.append(_summary(data, cal, channels, before, total.source, result, coverages, prep.origin))
    if opts.out:
        text.append(f"calibration written to {opts.out}")
    if opts.report:
        # the calibration first: a report that cannot be written must not cost it (said, and the exit status 1)
        try:
            path = _write_report(opts.report, source, said, report_data, cal, channels, coverages, warnings,
                                 total.source, rows)
            out.written.append(str(path))
            text.append(f"report: {path}")
            out.report = str(path)
        except (OSError, FluxcalError) as e:
            said("report", f"{opts.report}: the report could not be written: {e}")
            out.status = 1
    out.contract, out.summary, out.notes, out.calibration = result, "\n".join(text), said.notes, cal
    return out


#: a calibration whose scalar residual is this many times the raw data's is refused: a fit minimises an algebraic
#: residual, so data already calibrated may come out a few percent above their raw figure, never a quarter
WORSE_FACTOR = 1.25


def refuse_worse(cal, channels, before: dict[str, float], total_source: str) -> None:
    """CalibrationRefused where the calibration makes a probe's scalar residual worse than the raw data's (beyond
    WORSE_FACTOR: a calibration the data do not determine, or a total field that is not theirs), with what would
    help."""
    from fluxcal.drivers.errors import CalibrationRefused

    for p in cal.probes:
        name = f"{p.name}.scalar"
        after = rms(channels[name]) if name in channels else float("nan")
        if name in before and np.isfinite(after) and after > WORSE_FACTOR * before[name]:
            against = "estimated" if total_source == "estimated" else f"from {total_source}"
            reason = (f"{p.name}: the calibration makes the scalar residual worse than the raw data's "
                      f"({before[name]:,.1f} -> {after:,.1f} nT RMS against the total field {against}): these data do "
                      f"not determine it")
            advice = ("turn the probe about at least two axes so the field sweeps most directions, and check that the "
                      "total field given is the site's and the data are in nT")
            refused = CalibrationRefused(f"{reason}; {advice}")
            refused.reason, refused.advice = reason, advice
            raise refused


def _with_effects(data, cal, effects, prep: Prepared):
    """The calibration with `effects` fitted over (a thinning of) the data, refused where the data do not show one:
    (the fit, its calibration, channels, rows fitted, the data fitted, the thinning said, the parameters not
    determined said)."""
    from fluxcal.service.numerics.engine import fit_with_effects

    _progress(f"fitting effects {', '.join(effects)}")
    report_data, thinned = effects_data(data)
    ef, _ = fit_with_effects(report_data, effects, cal, total_nT=prep.total_nT, positions_m=prep.positions_m)
    refuse_not_shown(ef, effects, prep.source)
    method, align = cal.method, cal.align
    cal = ef.calibration()
    cal.method, cal.align = method, align
    channels = {name: values for name, values in ef.result.channels.as_dict().items()}
    return ef, cal, channels, ef.result.problem.rows, report_data, thinned, ef.size_warnings()


def refuse_not_shown(ef, effects, source: str) -> None:
    """CalibrationRefused where the data do not show an effect asked for (EffectsFit.not_shown: the service's
    add-effect asks the same), with what would help."""
    from fluxcal.drivers.errors import CalibrationRefused

    for name in effects:
        why = ef.not_shown(name)
        if why:
            n = ef.result.problem.data.n_samples
            reason = f"the {n:,} samples do not show {name}: {why}"
            advice = (f"fit without it (its values would be noise, and a calibration extrapolates them); "
                      f"`fluxcal diagnose {source}` ranks what is missing")
            refused = CalibrationRefused(f"{reason}; {advice}")
            refused.reason, refused.advice = reason, advice
            raise refused


#: fewest samples left to fit once the unusable ones are left out (as the effects' fits need)
MIN_USABLE_SAMPLES = 30


def usable_data(data: LabData, *, uses_temperature: bool = False) -> tuple[LabData, list[str]]:
    """The data without the samples no fit can use (a saturated or non-finite axis, no reference), and what
    was left out, per probe, as warnings; DataError when too few samples remain. Invalid temperatures matter
    only to the temperature terms: said when they are fitted, never a reason to leave a sample out."""
    b = data.block
    u = usable_samples(b, data.probe_names)
    notes = list(u.notes)
    if u.n_dropped:
        kept = b.n_samples - u.n_dropped
        if kept < MIN_USABLE_SAMPLES:
            raise DataError(f"{data.path}: only {kept} of {b.n_samples} samples are usable ({'; '.join(u.notes)}): "
                            f"too few to fit (at least {MIN_USABLE_SAMPLES})")
        data = replace(data, block=b.rows(u.keep))
    if uses_temperature:       # as diagnose says them: invalid temperatures, and a probe's borrowed from others
        notes += temperature_notes(data.block, data.probe_names) + borrowed_notes(data.block.temp_C, data.probe_names)
    return data, notes


def coloured_warnings(found) -> list[str]:
    """What coloured noise does to the linear calibration's standard errors, per probe (fitting.ColouredNoise)."""
    out = []
    for c in found:
        head = (f"{c.probe}: the residual is coloured (a power law, spectrum ~ f^{c.alpha:.1f} at the record's "
                f"longest periods, above the white noise)")
        if c.covered:
            out.append(f"{head}: the offsets' and matrix's standard errors include that wander within the record; "
                       f"if it is the sensor's noise (and not an effect the model lacks: see diagnose), the offsets "
                       f"wander on beyond the record, about {c.wander_nT:.2g} nT per decade of time, which this record "
                       f"cannot know")
        else:
            out.append(f"{head}: the offsets' and matrix's standard errors assume white noise and understate the "
                       f"error (on a simulated pair under 1/f noise of 0.3 nT/sqrt(Hz), 30 times): take them as "
                       f"lower bounds")
    return out


def effects_data(data: LabData) -> tuple[LabData, str | None]:
    """The samples the effects (and the linear part with them) are fitted to: every one, or one in k beyond
    NONLINEAR_PROBE_SAMPLES (the fit is nonlinear over every sample it is given); then what that costs, said
    among the warnings."""
    b = data.block
    k = keep_every(b.n_samples, b.n_probes, None, NONLINEAR_PROBE_SAMPLES)
    if k == 1:
        return data, None
    part = replace(data, block=b.rows(np.arange(0, b.n_samples, k)))       # a copy: rows by index
    return part, (f"effects fitted on one sample in {k} ({part.block.n_samples:,} of {b.n_samples:,}), the linear "
                  f"calibration refitted with them there (it started from a fit to every sample), to stay within "
                  f"{NONLINEAR_PROBE_SAMPLES:,} probe-samples: the standard errors are those of the samples used, "
                  f"and the residual channels cover those samples")


def _write_report(folder: str, source: str, said: Said, data, cal, channels, coverages, warnings, total_source,
                  rows) -> Any:
    from pathlib import Path

    from fluxcal.service.io.report import write_calibration_report
    from fluxcal.service.wiring.calib_report import section_from_fit

    section = section_from_fit(data, cal, channels, coverages, warnings, total_source, rows)
    b = data.block
    summary = (f"{data.path}: {b.n_samples} samples, {b.n_probes} probe(s), {b.t_s[-1] - b.t_s[0]:.1f} s; "
               f"residual RMS {rms_all(list(channels.values())):.3f} nT over every channel.")
    path, note = write_calibration_report(section, folder, title=f"fluxcal fit {Path(source).name}", summary=summary)
    if note:
        said("report", note, level="note")
    return path


def _fmt_param(value, se) -> str:
    """A parameter of any shape, with its standard error when there is one: 6 significant digits."""
    def one(v):
        return f"{v:.6g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)

    def seq(v):
        return "[" + ", ".join(one(x) for x in v) + "]" if isinstance(v, (list, tuple)) else one(v)

    if se is None or (isinstance(se, float) and not np.isfinite(se)):
        return seq(value)
    return f"{seq(value)} ± {seq(se)}"


def _fmt_effect_param(v: dict) -> str:
    """An effect parameter: value ± SE; a term's fixed reference (T0, a time origin) as fixed, with its value;
    a fitted one the data leave without an error as undetermined."""
    unit, se = v.get("unit", ""), v.get("se")
    if v.get("fixed"):
        return f"{v['value']:.6g} {unit} (fixed: {v.get('note') or 'held at this value, not fitted'})"
    if v.get("at_floor"):
        return f"{v['value']:.6g} {unit} (at its floor: {v['at_floor']})"
    if se is not None:
        return f"{v['value']:.6g} ± {se:.3g} {unit}"
    return f"{v['value']:.6g} {unit} (undetermined: the data do not determine it)"


def _fmt_pm(v: float, se: float, digits: int = 3) -> str:
    w = digits + 7
    return f"{v:{w}.{digits}f} ± {se:.1e}" if np.isfinite(se) else f"{v:{w}.{digits}f} ±     n/a"


def calibration_warnings(cal, coverages) -> list[str]:
    """Everything the fit itself flagged, and the directions about each fitted centre not seen."""
    out = [w for p in cal.probes for w in p.warnings]
    if cal.method in ("sinefit", "two-step"):
        return out                        # turns about chosen axes by design: no other turn is missing
    out += [f"{p.name}: only {c.fraction:.0%} of the field directions about the fitted offset were seen; {c.advice()}"
            for p, c in zip(cal.probes, coverages) if c.regions]
    return out


#: the residuals among a probe's params, each printed with what it is
_RESIDUALS = {
    "residual_rms_nT": "the scalar residual |corrected| − total field of this probe's own fit",
    "vector_residual_rms_nT": "the vector residual against the aligned reference, corrected {probe} − corrected "
                              "{ref}, over its three axes",
    "axis_rms_nT": "the residual of the sine fit to each raw axis (x, y, z)",
}


def _summary(data, cal, channels, before, total_source, result, coverages, origin=None) -> str:
    b = data.block
    lines = [f"{data.path}: {b.n_samples} samples, {b.n_probes} probe(s), {b.t_s[-1] - b.t_s[0]:.1f} s; "
             f"method {cal.method}, align {cal.align or '-'}, effects {', '.join(cal.effects) or '-'}; "
             + f"total field {reference_words(total_source)}"
             + (f"; {origin}" if origin == FROM_RECORDING else "")]
    for k, p in enumerate(cal.probes):
        lines.append(f"\n{p.name}")
        lines.append("  offset nT  " + "  ".join(_fmt_pm(v, s) for v, s in zip(p.offset_nT, p.offset_se_nT)))
        for i in range(3):
            lines.append("  matrix     " + "  ".join(_fmt_pm(v, s, 5) for v, s in zip(p.matrix[i], p.matrix_se[i])))
        if not (np.all(np.isfinite(p.offset_se_nT)) and np.all(np.isfinite(p.matrix_se))):
            lines.append("  (± n/a: " + ("the fit with effects gives the effects' and the offsets' errors, not the "
                                         "matrix's: `fit` without --effects gives them" if cal.effects else
                                         "no standard error: these data do not determine it") + ")")
        for key, val in p.params.items():
            if key in ("offset_nT", "samples", "align") or not isinstance(val, dict):
                continue
            if key == "residual_rms_nT" and f"{p.name}.scalar" in channels:
                continue            # the table below gives it, against the total field the command reports: one figure
            if key in _RESIDUALS:
                what = _RESIDUALS[key].format(probe=p.name, ref=cal.probes[0].name)
                lines.append(f"  {'residual':10s} {_fmt_param(val.get('value'), val.get('se'))} nT RMS: {what}")
                continue
            lines.append(f"  {key:10s} {_fmt_param(val.get('value'), val.get('se'))} {val.get('unit', '')}".rstrip())
        cov = coverages[k]
        if p.model_order != "full":
            lines.append(f"  model      {p.model_order} (fewer terms: the data do not determine the rest)")
        by_design = cal.method in ("sinefit", "two-step")
        lines.append(f"  coverage   {cov.fraction:.0%} of directions about the fitted offset" +
                     (" (turns about chosen axes, by design)" if by_design else f" — {cov.reason}" if cov.reason else ""))
        lines.append("  " + cov.text_map.replace("\n", "\n  "))
    if cal.effect_params:
        lines.append("\neffect parameters")
        for eff, params in cal.effect_params.items():
            for name, v in params.items():
                lines.append(f"  {eff:12s} {name:28s} {_fmt_effect_param(v)}".rstrip())
    lines.append("\nresidual RMS, nT          before       after")
    for name in channels:
        lines.append(f"  {name:20s} {before[name]:12.2f} {rms(channels[name]):11.3f}")
    # every channel has one value per sample: the RMS of them all is the root of the mean square of the RMSs
    lines.append(f"  {'all':20s} {float(np.sqrt(np.mean(np.square(list(before.values()))))):12.2f} "
                 f"{result['rms_nT']:11.3f}")
    ref = cal.probes[0].name
    lines.append("  (<probe>.scalar: the scalar residual |corrected| − total field" +
                 (f"; <probe>-{ref}.<axis>: the vector residual, corrected <probe> − corrected {ref} on that axis"
                  if len(cal.probes) > 1 else "") + "; before: with no calibration)")
    if result["warnings"]:
        lines.append("\nwarnings")
        lines += [f"  {w}" for w in result["warnings"]]
    return "\n".join(lines)
