"""What `fluxcal run` says about losses and faults, decided from the source's counters and the recorder's status
at the service's health tick (about once a second): a console line when a fault begins, its running count while
it lasts (at most every `every_s`), a line when it ends, and a summary at stop. The same lines go to the health
channel as events with their counts (`health.faults`), where the dashboard shows them.

The source's faults are said in its own bus's words: each counter its kind and protocol declare (drivers/kinds/,
fluxcal.drivers.declare.Counted: its fault name, label, what {n} of it are, the advice, a share or the counters said
beside it) is said as it declares, and only those (`words`, the Counters' words of the source opened). Besides:

    no_decode     input arrives but nothing of the unit's decodes for 2 s (a wrong baud rate, a wrong base id),
                  in the words the protocol declares (fluxcal.drivers.declare.NoDecode)
    silence       nothing from the unit for `silence_s` (unit.silence_s), and when data come again
    input_lost    the port or bus is down while the service reconnects (said on the console as it happens, by the
                  reader: input.Reconnecting; here its state, and its events for the health channel)
    persist       saves of the calibration in use that failed (a restart would not reload it)
    calibrations_refused, commands_refused: said where they happen; counted here, and in the summary at stop
    stalls        the bus waited for a subscriber that took nothing (the daemon adds bus.send_stalls)
    recording     write errors (a full disk): the messages dropped, running, and when recording resumes

No I/O and no clock of its own beyond the one it is given: the daemon feeds it counters and passes on what it
says; the tests feed it counters and a clock.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from fluxcal.drivers.declare import Counted, Words

#: input without a frame for this long is said (a stretch shorter than that is a partial frame, a glitch)
NO_DECODE_S = 2.0
#: a fault that was counted is over when its counter stayed still this long
QUIET_S = 3.0
#: events the health channel carries (the newest): a dashboard that missed a message still gets them
HEALTH_EVENTS = 10

#: the service's own counters that are said (the source's are its declaration's)
SERVICE = (
    Counted("persist_failures", "saves of the calibration in use that failed", fault="persist",
            label="calibration not persisted", what="{n:,} save(s) of the calibration in use failed",
            advice="it is in use, but a restart would not reload it: check the folder of calibration.file"),
    Counted("calibrations_refused", "calibrations refused by apply, or the persisted one at start",
            fault="calibrations_refused", label="calibrations refused",
            what="{n:,} calibration(s) refused (by apply, or the persisted one at start), each said as it came",
            quiet=True),
    Counted("calibrations_doubted", "calibrations in use that failed the data check once the data came",
            fault="calibrations_doubted", label="calibration in use doubted",
            what="{n:,} calibration(s) in use, started from or applied before any data, failed the data check on "
                 "the unit's data: another unit's or far off, or the total field given is",
            advice="`fluxcal command reset` learns anew, `apply` gives another; check estimator.total_nT"),
    Counted("commands_refused", "commands the service refused", fault="commands_refused", label="commands refused",
            what="{n:,} command(s) refused, each said as it came", quiet=True),
    Counted("duplicate_holders", "other services announcing this unit's name", fault="duplicate_holders",
            label="another service under this unit's name",
            what="{n:,} other service(s) announced this unit's name on the network", quiet=True),
    Counted("send_stalls", "waits of the bus for a subscriber that took nothing", fault="stalls",
            label="a subscriber took nothing",
            what="the streams waited {n:,} time(s) for a subscriber that took nothing (health: bus.send_stalls)",
            advice="a subscriber that takes nothing for zenoh.stall_close_ms is disconnected so that it holds back "
                   "no other one; it reconnects and counts what it missed by seq (docs/zenoh.md)"),
)


@dataclass
class _Episode:
    """A fault while it lasts: since when, the counter then, when it last grew, what was said last."""

    since: float
    start: int
    last_grew: float
    said_at: float
    said_value: int
    said_counters: Mapping[str, int] | None = None     # every counter when it was said last


def _ago(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.1f} s"


class RecordingWatch:
    """The recorder's trouble (a full disk, a removed drive): when it begins, its running count of messages dropped
    (at most every `every_s`), and when recording resumes; `event` says and records each line."""

    def __init__(self, event: Callable[[str, str, int, str], None], every_s: float) -> None:
        self._event, self.every_s = event, every_s
        self._prev: dict[str, Any] | None = None
        self._episode: _Episode | None = None
        self.troubles = 0                     # stretches of trouble
        self.dropped = 0

    @property
    def active(self) -> bool:
        return self._episode is not None

    def tick(self, st: Mapping[str, Any], now: float) -> None:
        prev = self._prev or {"errors": 0, "dropped": 0, "messages_written": 0}
        self._prev = dict(st)
        errors, dropped = int(st.get("errors", 0)), int(st.get("dropped", 0))
        self.dropped = dropped
        new_errors = errors > int(prev.get("errors", 0))
        ep = self._episode
        if ep is None and new_errors:
            self.troubles += 1
            start = int(prev.get("dropped", 0))
            self._episode = _Episode(since=now, start=start, last_grew=now, said_at=now, said_value=dropped)
            self._event("recording", "begin", dropped,
                        f"recording trouble: {st.get('last_error')}; {dropped - start:,} message(s) dropped so far, "
                        f"{st.get('pending', 0)} waiting to be written; retrying (health: recording)")
        elif ep is not None:
            resumed = (not new_errors and st.get("current") is not None
                       and int(st.get("messages_written", 0)) > int(prev.get("messages_written", 0)))
            if resumed:
                self._episode = None
                self._event("recording", "end", dropped,
                            f"recording resumed after {_ago(now - ep.since)} into {st.get('current')}: "
                            f"{dropped - ep.start:,} message(s) dropped meanwhile, {dropped:,} in all")
            elif now - ep.said_at >= self.every_s:
                self._event("recording", "ongoing", dropped,
                            f"recording still failing: {st.get('last_error')}; {dropped - ep.start:,} message(s) "
                            f"dropped since it began {_ago(now - ep.since)} ago ({dropped - ep.said_value:,} in the "
                            f"last {_ago(now - ep.said_at)}), {st.get('pending', 0)} waiting; {dropped:,} in all")
                ep.said_at, ep.said_value = now, dropped


class InputWatch:
    """The input's states: silence (nothing at all arrives for `silence_s`), input that decodes into no frame of the
    unit's, and the input's loss while the service reconnects; each said (by `event`) as it begins and ends."""

    def __init__(self, event: Callable[..., None], silence_s: float) -> None:
        self._event, self.silence_s = event, silence_s
        self._last_activity: float | None = None   # silence counts from the first tick: a unit that never sends is said
        self._silent_since: float | None = None
        self.silences = 0
        self._nd_since: float | None = None   # input without a frame since then (not said yet, or said)
        self._nd_input = 0
        self._nd_said = False
        self.no_decode = 0                    # stretches said
        self.no_decode_input = 0              # input in them (bytes, frames: as the protocol's NoDecode says)
        self._down: tuple[str, float] | None = None       # the input's loss while it lasts: why, since when

    @property
    def started(self) -> bool:
        return self._last_activity is not None

    def active(self) -> list[str]:
        return ((["input_lost"] if self._down is not None else []) + (["silence"] if self._silent_since is not None
                else []) + (["no_decode"] if self._nd_said else []))

    def tick(self, w: Words, d: Mapping[str, int], now: float, prev_t: float | None) -> None:
        """Silence (nothing at all arrives) and input that decodes into no frame of the unit's."""
        frames = sum(d.get(k, 0) for k in w.decoded)
        arrived = sum(d.get(k, 0) for k in w.arrival if k not in w.decoded)
        if self._last_activity is None:
            self._last_activity = now
        if arrived > 0 or frames > 0:
            if self._silent_since is not None:
                self._event("silence", "end", self.silences,
                            f"silence ended: data from the unit again after about {_ago(now - self._silent_since)}")
                self._silent_since = None
            self._last_activity = now
        elif self._silent_since is None and self._down is None and now - self._last_activity >= self.silence_s:
            # (not while the input is lost: the reader said why nothing comes, and asking whether the unit is powered
            # would send the user to the wrong end)
            self._silent_since = self._last_activity
            self.silences += 1
            self._event("silence", "begin", self.silences,
                        f"silence: no data from the unit for {_ago(now - self._last_activity)} (unit.silence_s = "
                        f"{self.silence_s:g}): is it powered, connected and sending? ({self.silences} silence(s) "
                        f"so far; health: faults.active)")
        nd = w.no_decode
        if nd is None:
            return
        if arrived > 0 and frames == 0:
            if self._nd_since is None:
                self._nd_since, self._nd_input = (prev_t if prev_t is not None else now), 0
            self._nd_input += arrived
            if not self._nd_said and now - self._nd_since >= NO_DECODE_S:
                self._nd_said = True
                self.no_decode += 1
                self.no_decode_input += self._nd_input
                self._event("no_decode", "begin", self._nd_input,
                            f"{nd.label}: " + nd.begin.format(n=self._nd_input, t=_ago(now - self._nd_since)))
            elif self._nd_said:
                self.no_decode_input += arrived
        elif frames > 0 and self._nd_since is not None:
            if self._nd_said:
                self._event("no_decode", "end", self._nd_input,
                            f"{nd.label} ended: " + nd.end.format(n=self._nd_input, t=_ago(now - self._nd_since)))
            self._nd_since, self._nd_said = None, False

    def lost(self, why: str | None, times: int, now: float) -> None:
        """The input's loss as a fault going on: while a reconnect is awaited the port's failure is what a viewer
        hears, not the faults that were counted before it (a field trial's watch blamed "CAN samples incomplete"
        while the adapter was gone). Said on the console by the reader as it happens: recorded here only."""
        if why is not None and self._down is None:
            self._down = (why, now)
            self._event("input_lost", "begin", times, f"input lost: {why}; reconnecting", say=False)
        elif why is None and self._down is not None:
            self._event("input_lost", "end", times, f"input back after about {_ago(now - self._down[1])}", say=False)
            self._down = None


