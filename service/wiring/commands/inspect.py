"""`fluxcal inspect FILE`: what a recording holds (a ROS 2 bag's topics, a PX4 or ArduPilot log's messages, a CSV's
columns) and how fit and diagnose would map it, as text or JSON (service.io.recordings.inspect)."""

from __future__ import annotations

import argparse
import json
from argparse import Namespace

from service.io.recordings.formats import Inspection
from service.io.recordings.inspect import inspect_file
from service.wiring.commands.options import CommandHelp

HELP = CommandHelp("list what a recording holds and how fit and diagnose would map it",
                   "  fluxcal inspect flight.ulg\n  fluxcal inspect robot_bag/ --json")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE", help="a ROS 2 bag (.mcap, rosbag2 directory, .db3), a PX4 .ulg, an "
                                                "ArduPilot .bin, a fluxcal .mcap or a lab .csv")
    p.add_argument("--json", action="store_true", help="the inspection as JSON")


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
    lines += [f"warning: {x}" for x in i.warnings]
    return "\n".join(lines)


def main(args: Namespace) -> int:
    i = inspect_file(args.file)
    print(json.dumps(i.as_dict()) if getattr(args, "json", False) else text(i))
    return 0
