"""How the commands that talk to a running service find it: its endpoints, its unit and TLS from --config, --connect,
--unit and --ca/--cert/--key (watch, command, dashboard, foxglove), and a --listen address."""

from __future__ import annotations

import argparse
import math
import re

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.io.bus import (
    DEFAULT_PORT,
    Keys,
    ZenohConfig,
    ZenohTlsConfig,
)
from fluxcal.service.wiring.faults import no_samples_words

DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

#: health counters of what arrived or was sent, by name: the service's own, and a service that does not say (the
#: dashboard's page keeps the same rule, static/app.js counterIsThroughput)
_FLOW = re.compile(r"(^|_)(received|accepted)$|^published_|^received")


def counter_words(state: object) -> dict | None:
    """The words of the source's own counters a state reply carries (source.counters), or None."""
    source = state.get("source") if isinstance(state, dict) else None
    return source.get("counters") if isinstance(source, dict) else None


def is_flow(name: str, about: object = None) -> bool:
    """Whether a health counter counts what arrived or was sent, never a loss however large: as the source's
    declaration says (the state's source.counters, docs/zenoh.md), else by its name.

    >>> is_flow("foreign_frames", {"foreign_frames": {"flow": True}}), is_flow("foreign_frames")
    (True, False)
    """
    entry = about.get(name) if isinstance(about, dict) else None
    return bool(entry.get("flow")) if isinstance(entry, dict) else bool(_FLOW.search(name))


def dashboard_endpoints(zcfg: ZenohConfig) -> list[str]:
    """Where a dashboard on this host reaches a service configured with `zcfg`: its listen endpoints (a
    wildcard address becomes loopback), else the router it connects to.

    >>> dashboard_endpoints(ZenohConfig(listen=["tcp/0.0.0.0:7447", "tcp/[::]:7448"]))
    ['tcp/127.0.0.1:7447', 'tcp/[::1]:7448']
    """
    eps = []
    for ep in zcfg.listen:
        ep = re.sub(r"^(\w+)/0\.0\.0\.0:", r"\1/127.0.0.1:", ep)
        ep = re.sub(r"^(\w+)/\[::\]:", r"\1/[::1]:", ep)
        if not re.search(r":0(?:$|[#?])", ep):          # port 0: chosen at start, unknown from here
            eps.append(ep)
    return eps or list(zcfg.connect)


def resolve(args: argparse.Namespace) -> tuple[list[str], str | None, ZenohTlsConfig]:
    endpoints: list[str] = []
    unit = getattr(args, "unit", None)
    tls = ZenohTlsConfig()
    if getattr(args, "config", None):
        from fluxcal.service.wiring.config import load_config

        cfg = load_config(args.config)
        endpoints = dashboard_endpoints(cfg.zenoh)
        tls = cfg.zenoh.tls
        unit = unit or cfg.unit.name
        if not endpoints and not args.connect:
            raise ConfigError(f"{args.config}: zenoh: the service neither listens on a fixed port nor connects to a "
                              f"router; give --connect ENDPOINT")
    if getattr(args, "connect", None):
        endpoints = [args.connect]
    if not endpoints:
        endpoints = [DEFAULT_ENDPOINT]
    given = {k: getattr(args, k, None) for k in ("ca", "cert", "key")}
    if any(given.values()):
        tls = ZenohTlsConfig(root_ca=given["ca"], cert=given["cert"], key=given["key"])
        try:
            tls.validate("tls")
        except ConfigError as e:
            key, _, why = str(e).partition(": ")
            flag = {"tls.root_ca": "--ca", "tls.cert": "--cert", "tls.key": "--key"}.get(key, key)
            raise ConfigError(f"{flag}: {why}") from None
    try:
        ZenohConfig.client(*endpoints, tls=tls)         # a typo in an endpoint is a usage error, not a retry loop
    except ConfigError as e:
        flag = "--connect" if getattr(args, "connect", None) else f"{args.config}: zenoh"
        raise ConfigError(f"{flag}: {str(e).split(': ', 1)[-1]}") from None
    if unit is not None:
        Keys(unit)
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise ConfigError(f"--seconds: {args.seconds!r} is not allowed (allowed: a positive number of seconds)")
    return endpoints, unit, tls


