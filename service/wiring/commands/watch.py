"""`fluxcal watch [--config F | --connect ENDPOINT] [--unit NAME] [--seconds S]`: a terminal view.

Connects to a running `fluxcal run` as a Zenoh client (directly to its listen endpoint, or to the
router it is connected to) and shows, refreshed 4 times a second: the corrected vector and |B| of
every probe, the gradiometer differences, the tensor, the model-vs-measurement error metric, the
health counters, and the calibration state (usable?, coverage, quality). On a terminal it redraws
in place with plain ANSI codes; when stdout is not a terminal (a log, a pipe, a test) it prints one
line per second instead. It says so when nothing arrives, and waits for the service to come up.

The view subscribes lossily (fluxcal.service.io.bus.BusClient(lossless=False)): it shows the newest
data and never holds the service back. Exit status: 0 after Ctrl-C / SIGTERM or after --seconds
with data received; 1 if --seconds passed without any data.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import deque
from typing import Any, Callable, TextIO

import numpy as np
import zenoh

from fluxcal.drivers.errors import ConfigError
from fluxcal.drivers.text import printable_json
from fluxcal.service.io.bus import (
    BusClient,
    BusError,
    Keys,
    Message,
    ZenohConfig,
    ZenohTlsConfig,
    discover_units,
    open_session,
)
from fluxcal.service.wiring.commands.client import DATA_STREAMS, STALE_S, counter_words, flow, is_flow, resolve
from fluxcal.service.wiring.commands.options import CommandHelp, connection_options

TTY_PERIOD_S = 0.25            # redraw rate on a terminal (4 Hz)
LINE_PERIOD_S = 1.0            # one line per second otherwise
STATE_EVERY_S = 2.0            # how often the calibration state is queried
STREAMS = ("raw", "corrected", "diff", "tensor", "calibration", "health", "error")


HELP = CommandHelp("terminal view of a running service: each probe's field and |B|, the error "
                   "against the noise, cal= the quality gate (usable or not; `fluxcal command state` says why), "
                   "cov= the share of field directions seen; one line a second when not on a terminal",
                   "  fluxcal watch --connect tcp/127.0.0.1:7447\n  fluxcal watch --config configs/sim-gradiometer.toml")


def add_options(p: argparse.ArgumentParser) -> None:
    connection_options(p, "terminal view")
    p.add_argument("--unit", metavar="NAME", help="the unit to watch (default: the first one found)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    p.add_argument("--json", action="store_true", help="one JSON object a second (JSON lines): what the view shows, "
                                                       "as data")


def _vec(v: np.ndarray, width: int = 10) -> str:
    return " ".join(f"{x:+{width}.1f}" if np.isfinite(x) else f"{'nan':>{width}}" for x in v)


def _vec_short(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:+.1f}" for x in v) + "]"


def _num(x: Any, fmt: str = ".3g") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def _judged(gate: dict[str, Any] | None) -> bool:
    """Whether the gate's latest check judged a candidate (and so has a coverage, condition and residual): the
    pipeline gives a check that found none an empty list of residuals."""
    return bool(gate) and gate.get("rms_nT") != []


def _gate_parts(gate: dict[str, Any] | None) -> list[str]:
    """The gate's latest check in the calibration line."""
    if not gate:
        return []
    if not _judged(gate):
        # a check found no candidate (the online estimate not determined yet, e.g. after the service started
        # from its saved calibration or a reset): no coverage, condition or residual to show
        return ["no residual yet: the online estimate has no candidate since the start or the last reset"]
    rms = gate.get("rms_nT")
    rms_txt = ", ".join(_num(r, ".2f") for r in rms) if isinstance(rms, list) else _num(rms, ".2f")
    return [f"coverage {_num(gate.get('coverage'), '.2f')}", f"condition {_num(gate.get('condition'))}",
            f"residual [{rms_txt}] nT"]


