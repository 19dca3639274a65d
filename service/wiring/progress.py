"""Progress of long work on the command line: one implementation for decode, replay, diagnose and simulate.

On a terminal: a tqdm bar on stderr, drawn only once the work has run for DELAY_S (short work shows
nothing) and erased at the end. Elsewhere (a log file, a pipe, CI): a plain line every LINE_S seconds,
so a log shows that long work goes on, and nothing at all for work shorter than that.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any, TextIO

from tqdm import tqdm

DELAY_S = 1.0        # a bar appears only for work that has run this long
LINE_S = 10.0        # without a terminal, one line per this many seconds
REDRAW_S = 0.2       # a bar is redrawn at most this often


def _columns(stream: TextIO) -> int:
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, OSError, ValueError):
        return 0


class Progress:
    """Progress of `total` units of work: `to(done)` with the units done so far, or `__call__(frac, msg)`
    with a fraction and what is being done (the diagnosis reports that way); `close()` at the end."""

    def __init__(self, total: float, label: str, *, unit: str = "sample", stream: TextIO | None = None,
                 fraction: bool = False, delay_s: float | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.total, self.label, self.unit = max(float(total), 1.0), label, unit
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.started = self.last = time.monotonic()
        self.bar: Any = None
        if self.tty:
            # a fraction (the diagnosis) has no unit to count: percent, elapsed time and what is being done
            form = "{desc}: {percentage:3.0f}%|{bar}| {elapsed}{postfix}" if fraction else None
            # a terminal that reports no width (a pty opened by a script) gets a fixed one
            width = _columns(self.stream)
            self.bar = tqdm(total=self.total if fraction else int(self.total), desc=label, unit=unit,
                            unit_scale=not fraction, file=self.stream, delay=DELAY_S if delay_s is None else delay_s,
                            leave=False, dynamic_ncols=width > 0, ncols=None if width > 0 else 80,
                            mininterval=REDRAW_S, bar_format=form)
        self.fraction = fraction

    def to(self, done: float, msg: str = "") -> None:
        """Report `done` units finished (absolute, not an increment)."""
        if self.bar is not None:
            if msg:
                self.bar.set_postfix_str(msg, refresh=False)
            self.bar.update(done - self.bar.n)
            return
        now = time.monotonic()
        if now - self.last >= LINE_S and done < self.total:
            self.last = now
            what = f" ({msg})" if msg else ""
            self.stream.write(f"fluxcal {self.label}: {100 * done / self.total:.0f} % of {self._amount()} "
                              f"after {now - self.started:.0f} s{what}\n")
            self.stream.flush()

    def __call__(self, frac: float, msg: str = "") -> None:
        self.to(min(max(frac, 0.0), 1.0) * self.total, msg)

    def _amount(self) -> str:
        if self.fraction:
            return "the work"
        return f"{self.total:.0f} {self.unit}s" if self.unit else f"{self.total:.0f}"

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
