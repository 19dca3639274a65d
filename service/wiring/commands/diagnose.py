"""`fluxcal diagnose DATA [--config FILE] [--calibration CAL.json] [--effects E,..] [--report DIR] [--json]`.

Compares the model (a linear calibration plus the named effects) with the measurement, says where
it fails and which catalogue effect is missing (fluxcal.service.numerics.diagnose). With --json, one JSON object
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

from fluxcal.drivers.errors import ConfigError  # noqa: E402
from fluxcal.service.wiring.commands.notes import check_output_file, check_output_folder  # noqa: E402
from fluxcal.service.wiring.commands.options import (  # noqa: E402
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
from fluxcal.service.wiring.commands.written import write_diagnosis_report, write_discovered  # noqa: E402
from fluxcal.service.wiring.fitting import NONLINEAR_PROBE_SAMPLES as DIAGNOSE_PROBE_SAMPLES  # noqa: E402
from fluxcal.service.wiring.prepare import Prepared, effect_input  # noqa: E402
from fluxcal.service.wiring.progress import Progress  # noqa: E402
from fluxcal.service.wiring.result import Result, Said, print_result, stderr_say  # noqa: E402

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
    """A diagnosis (fluxcal.service.numerics.diagnose.Diagnosis) and how the command line shows it."""

    diagnosis: Any = None
    title: str = ""                       # the source as the summary names it
    report: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return self.diagnosis.as_dict()

    def text(self) -> str:
        from fluxcal.service.numerics.diagnose import summary_text

        return summary_text(self.diagnosis, self.title) + (f"\n  report: {self.report}" if self.report else "")

    @property
    def verdict(self) -> dict[str, Any]:
        """The verdict (docs/contracts.md): its kind, the effect, what is left and what would explain it."""
        return self.diagnosis.verdict

    def rows(self) -> list[dict[str, Any]]:
        """Each candidate effect with its held-out figures and the verdict's word."""
        from fluxcal.service.numerics.diagnose import verdict_word

        return [{"effect": c.effect, "rms_nT": c.rms_nT, "heldout_rms_nT": c.heldout_rms_nT, "gain": c.gain,
                 "p_value": c.p_value, "significant": c.significant,
                 "verdict": verdict_word(c, self.diagnosis.heldout_weak) if c.testable else "not testable"}
                for c in self.diagnosis.candidates]


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
    """`fluxcal diagnose SOURCE`: the Python API's diagnose (fluxcal.service.wiring.api), with the command line's options."""
    from fluxcal.service.wiring import api

    return api.diagnose(source, effects=opts.effects, report=opts.report, write_effect=opts.write_effect,
                        max_samples=opts.max_samples, calibration=opts.calibration, said=said, progress=progress,
                        config=opts.config, site=opts.site, skip=opts.skip, topics=opts.topics, mags=opts.mags)


def checked(opts: DiagnoseOptions, source: str | None) -> DiagnoseOptions:
    """The options with the outputs checked and the model's effects known (installed ones loaded, a user's
    file.py:Class registered), before any work (source: the input, which no output may be)."""
    from fluxcal.service.numerics.effects import known_effects
    from fluxcal.service.wiring.user_effects import load_installed_effects, resolve_effects

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
    return opts


def read_limits(opts: DiagnoseOptions) -> dict[str, int]:
    """How many samples a diagnosis reads at most: --max-samples, else the default budget of probe-samples."""
    limit = opts.max_samples
    return {"max_probe_samples": DIAGNOSE_PROBE_SAMPLES} if limit is None else {"max_samples": limit}


def with_held_effects(prep: Prepared, opts: DiagnoseOptions) -> DiagnoseOptions:
    """The options with the model the held calibration's file describes, where no effects were given."""
    from fluxcal.service.numerics.effects import known_effects

    if prep.held is None or opts.effects:
        return opts
    missing = [e for e in prep.held_effects if e not in known_effects()]
    if missing:
        raise ConfigError(f"{opts.calibration}: names the effect(s) {', '.join(map(repr, missing))}, which "
                          f"are neither in the catalogue nor installed: give them with --effects "
                          f"file.py:ClassName")
    return replace(opts, effects=list(prep.held_effects))


def run(prep: Prepared, opts: DiagnoseOptions, said: Said, *, progress: bool = True) -> DiagnoseResult:
    """The diagnosis of the prepared data (and its outputs, when asked): figures and notes as data. The data go one
    way: prepared (effect_input), diagnosed (fluxcal.service.numerics), written."""
    from fluxcal.service.numerics.calib.determinacy import refuse_undetermined
    from fluxcal.service.numerics.calib.track import follows_height_note
    from fluxcal.service.numerics.diagnose.diagnostics import diagnose
    from fluxcal.service.wiring.commands.fit import usable_data
    from fluxcal.service.wiring.fitting import gate_centres, judge_data

    limit = opts.max_samples
    budget = (f"--max-samples {limit:,}" if limit is not None
              else f"the default budget of {DIAGNOSE_PROBE_SAMPLES:,} probe-samples (--max-samples N; 0: all)")
    # the one determinacy gate, asked as fit asks it of the same samples against the same reference (one verdict,
    # one cone), before anything else is made of them
    judged = judge_data(usable_data(prep.data)[0], prep.total_nT, prep.total_source or "")
    then = ("; the linear calibration these data would refit is not determined, so no effect can be judged on top of "
            "it (or hold one made from a fuller turn fixed: --calibration CAL.json)")
    if prep.held is None:
        refuse_undetermined(judged, then=then)        # before any fit: a refusal costs nothing more
    ready = effect_input(prep, said, budget=budget, centres_nT=gate_centres(judged))   # the data's size as fit says
    data = ready.data
    bar = Progress(1.0, "diagnose", fraction=True) if progress else None
    try:
        result = diagnose(data, effects=list(opts.effects), calibration=prep.held, progress=bar,
                          check_linear=lambda lin: refuse_undetermined(judged, then=then))
    finally:
        if bar is not None:
            bar.close()
    if ready.thinned is not None:
        result.thinned = ready.thinned
    if prep.site is not None and result.reference == "config":     # the total is the site's: said as fit says it
        result.reference = f"the site ({prep.site.model})"
    # what reading the file lost or left out, said as it came (in the JSON too), then data not in nT: every figure
    # after it is in their unit
    result.notes[0:0] = said.lost_in_reading(besides=ready.notes + result.notes) + ready.notes
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