class TerminalView:
    """What `fluxcal watch` shows on the terminal (updated from messages) and how it draws it; no I/O here."""

    def __init__(self, unit: str | None, endpoints: list[str], clock: Callable[[], float] = time.monotonic) -> None:
        self.unit = unit
        self.endpoints = endpoints
        self.secure = any(ep.startswith(("tls/", "quic/")) for ep in endpoints)     # for the hints below
        self.clock = clock
        self.t_start = clock()
        self.connected = False
        self.alive: bool | None = None
        self.last_msg_t: float | None = None
        self.last_data_t: float | None = None     # the newest samples (DATA_STREAMS): what says the input flows
        self.n_messages = 0
        self.raw = None
        self.corrected = None
        self.diff = None
        self.tensor = None
        self.error: dict[str, Any] | None = None
        self.health: dict[str, Any] | None = None
        self.state: dict[str, Any] | None = None
        self.probe_names: list[str] | None = None
        self._rates: dict[str, deque] = {"raw": deque(), "corrected": deque()}

    # --- updates -------------------------------------------------------------------------------

    #: streams whose newest message is kept as the attribute of the same name
    LATEST = ("raw", "corrected", "diff", "tensor", "error", "health")

    def update(self, msg: Message) -> None:
        now = self.clock()
        self.last_msg_t = now
        if msg.stream in DATA_STREAMS:
            self.last_data_t = now
        self.n_messages += 1
        # what a peer sent is shown escaped: only this view's own codes act on the terminal
        v = printable_json(msg.value) if isinstance(msg.value, dict) else msg.value
        if msg.stream in self._rates:
            q = self._rates[msg.stream]
            q.append((now, v.n_samples))
            while q and q[0][0] < now - 2.0:
                q.popleft()
        if msg.stream in self.LATEST:
            setattr(self, msg.stream, v)                  # the newest of each stream is what is shown
        elif msg.stream == "calibration" and isinstance(v.get("state"), dict):
            self.update_state(v["state"])

    def update_state(self, st: dict[str, Any]) -> None:
        st = printable_json(st)
        self.state = {**(self.state or {}), **st}
        names = st.get("probe_names") or [p.get("name") for p in st.get("probes") or [] if isinstance(p, dict)]
        if names and all(isinstance(n, str) for n in names):
            self.probe_names = list(names)

    def rate_hz(self, stream: str) -> float:
        q = self._rates[stream]
        now = self.clock()
        while q and q[0][0] < now - 2.0:
            q.popleft()
        if not q:
            return 0.0
        span = max(now - q[0][0], 1.0)
        return sum(n for _, n in q) / span

    # --- text ----------------------------------------------------------------------------------

    def _names(self, n: int) -> list[str]:
        if self.probe_names and len(self.probe_names) == n:
            return self.probe_names
        return [f"s{k + 1}" for k in range(n)]

    def waiting_message(self) -> str | None:
        """Why nothing is shown, or None when data flows."""
        where = ", ".join(self.endpoints)
        if not self.connected:
            return (f"cannot reach {where} — is `fluxcal run` running and listening there? (retrying every second)"
                    + (" With TLS, also: is this certificate signed by the CA the service trusts, and does the "
                       "service's certificate name the host?" if self.secure else ""))
        if self.unit is None:
            return f"no fluxcal unit visible via {where} yet — is `fluxcal run` running? (or give --unit)"
        if self.last_msg_t is None:
            return (f"no data from fluxcal/{self.unit} yet — is `fluxcal run` running and listening on "
                    f"{where}?" + (" (no such unit is alive there)" if self.alive is False else "")
                    + (" On a secured bus, also: is this certificate's name among the unit's [zenoh.access] "
                       "readers?" if self.secure else ""))
        kind, sentence = flow(self.unit, self.clock(), self.last_msg_t, self.last_data_t, self.alive, self.health)
        return None if kind == "live" else sentence

    def _sample_parts(self) -> list[str]:
        """The one-line view's newest vectors (corrected, else raw), differences, tensor and error."""
        parts: list[str] = []
        c = self.corrected
        if c is not None and c.n_samples:
            for name, v in zip(self._names(c.n_probes), c.corrected_nT[-1]):
                parts.append(f"{name}={_vec_short(v)} |B|={float(np.linalg.norm(v)):.1f}")
        elif self.raw is not None and self.raw.n_samples:
            for name, v in zip(self._names(self.raw.n_probes), self.raw.field_nT[-1]):
                parts.append(f"raw {name}={_vec_short(v)}")
        if self.diff is not None and self.diff.values.size:
            names = self._names(self.diff.values.shape[1] + 1)
            for k, d in enumerate(self.diff.values[-1]):
                parts.append(f"{names[k + 1]}-{names[0]}={_vec_short(d)}")
        if self.tensor is not None and self.tensor.values.size:
            g = self.tensor.values[-1]
            parts.append("G=[" + ", ".join(f"{x:+.2f}" for x in g.ravel()) + "] nT/m")
        if self.error:
            parts.append("err " + " ".join(f"{k}={_num(v, '.3f')}" for k, v in (self.error.get("rms_nT") or {}).items()))
        return parts

    def _heard(self) -> bool:
        """Whether the service itself is heard now (any of its messages), whatever its input does."""
        return self.connected and self.last_msg_t is not None and self.clock() - self.last_msg_t <= STALE_S

    def calibration_summary(self) -> str:
        st = self.state
        if not st:
            return "calibration: unknown (no state yet)"
        gate = st.get("gate") or {}
        usable = "USABLE" if st.get("usable") else "not usable yet"
        parts = [f"calibration: {usable}", f"cal_id {st.get('cal_id', '-')}"]
        if st.get("method"):
            parts.append(f"method {st['method']}")
        if st.get("frozen"):
            parts.append("FROZEN")
        if st.get("held"):
            parts.append("APPLIED (held until reset)")
        judged = _judged(gate)
        parts += _gate_parts(gate)
        if st.get("samples_seen") is not None:
            parts.append(f"{st['samples_seen']} samples seen")
        if st.get("stale"):
            age = st.get("state_age_s")
            parts.append(f"(state {_num(age, '.0f')} s old: the service is busy, e.g. reconnecting its input)")
        text = "  ".join(parts)
        reasons = gate.get("reasons") if gate else None
        if reasons and (not st.get("usable") or not judged):
            text += "\n  gate: " + "; ".join(map(str, reasons))
        return text

    def frame_lines(self) -> list[str]:
        """The full-screen view (terminal mode)."""
        head = (f"fluxcal watch — fluxcal/{self.unit or '?'} via {', '.join(self.endpoints)} — "
                f"{time.strftime('%H:%M:%S')}")
        lines = [head]
        waiting = self.waiting_message()
        if waiting:
            lines.append(f"\x1b[33m{waiting}\x1b[0m")
        lines.append(f"receiving: raw {self.rate_hz('raw'):.0f} samples/s, corrected {self.rate_hz('corrected'):.0f} "
                     f"samples/s, {self.n_messages} messages")
        lines.append(self.calibration_summary())
        lines.append("")
        lines += _field_panels(self, stale=bool(waiting))
        if self.error:
            rms = self.error.get("rms_nT") or {}
            lines.append("")
            lines.append("error, rms nT: " + "  ".join(f"{k} {_num(v, '.3f')}" for k, v in rms.items()))
        if self.health:
            counters, about = self.health.get("counters") or {}, counter_words(self.state)
            txt = "  ".join(f"\x1b[31m{k} {v}\x1b[0m" if v and not is_flow(k, about) else f"{k} {v}"
                            for k, v in counters.items() if isinstance(v, (int, float)))
            lines.append("")
            lines.append("health: " + txt)
        lines.append("")
        lines.append("Ctrl-C to quit")
        return lines

    def render_tty(self) -> str:
        # home, then every line cleared to its end, then clear below: no flicker, no curses
        return "\x1b[H" + "".join(f"{ln}\x1b[K\n" for ln in "\n".join(self.frame_lines()).split("\n")) + "\x1b[J"

    def line(self) -> str:
        """One line (non-terminal mode)."""
        t = self.clock() - self.t_start
        waiting = self.waiting_message()
        if waiting and not self._heard():
            return f"{t:6.1f}s {waiting}"
        st = self.state or {}
        gate = st.get("gate") or {}
        parts = [f"{t:6.1f}s fluxcal/{self.unit}",
                 f"cal={'usable' if st.get('usable') else 'not-usable' if st else '?'}"
                 + (f" cov={_num(gate.get('coverage'), '.2f')}" if _judged(gate) else
                    " no-candidate-yet" if gate else "")
                 + (f" state-age={_num(st.get('state_age_s'), '.0f')}s" if st.get("stale") else "")]
        parts += [waiting] if waiting else self._sample_parts()    # samples not arriving: no old vectors as live
        if self.health:
            counters, about = self.health.get("counters") or {}, counter_words(self.state)
            parts.append(" ".join(f"{k}={v}" for k, v in counters.items() if isinstance(v, (int, float)) and
                                  (v or is_flow(k, about))))
        return " | ".join(p for p in parts if p)


