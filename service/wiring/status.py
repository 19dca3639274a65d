"""What `fluxcal run` says on stderr as it goes, beyond Zenoh and MCAP: a status line at an interval
(samples per second, learning or usable with the gate's figures, the error), the quality gate's
reasons when they change, and every command with its answer."""

from __future__ import annotations

import math
import re
import time
from typing import Any, Callable, Mapping


class StatusLog:
    """Counts what the service processed between status lines and says the line every `every_s`."""

    def __init__(self, say: Callable[[str], None], every_s: float) -> None:
        self.say, self.every_s = say, float(every_s)
        self._since = time.monotonic()
        self._samples = 0
        self._error: dict[str, float] = {}
        self._reasons: tuple[str, ...] = ()
        self._bus_refused = 0             # the bus's refusals already said
        self.refused = 0                  # commands the service refused (health: commands_refused)

    def block(self, n_samples: int, error: Mapping[str, float]) -> None:
        self._samples += n_samples
        if error:
            self._error = dict(error)

    def gate(self, usable: bool, reasons: list[str]) -> None:
        """The gate's verdict on a candidate: its reasons are said when they change."""
        # the same reasons with other figures (samples seen, a condition number) are not news
        key = () if usable else tuple(re.sub(r"[-+]?\d[\d.,e+-]*", "#", r) for r in reasons)
        if key != self._reasons:
            self._reasons = key
            self.say("quality gate: candidate usable" if usable else "quality gate: not yet: " + "; ".join(reasons))

    def command(self, name: str, payload: Any, answer: Mapping[str, Any]) -> None:
        what = name + (f" {str(payload)[:64]}" if payload and name != "apply" else "")
        if answer.get("ok"):
            self.say(f"command {what}: applied (calibration {answer.get('cal_id')})")
        else:
            self.refused += 1
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

    def tick(self, state: Mapping[str, Any]) -> None:
        """The status line, when `every_s` has passed since the last one."""
        now = time.monotonic()
        if now - self._since < self.every_s:
            return
        rate = self._samples / (now - self._since)
        self._since, self._samples = now, 0
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
        err = ", ".join(f"{k} {v:.3g}" for k, v in list(self._error.items())[:4])
        self.say(f"status: {rate:,.0f} samples/s; {where}" + (f"; error rms nT: {err}" if err else ""))