def resolve_units(args: argparse.Namespace) -> tuple[list[str], list[str] | None, ZenohTlsConfig]:
    """As `_resolve`, for commands whose --unit may be repeated (dashboard, foxglove): the units named, the
    configuration's unit, or None (every unit found)."""
    named = list(args.unit or [])
    endpoints, unit, tls = resolve(argparse.Namespace(**{**vars(args), "unit": named[0] if named else None}))
    for u in named:
        Keys(u)
    return endpoints, named or ([unit] if unit else None), tls


def parse_listen(text: str, flag: str = "--listen") -> tuple[str, int]:
    """A server address HOST:PORT (IPv6 in brackets) for --listen; ConfigError naming the option.

    >>> parse_listen("127.0.0.1:0"), parse_listen("[::1]:8765")
    (('127.0.0.1', 0), ('::1', 8765))
    """
    m = re.fullmatch(r"\[([0-9A-Fa-f:.]+)\]:(\d{1,5})|([^:\[\]]+):(\d{1,5})", text or "")
    port = int(m.group(2) or m.group(4)) if m else -1
    if not m or port > 65535:
        raise ConfigError(f"{flag}: {text!r} is not allowed (allowed: HOST:PORT, e.g. 127.0.0.1:8090; port 0: "
                          f"a free one)")
    return m.group(1) or m.group(3), port


#: a viewer's streams that carry samples: their silence is the input's, whatever else the service still sends
DATA_STREAMS = ("raw", "corrected")
#: nothing heard for this long: say so
STALE_S = 3.0


def _active(health: object) -> list[str]:
    """The names of the faults the service says are going on (its health's faults.active)."""
    faults = health.get("faults") if isinstance(health, dict) else None
    return [a for a in faults.get("active") or [] if isinstance(a, str)] if isinstance(faults, dict) else []


def active_faults(health: object) -> str:
    """The faults the service says are going on (its health's faults.active), each with its newest event's words."""
    faults = health.get("faults") if isinstance(health, dict) else None
    if not isinstance(faults, dict):
        return ""
    active = _active(health)
    events = [e for e in faults.get("events") or [] if isinstance(e, dict)]
    said = []
    for kind in active:
        newest = next((e for e in reversed(events) if e.get("kind") == kind and e.get("phase") != "end"), None)
        said.append(str(newest["text"]) if newest and newest.get("text") else kind)
    return "; ".join(said)


def flow(unit: object, now: float, last_msg_t: float | None, last_data_t: float | None, alive: bool | None,
         health: object = None) -> tuple[str, str]:
    """(kind, sentence) of what a viewer hears from a unit: "live" (its samples arrive), "silent" (none for STALE_S:
    where the service is still heard, its input is silent, and its active faults are said), "stopped" (its liveliness
    token is gone), "waiting" (never heard). The timing is the samples' (DATA_STREAMS): health and calibration
    messages go on while the input is silent."""
    if last_data_t is not None and now - last_data_t <= STALE_S:
        return "live", f"receiving from fluxcal/{unit}"
    since = "yet" if last_data_t is None else f"for {now - last_data_t:.0f} s"
    if alive is False:
        return "stopped", (f"no data from fluxcal/{unit} {since} — the service has stopped (its liveliness token is "
                           f"gone)")
    if last_msg_t is None:
        return "waiting", f"no data from fluxcal/{unit} yet"
    if now - last_msg_t <= STALE_S:
        faults = active_faults(health)
        return "silent", (f"no samples from fluxcal/{unit} {since}: the service runs, "
                          f"{no_samples_words(_active(health)).replace('the input', 'its input')}"
                          + (f" ({faults})" if faults else ""))
    return "silent", f"no data from fluxcal/{unit} for {now - last_msg_t:.0f} s"
