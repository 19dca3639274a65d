"""What `fluxcal run` says about losses and faults, decided from the source's counters and the recorder's status
at the service's health tick (about once a second): a console line when a fault begins, its running count while
it lasts (at most every `every_s`), a line when it ends, and a summary at stop. The same lines go to the health
channel as events with their counts (`health.faults`), where the dashboard shows them.

    crc           frames failing their CRC, with the share of frames that fail (bit errors on the line)
    bad_frames, wrong_length, remote_frames, error_frames: what a CAN adapter or bus gave that is no frame of the
                  unit's (CAN has no CRC failures: its controller drops those)
    no_decode     bytes arrive but no frame decodes for 2 s (a wrong baud rate, a wrong probe count)
    silence       nothing from the unit for `silence_s` (unit.silence_s), and when data come again
    gaps          samples missed in gaps of the unit's counter
    can_incomplete, duplicates, backsteps, saturated, temp_invalid, implausible: as counted by the driver
    restarts      the unit restarted (counter and clock back near zero): said each time
    clock_jumps, counter_jumps: the unit's clock (or counter) jumped while the other ran on: said each time
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
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

#: bytes without a frame for this long are said (a stretch shorter than that is a partial frame, a glitch)
NO_DECODE_S = 2.0
#: a fault that was counted is over when its counter stayed still this long
QUIET_S = 3.0
#: events the health channel carries (the newest): a dashboard that missed a message still gets them
HEALTH_EVENTS = 10


@dataclass(frozen=True)
class CountedKind:
    """A fault followed by one counter: the name in health.faults, the counter, how it is said."""

    name: str
    counter: str
    label: str                    # what the line starts with: "CRC failures"
    what: str                     # what {n} counts: "{n} frame(s) failed their CRC"
    advice: str = ""
    one_shot: bool = False        # said each time it counts (a restart), never "begins" or "ends"
    quiet: bool = False           # said where it happens (a refused command): here only counted and summarised


KINDS = (
    CountedKind("crc", "crc_failures", "CRC failures", "{n:,} frame(s) failed their CRC",
                "bit errors on the line: check the cable, its screen and its length for the baud rate"),
    CountedKind("bad_frames", "bad_frames", "bad CAN frames",
                "{n:,} line(s) or frame(s) from the CAN adapter that are no frame, dropped",
                "garbled on the adapter's serial link or by its firmware: check the USB cable and the adapter"),
    CountedKind("wrong_length", "wrong_length", "CAN frames of a wrong length",
                "{n:,} frame(s) with the unit's ids that are no 8-byte data frame, dropped",
                "another node sends on the unit's ids, or the unit speaks another ICD version: check source.base_id"),
    CountedKind("remote_frames", "remote_frames", "CAN remote frames",
                "{n:,} remote frame(s) with the unit's ids, ignored",
                "another node on the bus asks for the unit's ids"),
    CountedKind("error_frames", "error_frames", "CAN error frames", "{n:,} error frame(s) reported by the interface",
                "faults on the bus itself: check its termination, wiring and bitrate"),
    CountedKind("gaps", "samples_missed", "samples missed", "{n:,} sample(s) missed in gaps of the unit's counter"),
    CountedKind("can_incomplete", "can_incomplete", "CAN samples incomplete",
                "{n:,} CAN sample(s) dropped, a frame of each never came"),
    CountedKind("duplicates", "duplicates", "duplicate frames",
                "{n:,} frame(s) repeating one received before bit for bit, dropped",
                "sent again by the unit or a link that replays its buffer"),
    CountedKind("backsteps", "seq_backsteps", "frames stepping back",
                "{n:,} frame(s) whose counter or clock stepped back, no copy of one received, dropped",
                "a stale frame, or a unit counter that jumped back"),
    CountedKind("clock_jumps", "clock_jumps", "unit clock jump",
                "{n:,} jump(s) of the unit's clock while its counter ran on",
                "time repaired from the counter at the unit's period: no sample lost or made up", one_shot=True),
    CountedKind("counter_jumps", "counter_jumps", "unit counter jump",
                "{n:,} jump(s) of the unit's counter while its clock ran on",
                "followed by the clock: no sample counted missed that the clock says never existed", one_shot=True),
    CountedKind("restarts", "restarts", "unit restart",
                "{n:,} restart(s) of the unit: its counter and clock went back near zero",
                "followed: seq and time go on from the last sample's, no sample counted missed", one_shot=True),
    CountedKind("implausible", "implausible_samples", "implausible values",
                "{n:,} sample(s) with a good CRC but values no probe gives, kept out of the estimator"),
    CountedKind("saturated", "saturated_axes", "saturation", "{n:,} saturated axis reading(s), NaN"),
    CountedKind("temp_invalid", "temp_invalid", "temperature invalid", "{n:,} sample(s) flagged temperature-invalid"),
    CountedKind("persist", "persist_failures", "calibration not persisted",
                "{n:,} save(s) of the calibration in use failed",
                "it is in use, but a restart would not reload it: check the folder of calibration.file"),
    CountedKind("calibrations_refused", "calibrations_refused", "calibrations refused",
                "{n:,} calibration(s) refused (by apply, or the persisted one at start), each said as it came",
                quiet=True),
    CountedKind("commands_refused", "commands_refused", "commands refused",
                "{n:,} command(s) refused, each said as it came", quiet=True),
    CountedKind("duplicate_holders", "duplicate_holders", "another service under this unit's name",
                "{n:,} other service(s) announced this unit's name on the network", quiet=True),
    CountedKind("stalls", "send_stalls", "a subscriber took nothing",
                "the streams waited {n:,} time(s) for a subscriber that took nothing (health: bus.send_stalls)",
                "a subscriber that takes nothing for zenoh.stall_close_ms is disconnected so that it holds back no "
                "other one; it reconnects and counts what it missed by seq (docs/zenoh.md)"),
)

#: counters whose growth means something arrived from the unit's port or bus, whatever it was
ACTIVITY = ("crc_failures", "bad_frames", "wrong_length", "remote_frames", "error_frames", "foreign_frames")

#: the counters behind `implausible`, said as its reasons
IMPLAUSIBLE_REASONS = (("reserved_flags", "reserved flag bits"), ("beyond_full_scale", "axes beyond full scale"),
                       ("zero_vectors", "zero vectors"), ("temp_out_of_range", "temperatures out of range"))


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


class FaultWatch:
    """Decides what to say about losses and faults from counters, at each `tick`; keeps the health field."""

    def __init__(self, say: Callable[[str], None], *, silence_s: float = 5.0, every_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time) -> None:
        self.say, self.silence_s, self.every_s = say, float(silence_s), float(every_s)
        self.clock, self.wall = clock, wall
        self._prev: dict[str, int] = {}
        self._prev_t: float | None = clock()  # the first tick compares with the start: nothing counted yet
        self._episodes: dict[str, _Episode] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=HEALTH_EVENTS)
        self.n_events = 0
        self.totals: dict[str, int] = {}
        self._last_activity: float | None = None   # silence counts from the first tick: a unit that never sends is said
        self._silent_since: float | None = None
        self.silences = 0
        self._nd_since: float | None = None   # bytes without a frame since then (not said yet, or said)
        self._nd_bytes = 0
        self._nd_said = False
        self.no_decode = 0                    # stretches said
        self.no_decode_bytes = 0              # bytes in them
        self.recording = RecordingWatch(self._event, self.every_s)

    # --- saying ---------------------------------------------------------------------------------------

    def _event(self, kind: str, phase: str, count: int, text: str) -> None:
        self.say(text)
        self.n_events += 1
        self.events.append({"n": self.n_events, "kind": kind, "phase": phase, "count": int(count), "text": text,
                            "time_unix_s": self.wall()})

    # --- the tick ----------------------------------------------------------------------------------------

    def tick(self, counters: Mapping[str, int], recording: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Compare with the last tick, say what began, goes on or ended; returns the health field."""
        now = self.clock()
        dt = now - self._prev_t if self._prev_t is not None else None
        prev = self._prev or {}
        delta = {k: int(v) - int(prev.get(k, 0)) for k, v in counters.items()}
        self._input(counters, delta, now)
        for kind in KINDS:
            if kind.counter in counters:
                self._counted(kind, counters, delta, now, dt)
        if recording is not None:
            self.recording.tick(recording, now)
            self.totals["recording_dropped"] = self.recording.dropped
        self._prev, self._prev_t = {k: int(v) for k, v in counters.items()}, now
        return self.health()

    def _input(self, c: Mapping[str, int], d: Mapping[str, int], now: float) -> None:
        """Silence (nothing at all arrives) and bytes that decode into no frame."""
        got_bytes, frames = d.get("bytes_received", 0), d.get("frames_accepted", 0)
        if self._last_activity is None:
            self._last_activity = now
        if got_bytes > 0 or frames > 0 or any(d.get(k, 0) > 0 for k in ACTIVITY):
            if self._silent_since is not None:
                self._event("silence", "end", self.silences,
                            f"silence ended: data from the unit again after about {_ago(now - self._silent_since)}")
                self._silent_since = None
            self._last_activity = now
        elif self._silent_since is None and now - self._last_activity >= self.silence_s:
            self._silent_since = self._last_activity
            self.silences += 1
            self._event("silence", "begin", self.silences,
                        f"silence: no data from the unit for {_ago(now - self._last_activity)} (unit.silence_s = "
                        f"{self.silence_s:g}): is it powered, connected and sending? ({self.silences} silence(s) "
                        f"so far; health: faults.active)")
        if got_bytes > 0 and frames == 0:
            if self._nd_since is None:
                self._nd_since, self._nd_bytes = (self._prev_t if self._prev_t is not None else now), 0
            self._nd_bytes += got_bytes
            if not self._nd_said and now - self._nd_since >= NO_DECODE_S:
                self._nd_said = True
                self.no_decode += 1
                self.no_decode_bytes += self._nd_bytes
                self._event("no_decode", "begin", self._nd_bytes,
                            f"no frame decodes: bytes arrive but no frame decodes (baud rate? probe count?): "
                            f"{self._nd_bytes:,} bytes in {_ago(now - self._nd_since)}, 0 frames; check "
                            f"source.baudrate and unit.n_probes against the unit (health: counters.bytes_skipped)")
            elif self._nd_said:
                self.no_decode_bytes += got_bytes
        elif frames > 0 and self._nd_since is not None:
            if self._nd_said:
                self._event("no_decode", "end", self._nd_bytes,
                            f"no frame decodes ended: frames decode again after {_ago(now - self._nd_since)}; "
                            f"{self._nd_bytes:,} bytes in between decoded into no frame")
            self._nd_since, self._nd_said = None, False

    def _counted(self, kind: CountedKind, c: Mapping[str, int], d: Mapping[str, int], now: float,
                 dt: float | None) -> None:
        value, grew = int(c[kind.counter]), d.get(kind.counter, 0)
        self.totals[kind.name] = value
        ep = self._episodes.get(kind.name)
        if kind.quiet:
            return
        if grew > 0 and kind.one_shot:
            self._event(kind.name, "event", value, f"{kind.label}: {kind.what.format(n=value)} ({kind.advice}; "
                                                   f"health: counters.{kind.counter})")
        elif grew > 0 and ep is None:
            began = self._prev_t if self._prev_t is not None else now       # within the last interval
            self._episodes[kind.name] = _Episode(since=began, start=value - grew, last_grew=now, said_at=now,
                                                 said_value=value, said_counters=dict(c))
            window = f" in the last {_ago(dt)}" if dt else ""
            self._event(kind.name, "begin", value,
                        f"{kind.label}: {kind.what.format(n=grew)}{window}{self._detail(kind, c, self._prev)}; "
                        f"{value:,} so far" + (f" ({kind.advice})" if kind.advice else "")
                        + f" (health: counters.{kind.counter})")
        elif grew > 0:
            ep.last_grew = now
            if now - ep.said_at >= self.every_s:
                self._event(kind.name, "ongoing", value,
                            f"{kind.label} go on: {kind.what.format(n=value - ep.said_value)} in the last "
                            f"{_ago(now - ep.said_at)}{self._detail(kind, c, ep.said_counters or {})}; "
                            f"{value - ep.start:,} since they began {_ago(now - ep.since)} ago, {value:,} so far")
                ep.said_at, ep.said_value, ep.said_counters = now, value, dict(c)
        elif ep is not None and now - ep.last_grew >= QUIET_S:
            del self._episodes[kind.name]
            self._event(kind.name, "end", value,
                        f"{kind.label} stopped: {kind.what.format(n=value - ep.start)} over "
                        f"{_ago(ep.last_grew - ep.since)}, none for {_ago(now - ep.last_grew)}; {value:,} so far")

    @staticmethod
    def _detail(kind: CountedKind, c: Mapping[str, int], ref: Mapping[str, int]) -> str:
        """The figures a kind's line carries besides its count, over the stretch since the counters `ref`."""
        def grew(key: str) -> int:
            return int(c.get(key, 0)) - int(ref.get(key, 0))

        if kind.name == "crc":
            bad, good = grew("crc_failures"), grew("frames_accepted")
            share = bad / max(bad + good, 1)
            return f" ({share:.1%} of the frames)" if share < 0.1 else f" ({share:.0%} of the frames)"
        if kind.name == "gaps":
            return f" ({grew('seq_gaps'):,} gap(s))"
        if kind.name == "implausible":
            parts = [f"{label} {grew(key):,}" for key, label in IMPLAUSIBLE_REASONS if grew(key)]
            return f" ({', '.join(parts)})" if parts else ""
        return ""

    # --- what the health channel and the summary carry ------------------------------------------------------

    @property
    def started(self) -> bool:
        """Whether a tick has come: the service's loop ran."""
        return self._last_activity is not None

    def active(self) -> list[str]:
        """The faults going on now."""
        out = list(self._episodes)
        if self._silent_since is not None:
            out.append("silence")
        if self._nd_said:
            out.append("no_decode")
        if self.recording.active:
            out.append("recording")
        return out

    def health(self) -> dict[str, Any]:
        """health.faults: what is going on, every kind's total, and the newest events (numbered, with counts)."""
        totals = {**self.totals, "silence": self.silences, "no_decode": self.no_decode,
                  "no_decode_bytes": self.no_decode_bytes, "recording_troubles": self.recording.troubles}
        return {"active": self.active(), "totals": totals, "n_events": self.n_events, "events": list(self.events)}

    def summary(self, counters: Mapping[str, int], recording: Mapping[str, Any] | None = None,
                outputs: Mapping[str, int] | None = None) -> list[str]:
        """The lines said at stop: every loss and fault of the run with its count, or that there was none.
        outputs: by output (recording, bus, ros2-bag, ...), the messages it failed to take."""
        c = {k: int(v) for k, v in counters.items()}
        lines = []
        frames = c.get("frames_accepted", 0)
        for kind in KINDS:
            n = c.get(kind.counter, 0)
            if not n:
                continue
            lines.append(f"{kind.label}: {kind.what.format(n=n)}{self._detail(kind, c, {})}")
        if self.silences:
            lines.append(f"silence: the unit was silent {self.silences} time(s) for {self.silence_s:g} s or more")
        if self.no_decode:
            lines.append(f"no frame decodes: {self.no_decode} stretch(es) of bytes that decoded into no frame "
                         f"({self.no_decode_bytes:,} bytes)")
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
        head = f"summary at stop: {frames:,} frame(s) accepted"
        if not lines:
            return [head + "; no loss and no fault seen"]
        return [head + f"; {len(lines)} kind(s) of loss or fault:"] + [f"summary: {x}" for x in lines]
