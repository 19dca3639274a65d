"""`fluxcal diagnose DATA [--config FILE] [--calibration CAL.json] [--effects E,..] [--report DIR] [--json]`.

Compares the model (a linear calibration plus the named effects) with the measurement, says where
it fails and which catalogue effect is missing (service.numerics.diagnose). With --json, one JSON object
on stdout (docs/contracts.md); otherwise a readable summary. A progress bar goes to stderr when it is
a terminal. --calibration holds that linear calibration fixed (the model compared is that file's linear part
plus the effects: --effects, else those the file names, their parameters refitted); without it the
linear part is refitted to DATA. --config gives the probe
positions ([[probes]] position_m, or the [sim] probes) and the total field (estimator.total_nT).
"""

from __future__ import annotations

import os

# The fits multiply many small matrices: on a machine whose cores are busy, OpenBLAS worker threads spin
# for them and double the CPU time (measured: 41 s against 20 s for bench/bench_diagnose.py). One thread
# unless the user says otherwise; this only takes effect when numpy is not loaded yet (the CLI).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from dataclasses import dataclass, field, replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from drivers.errors import ConfigError, DataError, FluxcalError  # noqa: E402
from service.wiring.commands.notes import check_output_file, check_output_folder, field_scale_notes  # noqa: E402
from service.wiring.commands.options import (  # noqa: E402
    CONFIG_HELP,
    DATA_HELP,
    EFFECT_NAMES,
    OWN_EFFECT,
    CommandHelp,
    data_options,
    effect_names,
    fleet_help,
    fleet_options,
    max_samples,
)
from service.wiring.fitting import NONLINEAR_PROBE_SAMPLES as DIAGNOSE_PROBE_SAMPLES  # noqa: E402
from service.wiring.prepare import Prepared, prepare  # noqa: E402
from service.wiring.progress import Progress  # noqa: E402
from service.wiring.result import Result, Said, print_result, stderr_say  # noqa: E402

HELP = CommandHelp("compare model and measurement; find the missing effect",
                   "  fluxcal diagnose recordings/grad1-hidden-effect.mcap\n"
                   "  fluxcal diagnose rec.mcap --effects temperature --report report/")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA", nargs="+", help=DATA_HELP + fleet_help("--report"))
    p.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    p.add_argument("--calibration", metavar="CAL.json",
                   help="hold this calibration fixed (a file of `fit --out`, or `fit --json`); default: refit")
    p.add_argument("--effects", type=effect_names, default=[], metavar="E,..",
                   help=f"the effects already in the model (allowed: {EFFECT_NAMES}; {OWN_EFFECT}); default: none. "
                        f"Effects installed in the entry-point group fluxcal.effects are tried as candidates too")
    data_options(p)
    p.add_argument("--report", metavar="DIR",
                   help="also write an HTML report here (plots: matplotlib; without it the page has the text and "
                        "tables)")
    p.add_argument("--write-effect", dest="write_effect", metavar="FILE.py",
                   help="where the diagnosis discovers a term beyond the catalogue, write it here as an effect of your "
                        "own (docs/effects.md), which --effects FILE.py:Discovered takes back; rename and edit it "
                        "(default: none)")
    p.add_argument("--max-samples", type=max_samples, default=None, metavar="N",
                   help="diagnose at most N samples: a longer recording is thinned to every k-th sample, and "
                        "the output says so (default: 500,000 probe-samples, e.g. 125,000 samples of 4 probes, "
                        "about 1.5 GB; 0: all)")
    p.add_argument("--json", action="store_true", help="print JSON (docs/contracts.md) instead of the summary")
    fleet_options(p)


def load_calibration(path: str, n_probes: int) -> tuple[Any, list[str]]:
    """A calibration file: the calibration file of `fit --out` (service.io.calfile), or the JSON of
    `fit --json` (sensors with offset_nT and matrix). Returns the linear part and the effect names the
    file carries."""
    from service.io.calfile import calibration_from_json, parse_json, read_calibration_text
    from service.numerics.engine import LinearCalibration

    p = Path(path)
    text = read_calibration_text(p)                       # bounded; DataError for what cannot be read
    try:
        cal = calibration_from_json(text, origin=str(p))
        return LinearCalibration.from_any(cal, n_probes), list(cal.effects)
    except DataError as e:
        first_error = e                                   # perhaps `fit --json` output: try that below
    try:
        obj = parse_json(text, str(p))
        effects = list(obj.get("effects") or []) if isinstance(obj, dict) else []
        return LinearCalibration.from_any(obj, n_probes), effects
    except (DataError, TypeError, ValueError, AttributeError):
        raise first_error from None