def view_record(view: TerminalView) -> dict[str, Any]:
    """What the one-line view shows, as data (--json): whether samples flow (`status`: why not, else null), the newest
    vectors (corrected, else raw; left out while samples do not arrive, as the line leaves them out), differences,
    tensor, error, the calibration state and the counters."""
    waiting = view.waiting_message()
    st, rec = view.state or {}, {"t_s": round(view.clock() - view.t_start, 3), "unit": view.unit,
                                 "status": waiting, "messages": view.n_messages}
    gate = st.get("gate") or {}
    rec["calibration"] = {"usable": st.get("usable"), "cal_id": st.get("cal_id"), "stale": bool(st.get("stale")),
                          **({k: gate.get(k) for k in ("coverage", "condition", "rms_nT")} if _judged(gate) else {}),
                          "reasons": list(gate.get("reasons") or [])} if st else None
    rec["counters"] = dict((view.health or {}).get("counters") or {})
    if waiting is None:
        c, raw = view.corrected, view.raw
        if c is not None and c.n_samples:
            rec["probes"] = [{"name": n, "corrected_nT": v.tolist(), "total_nT": float(np.linalg.norm(v))}
                             for n, v in zip(view._names(c.n_probes), c.corrected_nT[-1])]
        elif raw is not None and raw.n_samples:
            rec["probes"] = [{"name": n, "raw_nT": v.tolist()} for n, v in zip(view._names(raw.n_probes),
                                                                                raw.field_nT[-1])]
        if view.diff is not None and view.diff.values.size:
            names = view._names(view.diff.values.shape[1] + 1)
            rec["differences"] = {f"{names[k + 1]}-{names[0]}": d.tolist() for k, d in enumerate(view.diff.values[-1])}
        if view.tensor is not None and view.tensor.values.size:
            rec["tensor_nT_m"] = view.tensor.values[-1].tolist()
        if view.error:
            rec["error_rms_nT"] = dict(view.error.get("rms_nT") or {})
    return rec


