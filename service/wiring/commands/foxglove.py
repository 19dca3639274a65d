"""`fluxcal foxglove [--config F | --connect ENDPOINT] [--unit NAME ...] [--listen HOST:PORT]`: the live bridge
for the Foxglove app.

Subscribes to running units over Zenoh like `fluxcal watch` (a client session, lossy: it never holds a unit
back) and serves their products on a Foxglove WebSocket server (foxglove-sdk), on the same topics and with the
same JSON schemas as the MCAP recording's Foxglove channels (fluxcal.service.io.foxglove_schemas builds both):
`/fluxcal/<unit>/vectors`, `diff`, `tensor`, `error`, `params` (10 Hz means / per calibration record), and
`calibration`, `health` as the unit publishes them. Several units at once: every unit named with --unit, or
every unit found on the bus (new ones are picked up as they appear).

It says when it cannot reach the endpoint or finds no unit and keeps retrying. Ctrl-C / SIGTERM or --seconds
stop it; exit status 0. docs/foxglove.md says how to connect the app.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from typing import Any, TextIO

import foxglove
import zenoh

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.io.bus import (
    BusClient,
    BusError,
    Message,
    ZenohConfig,
    ZenohTlsConfig,
    discover_units,
    open_session,
)
from fluxcal.service.io.encoding import encode_json
from fluxcal.service.io.foxglove_schemas import PRODUCT_STREAMS, Products, error_message, json_channels
from fluxcal.service.wiring.commands.options import CommandHelp, client_options

from .client import parse_listen, resolve_units

#: Zenoh streams the bridge subscribes to, and the Foxglove channels it serves
SUBSCRIBED = ("corrected", "error", "calibration", "health")
SERVED = (*PRODUCT_STREAMS, "calibration", "health")
RETRY_S = 1.0                 # reconnect / rediscover period
REPORT_S = 30.0               # a status line this often while it runs
_wall_ns = time.time_ns


HELP = CommandHelp("live bridge for the Foxglove app: a running unit's products on a Foxglove "
                   "WebSocket server",
                   "  fluxcal foxglove --config configs/sim-gradiometer.toml   # then in Foxglove: Open connection, "
                   "ws://127.0.0.1:8765",
                   more=" It subscribes over Zenoh like `watch` and never holds the unit back. Ctrl-C stops it.")


def add_options(p: argparse.ArgumentParser) -> None:
    client_options(p, "bridge")
    p.add_argument("--listen", default="127.0.0.1:8765", metavar="HOST:PORT",
                   help="the Foxglove WebSocket server's address (default: %(default)s; port 0: a free one)")


class UnitFeed:
    """One unit: its Zenoh subscription, its decimators and its Foxglove channels. log_time is unit time placed on
    the wall clock as in the recordings (epoch = wall clock at the first sample minus its t_s); a unit whose
    clock restarts (a new run) gets a new epoch."""

    def __init__(self, session: Any, unit: str, ctx: foxglove.Context) -> None:
        self.unit = unit
        self.client = BusClient(session, unit, streams=SUBSCRIBED, lossless=False, capacity=256)
        state = None
        try:
            state = self.client.query_state(timeout=2.0)
        except BusError:
            pass                      # not answering yet: s1, s2, ... until a calibration record names them
        names = list(state.get("probe_names") or []) if isinstance(state, dict) else []
        self.products = Products(names)
        self.channels = {
            stream: foxglove.Channel(f"/fluxcal/{unit}/{stream}", message_encoding="json", context=ctx,
                                     schema=foxglove.Schema(name=name, encoding="jsonschema",
                                                            data=json.dumps(schema).encode()))
            for stream, (name, schema) in json_channels(names).items() if stream in SERVED}
        self.sent: Counter[str] = Counter()
        self.epoch_ns: int | None = None
        self.last_t_s = float("-inf")
        self.last_log_ns: int | None = None
        if isinstance(state, dict) and state.get("usable") is not None:
            self._log("params", Products.calibration(state)[0][1])

    def _log_ns(self, t_s: Any) -> int:
        if not isinstance(t_s, (int, float)) or not math.isfinite(t_s):
            return self.last_log_ns if self.last_log_ns is not None else _wall_ns()
        if self.epoch_ns is None or t_s < self.last_t_s - 1.0:        # first data, or the unit's clock restarted
            self.epoch_ns = _wall_ns() - round(t_s * 1e9)
            self.last_t_s = t_s
        self.last_t_s = max(self.last_t_s, t_s)
        self.last_log_ns = self.epoch_ns + round(t_s * 1e9)
        return self.last_log_ns

    def _log(self, stream: str, message: dict[str, Any]) -> None:
        self.channels[stream].log(encode_json(message), log_time=self._log_ns(message.get("t_s")))
        self.sent[stream] += 1

    def _restarted(self, t_s: Any) -> None:
        if isinstance(t_s, (int, float)) and t_s < self.last_t_s - 1.0:
            self.products = Products(self.products.probe_names)     # a new run: no interval spans the two

    def handle(self, msg: Message) -> None:
        v = msg.value
        out: list[tuple[str, dict[str, Any]]]
        if msg.stream == "corrected":
            if not v.n_samples:
                return
            self._restarted(float(v.t_s[0]))
            out = self.products.corrected(v)
        elif msg.stream == "error":
            rms = v.get("rms_nT") or {}
            t_s, n = v.get("t_s"), v.get("n")
            if isinstance(t_s, (int, float)):
                self._restarted(t_s)
                out = self.products.error(rms, t_s=float(t_s), seq=v.get("seq"), n=int(n) if n else 1)
            else:                    # a service that does not say when: forward the block's figures as they are
                out = [("error", error_message({"t_s": None, "seq": v.get("seq"), "n": n or 0, "rms_nT": rms}))]
        elif msg.stream == "calibration":
            self._log("calibration", v)
            out = Products.calibration(v) if isinstance(v.get("state"), dict) else []
            names = (v.get("state") or {}).get("probes") or []
            if names and not self.products.probe_names:
                self.products.probe_names = [str(p.get("name")) for p in names if isinstance(p, dict)]
        else:
            out = [("health", v)]
        for stream, m in out:
            self._log(stream, m)

    def pump(self) -> int:
        """Send what has arrived; returns how many Zenoh messages were handled."""
        msgs = self.client.drain()
        for m in msgs:
            self.handle(m)
        return len(msgs)

    def dropped(self) -> int:
        """Messages the lossy subscription dropped because the bridge fell behind, and undecodable ones."""
        return self.client.stats["dropped"] + self.client.stats["decode_errors"]

    def close(self) -> None:
        for stream, m in self.products.flush():
            self._log(stream, m)
        self.client.close()
        for ch in self.channels.values():
            ch.close()


class Bridge:
    """The bridge's loop: connect (retrying), find the units, pump their messages into the WebSocket server."""

    def __init__(self, endpoints: list[str], units: list[str] | None, tls: ZenohTlsConfig, host: str, port: int,
                 err: TextIO) -> None:
        self.endpoints, self.wanted, self.tls, self.err = endpoints, units, tls, err
        self.ctx = foxglove.Context()
        try:
            self.server = foxglove.start_server(name="fluxcal", host=host, port=port, context=self.ctx)
        except Exception as e:  # noqa: BLE001 -- the SDK raises its own error types (address in use, bad host)
            raise ConfigError(f"--listen: cannot serve on {host}:{port}: {e}") from None
        shown = f"[{host}]" if ":" in host else host
        self.url = f"ws://{shown}:{self.server.port}"
        self.session: Any = None
        self.feeds: dict[str, UnitFeed] = {}
        self.said = ""

    def say(self, text: str, *, once: bool = False) -> None:
        if once and text == self.said:
            return
        self.said = text
        print(f"fluxcal foxglove: {text}", file=self.err, flush=True)

    def _connect(self) -> None:
        try:
            self.session = open_session(ZenohConfig.client(*self.endpoints, tls=self.tls))
        except BusError as e:
            self.say(f"cannot reach {', '.join(self.endpoints)}: {e} (retrying every {RETRY_S:g} s)", once=True)

    def _attach(self) -> None:
        units = self.wanted
        if units is None:
            units = discover_units(self.session, timeout=0.3)
            if not units:
                self.say(f"no fluxcal unit visible via {', '.join(self.endpoints)} yet — is `fluxcal run` running? "
                         f"(waiting)", once=True)
        for u in units:
            if u not in self.feeds:
                self.feeds[u] = UnitFeed(self.session, u, self.ctx)
                self.say(f"serving fluxcal/{u} on /fluxcal/{u}/{{{','.join(SERVED)}}}")

    def run(self, seconds: float | None) -> int:
        self.say(f"Foxglove WebSocket server on {self.url} (in Foxglove: Open connection > Foxglove WebSocket)")
        deadline = None if seconds is None else time.monotonic() + seconds
        next_try = next_report = 0.0
        try:
            while deadline is None or time.monotonic() < deadline:
                now = time.monotonic()
                if now >= next_try:
                    next_try = now + RETRY_S
                    if self.session is None:
                        self._connect()
                    if self.session is not None and (self.wanted is None or len(self.feeds) < len(self.wanted)):
                        self._attach()
                if now >= next_report and self.feeds:
                    next_report = now + REPORT_S
                    self._report("running")
                if not sum(f.pump() for f in self.feeds.values()):
                    time.sleep(0.02)
        except KeyboardInterrupt:
            pass
        finally:
            self.close()
        return 0

    def _report(self, what: str) -> None:
        sent = sum((f.sent for f in self.feeds.values()), Counter())
        self.say(f"{what}: {sum(sent.values())} messages sent ({', '.join(f'{k} {v}' for k, v in sorted(sent.items()))})"
                 f"; {sum(f.dropped() for f in self.feeds.values())} Zenoh messages dropped (the bridge fell behind) "
                 f"or undecodable")

    def close(self) -> None:
        """Flush the intervals being filled, close the subscriptions, the session and the server. Idempotent."""
        feeds, self.feeds = self.feeds, {}
        for u, f in feeds.items():
            try:
                f.close()
            except Exception as e:  # noqa: BLE001 -- closing one unit must not keep the others open
                self.say(f"closing fluxcal/{u}: {type(e).__name__}: {e}")
        if feeds:
            self.feeds = feeds
            self._report("stopped")
            self.feeds = {}
        if self.session is not None:
            try:
                self.session.close()
            except zenoh.ZError as e:
                self.say(f"closing the Zenoh session: {e}")
            self.session = None
        self.server.stop()


def main(args: argparse.Namespace) -> int:
    endpoints, units, tls = resolve_units(args)
    host, port = parse_listen(args.listen)
    return Bridge(endpoints, units, tls, host, port, sys.stderr).run(args.seconds)
