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
from typing import Any  # noqa: E402

from drivers.errors import ConfigError  # noqa: E402
from service.wiring.commands.notes import check_output_file, check_output_folder  # noqa: E402
from service.wiring.commands.options import (  # noqa: E402
    CONFIG_HELP,
    DATA_HELP,
    EFFECT_NAMES,
    EFFECT_SPECS,
    OWN_EFFECT,
    PATH,
    CommandHelp,
    data_options,
    effect_names,
    fleet_help,
    fleet_options,
    max_samples,
)
from service.wiring.commands.written import write_diagnosis_report, write_discovered  # noqa: E402
from service.wiring.fitting import NONLINEAR_PROBE_SAMPLES as DIAGNOSE_PROBE_SAMPLES  # noqa: E402
from service.wiring.prepare import Prepared, effect_input, prepare  # noqa: E402
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


@dataclass
class DiagnoseOptions:
    """What `diagnose` is asked to do with one recording (the command line's options, or a fleet's)."""

    effects: list[str] = field(default_factory=list, metadata=EFFECT_SPECS)
    calibration: str | None = field(default=None, metadata=PATH)  # a calibration file held fixed
    config: str | None = field(default=None, metadata=PATH)
    site: str | None = None
    skip: list[tuple[float, float]] | None = None
    topics: dict[str, str | None] | None = None   # another ecosystem's log: what becomes what
    mags: tuple[int, ...] | None = None
    max_samples: int | None = None        # None: the default budget of probe-samples; 0: all
    report: str | None = field(default=None, metadata=PATH)  # the folder of an HTML report
    # where to write a discovered term as an effect module
    write_effect: str | None = field(default=None, metadata=PATH)


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
    """`fluxcal diagnose SOURCE`: the outputs checked before any work, the input prepared (with the calibration
    held fixed, when given), the model's effects known, the diagnosis."""
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
                   mags=opts.mags, calibration=opts.calibration,
                   **({"max_probe_samples": DIAGNOSE_PROBE_SAMPLES} if limit is None else {"max_samples": limit}))
    if prep.held is not None and not opts.effects:            # the model the file describes
        missing = [e for e in prep.held_effects if e not in known]
        if missing:
            raise ConfigError(f"{opts.calibration}: names the effect(s) {', '.join(map(repr, missing))}, which "
                              f"are neither in the catalogue nor installed: give them with --effects "
                              f"file.py:ClassName")
        opts = replace(opts, effects=list(prep.held_effects))
    return run(prep, opts, said, progress=progress)


def run(prep: Prepared, opts: DiagnoseOptions, said: Said, *, progress: bool = True) -> DiagnoseResult:
    """The diagnosis of the prepared data (and its outputs, when asked): figures and notes as data. The data go one
    way: prepared (effect_input), diagnosed (service.numerics), written."""
    from service.numerics.calib.excitation import refuse_one_cone
    from service.numerics.calib.track import follows_height_note
    from service.numerics.diagnose.diagnostics import diagnose

    limit = opts.max_samples
    budget = (f"--max-samples {limit:,}" if limit is not None
              else f"the default budget of {DIAGNOSE_PROBE_SAMPLES:,} probe-samples (--max-samples N; 0: all)")
    ready = effect_input(prep, said, budget=budget)
    data = ready.data
    bar = Progress(1.0, "diagnose", fraction=True) if progress else None
    try:
        result = diagnose(data, effects=list(opts.effects), calibration=prep.held, progress=bar,
                          check_linear=lambda lin: refuse_one_cone(
                              data.raw_nT, lin.offset_nT, lin.matrix, data.ref_total_nT, data.probe_names,
                              then="; the linear calibration these data would refit is not determined, so no effect "
                                   "can be judged on top of it (or hold one made from a fuller turn fixed: "
                                   "--calibration CAL.json)"))
    finally:
        if bar is not None:
            bar.close()
    if ready.thinned is not None:
        result.thinned = ready.thinned
    result.notes[0:0] = ready.notes               # data not in nT first: every figure after it is in their unit
    height = follows_height_note(result.where, track_used=prep.track is not None)
    if height:
        result.notes.append(height)
    if prep.held is not None and opts.effects:
        result.notes.append(f"{opts.calibration}: linear part held fixed; the parameters of "
                            f"{', '.join(opts.effects)} are refitted to these data")
    source, origin = prep.source, prep.origin
    out = DiagnoseResult("diagnose", source, diagnosis=result, title=source + (f" ({origin})" if origin else ""))
    if opts.write_effect:
        write_discovered(out, opts.write_effect, source, said)
    if opts.report:
        write_diagnosis_report(out, opts.report, said)
    out.notes = said.notes
    return out