class FaultWatch:
    """Decides what to say about losses and faults from counters, at each `tick`; keeps the health field.
    words: the source's counters and their words (its Counters' `words`; the daemon sets them once it is open)."""

    def __init__(self, say: Callable[[str], None], *, words: Words = Words(()), silence_s: float = 5.0,
                 every_s: float = 10.0, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time) -> None:
        self.say, self.silence_s, self.every_s = say, float(silence_s), float(every_s)
        self.words = words
        self.clock, self.wall = clock, wall
        self._prev: dict[str, int] = {}
        self._prev_t: float | None = clock()  # the first tick compares with the start: nothing counted yet
        self._episodes: dict[str, _Episode] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=HEALTH_EVENTS)
        self.n_events = 0
        self.totals: dict[str, int] = {}
        self.input = InputWatch(self._event, self.silence_s)
        self.recording = RecordingWatch(self._event, self.every_s)

    # --- saying ---------------------------------------------------------------------------------------

    def _event(self, kind: str, phase: str, count: int, text: str, *, say: bool = True) -> None:
        if say:
            self.say(text)
        self.n_events += 1
        self.events.append({"n": self.n_events, "kind": kind, "phase": phase, "count": int(count), "text": text,
                            "time_unix_s": self.wall()})

    def _said(self) -> tuple[Counted, ...]:
        """The counters said: the source's faults, then the service's."""
        return tuple(k for k in self.words.counted + SERVICE if k.fault)

    # --- the tick ----------------------------------------------------------------------------------------

    def tick(self, counters: Mapping[str, int], recording: Mapping[str, Any] | None = None,
             input_lost: str | None = None) -> dict[str, Any]:
        """Compare with the last tick, say what began, goes on or ended; returns the health field. input_lost: why
        the input is down, while it is (None while it is up)."""
        now = self.clock()
        self.input.lost(input_lost, int(counters.get("read_errors", 0)), now)
        dt = now - self._prev_t if self._prev_t is not None else None
        prev = self._prev or {}
        delta = {k: int(v) - int(prev.get(k, 0)) for k, v in counters.items()}
        self.input.tick(self.words, delta, now, self._prev_t)
        for kind in self._said():
            if kind.name in counters:
                self._counted(kind, counters, delta, now, dt)
        if recording is not None:
            self.recording.tick(recording, now)
            self.totals["recording_dropped"] = self.recording.dropped
        self._prev, self._prev_t = {k: int(v) for k, v in counters.items()}, now
        return self.health()

    def _counted(self, kind: Counted, c: Mapping[str, int], d: Mapping[str, int], now: float,
                 dt: float | None) -> None:
        value, grew = int(c[kind.name]), d.get(kind.name, 0)
        self.totals[kind.fault] = value
        ep = self._episodes.get(kind.fault)
        if kind.quiet:
            return
        if grew > 0 and kind.one_shot:
            self._event(kind.fault, "event", value, f"{kind.label}: {kind.what.format(n=value)} ({kind.advice}; "
                                                    f"health: counters.{kind.name})")
        elif grew > 0 and ep is None:
            began = self._prev_t if self._prev_t is not None else now       # within the last interval
            self._episodes[kind.fault] = _Episode(since=began, start=value - grew, last_grew=now, said_at=now,
                                                  said_value=value, said_counters=dict(c))
            window = f" in the last {_ago(dt)}" if dt else ""
            self._event(kind.fault, "begin", value,
                        f"{kind.label}: {kind.what.format(n=grew)}{window}{self._detail(kind, c, self._prev)}; "
                        f"{value:,} so far" + (f" ({kind.advice})" if kind.advice else "")
                        + f" (health: counters.{kind.name})")
        elif grew > 0:
            ep.last_grew = now
            if now - ep.said_at >= self.every_s:
                self._event(kind.fault, "ongoing", value,
                            f"{kind.label} go on: {kind.what.format(n=value - ep.said_value)} in the last "
                            f"{_ago(now - ep.said_at)}{self._detail(kind, c, ep.said_counters or {})}; "
                            f"{value - ep.start:,} since they began {_ago(now - ep.since)} ago, {value:,} so far")
                ep.said_at, ep.said_value, ep.said_counters = now, value, dict(c)
        elif ep is not None and now - ep.last_grew >= QUIET_S:
            del self._episodes[kind.fault]
            self._event(kind.fault, "end", value,
                        f"{kind.label} stopped: {kind.what.format(n=value - ep.start)} over "
                        f"{_ago(ep.last_grew - ep.since)}, none for {_ago(now - ep.last_grew)}; {value:,} so far")

    def _detail(self, kind: Counted, c: Mapping[str, int], ref: Mapping[str, int]) -> str:
        """The figures a counter's line carries besides its count, over the stretch since the counters `ref`: its
        share of the frames, the counters said beside it (as its declaration says)."""
        def grew(key: str) -> int:
            return int(c.get(key, 0)) - int(ref.get(key, 0))

        if kind.share:
            bad, good = grew(kind.name), sum(grew(k) for k in self.words.decoded)
            share = bad / max(bad + good, 1)
            return f" ({share:.1%} of the {kind.share})" if share < 0.1 else f" ({share:.0%} of the {kind.share})"
        parts = [words.format(n=grew(key)) for key, words in kind.beside if grew(key)]
        return f" ({', '.join(parts)})" if parts else ""

    # --- what the health channel and the summary carry ------------------------------------------------------

    @property
    def started(self) -> bool:
        """Whether a tick has come: the service's loop ran."""
        return self.input.started

    def active(self) -> list[str]:
        """The faults going on now."""
        inp = self.input.active()          # the input's loss first: while it lasts it is what a viewer hears
        out = [a for a in inp if a == "input_lost"] + list(self._episodes) + [a for a in inp if a != "input_lost"]
        if self.recording.active:
            out.append("recording")
        return out

    def health(self) -> dict[str, Any]:
        """health.faults: what is going on, every kind's total, and the newest events (numbered, with counts)."""
        totals = {**self.totals, "silence": self.input.silences, "no_decode": self.input.no_decode,
                  "recording_troubles": self.recording.troubles}
        if self.words.no_decode is not None:
            totals[f"no_decode_{self.words.no_decode.arrives}"] = self.input.no_decode_input
        return {"active": self.active(), "totals": totals, "n_events": self.n_events, "events": list(self.events)}

    def summary(self, counters: Mapping[str, int], recording: Mapping[str, Any] | None = None,
                outputs: Mapping[str, int] | None = None) -> list[str]:
        """The lines said at stop: every loss and fault of the run with its count, or that there was none.
        outputs: by output (recording, bus, ros2-bag, ...), the messages it failed to take."""
        c = {k: int(v) for k, v in counters.items()}
        lines = [f"{kind.label}: {kind.what.format(n=c[kind.name])}{self._detail(kind, c, {})}"
                 for kind in self._said() if c.get(kind.name, 0)]
        inp = self.input
        if inp.silences:
            lines.append(f"silence: the unit was silent {inp.silences} time(s) for {self.silence_s:g} s or more")
        if inp.no_decode and self.words.no_decode is not None:
            nd = self.words.no_decode
            lines.append(f"{nd.label}: " + nd.total.format(k=inp.no_decode, n=inp.no_decode_input))
        if c.get("read_errors", 0):
            lines.append(f"port failures: the input went down {c['read_errors']:,} time(s), {c.get('reconnects', 0):,} "
                         f"reconnect(s)")
        if c.get("processing_errors", 0):
            lines.append(f"processing failed: {c['processing_errors']:,} block(s)")
        if recording is not None and (recording.get("dropped") or recording.get("errors")):
            lines.append(f"recording: {int(recording.get('dropped', 0)):,} message(s) dropped, "
                         f"{int(recording.get('errors', 0)):,} write error(s) in {self.recording.troubles} stretch(es) "
                         f"of trouble")
        failed = {k: int(v) for k, v in (outputs or {}).items() if v}
        if failed:
            lines.append("outputs failed: " + ", ".join(f"{k} {v:,} message(s)" for k, v in failed.items())
                         + " not taken (each said as it began)")
        head = "summary at stop: " + "; ".join(k.what.format(n=c.get(k.name, 0)) for k in self.words.counted
                                               if k.decoded) if self.words.decoded else "summary at stop"
        if not lines:
            return [head + "; no loss and no fault seen"]
        return [head + f"; {len(lines)} kind(s) of loss or fault:"] + [f"summary: {x}" for x in lines]


def no_samples_words(active: Sequence[str]) -> str:
    """What the input does while no sample comes, from the faults going on (FaultWatch.active): the status line and
    `watch` said "the input is silent" while 10 kB/s of another probe count's frames arrived (a field trial)."""
    if "input_lost" in active:
        return "the input is lost (reconnecting)"
    if "no_decode" in active:
        return "the input arrives but decodes into no frame of the unit's"
    return "the input is silent"
