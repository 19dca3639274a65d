"""What `fluxcal run` says on stderr as it goes, beyond Zenoh and MCAP: a status line at an interval
(samples per second, learning or usable with the gate's figures, the error as an RMS over the interval with
the interval stated), the quality gate's reasons when they change (once a calibration is in use, said as the
latest candidate refused while the calibration in use stays), and every command with its answer."""

from __future__ import annotations

import math
import re
import time
from typing import Any, Callable, Mapping, Sequence

from .faults import no_samples_words


class StatusLog:
    """Counts what the service processed between status lines and says the line every `every_s`."""

    def __init__(self, say: Callable[[str], None], every_s: float) -> None:
        self.say, self.every_s = say, float(every_s)
        self._since = time.monotonic()
        self._samples = 0
        self._last_samples = self._since         # when samples last came (monotonic), for a silent input's line
        self._err_sq: dict[str, float] = {}       # per channel: sum of n x rms^2 over the interval's blocks
        self._err_n: dict[str, int] = {}          # ... and of n
        self._reasons: tuple[str, ...] | None = ()
        self._in_use: tuple[bool, Any] = (False, None)     # (a calibration in use, its cal_id): from the state
        self._refusals_said: set[tuple[str, ...]] = set()  # refusals said while this calibration is in use
        self._bus_refused = 0             # the bus's refusals already said
        self.refused = 0                  # commands the service refused (health: commands_refused)
        self._holders_said: set[str] = set()   # other services announcing this unit's name, said
        self._commands_said = 0           # command lines said since the last status line
        self._unsaid: list[int] = [0, 0]  # ... and beyond COMMAND_LINES: applied, refused (said at the next one)

    def block(self, n_samples: int, error: Mapping[str, float]) -> None:
        """A block processed: its samples, and its error per channel (an RMS over its n_samples)."""
        self._samples += n_samples
        if n_samples:
            self._last_samples = time.monotonic()
        for ch, rms in error.items():
            if isinstance(rms, (int, float)) and math.isfinite(rms):
                # the interval's RMS: sqrt(sum n_i rms_i^2 / sum n_i) over its blocks
                self._err_sq[ch] = self._err_sq.get(ch, 0.0) + n_samples * float(rms) ** 2
                self._err_n[ch] = self._err_n.get(ch, 0) + n_samples

    def gate(self, usable: bool, reasons: list[str]) -> None:
        """The gate's verdict on a candidate: its reasons are said when they change. While a calibration is in
        use a refusal is said as what it is (the latest candidate refused, the calibration in use stays), once
        for each set of reasons until another calibration comes into use."""
        # the same reasons with other figures (samples seen, a condition number) are not news
        key = () if usable else tuple(re.sub(r"[-+]?\d[\d.,e+-]*", "#", r) for r in reasons)
        if usable:
            self._in_use = (True, None)
            self._refusals_said.clear()
        if key == self._reasons:
            return
        self._reasons = key
        if usable:
            self.say("quality gate: candidate usable")
        elif not self._in_use[0]:
            self.say("quality gate: not yet: " + "; ".join(reasons))
        elif key not in self._refusals_said:
            self._refusals_said.add(key)
            cal = f" {self._in_use[1]}" if self._in_use[1] is not None else ""
            self.say(f"quality gate: the latest candidate was refused; the calibration{cal} in use stays: "
                     + "; ".join(reasons))

    #: command lines said between two status lines; the rest are counted and said with the next (500 commands in
    #: 5 s were 500 lines: a field trial)
    COMMAND_LINES = 10

    def command(self, name: str, payload: Any, answer: Mapping[str, Any]) -> None:
        what = name + (f" {str(payload)[:64]}" if payload and name != "apply" else "")
        self.refused += 0 if answer.get("ok") else 1
        self._commands_said += 1
        if self._commands_said > self.COMMAND_LINES:
            self._unsaid[0 if answer.get("ok") else 1] += 1
            return
        if answer.get("ok"):
            self.say(f"command {what}: applied (calibration {answer.get('cal_id')})")
        else:
            why = str(answer.get("error"))
            self.say(f"command {what}: refused: {why if len(why) <= 400 else why[:400] + ' ...'}")

    def bus_refusals(self, bus: Any) -> None:
        """Commands the bus refused on its own (too large, not UTF-8, not an effect name), said from the
        service's thread at its health tick: how many and the last reason, never the payload."""
        refused = getattr(bus, "stats", {}).get("commands_refused", 0)
        if refused > self._bus_refused:
            n, self._bus_refused = refused - self._bus_refused, refused
            self.say(f"{n} command(s) refused by the bus; the last: {getattr(bus, 'last_refused', '')} "
                     f"(state: bus.commands_refused)")

    def holders(self, bus: Any) -> None:
        """Another live service that announces this unit's name (they started at once, or one ignored the other):
        said once for each, with what it costs (bus.duplicate_holders counts them)."""
        for zid in getattr(bus, "other_holders", lambda: [])():
            if zid not in self._holders_said:
                self._holders_said.add(zid)
                self.say(f"another service announces unit {getattr(bus, 'unit', '?')} on this Zenoh network (zenoh "
                         f"id {zid}): the subscribers of fluxcal/{getattr(bus, 'unit', '?')}/... receive both "
                         f"streams interleaved and both obey every command; stop one, or give it another unit.name "
                         f"(health: bus.duplicate_holders)")

    def tick(self, state: Mapping[str, Any], active: Sequence[str] = ()) -> None:
        """The status line, when `every_s` has passed since the last one (active: the faults going on)."""
        now = time.monotonic()
        if state.get("usable"):
            in_use = (True, state.get("cal_id"))
            if in_use != self._in_use:
                self._refusals_said.clear()       # another calibration in use: its refusals are news again
                if self._reasons:
                    self._reasons = None
            self._in_use = in_use
        if now - self._since < self.every_s:
            return
        span = now - self._since
        rate = self._samples / span
        err = ", ".join(f"{k} {math.sqrt(self._err_sq[k] / self._err_n[k]):.3g}"
                        for k in list(self._err_sq)[:4] if self._err_n[k])
        n_err = max(self._err_n.values(), default=0)
        got, self._since, self._samples = self._samples, now, 0
        if sum(self._unsaid):
            self.say(f"{sum(self._unsaid):,} more command(s) since the last status line, not said one by one: "
                     f"{self._unsaid[0]:,} applied, {self._unsaid[1]:,} refused (state: commands_refused)")
        self._commands_said, self._unsaid = 0, [0, 0]
        self._err_sq, self._err_n = {}, {}
        gate = state.get("gate") or {}
        if state.get("usable"):
            where = f"calibration {state.get('cal_id')} in use" + (" (frozen)" if state.get("frozen") else "") + (
                " (applied: held until reset)" if state.get("held") else "")
        else:
            where = f"learning ({state.get('samples_seen', 0)} samples seen)"
        if gate:
            verdict = "passed" if gate.get("usable") else "refused"
            cov = gate.get("coverage")
            where += f"; latest check {verdict}" + (
                f": coverage {cov:.0%} of its window, condition {gate.get('condition', math.nan):.3g}"
                if isinstance(cov, (int, float)) and math.isfinite(cov) else "")
        if not got and now - self._last_samples >= self.every_s:
            quiet = now - self._last_samples
            since = time.strftime("%H:%M:%S", time.localtime(time.time() - quiet))
            where = f"no samples for {quiet:,.0f} s (since {since}): {no_samples_words(active)}; {where}"
        self.say(f"status: {rate:,.0f} samples/s; {where}"
                 + (f"; error rms nT over the last {span:.0f} s ({n_err:,} samples): {err}" if err else ""))
