"""`fluxcal inspect FILE`: what a recording holds (a ROS 2 bag's topics, a PX4 or ArduPilot log's messages, a CSV's
columns) and how fit and diagnose would map it, as text or JSON (fluxcal.service.io.recordings.inspect): the probes, columns,
samples, duration and clock of the one reading fit and diagnose use (fluxcal.service.wiring.prepare, with the same options),
and each probe's verdict of the one determinacy gate they ask (fluxcal.service.numerics.calib.determinacy)."""

from __future__ import annotations

import argparse
import json
from argparse import Namespace
from dataclasses import replace

from fluxcal.drivers.errors import CalibrationRefused, DataError
from fluxcal.service.io.recordings.formats import Inspection
from fluxcal.service.io.recordings.inspect import inspect_file, reading
from fluxcal.service.wiring.commands.options import CONFIG_HELP, CommandHelp, data_options

HELP = CommandHelp("list what a recording holds and how fit and diagnose would map it",
                   "  fluxcal inspect flight.ulg\n  fluxcal inspect robot_bag/ --json")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE", help="a ROS 2 bag (.mcap, rosbag2 directory, .db3), a PX4 .ulg, an "
                                                "ArduPilot .bin, a fluxcal .mcap or a lab .csv")
    p.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    data_options(p)
    p.add_argument("--json", action="store_true", help="the inspection as JSON")


def _verdict_line(v: dict) -> str:
    head = f"  {v['probe']}: "
    if not v["determined"]:
        return head + f"not determined: {v['reason']}"
    cone = v.get("cone") or {}
    return head + (f"determined ({v['samples']:,} samples; directions within ±{cone.get('band_deg', 0):.1f}° of a cone "
                   f"about {cone.get('axis_name', '-')}, misfit {cone.get('misfit_nT', 0):.3g} nT, field "
                   f"{v['field_nT']:,.0f} nT; {v['coverage']['fraction']:.0%} of directions seen)")


def text(i: Inspection) -> str:
    lines = [f"{i.path}: {i.format_name}" + (f", {i.duration_s:.1f} s" if i.duration_s is not None else "")]
    w = max([len(s.name) for s in i.streams] + [6])
    k = max([len(s.kind) for s in i.streams] + [4])
    lines.append(f"  {'stream':<{w}}  {'type':<{k}}  {'count':>9}  {'rate Hz':>8}  maps to")
    for s in i.streams:
        r = f"{s.rate_hz:8.3g}" if s.rate_hz is not None else f"{'-':>8}"
        lines.append(f"  {s.name:<{w}}  {s.kind:<{k}}  {s.count:>9,}  {r}  {s.maps_to or '-'}"
                     + (f"  ({s.note})" if s.note else ""))
    lines.append(f"probes: {', '.join(i.probes) or 'none'}")
    lines.append(f"columns: {', '.join(i.columns) or 'none'}")
    if i.samples is not None:
        clock = i.clock or {}
        t0 = clock.get("t0_unix_s")
        lines.append(f"samples: {i.samples:,}" + (f" over {i.duration_s:.1f} s" if i.duration_s is not None else "")
                     + (f"; t: {clock['t_s']}" if clock.get("t_s") else "")
                     + (f", t = 0 at UNIX {t0:.3f} s" if t0 is not None else ", its date unknown" if clock else ""))
    if i.fit_refuses:
        lines.append(f"nothing to calibrate: {i.fit_refuses}")
    if i.verdict:
        lines.append("verdict (the gate fit and diagnose ask):")
        lines += [_verdict_line(v) for v in i.verdict]
    lines += [f"warning: {x}" for x in i.warnings]
    return "\n".join(lines)


def inspect(args: Namespace) -> Inspection:
    """The file's streams, then what fit would take of it (prepare and usable_data, as fit does) and each probe's
    verdict of the determinacy gate, with the total field fit would take."""
    from fluxcal.service.wiring.commands.fit import usable_data
    from fluxcal.service.wiring.fitting import judge_data
    from fluxcal.service.wiring.prepare import log_mapping, prepare
    from fluxcal.service.wiring.result import Said
    from fluxcal.service.wiring.scale_notes import data_scale_notes

    topics, mags = getattr(args, "topics", None), getattr(args, "mags", None)
    i = inspect_file(args.file, log_mapping(args.file, topics, mags), read=False)
    read = False
    said = Said("inspect")
    try:
        prep = prepare(args.file, said, config=getattr(args, "config", None),
                       site=getattr(args, "site", None), skip=getattr(args, "skip", None), topics=topics, mags=mags)
        data, left_out = usable_data(prep.data)
        # what the reading fit and diagnose share left out (a logger's holds, a gap), as they say it
        carried = [w for w in (prep.config_warning, prep.part_of_run) if w]       # as fit carries them
        lost = [w for w in said.lost_in_reading(besides=i.warnings) + left_out + carried if w not in i.warnings]
        i, read = replace(i, **reading(data), warnings=i.warnings + lost), True
        judged = judge_data(data, prep.total_nT, prep.total_source or "")
        scale = data_scale_notes(said, prep, data, judged)             # the data's scale, as fit says it
        i = replace(i, warnings=i.warnings + [w for w in scale if w not in i.warnings])
    except (DataError, CalibrationRefused) as e:
        # what was read stays said (its samples, duration, clock): the refusal is of a calibration from them
        left = {} if read else {"probes": [], "columns": [], "samples": 0}
        return replace(i, fit_refuses=str(e), warnings=[w for w in i.warnings if "nothing to calibrate" not in w],
                       **left)
    return replace(i, verdict=[j.as_dict() for j in judged])


def main(args: Namespace) -> int:
    i = inspect(args)
    print(json.dumps(i.as_dict()) if getattr(args, "json", False) else text(i))
    return 0
