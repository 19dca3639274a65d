"""`fluxcal diagnose DATA [--config FILE] [--calibration CAL.json] [--effects E,..] [--report DIR] [--json]`.

Compares the model (a linear calibration plus the named effects) with the measurement, says where
it fails and which catalogue effect is missing (service.numerics.diagnose). With --json, one JSON object
on stdout (CONTRACTS.md §3); otherwise a readable summary. A progress bar goes to stderr when it is
a terminal. --calibration holds that linear calibration fixed (the model compared is that file's linear part
plus the effects: --effects, else those the file names, their parameters refitted); without it the
linear part is refitted to DATA. --config gives the probe
positions ([[probes]] position_m, or the [sim] probes) and the total field (estimator.total_nT).
"""

from __future__ import annotations

import os

from service.wiring.commands.notes import say_field_scale, say_part_of_run, say_read_warnings, skip_spans

# The fits multiply many small matrices: on a machine whose cores are busy, OpenBLAS worker threads spin
# for them and double the CPU time (measured: 41 s against 20 s for bench/bench_diagnose.py). One thread
# unless the user says otherwise; this only takes effect when numpy is not loaded yet (the CLI).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from drivers.config import read_toml  # noqa: E402
from drivers.errors import ConfigError, DataError  # noqa: E402
from service.wiring.fitting import NONLINEAR_PROBE_SAMPLES as DIAGNOSE_PROBE_SAMPLES  # noqa: E402
from service.wiring.progress import Progress  # noqa: E402

def config_geometry(path: str, n_probes: int) -> tuple[np.ndarray | None, float | None]:
    """Probe positions (P, 3) and the total field from a configuration file (recorded_config.geometry: the
    sections diagnose uses validated strictly, unknown section names errors)."""
    from service.wiring.config import require_content
    from service.wiring.recorded_config import geometry

    raw = read_toml(path)
    require_content(raw, path)
    try:
        return geometry(raw, n_probes)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


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


def main(args: argparse.Namespace) -> int:
    from service.io.recordings.labdata import load_data
    from service.numerics.diagnose import diagnose, summary_text
    from service.numerics.effects import known_effects
    from service.numerics.effects.base import EffectData
    from service.wiring.user_effects import load_installed_effects, resolve_effects

    if args.report:
        from service.wiring.commands.notes import check_output_folder

        check_output_folder(args.report, "--report")          # before any work
    load_installed_effects()
    args.effects = resolve_effects(args.effects)
    known = known_effects()
    unknown = [e for e in args.effects if e not in known]
    if unknown:
        raise ConfigError(f"--effects: {', '.join(map(repr, unknown))} not an effect "
                          f"(allowed: {', '.join(known)}; or file.py:ClassName for one of your own)")
    limit = getattr(args, "max_samples", None)
    lab = load_data(args.data, **({"max_probe_samples": DIAGNOSE_PROBE_SAMPLES} if limit is None
                                  else {"max_samples": limit}))
    say_read_warnings("diagnose", args.data, getattr(lab, "warnings", []))
    lab = skip_spans("diagnose", str(args.data), lab, getattr(args, "skip", None))
    say_part_of_run("diagnose", str(args.data))
    block = getattr(lab, "block", lab)
    names = getattr(lab, "probe_names", None)
    origin = None
    if args.config:
        positions, total = config_geometry(args.config, block.n_probes)
    else:                                         # the configuration a service recording stores, said
        from service.wiring.recorded_config import stored_config

        given = stored_config(getattr(lab, "metadata", {}), str(args.data), block.n_probes)
        positions, total, origin = given.positions_m, given.total_nT, given.origin
        if given.warning:
            print(f"fluxcal diagnose: warning: {given.warning}", file=sys.stderr)
    if getattr(args, "site", None):
        from service.numerics.calib.site import site_from_text

        total = site_from_text(args.site).total_nT
    data = EffectData.from_block(block, names, total_nT=total, positions_m=positions)
    ref = data.ref_total_nT                       # the reference the fits use before a configured total
    scale = say_field_scale("diagnose", args.data, data.raw_nT, data.probe_names, about="a sphere fitted to them",
                            total_nT=ref if ref is not None else total,
                            total_source="the ref_total column" if ref is not None else "the site" if args.site
                            else f"configuration from {args.config}" if args.config else origin or "given")
    thinned = thinning(lab, limit)
    del lab, block                                  # the samples live on in `data` only
    cal, effects = None, list(args.effects)
    if args.calibration:
        cal, cal_effects = load_calibration(args.calibration, data.n_probes)
        if not effects:
            missing = [e for e in cal_effects if e not in known]
            if missing:
                raise ConfigError(f"{args.calibration}: names the effect(s) {', '.join(map(repr, missing))}, which are "
                                  f"neither in the catalogue nor installed: give them with --effects "
                                  f"file.py:ClassName")
            effects = list(cal_effects)                             # the model the file describes
    bar = Progress(1.0, "diagnose", fraction=True)
    try:
        result = diagnose(data, effects=effects, calibration=cal, progress=bar,
                          check_linear=lambda lin: _refuse_one_cone(data, lin))
    finally:
        bar.close()
    if thinned is not None:
        result.thinned, text = thinned
        result.notes.insert(0, text)
    result.notes[0:0] = scale                     # data not in nT first: every figure after it is in their unit
    taken = (([f"total field {total:,.0f} nT (estimator.total_nT)"] if total is not None and not args.site else [])
             + ([f"probe positions of {len(positions)} probes"] if positions is not None else []))
    if origin and taken:
        result.notes.insert(0, f"{origin}: {'; '.join(taken)}")
    if args.calibration and effects:
        result.notes.append(f"{args.calibration}: linear part held fixed; the parameters of "
                            f"{', '.join(effects)} are refitted to these data")
    # the diagnosis first: a report that cannot be written (matplotlib missing, a full disk) must not cost it
    if args.json:
        json.dump(result.as_dict(), sys.stdout)
        sys.stdout.write("\n")
    else:
        print(summary_text(result, args.data + (f" ({origin})" if origin else "")))
    sys.stdout.flush()
    if args.report:
        from service.io.report import write_report
        from service.wiring.calib_report import section_from_diagnosis

        from service.io.report.page import NO_MATPLOTLIB, has_matplotlib

        report_path = write_report(result, args.report, title=f"fluxcal diagnose {Path(args.data).name}",
                                   calibration=section_from_diagnosis(result))
        if not has_matplotlib():
            print(f"fluxcal diagnose: report without plots: {NO_MATPLOTLIB}", file=sys.stderr)
        if args.json:
            print(f"fluxcal diagnose: report written to {report_path}", file=sys.stderr)
        else:
            print(f"  report: {report_path}")
    return 0


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