@dataclass
class DiagnoseOptions:
    """What `diagnose` is asked to do with one recording (the command line's options, or a fleet's)."""

    effects: list[str] = field(default_factory=list)
    calibration: str | None = None        # a calibration file held fixed
    config: str | None = None
    site: str | None = None
    skip: list[tuple[float, float]] | None = None
    topics: dict[str, str | None] | None = None   # another ecosystem's log: what becomes what
    mags: tuple[int, ...] | None = None
    max_samples: int | None = None        # None: the default budget of probe-samples; 0: all
    report: str | None = None             # the folder of an HTML report
    write_effect: str | None = None       # where to write a discovered term as an effect module


@dataclass
class DiagnoseResult(Result):
    """A diagnosis (service.numerics.diagnose.Diagnosis) and how the command line shows it."""

    diagnosis: Any = None
    title: str = ""                       # the source as the summary names it
    report: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return self.diagnosis.as_dict()

    def text(self) -> str:
        from service.numerics.diagnose import summary_text

        return summary_text(self.diagnosis, self.title) + (f"\n  report: {self.report}" if self.report else "")


def main(args: argparse.Namespace) -> int:
    """The command line: the diagnosis as text, or JSON (--json); notes and progress on stderr as they come."""
    result = execute(args.data, options(args), Said("diagnose", stderr_say("diagnose")))
    print_result(result, args.json)
    if args.json and result.report:
        print(f"fluxcal diagnose: report written to {result.report}", file=sys.stderr)
    return result.status


def options(args: argparse.Namespace) -> DiagnoseOptions:
    return DiagnoseOptions(effects=list(args.effects), calibration=args.calibration, config=args.config,
                           site=args.site, skip=args.skip, topics=args.topics, mags=args.mags,
                           max_samples=args.max_samples, report=args.report, write_effect=args.write_effect)


def execute(source: str, opts: DiagnoseOptions, said: Said, *, progress: bool = True) -> DiagnoseResult:
    """`fluxcal diagnose SOURCE`: the report folder checked before any work, the input prepared, the diagnosis."""
    from service.numerics.effects import known_effects
    from service.wiring.user_effects import load_installed_effects, resolve_effects

    if opts.report:
        check_output_folder(opts.report, "--report")          # before any work
    if opts.write_effect:
        check_output_file(opts.write_effect, "--write-effect", suffixes=(".py",), example="found.py",
                          not_this=source)
    load_installed_effects()
    opts = replace(opts, effects=resolve_effects(opts.effects))
    known = known_effects()
    unknown = [e for e in opts.effects if e not in known]
    if unknown:
        raise ConfigError(f"--effects: {', '.join(map(repr, unknown))} not an effect "
                          f"(allowed: {', '.join(known)}; or file.py:ClassName for one of your own)")
    limit = opts.max_samples
    prep = prepare(source, said, config=opts.config, site=opts.site, skip=opts.skip, topics=opts.topics,
                   mags=opts.mags,
                   **({"max_probe_samples": DIAGNOSE_PROBE_SAMPLES} if limit is None else {"max_samples": limit}))
    return run(prep, opts, said, progress=progress)


def run(prep: Prepared, opts: DiagnoseOptions, said: Said, *, progress: bool = True) -> DiagnoseResult:
    """The diagnosis of the prepared data (and its report, when asked): figures and notes as data."""
    from service.numerics.diagnose import diagnose
    from service.numerics.effects import known_effects
    from service.numerics.effects.base import EffectData

    lab, source, limit = prep.take_data(), prep.source, opts.max_samples
    positions, total, origin = prep.positions_m, prep.total_nT, prep.origin
    data = EffectData.from_block(lab.block, lab.probe_names, total_nT=total, positions_m=positions)
    ref = data.ref_total_nT                       # the reference the fits use before a configured total
    scale = field_scale_notes(said, source, data.raw_nT, data.probe_names, about="a sphere fitted to them",
                              total_nT=ref if ref is not None else total,
                              total_source=prep.total_source if prep.track is not None else
                              "the ref_total column" if ref is not None else "the site" if opts.site
                              else f"configuration from {opts.config}" if opts.config else origin or "given")
    thinned = thinning(lab, limit)
    del lab                                       # the samples live on in `data` only (hours of them)
    cal, effects = None, list(opts.effects)
    if opts.calibration:
        cal, cal_effects = load_calibration(opts.calibration, data.n_probes)
        if not effects:
            known = known_effects()
            missing = [e for e in cal_effects if e not in known]
            if missing:
                raise ConfigError(f"{opts.calibration}: names the effect(s) {', '.join(map(repr, missing))}, which "
                                  f"are neither in the catalogue nor installed: give them with --effects "
                                  f"file.py:ClassName")
            effects = list(cal_effects)                             # the model the file describes
    bar = Progress(1.0, "diagnose", fraction=True) if progress else None
    try:
        result = diagnose(data, effects=effects, calibration=cal, progress=bar,
                          check_linear=lambda lin: _refuse_one_cone(data, lin))
    finally:
        if bar is not None:
            bar.close()
    if thinned is not None:
        result.thinned, text = thinned
        result.notes.insert(0, text)
    result.notes[0:0] = scale                     # data not in nT first: every figure after it is in their unit
    taken = (([f"total field {total:,.0f} nT (estimator.total_nT)"] if total is not None and not opts.site else [])
             + ([f"probe positions of {len(positions)} probes"] if positions is not None else []))
    if origin and taken:
        result.notes.insert(0, f"{origin}: {'; '.join(taken)}")
    from service.numerics.calib.track import follows_height_note

    height = follows_height_note(result.where,
                                 track_used=prep.track is not None)
    if height:
        result.notes.append(height)
    if opts.calibration and effects:
        result.notes.append(f"{opts.calibration}: linear part held fixed; the parameters of "
                            f"{', '.join(effects)} are refitted to these data")
    out = DiagnoseResult("diagnose", source, diagnosis=result, title=source + (f" ({origin})" if origin else ""))
    if opts.write_effect:
        write_discovered(out, opts.write_effect, source, said)
    if opts.report:
        # the diagnosis first: a report that cannot be written (a full disk) must not cost it (said, exit 1)
        from service.io.report import write_report
        from service.io.report.page import NO_MATPLOTLIB, has_matplotlib
        from service.wiring.calib_report import section_from_diagnosis

        try:
            out.report = str(write_report(result, opts.report, title=f"fluxcal diagnose {Path(source).name}",
                                          calibration=section_from_diagnosis(result)))
            out.written.append(out.report)
            if not has_matplotlib():
                said("report", f"report without plots: {NO_MATPLOTLIB}", level="note")
        except (OSError, FluxcalError) as e:
            said("report", f"{opts.report}: the report could not be written: {e}")
            out.status = 1
    out.notes = said.notes
    return out


