"""What a command says on stderr besides its result: what reading its input lost, and how to mend it."""

from __future__ import annotations

import sys
from typing import Sequence


def say_read_warnings(command: str, source: str, warnings: Sequence[str]) -> None:
    """One line per thing reading lost or skipped (a cut tail, a damaged record), then how to mend it."""
    for w in warnings:
        print(f"fluxcal {command}: warning: {w}", file=sys.stderr)
    if warnings:
        print(f"fluxcal {command}: the data above were read without what is listed; "
              f"`fluxcal repair {source} FIXED.mcap` writes a finished copy of what is readable", file=sys.stderr)
