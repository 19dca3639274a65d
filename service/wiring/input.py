"""The service's input side: blocks of about `unit.block_ms` read from a source, and the sample rate the
unit's clock shows against the configured one."""

from __future__ import annotations

import math
import threading
import time
from typing import Callable

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import DriverError
from fluxcal.drivers.registry import source_kind
from fluxcal.drivers.source import Source

from .config import FluxcalConfig


class Reconnecting:
    """Reads blocks (BatchReader) and, when the input is lost (a pulled cable, a closed pty), says so and reopens the
    source with a backoff from 0.1 s doubling to 5 s, counting read_errors and reconnects (whatever the source).
    `read` returns a block, or None while nothing came or the input is down; `stopped` turns True when the stop
    event came during a backoff."""

    def __init__(self, reader: "BatchReader", stop: threading.Event, say: Callable[[str], None]) -> None:
        self.reader, self.stop, self.say = reader, stop, say
        self.backoff = 0.1
        self.down_since: float | None = None  # monotonic time the input was lost, while it stays down
        self.down_why: str | None = None      # ... and why (the source's error), while it stays down
        self.attempts = 0
        self.stopped = False
        self.read_errors = 0                  # times the input went down
        self.reconnects = 0                   # ... and came back

    def counts(self) -> dict[str, int]:
        """The input's losses and returns, for the health counters."""
        return {"read_errors": self.read_errors, "reconnects": self.reconnects}

    def read(self, source: Source) -> SampleBlock | None:
        if self.down_since is None:
            try:
                return self.reader.read(source)
            except DriverError as e:
                self.say(f"input lost: {e}; reconnecting (backoff from {self.backoff:.1f} s)")
                self.read_errors += 1
                self.down_since, self.down_why, self.attempts = time.monotonic(), str(e), 0
        if self.stop.wait(self.backoff):
            self.stopped = True
            return None
        self.backoff = min(self.backoff * 2, 5.0)
        self.attempts += 1
        try:
            source.reopen()
        except DriverError as e:
            if self.attempts in (5, 20) or self.attempts % 100 == 0:
                self.say(f"input still down after {time.monotonic() - self.down_since:.0f} s and {self.attempts} "
                         f"attempts: {e}; retrying every {self.backoff:.0f} s")
        else:
            self.reconnects += 1
            self.say(f"input reconnected after {time.monotonic() - self.down_since:.1f} s")
            self.down_since, self.down_why, self.backoff = None, None, 0.1
        return None


class BatchReader:
    """Reads a source in blocks of about `block_ms`: fewer, larger blocks cost less CPU per sample."""

    #: waits up to this long are a plain sleep (the stop is seen when it ends): a sleep costs the service's thread
    #: about two thirds of a wait on the stop event (22-30 against 34-46 us of CPU a block, measured on the
    #: benchmark machine), once a block
    SLEEP_S = 0.05

    def __init__(self, block_ms: float, stop: threading.Event) -> None:
        self.block_ms, self.stop = block_ms, stop
        self._pending_error: DriverError | None = None
        self._flowing = False             # the last read brought samples: the next block is surely on its way

    def _gather(self) -> bool:
        """Let the rest of the block arrive in the port's buffer; whether the stop came (then, or before)."""
        wait = self.block_ms / 1000.0
        if wait > self.SLEEP_S:
            return self.stop.wait(wait)
        time.sleep(wait)
        return self.stop.is_set()

    def read(self, source: Source):
        """One block (None if nothing came). A port that fails mid-batch: the samples already read are
        returned first, the error comes at the next call."""
        if self._pending_error is not None:
            e, self._pending_error = self._pending_error, None
            raise e
        if self._flowing:
            # samples came last time: gather the block and read it, without first asking whether input is there
            # (one system call fewer a block); nothing there: wait for input as below
            self._gather()
            block = source.read(timeout=0.001)
            self._flowing = block is not None
            if block is not None:
                return block
        ready = source.wait_readable(0.05)
        if ready is not None:
            if not ready:
                return None
            # input is there: let the rest of the block arrive in the port's buffer, then one read and one
            # parse (when stopping, still read what is there: nothing that arrived is lost)
            self._gather()
            block = source.read(timeout=0.001)
            self._flowing = block is not None
            return block
        first = source.read(timeout=0.05)
        if first is None:
            return None
        parts = [first]
        # let the rest of the block arrive in the port's buffer, then take it in one read and one parse
        if self._gather():
            return first
        try:
            more = source.read(timeout=0.001)
            if more is not None:
                parts.append(more)
        except DriverError as e:
            self._pending_error = e
        return parts[0] if len(parts) == 1 else SampleBlock.concat(parts)



class RateCheck:
    """Once, after RATE_CHECK_S of unit clock: the sample rate the frames show (samples counted by seq
    over the unit clock's t_s) against the configured one, which sets how many samples the estimator's
    durations span. A mismatch is said with the value to set; the service goes on (it is a setting).
    Only spans inside a block count: a gap between blocks (an outage, a restarted unit, a counter that
    wrapped while the cable was out) can make seq and clock disagree, the unit's rate cannot."""

    #: unit-clock time over which the configured sample rate is checked, s; and the mismatch said
    RATE_CHECK_S, RATE_TOLERANCE = 5.0, 0.02

    def __init__(self, cfg: FluxcalConfig, say: Callable[[str], None]) -> None:
        self.cfg, self.say = cfg, say
        self._seen: tuple[int, float] = (0, 0.0)       # samples (by seq) and unit-clock seconds seen
        # the unit clock is compared with the configured rate once; an input whose time is no unit clock of its
        # own (t_s = seq / rate, its kind's declaration says) has nothing to compare
        self.checked = not source_kind(cfg.source.kind).clock(getattr(cfg.source, "protocol", ""))

    def check(self, block: SampleBlock) -> None:

        if block.n_samples < 2:
            return
        dseq = int(block.seq[-1]) - int(block.seq[0])
        dt = float(block.t_s[-1]) - float(block.t_s[0])
        if not (math.isfinite(dt) and dt > 0 and dseq > 0):
            return
        n, span = self._seen
        n, span = n + dseq, span + dt
        self._seen = (n, span)
        if span < self.RATE_CHECK_S:
            return
        self.checked = True
        seen, configured = n / span, self.cfg.rate_hz
        if configured and abs(seen / configured - 1.0) > self.RATE_TOLERANCE:
            key = "source.rate_hz" if getattr(self.cfg.source, "rate_hz", None) else "sim.rate_hz"
            self.say(f"the unit's clock shows {seen:.6g} samples/s but {key} = {configured:g}: the estimator's "
                     f"window_s, check_every_s and update_every_s last {configured / seen:.3g} x the seconds "
                     f"configured; set {key} = {seen:.6g}")