def write_discovered(out: DiagnoseResult, path: str, source: str, said: Said) -> None:
    """The terms discovery found, written as an effect module at `path` (atomically: a temporary file renamed), said
    with how to take it back; where it found none, no file, and that is said instead (the exit status stays 0)."""
    import os
    import tempfile

    from service.numerics.diagnose.write_effect import effect_classes, effect_source

    found = getattr(out.diagnosis, "discovery", None)
    if found is None or not found.claimed:
        why = "discovery did not run" if found is None else (found.reason or "it claims nothing")
        said("write-effect", f"--write-effect {path}: nothing written: no term was discovered beyond the catalogue "
                             f"({why})")
        return
    text = effect_source(found, data_name=Path(source).name)
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=target.name + ".", suffix=".tmp", dir=target.parent or ".")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    out.written.append(str(target))
    use = ",".join(f"{target}:{c}" for c in effect_classes([g.group for g in found.groups]))
    said("write-effect", f"the discovered term written to {target} as an effect of your own: rename it and give it "
                         f"back with --effects {use} (fit, diagnose; a running service takes it from [effects] "
                         f"plugins where it acts on each sample alone)", level="say")


def thinning(lab: Any, limit: int | None) -> tuple[dict[str, Any], str] | None:
    """What keeping every k-th sample (LabData.every) costs, for the JSON and a note; None when all were kept."""
    k, n_read, t = lab.every, lab.n_read, lab.block.t_s
    if k <= 1 or n_read is None:
        return None
    used = lab.block.n_samples
    dt = float(np.median(np.diff(t))) if used > 1 else float("nan")
    rate = 1.0 / dt if dt > 0 else float("nan")
    why = (f"--max-samples {limit:,}" if limit is not None
           else f"the default budget of {DIAGNOSE_PROBE_SAMPLES:,} probe-samples (--max-samples N; 0: all)")
    info = {"every": k, "n_used": used, "n_read": n_read, "rate_hz": rate, "limit": why}
    text = (f"thinned: one sample in {k} diagnosed ({used:,} of {n_read:,}; {rate:.3g} Hz, {k} x the recorded "
            f"interval) to stay within {why}. Motion and effects faster than {rate / 2:.3g} Hz are not seen; the "
            f"standard errors are those of the samples used, up to {np.sqrt(k):.1f} x the whole recording's under "
            f"white noise (less under 1/f noise, whose slow wander thinning does not lose)")
    return info, text


def _refuse_one_cone(data, lin) -> None:
    """A linear part refitted to a single-axis turn is not determined along the turn's axis (fit refuses it,
    excitation.band_problem): an effect found on top of it would be that error, and the advice would send the user
    to a fit that is refused (a real turn was 'explained by crossfield'). Refused alike, with the way out, as soon as
    the linear part is refitted (before the candidates are tried)."""
    from drivers.errors import CalibrationRefused
    from service.numerics.calib.excitation import turn_problem

    for k, name in enumerate(data.probe_names):
        problem = turn_problem(data.raw_nT[:, k], lin.offset_nT[k], lin.matrix[k], data.ref_total_nT)
        if problem:
            raise CalibrationRefused(f"{name}: {problem}; the linear calibration these data would refit is not "
                                     f"determined, so no effect can be judged on top of it (or hold one made from "
                                     f"a fuller turn fixed: --calibration CAL.json)")