def _field_panels(view: TerminalView, stale: bool) -> list[str]:
    """The terminal view's newest vectors (corrected, else raw), differences and tensor; `stale`: the samples are not
    arriving, so the vectors are marked as the last ones."""
    lines: list[str] = []
    c = view.corrected
    if c is not None and c.n_samples:
        lines.append(f"{'corrected':<12}{'Bx nT':>11}{'By nT':>11}{'Bz nT':>11}{'|B| nT':>12}   cal_id {c.cal_id}"
                     + ("   (the last samples, not live)" if stale else ""))
        for name, v in zip(view._names(c.n_probes), c.corrected_nT[-1]):
            lines.append(f"{name:<12}{_vec(v)} {float(np.linalg.norm(v)):11.1f}")
        if c.center_nT is not None:
            lines.append(f"{'centre':<12}{_vec(c.center_nT[-1])} {float(np.linalg.norm(c.center_nT[-1])):11.1f}")
    elif view.raw is not None and view.raw.n_samples:
        lines.append(f"{'raw (uncal.)':<12}{'x nT':>11}{'y nT':>11}{'z nT':>11}{'|B| nT':>12}")
        for name, v in zip(view._names(view.raw.n_probes), view.raw.field_nT[-1]):
            lines.append(f"{name:<12}{_vec(v)} {float(np.linalg.norm(v)):11.1f}")
    if view.diff is not None and view.diff.values.size:
        names = view._names(view.diff.values.shape[1] + 1)
        lines.append("")
        for k, d in enumerate(view.diff.values[-1]):
            lines.append(f"{names[k + 1] + '-' + names[0]:<12}{_vec(d)} {float(np.linalg.norm(d)):11.2f}  nT")
    if view.tensor is not None and view.tensor.values.size:
        g = view.tensor.values[-1]
        lines.append("")
        lines.append("tensor G[i,j] = dB_j/dx_i, nT/m   trace %+.2f" % float(np.trace(g)))
        for i, ax in enumerate("xyz"):
            lines.append(f"  d/d{ax}      " + " ".join(f"{x:+10.2f}" for x in g[i]))
    return lines


