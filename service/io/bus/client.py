"""The client side of the bus: dashboards, recorders and tests subscribe to a unit's streams, query its
state and send it commands.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator

import zenoh

from fluxcal.drivers.errors import ConfigError, DataError

from .keys import _KEY_CHUNK, COMMANDS, STREAMS, Keys, _decode_json
from .settings import BusError, SessionHolder, ZenohConfig


@dataclass(frozen=True)
class Message:
    """One decoded message: `value` is a SampleBlock (raw), CorrectedBlock (corrected, corrected/<probe>),
    Series (diff, tensor) or dict (calibration, health, error)."""

    stream: str
    key: str
    value: Any
    received_s: float = field(default=0.0)     # time.monotonic() when the reader thread took it


_STOP = object()


class BusClient(SessionHolder):
    """Subscribes to a unit's streams and decodes them on its own threads; queries state; sends commands.

    `lossless=True` (tests, recorders): a full receive queue holds zenoh back, which holds the publisher
    back (BLOCK streams): nothing is lost, but a consumer that stops reading stalls the service.
    `lossless=False` (dashboards): the oldest undelivered messages are dropped on this side instead and
    the service never waits for us. `recv()` returns the messages in arrival order across streams.
    """

    def __init__(self, zenoh_cfg: "ZenohConfig | zenoh.Config | zenoh.Session", unit: str, *,
                 streams: Iterable[str] | None = None, lossless: bool = True, capacity: int = 4096) -> None:
        self.keys = Keys(unit)
        self.unit = unit
        self.lossless = lossless
        names = list(STREAMS) if streams is None else list(streams)
        for s in names:
            base = s.split("/", 1)[0]
            if base not in STREAMS or (s != base and (base != "corrected" or not _KEY_CHUNK.match(s[10:]))):
                raise ConfigError(f"stream {s!r} is not allowed (allowed: {', '.join(STREAMS)}, corrected/<probe>)")
        self.stats: dict[str, int] = {"decode_errors": 0, "dropped": 0, "missed_raw_samples": 0, "raw_gaps": 0,
                                      **{f"received_{s}": 0 for s in names}}
        self._next_raw_seq: int | None = None
        self.last_decode_error = ""
        self._queue: queue.Queue[Message] = queue.Queue(maxsize=capacity)
        self._closed = threading.Event()
        self._subs: list[Any] = []
        self._threads: list[threading.Thread] = []
        self._hold(zenoh_cfg)
        try:
            for s in names:
                handler = zenoh.handlers.FifoChannel(capacity) if lossless else zenoh.handlers.RingChannel(capacity)
                sub = self.session.declare_subscriber(self.keys.stream(s), handler)
                self._subs.append(sub)
                # read the handler, not the subscriber: undeclare() needs the subscriber unborrowed
                t = threading.Thread(target=self._reader, args=(s, sub.handler), daemon=True,
                                     name=f"fluxcal-bus-{s}")
                t.start()
                self._threads.append(t)
        except BaseException:
            self.close()
            raise

    def _reader(self, stream: str, handler: Any) -> None:
        decode = STREAMS[stream.split("/", 1)[0]].decode
        stat = f"received_{stream}"
        while not self._closed.is_set():
            try:
                sample = handler.recv()
            except zenoh.ZError:            # channel closed: the subscriber was undeclared
                return
            try:
                value = decode(sample.payload.to_bytes())
            except (DataError, ValueError) as e:
                self.stats["decode_errors"] += 1
                self.last_decode_error = f"{sample.key_expr}: {e}"
                continue
            self.stats[stat] += 1
            if stream == "raw" and getattr(value, "n_samples", 0):
                self._count_raw_gap(value)
            msg = Message(stream, str(sample.key_expr), value, time.monotonic())
            while not self._closed.is_set():
                try:
                    if self.lossless:
                        self._queue.put(msg, timeout=0.1)     # wait: zenoh holds the publisher back meanwhile
                    else:
                        self._queue.put_nowait(msg)
                    break
                except queue.Full:
                    if not self.lossless:
                        try:                   # drop the oldest: a dashboard wants the newest
                            self._queue.get_nowait()
                            self.stats["dropped"] += 1
                        except queue.Empty:
                            pass

    def _count_raw_gap(self, block: Any) -> None:
        """Samples between the last raw block received and this one: what this subscriber missed (a link closed
        because it took nothing for the service's zenoh.stall_close_ms, or samples the unit itself lost: the
        service's health `missed` tells those apart). A seq that goes back (a restarted service) starts afresh."""
        first, last = int(block.seq[0]), int(block.seq[-1])
        if self._next_raw_seq is not None and first > self._next_raw_seq:
            self.stats["missed_raw_samples"] += first - self._next_raw_seq
            self.stats["raw_gaps"] += 1
        self._next_raw_seq = last + 1

    def recv(self, timeout: float | None = None) -> Message | None:
        """The next message, or None after `timeout` seconds (None: wait until one comes or close)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._closed.is_set():
            wait = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
            if wait <= 0:
                return None
            try:
                return self._queue.get(timeout=wait)
            except queue.Empty:
                continue
        return None

    def drain(self) -> list[Message]:
        """Every message waiting now, without blocking."""
        out = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out

    def __iter__(self) -> Iterator[Message]:
        while True:
            m = self.recv()
            if m is None:
                return
            yield m

    def _query(self, key: str, payload: str | None, timeout: float, parameters: str = "") -> Any:
        # every service's answer, not one per key: two services under one name both answer on one key
        kwargs: dict[str, Any] = {"timeout": float(timeout), "consolidation": zenoh.ConsolidationMode.NONE}
        if payload:
            kwargs["payload"] = payload.encode()
        replies = list(self.session.get(f"{key}?{parameters}" if parameters else key, **kwargs))
        oks = [r for r in replies if r.ok is not None]
        if oks:
            return self._answer(oks)
        for r in replies:
            err = r.err
            if err is not None:
                text = err.payload.to_bytes().decode("utf-8", "replace")
                if text == "Timeout":          # zenoh's own error reply when the query's timeout passes
                    break
                try:
                    text = json.loads(text).get("error", text)
                except (ValueError, AttributeError):
                    pass
                raise BusError(f"{key}: refused: {text}")
        raise BusError(f"no answer from {key} within {timeout:g} s: is `fluxcal run` running for unit "
                       f"{self.unit!r} and reachable from here? (on a bus with access control, a certificate "
                       f"whose name is not granted this key gets no answer either: docs/security.md)")

    def _answer(self, oks: list) -> Any:
        """The first answer; when several services answered (two under one unit name: each took the query), said in
        it: `answered_by`, each one's `answers`, and a `warning` a person reads."""
        answer = _decode_json(oks[0].ok.payload.to_bytes())
        repliers = {str(r.replier_id) if r.replier_id is not None else f"#{i}" for i, r in enumerate(oks)}
        if len(repliers) > 1 and isinstance(answer, dict):
            answer = {**answer, "answered_by": len(repliers),
                      "answers": [_decode_json(r.ok.payload.to_bytes()) for r in oks],
                      "warning": f"{len(repliers)} services answered for unit {self.unit!r} (zenoh ids "
                                 f"{', '.join(sorted(repliers))}): each of them took this query; two services run "
                                 f"under one unit name: stop one, or give it its own unit.name"}
        return answer

    def query_state(self, timeout: float = 2.0) -> dict[str, Any]:
        """The service's current calibration and health (JSON object)."""
        return self._query(self.keys.state, None, timeout)

    def command(self, name: str, payload: str = "", timeout: float = 5.0) -> dict[str, Any]:
        """Send a command and wait for the service's answer {"id", "command", "ok", ...}.

        {"ok": false, "error": ...} means it was not applied: the service refused it, or was too busy to take
        it within `timeout` less a margin (the bus then withdraws it, so retrying never applies it twice).
        Raises BusError when the bus refuses it outright (busy, malformed) or nothing answers in time."""
        if name not in COMMANDS:
            raise ConfigError(f"command {name!r} is not allowed (allowed: {', '.join(COMMANDS)})")
        # the bus must give up before we do, or its "not applied" would arrive after we stopped listening
        wait_s = max(0.0, timeout - max(0.1, min(0.5, 0.2 * timeout)))
        return self._query(self.keys.cmd(name), payload, timeout, parameters=f"wait_s={wait_s:.3f}")

    def alive(self, timeout: float = 1.0) -> bool:
        """Whether the unit's liveliness token is present."""
        return any(r.ok is not None for r in self.session.liveliness().get(self.keys.alive, timeout=timeout))

    def close(self) -> None:
        """Undeclare the subscribers (their reader threads end), close the session if we opened it. Idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        for t in self._threads:
            t.join(timeout=2.0)
        self._subs.clear()
        self._release()



def discover_units(session: zenoh.Session, timeout: float = 1.0) -> list[str]:
    """Names of the units whose liveliness token `fluxcal/<unit>/alive` is visible from `session`."""
    units = set()
    for r in session.liveliness().get("fluxcal/*/alive", timeout=timeout):
        if r.ok is not None:
            parts = str(r.ok.key_expr).split("/")
            if len(parts) == 3:
                units.add(parts[1])
    return sorted(units)
