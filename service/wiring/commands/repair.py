"""`fluxcal repair REC OUT`: a killed writer's (or a damaged) recording copied into a finished, indexed one,
which records what its original lost (the holes, with the samples' seq and time spans, and the cut tail)."""

from __future__ import annotations

import argparse
from argparse import Namespace
from dataclasses import dataclass, field
from typing import Any

from fluxcal.service.io.recordings.reader import repair_recording
from fluxcal.service.wiring.commands.options import CommandHelp
from fluxcal.service.wiring.result import Result, Said, print_result, stderr_say

HELP = CommandHelp("copy a recording cut by a killed writer (or damaged) into a finished one",
                   "  fluxcal repair recordings/live/grad1-20261124T101500-0003.mcap fixed.mcap\n"
                   "  fluxcal repair recordings/live/ fixed/")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="REC", help="an MCAP file, or a directory of them")
    p.add_argument("out", metavar="OUT", help="the finished copy (a file, or a directory for a directory)")


@dataclass
class RepairResult(Result):
    """A recording copied whole where it could be read: what was lost (holes, a cut tail) and what was copied."""

    messages: int = 0
    files: int = 0
    holes: list[str] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "messages": self.messages, "files": self.files, "holes": self.holes}

    def text(self) -> str:
        return "\n".join(self.lines)


def main(args: Namespace) -> int:
    """The command line: what was lost and what was copied, on stdout."""
    result = execute(args.recording, args.out, Said("repair", stderr_say("repair")))
    print_result(result, False)
    return result.status


def execute(source: str, out: str, said: Said) -> RepairResult:
    """`fluxcal repair SOURCE OUT`: every intact chunk copied, the holes and the cut written into the copy."""
    report = repair_recording(source, out)
    lines = [f"lost: {line}" if "nothing lost" not in line else f"damaged: {line}"
             for line in report.truncated + report.damaged]
    lines += [f"hole: {hole.describe()}" for hole in report.holes]
    lines.append(f"{out}: {report.messages} message(s) of {len(report.files)} file(s) copied"
                 + (f"; {report.truncated_bytes} byte(s) at file ends held no complete record"
                    if report.truncated_bytes else "")
                 + (f"; {len(report.holes)} hole(s), recorded in the copy's \"fluxcal.repair\" metadata with the cut"
                    if report.holes else "; the cut recorded in the copy's \"fluxcal.repair\" metadata"
                    if report.truncated else ""))
    return RepairResult("repair", str(source), notes=said.notes, written=[str(out)], messages=report.messages,
                        files=len(report.files), holes=[h.describe() for h in report.holes], lines=lines)