class _StateQuery:
    """A `state` query in flight, polled without blocking the redraw loop."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.handler = session.get(key, timeout=1.5)

    def poll(self) -> tuple[bool, dict | None]:
        """(finished, state or None)."""
        try:
            reply = self.handler.try_recv()
        except zenoh.ZError:
            return True, None
        if reply is None:
            return False, None
        if reply.ok is not None:
            try:
                return True, json.loads(reply.ok.payload.to_bytes())
            except ValueError:
                return True, None
        return True, None


class _Link:
    """The watch's connection to a unit: the session (tried again every second), the unit (found when not named),
    its streams, its liveliness and its state (asked every STATE_EVERY_S); `poll` feeds the view what came."""

    def __init__(self, endpoints: list[str], tls: ZenohTlsConfig | None, view: TerminalView) -> None:
        self.endpoints, self.tls, self.view = endpoints, tls, view
        self.session = self.client = self.alive_sub = None
        self.state_q: _StateQuery | None = None
        self.next_state = self.next_connect = self.next_discover = 0.0

    def poll(self, now: float) -> None:
        view = self.view
        if self.session is None and now >= self.next_connect:
            try:
                self.session = open_session(ZenohConfig.client(*self.endpoints, tls=self.tls))
                view.connected = True
            except BusError:
                self.next_connect = now + 1.0
        if self.session is not None and view.unit is None and now >= self.next_discover:
            units = discover_units(self.session, timeout=0.3)
            self.next_discover = now + 1.0
            if len(units) == 1:
                view.unit = units[0]
            elif len(units) > 1:
                raise ConfigError(f"several units are running via {', '.join(self.endpoints)}: {', '.join(units)}; "
                                  f"choose one with --unit")
        if self.session is not None and view.unit is not None and self.client is None:
            keys = Keys(view.unit)
            self.client = BusClient(self.session, view.unit, streams=STREAMS, lossless=False, capacity=64)
            self.alive_sub = self.session.liveliness().declare_subscriber(keys.alive, zenoh.handlers.RingChannel(16),
                                                                          history=True)
            view.alive = False                  # until the token's history says otherwise
        if self.client is not None:
            self._state(now)
            self._alive()
            for msg in self.client.drain():
                view.update(msg)

    def _state(self, now: float) -> None:
        if self.state_q is None and now >= self.next_state:
            self.state_q, self.next_state = _StateQuery(self.session, Keys(self.view.unit).state), now + STATE_EVERY_S
        if self.state_q is not None:
            done, st = self.state_q.poll()
            if st is not None:
                self.view.update_state(st)
            if done:
                self.state_q = None

    def _alive(self) -> None:
        while True:
            try:
                s = self.alive_sub.try_recv()
            except zenoh.ZError:
                return
            if s is None:
                return
            self.view.alive = s.kind == zenoh.SampleKind.PUT

    def wait(self, seconds: float) -> None:
        """Wait up to `seconds` (at most 0.05) for a message, feeding it to the view."""
        if self.client is not None:
            msg = self.client.recv(timeout=max(0.0, min(seconds, 0.05)))
            if msg is not None:
                self.view.update(msg)
        else:
            time.sleep(max(0.0, min(seconds, 0.05)))

    def close(self) -> None:
        for closer in (getattr(self.alive_sub, "undeclare", None), getattr(self.client, "close", None),
                       getattr(self.session, "close", None)):
            if closer is not None:
                try:
                    closer()
                except (zenoh.ZError, KeyboardInterrupt):
                    pass


def run(endpoints: list[str], unit: str | None, seconds: float | None, out: TextIO, *,
        tty: bool | None = None, tls: ZenohTlsConfig | None = None, as_json: bool = False) -> int:
    """The watch's loop; returns the exit status. as_json: one JSON object a second (view_record), never redrawn."""
    tty = False if as_json else out.isatty() if tty is None else tty
    period = TTY_PERIOD_S if tty else LINE_PERIOD_S
    start = time.monotonic()
    deadline = None if seconds is None else start + seconds
    view = TerminalView(unit, endpoints)
    link = _Link(endpoints, tls, view)
    next_frame = start + (0.5 if not tty else 0.0)
    if tty:
        out.write("\x1b[?25l\x1b[2J")              # hide the cursor, clear once
    try:
        while deadline is None or time.monotonic() < deadline:
            link.poll(time.monotonic())
            now = time.monotonic()
            if now >= next_frame:
                out.write(view.render_tty() if tty else (json.dumps(view_record(view)) if as_json else view.line())
                          + ("" if tty else "\n"))
                out.flush()
                next_frame = now + period
            link.wait(min(next_frame, deadline if deadline is not None else next_frame) - time.monotonic())
    except KeyboardInterrupt:
        pass
    finally:
        if tty:
            out.write("\x1b[?25h\n")
            out.flush()
        link.close()
    return 0 if view.n_messages or seconds is None else 1


def main(args: argparse.Namespace) -> int:
    endpoints, unit, tls = resolve(args)
    status = run(endpoints, unit, args.seconds, sys.stdout, tls=tls, as_json=getattr(args, "json", False))
    if status:
        where = f"fluxcal/{unit}" if unit else "any fluxcal unit"
        print(f"fluxcal watch: nothing received from {where} via {', '.join(endpoints)} in {args.seconds:g} s",
              file=sys.stderr)
    return status
