"""`fluxcal repair REC OUT`: a killed writer's (or a damaged) recording copied into a finished, indexed one."""

from __future__ import annotations

from argparse import Namespace

from service.io.recordings.reader import repair_recording


def main(args: Namespace) -> int:
    report = repair_recording(args.recording, args.out)
    for line in report.warnings:
        print(f"lost: {line}")
    print(f"{args.out}: {report.messages} message(s) of {len(report.files)} file(s) copied"
          + (f"; {report.truncated_bytes} byte(s) at file ends held no complete record" if report.truncated_bytes else ""))
    return 0
