"""`fluxcal repair REC OUT`: a killed writer's (or a damaged) recording copied into a finished, indexed one,
which records what its original lost (the holes, with the samples' seq and time spans, and the cut tail)."""

from __future__ import annotations

from argparse import Namespace

from service.io.recordings.reader import repair_recording


def main(args: Namespace) -> int:
    report = repair_recording(args.recording, args.out)
    for line in report.truncated + report.damaged:
        print(f"lost: {line}" if "nothing lost" not in line else f"damaged: {line}")
    for hole in report.holes:
        print(f"hole: {hole.describe()}")
    print(f"{args.out}: {report.messages} message(s) of {len(report.files)} file(s) copied"
          + (f"; {report.truncated_bytes} byte(s) at file ends held no complete record"
             if report.truncated_bytes else "")
          + (f"; {len(report.holes)} hole(s), recorded in the copy's \"fluxcal.repair\" metadata with the cut"
             if report.holes else "; the cut recorded in the copy's \"fluxcal.repair\" metadata"
             if report.truncated else ""))
    return 0
