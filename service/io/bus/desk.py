"""Commands and state queries of the service's side of the bus: zenoh's callbacks only queue them, the
service's thread answers them between blocks, and a small thread of the bus answers what waits too long."""

from __future__ import annotations

import itertools
import re
import threading
import time
from collections import deque
from typing import Any, Callable, Mapping, Sequence

import zenoh

from .keys import COMMANDS, JSON, MAX_COMMAND_PAYLOAD_BYTES, Command, Keys, _json_bytes
from .settings import BusError

#: how long a command waits for the service's thread before it is withdrawn (the client may ask for less)
COMMAND_WAIT_S = 5.0
#: a state query not answered by the service's thread within this long is answered from the last state
STATE_GRACE_S = 0.25
#: the state is recomputed at most this often when no query asks for it
STATE_REFRESH_S = 1.0


class Desk:
    """The queues between zenoh's callback threads and the service's thread (see server.ServiceBus).

    `state_fn()` returns the JSON-ready state; `published_state()` what the bus last published, for when
    there is no state_fn or the service's thread is busy. Counters go into the bus's `stats`."""

    def __init__(self, keys: Keys, stats: dict[str, int], *, state_fn: Callable[[], Mapping[str, Any]] | None,
                 published_state: Callable[[], dict[str, Any]], probe_names: Sequence[str] | None,
                 command_queue_size: int, command_wait_s: float, state_grace_s: float,
                 identity: Mapping[str, Any] | None = None) -> None:
        self.keys, self.unit, self.stats = keys, keys.unit, stats
        self.identity = dict(identity or {})       # who this service is (claim.service_identity): in every state
        self.state_fn, self.probe_names, self._published_state = state_fn, probe_names, published_state
        self.command_wait_s, self.state_grace_s = float(command_wait_s), float(state_grace_s)
        # commands and state queries wait here for the service's thread; one lock, one condition
        self._cond = threading.Condition()
        self._commands: deque[Command] = deque()
        self._command_queue_size = int(command_queue_size)
        self._state_queries: deque[tuple[float, zenoh.Query]] = deque()
        self._state_queue_size = 16
        self._state_cache: tuple[float, dict[str, Any]] | None = None
        self._ids = itertools.count(1)
        self._closed = False
        self.last_refused = ""          # the last refusal, short, for the service's log (stats counts them)
        self._stop = threading.Event()
        self._watchdog = threading.Thread(target=self._watch_late, daemon=True, name=f"fluxcal-bus-{self.unit}-late")
        self._watchdog.start()

    # --- zenoh callbacks: never block, never call zenoh except to refuse a query ------------------

    def on_state_query(self, query: zenoh.Query) -> None:
        with self._cond:
            if len(self._state_queries) < self._state_queue_size and not self._closed:
                self._state_queries.append((time.monotonic(), query))
                self._cond.notify_all()
                return
        query.reply_err(_json_bytes({"error": "busy: too many state queries pending"}), encoding=JSON)

    def command_callback(self, name: str) -> Callable[[zenoh.Query], None]:
        key = self.keys.cmd(name)

        def on_query(query: zenoh.Query) -> None:
            self.stats["commands_received"] += 1
            if self._closed:
                return self._refuse(query, name, "the service is stopping")
            if str(query.key_expr) != key:      # a wildcard that reaches every key (a browser's get of fluxcal/**)
                return self._refuse(query, name, _not_its_own(str(query.key_expr), key))
            raw = query.payload.to_bytes() if query.payload is not None else b""
            if len(raw) > MAX_COMMAND_PAYLOAD_BYTES:
                return self._refuse(query, name, f"payload of {len(raw):,} bytes is too large (at most "
                                                 f"{MAX_COMMAND_PAYLOAD_BYTES:,}; {name} takes {COMMANDS[name]})")
            try:
                payload = raw.decode("utf-8").strip()
            except UnicodeDecodeError:
                return self._refuse(query, name, f"payload of {len(raw):,} bytes is not UTF-8 text")
            if COMMANDS[name] is not None and not payload:
                return self._refuse(query, name, f"needs a payload: {COMMANDS[name]}")
            if name == "add-effect" and not re.fullmatch(r"[a-z][a-z0-9_\-]{0,63}", payload):
                shown = repr(payload) if len(payload) <= 64 else f"{payload[:40]!r}... ({len(payload):,} characters)"
                return self._refuse(query, name, f"{shown} is not an effect name")
            wait_s = self.command_wait_s
            asked = query.parameters.get("wait_s")       # the client's own patience, less a margin
            if asked is not None:
                try:
                    wait_s = min(wait_s, max(0.0, float(asked)))
                except ValueError:
                    return self._refuse(query, name, f"wait_s={asked!r} is not a number of seconds")
            cmd = Command(next(self._ids), name, payload, key, query, expires_at=time.monotonic() + wait_s)
            with self._cond:
                if len(self._commands) < self._command_queue_size:
                    self._commands.append(cmd)
                    self._cond.notify_all()
                    return
            self._refuse(query, name, f"busy: {self._command_queue_size} commands pending; try again")

        return on_query

    def _refuse(self, query: zenoh.Query, name: str, why: str) -> None:
        self.stats["commands_refused"] += 1
        self.last_refused = f"{name}: {why}"
        query.reply_err(_json_bytes({"command": name, "ok": False, "error": why}), encoding=JSON)

    # --- the bus's own thread: late answers (never a zenoh callback) ----------------------------

    def _watch_late(self) -> None:
        """Answer what waited too long; asleep until the first of it is due (a query or command queued wakes it)."""
        while True:
            with self._cond:
                if self._stop.is_set():
                    return
                now = time.monotonic()
                late_q, expired, wait = _take_late(self._state_queries, self._commands, self.state_grace_s, now)
                if not (late_q or expired):
                    self._cond.wait(wait)
                    continue
            for q in late_q:
                self.stats["state_queries_stale"] += 1
                self.reply_state(q, self._stale_state(now))
            for c in expired:
                self.stats["commands_expired"] += 1
                c.reply({"ok": False, "error": "not applied: the service was busy (reconnecting its input or "
                                               "processing a block) and did not take the command in time; try again"})

    def _stale_state(self, now: float) -> dict[str, Any]:
        cache = self._state_cache
        if cache is None:
            st = self._published_state()
            age = None
        else:
            st, age = dict(cache[1]), now - cache[0]
        return self._stamped(st, stale=True, age=age)

    # --- the service's thread ------------------------------------------------------------------

    def pending_commands(self) -> list[Command]:
        """Commands received since the last call, oldest first; answers pending `state` queries on the way.

        Call it from the service's loop between blocks; answer each command with `cmd.reply({...})`."""
        cache = self._state_cache          # the usual turn: nothing came, the state is fresh (no lock taken)
        if not (self._commands or self._state_queries) and cache and time.monotonic() - cache[0] < STATE_REFRESH_S:
            return []
        self.answer_state_queries()
        with self._cond:
            out = list(self._commands)
            self._commands.clear()
        return out

    def next_command(self, timeout: float | None = None) -> Command | None:
        """Wait up to `timeout` s for one command (for a service thread that only serves commands)."""
        self.answer_state_queries()
        with self._cond:
            self._cond.wait_for(lambda: self._commands or self._closed, timeout)
            return self._commands.popleft() if self._commands else None

    def state(self) -> dict[str, Any]:
        """What a `state` query answers: state_fn() (or the last calibration and health published) + identity."""
        st = dict(self.state_fn()) if self.state_fn is not None else self._published_state()
        if self.probe_names is not None:
            st.setdefault("probe_names", self.probe_names)
        return self._stamped(st, stale=False, age=0.0)

    def _stamped(self, st: dict[str, Any], *, stale: bool, age: float | None) -> dict[str, Any]:
        """A state with who answers it (the unit, this service: claim.service_identity), the bus's counters, when
        and whether it is the last one computed (stale) and how old."""
        st.setdefault("unit", self.unit)
        if self.identity:
            st["service"] = self.identity
        st.update(bus=dict(self.stats), time_unix_s=time.time(), stale=stale, state_age_s=age)
        return st

    def reply_state(self, q: zenoh.Query, st: dict[str, Any] | Exception) -> None:
        try:
            if isinstance(st, Exception):   # a broken state callback must not stop the service
                q.reply_err(_json_bytes({"error": f"state unavailable: {type(st).__name__}: {st}"}), encoding=JSON)
            else:
                q.reply(self.keys.state, _json_bytes(st), encoding=JSON)
        except zenoh.ZError:
            pass                          # the client's timeout passed
        finally:
            try:
                q.drop()
            except zenoh.ZError:
                pass

    def answer_state_queries(self) -> None:
        now = time.monotonic()
        with self._cond:
            queries = [q for _, q in self._state_queries]
            self._state_queries.clear()
        cache = self._state_cache
        if not queries and cache is not None and now - cache[0] < STATE_REFRESH_S:
            return
        self.stats["state_queries"] += len(queries)
        try:
            st: dict[str, Any] | Exception = self.state()
            self._state_cache = (now, st)
        except Exception as e:  # noqa: BLE001 - reported to the client, never raised into the service loop
            st = e
        for q in queries:
            self.reply_state(q, st)

    def refuse_new(self) -> None:
        """From now on commands and state queries are refused: the service is stopping."""
        with self._cond:
            self._closed = True

    def close(self, why: str) -> None:
        """Refuse what still waits (a waiting next_command() returns None) and end the bus's thread."""
        with self._cond:
            self._closed = True
            commands, self._commands = list(self._commands), deque()
            states, self._state_queries = [q for _, q in self._state_queries], deque()
            self._stop.set()
            self._cond.notify_all()
        if self._watchdog is not threading.current_thread():
            self._watchdog.join(2.0)
        for cmd in commands:
            cmd.reply({"ok": False, "error": "the service is stopping; the command was not applied"})
        for q in states:                             # not state_fn(): the source may be closed already
            self.reply_state(q, BusError(why))


def _take_late(queries: deque, commands: deque, grace_s: float, now: float) -> tuple[list, list, float]:
    """The state queries older than grace_s and the commands past their wait, taken from their queues (oldest
    first), and how long until the next of those left is due (at most 1 s)."""
    late_q = [q for t, q in queries if now - t >= grace_s]
    for _ in late_q:
        queries.popleft()                             # oldest first: the late ones are at the front
    expired = [c for c in commands if now >= c.expires_at]
    for c in expired:
        commands.remove(c)
    due = [t + grace_s for t, _ in queries] + [c.expires_at for c in commands]
    return late_q, expired, min(max(min(due, default=now + 1.0) - now, 0.001), 1.0)


def _not_its_own(asked: str, key: str) -> str:
    """Why a command asked by a wider key expression than its own is refused (nothing is done)."""
    return (f"a command runs only when asked by its own key ({key}); {asked[:120]!r} reaches more than one: nothing "
            f"was done")
