"""The service's side of the bus: what it publishes, answers and obeys (ServiceBus).

Key expressions, all under ``fluxcal/<unit>/`` (docs/zenoh.md has the full table):

    raw                binary SampleBlock      BLOCK  (never dropped)
    corrected          binary CorrectedBlock   BLOCK  all probes, diff, centre and tensor included
    corrected/<probe>  binary CorrectedBlock   BLOCK  one probe (P = 1), if ZenohConfig.per_probe
    diff               binary series           BLOCK  probe k minus probe 1, (N, P-1, 3) nT
    tensor             binary series           BLOCK  G[i, j] = dB_j/dx_i, (N, 3, 3) nT/m
    calibration        JSON                    BLOCK  every calibration event and the state after it
    health             JSON                    DROP   source counters and the bus's own counters, ~1 Hz
    error              JSON                    DROP   model-vs-measurement rms_nT per channel, per block

The data streams (HEARD_STREAMS and corrected/<probe>) are made and put only while some subscriber matches them;
what nobody hears is counted (stats "unheard_<stream>"), not encoded.
    alive              liveliness token               present while the service runs
    state              queryable (JSON)               current calibration + health
    cmd/<name>         queryables (JSON reply)        freeze, unfreeze, reset, apply, add-effect

Threads: zenoh calls our queryable callbacks on its own threads. They never block and never call
zenoh (except to refuse a query at once): they put the query in a bounded queue and return. The
service's own thread drains that queue with `ServiceBus.pending_commands()`, applies each command
between blocks and answers it with `Command.reply(...)`, which replies on the queryable's own concrete
key: the client gets the service's real answer, not just an acknowledgement. State queries are
answered on the same thread, so the state callback needs no locking. When the service's thread is
busy (a reconnect back-off of up to 5 s, a long refit), a small thread of the bus (never a zenoh
callback) answers state queries after 0.25 s from the last state computed (`"stale": true`,
`"state_age_s"`), and withdraws a command not taken within its wait (`?wait_s=` from the client,
at most 5 s), answering {"ok": false, "error": "not applied: ..."}: a command is applied if and only
if the client is told ok, so a retry never applies it twice.

Sessions opened here must be closed (`close()`, or `with`): a session left open with callbacks
hangs the interpreter at exit (/work/shared/DEPENDENCIES.md).
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Mapping, Sequence

import zenoh

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.io.encoding import corrected_payload, probe_payloads, raw_payload
from fluxcal.service.numerics.outputs import CorrectedBlock

from . import claim
from .desk import COMMAND_WAIT_S, STATE_GRACE_S, Desk
from .heard import HEARD_STREAMS, Heard, unheard_stats
from .keys import _KEY_CHUNK, COMMANDS, STREAMS, Command, Keys, StreamSpec, _json_bytes, encode_series
from .sender import Sender
from .settings import BusError, SessionHolder, ZenohConfig

#: messages waiting for the bus's sender thread, at most (bytes); beyond it the oldest are dropped, counted
SEND_BACKLOG_BYTES = 16 << 20


def _new_stats() -> dict[str, int]:
    """The bus's counters (health's "bus"), each at zero."""
    return {"commands_received": 0, "commands_refused": 0, "commands_expired": 0, "state_queries": 0,
            "state_queries_stale": 0, "publish_errors": 0, "duplicate_holders": 0,
            **{f"published_{name}": 0 for name in STREAMS}, "published_corrected_probe": 0, "send_dropped": 0,
            **unheard_stats()}


def _check_key_segments(probe_names: Sequence[str]) -> None:
    for name in probe_names:
        if not _KEY_CHUNK.match(name):
            raise ConfigError(f"probe name {name!r} cannot be a key segment (allowed: letters, digits, '_', '-', '.')")


class ServiceBus(SessionHolder):
    """Publishes one unit's streams, holds its liveliness token, answers `state` and queues commands.

    `zenoh_cfg` is a ZenohConfig or zenoh.Config (the bus opens and closes its own session) or an open
    zenoh.Session (left open by `close()`). `state_fn()` returns the JSON-ready state for `state` queries;
    it runs on the thread that calls `pending_commands()` (the service's), never on a zenoh thread, so it
    needs no locking. When that thread is busy (a reconnect back-off, a long refit), a small thread of
    the bus answers state queries after STATE_GRACE_S from the state last computed, marked
    `"stale": true` with its age, and withdraws commands not taken within their wait, answering
    {"ok": false, "error": "... not applied ..."}: a command is applied exactly when the client is told so.
    """

    def __init__(self, zenoh_cfg: "ZenohConfig | zenoh.Config | zenoh.Session", unit: str, *,
                 state_fn: Callable[[], Mapping[str, Any]] | None = None,
                 probe_names: Sequence[str] | None = None, per_probe: bool | None = None,
                 express: bool | None = None, command_queue_size: int = 32,
                 command_wait_s: float = COMMAND_WAIT_S, state_grace_s: float = STATE_GRACE_S,
                 send_backlog_bytes: int = SEND_BACKLOG_BYTES, duplicate: str = "refuse", config: str = "") -> None:
        """`duplicate`, `config`: when another live service holds `unit`, refuse or take a suffix (claim_note says
        which), and the configuration's path said to one that finds this holding it (fluxcal.service.io.bus.claim)."""
        self.keys, self.unit, self.claim_note = Keys(unit), unit, ""
        self.probe_names = list(probe_names) if probe_names is not None else None
        _check_key_segments(self.probe_names or [])
        cfg_obj = zenoh_cfg if isinstance(zenoh_cfg, ZenohConfig) else None
        self.per_probe = per_probe if per_probe is not None else (cfg_obj.per_probe if cfg_obj else True)
        express = express if express is not None else (cfg_obj.express if cfg_obj else False)
        self.stats = _new_stats()
        self._sender: Sender | None = None
        self._desk: Desk | None = None
        self._last_calibration: dict[str, Any] | None = None
        self._last_health: dict[str, Any] | None = None
        self._closed, self._close_lock = False, threading.Lock()
        self._entities: list[Any] = []
        self._probe_pubs: dict[str, zenoh.Publisher] = {}
        self._heard = Heard(self.stats)     # whether a subscriber anywhere matches each data stream
        self._watch: claim.Watch | None = None
        self._hold(zenoh_cfg, self.keys.unit)
        self._express = bool(express)
        try:
            claim.take_name(self, zenoh_cfg, duplicate)
            self.identity = claim.service_identity(self.session, config)
            self._pubs = {name: self._declare_pub(self.keys.stream(name), s) for name, s in STREAMS.items()}
            self._entities += [self._heard.watch(name, self._pubs[name]) for name in HEARD_STREAMS]
            for name in (self.probe_names or []) if self.per_probe else []:
                self._declare_probe_pub(name)
            self._desk = Desk(self.keys, self.stats, state_fn=state_fn, published_state=self._published_state,
                              probe_names=self.probe_names, command_queue_size=command_queue_size,
                              command_wait_s=command_wait_s, state_grace_s=state_grace_s, identity=self.identity)
            self._sender = Sender(self.stats, send_backlog_bytes, f"fluxcal-bus-{unit}-send")
            self._entities.append(self.session.declare_queryable(self.keys.state, self._desk.on_state_query))
            self._entities += [self.session.declare_queryable(self.keys.cmd(name), self._desk.command_callback(name))
                               for name in COMMANDS]
            self._token = self.session.liveliness().declare_token(self.keys.alive)
            self._watch = claim.Watch(self.session, self.keys)
        except BaseException:
            self.close()
            raise

    def other_holders(self) -> list[str]:
        """The zenoh ids of other live services announcing this unit's name (stats: duplicate_holders)."""
        return claim.other_holders(self._watch, self.stats)

    def _declare_pub(self, key: str, s: StreamSpec) -> zenoh.Publisher:
        pub = self.session.declare_publisher(
            key, encoding=s.encoding, priority=s.priority, express=self._express,
            congestion_control=zenoh.CongestionControl.BLOCK if s.lossless else zenoh.CongestionControl.DROP)
        self._entities.append(pub)
        return pub

    def _declare_probe_pub(self, probe: str) -> zenoh.Publisher:
        pub = self._probe_pubs[probe] = self._declare_pub(self.keys.probe(probe), STREAMS["corrected"])
        self._entities.append(self._heard.watch(f"corrected/{probe}", pub))
        return pub

    # --- the service's thread: commands and state (fluxcal.service.io.bus.desk) ---------------------------

    def pending_commands(self) -> list[Command]:
        """Commands received since the last call, oldest first; answers pending `state` queries on the way. Call it
        from the service's loop between blocks; answer each command with `cmd.reply({...})`."""
        return self._desk.pending_commands()

    def next_command(self, timeout: float | None = None) -> Command | None:
        """Wait up to `timeout` s for one command (for a service thread that only serves commands)."""
        return self._desk.next_command(timeout)

    @property
    def last_refused(self) -> str:
        """The last command the bus refused (malformed, too large, busy) and why, short; stats counts them."""
        return self._desk.last_refused if self._desk is not None else ""

    def state(self) -> dict[str, Any]:
        """What a `state` query answers: state_fn() (or the last calibration and health published) + identity."""
        return self._desk.state()

    def _published_state(self) -> dict[str, Any]:
        st = dict((self._last_calibration or {}).get("state") or {"usable": False})
        return st if self._last_health is None else {**st, "health": self._last_health.get("counters")}

    # --- publishing (the service's thread) -------------------------------------------------------

    def _put(self, *messages: tuple[str, zenoh.Publisher, bytes]) -> None:
        """(stream, publisher, payload) messages to the sender thread (bus.sender), together: never blocking."""
        if self._closed:
            raise BusError(f"publish on {self.keys.root}/{messages[0][0]} after the bus was closed")
        self._sender.put_all(messages)

    def gather_sends(self, on: bool = True) -> None:
        """With `on`, what is published waits for `send()` (once a turn): the sender wakes once for all of it."""
        if self._sender is not None:
            self._sender.gather = on

    def send(self) -> None:
        """Send what was published since the last call (with gather_sends; otherwise it is on its way already)."""
        if self._sender is not None:
            self._sender.release()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every message handed to the bus has been put (True) or `timeout` passed (False)."""
        return self._sender.flush(timeout) if self._sender is not None else True

    def publish_raw(self, block: SampleBlock) -> None:
        if block.n_samples and self._heard("raw"):
            self._put(("raw", self._pubs["raw"], raw_payload(block)))

    def publish_corrected(self, block: CorrectedBlock) -> None:
        """`corrected` (everything), and `diff`, `tensor`, `corrected/<probe>` when they exist."""
        if not block.n_samples:
            return
        heard = self._heard
        out = [("corrected", self._pubs["corrected"], corrected_payload(block))] if heard("corrected") else []
        out += [(name, self._pubs[name], encode_series(block.t_s, block.seq, series, block.cal_id))
                for name, series in (("diff", block.diff_nT), ("tensor", block.tensor_nT_m))
                if series is not None and heard(name)]
        if self.per_probe:
            names = self.probe_names or [f"s{k + 1}" for k in range(block.n_probes)]
            if len(names) != block.n_probes:
                raise DataError(f"corrected block has {block.n_probes} probes, the bus knows {len(names)}: {names}")
            pubs = [self._probe_pubs.get(name) or self._declare_probe_pub(name) for name in names]
            if any(hear := [heard(f"corrected/{name}") for name in names]):
                out += [("corrected_probe", pub, data) for pub, data, h in zip(pubs, probe_payloads(block), hear) if h]
        if out:
            self._put(*out)

    def publish_calibration(self, record: Mapping[str, Any]) -> None:
        """A calibration event (kind, seq, t_s, ..., "state": {...}) as JSON; kept for `state` queries."""
        self._last_calibration = dict(record)
        self._put(("calibration", self._pubs["calibration"],
                   _json_bytes({**record, "unit": self.unit, "time_unix_s": time.time()})))

    def publish_health(self, counters: Mapping[str, Any], faults: Mapping[str, Any] | None = None) -> None:
        """{"counters": source counters, "bus": this bus's counters, "faults": the faults said} as JSON; may be
        dropped under congestion."""
        msg = {"unit": self.unit, "time_unix_s": time.time(), "counters": dict(counters), "bus": dict(self.stats)}
        if faults is not None:
            msg["faults"] = dict(faults)
        self._last_health = msg
        self._put(("health", self._pubs["health"], _json_bytes(msg)))

    def publish_error(self, rms_nT: Mapping[str, float], *, seq: int | None = None, t_s: float | None = None,
                      n: int | None = None) -> None:
        """The model-vs-measurement error metric of a block of n samples from seq (unit time t_s),
        {"rms_nT": {channel: nT}}; may be dropped."""
        if self._heard("error"):
            self._put(("error", self._pubs["error"], _json_bytes({"unit": self.unit, "time_unix_s": time.time(), "seq": seq,
                                                                 "t_s": t_s, "n": n, "rms_nT": dict(rms_nT)})))

    def has_subscribers(self, stream: str) -> bool:
        """Whether any subscriber anywhere matches `stream` ("raw", ..., "corrected/<probe>"), e.g. to wait for
        a dashboard before a burst: for a data stream, as the bus knows it when it decides to send (_heard)."""
        if (known := self._heard.known(stream)) is not None:
            return known
        pub = self._probe_pubs.get(stream[10:]) if stream.startswith("corrected/") else self._pubs[stream]
        return pub is not None and bool(pub.matching_status.matching)

    # --- lifetime ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Answer what is pending, undeclare everything, close the session if the bus opened it. Idempotent."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        if self._desk is not None:
            self._desk.refuse_new()
        self.flush(2.0)                              # what was published goes out first, if it can
        if self._sender is not None:
            self._sender.stop()                      # a subscriber frozen past the flush: counted, not sent
        if self._desk is not None:
            self._desk.close("the service is stopping")
        if self._watch is not None:
            self._watch.close()
        for ent in [getattr(self, "_token", None), *reversed(self._entities)]:    # a listener before its publisher
            try:
                if ent is not None:
                    ent.undeclare()
            except zenoh.ZError:
                pass
        self._entities.clear()
        self._probe_pubs.clear()
        self._release()
