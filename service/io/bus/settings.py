"""Zenoh configuration and security: endpoints, TLS with mutual authentication, access control, and
opening a session (docs/security.md). Sessions opened here must be closed (`close()`, or `with`): a
session left open with callbacks hangs the interpreter at exit.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from fluxcal.drivers.config import spec
from fluxcal.drivers.errors import ConfigError, FluxcalError

from .keys import Keys


class BusError(FluxcalError):
    """The Zenoh session cannot open, or the service does not answer a query or command."""


DEFAULT_PORT = 7447


DEFAULT_LISTEN = [f"tcp/127.0.0.1:{DEFAULT_PORT}"]


_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "vsock", "serial")


_HOST_PORT = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):(\d{1,5})$")


def _check_endpoint(ep: str, key: str) -> None:
    proto, sep, addr = ep.partition("/")
    if not sep or proto not in _PROTOCOLS or not addr:
        raise ConfigError(f"{key}: {ep!r} is not a Zenoh endpoint (allowed: <protocol>/<address>, protocol one of "
                          f"{', '.join(_PROTOCOLS)}; e.g. 'tcp/127.0.0.1:{DEFAULT_PORT}')")
    if proto in ("tcp", "udp", "tls", "quic"):
        m = _HOST_PORT.match(addr.split("#", 1)[0].split("?", 1)[0])
        if not m or int(m.group(2)) > 65535:
            raise ConfigError(f"{key}: {ep!r} needs host:port with a port 0..65535 (e.g. 'tcp/127.0.0.1:{DEFAULT_PORT}')")


_SECURE_PROTOCOLS = ("tls", "quic")


_LOOPBACK_HOST = re.compile(r"^(127\.\d+\.\d+\.\d+|localhost|\[::1\])$")


def _check_pem(path: str, key: str, what: str) -> None:
    """A PEM file that exists and can be read: checked at start, not at the first connection."""
    p = Path(path)
    try:
        head = p.read_bytes()[:1 << 20]
    except FileNotFoundError:
        raise ConfigError(f"{key}: {path!r}: file not found (allowed: the path of a PEM {what}; relative paths "
                          f"are relative to the working directory {Path.cwd()})") from None
    except OSError as e:
        raise ConfigError(f"{key}: {path!r}: cannot read it: {e.strerror}") from None
    if b"-----BEGIN " not in head:
        raise ConfigError(f"{key}: {path!r} is not a PEM file (allowed: a PEM {what}, text starting "
                          f"'-----BEGIN ...')")


@dataclass
class ZenohTlsConfig:
    """The [zenoh.tls] table: TLS links with the site's certificate authority.

    With `mutual = true` (the default) both ends prove who they are: the service accepts only peers whose
    certificate the CA signed, and `[zenoh.access]` can tell them apart by their certificate's common name.
    The same certificate and key serve the links this node accepts and those it opens.
    """

    root_ca: str | None = spec(None, doc="PEM certificate of the site's certificate authority")
    cert: str | None = spec(None, doc="PEM certificate of this node, signed by root_ca")
    key: str | None = spec(None, doc="PEM private key of this node's certificate")
    mutual: bool = spec(True, doc="require a certificate signed by root_ca from every peer (mutual TLS)")
    verify_name: bool = spec(True, doc="check that the certificate of a node we connect to names its host")

    @property
    def enabled(self) -> bool:
        return any(getattr(self, k) is not None for k in ("root_ca", "cert", "key"))

    def validate(self, path: str) -> None:
        if not self.enabled:
            return
        files = (("root_ca", "CA certificate"), ("cert", "certificate"), ("key", "private key"))
        for name, _ in files:
            if getattr(self, name) is None:
                raise ConfigError(f"{path}.{name}: required with TLS (set root_ca, cert and key together: the "
                                  f"site's CA, this node's certificate and its private key)")
        for name, what in files:
            _check_pem(getattr(self, name), f"{path}.{name}", what)

    def zenoh_json(self) -> dict[str, Any]:
        return {"root_ca_certificate": self.root_ca,
                "listen_certificate": self.cert, "listen_private_key": self.key,
                "connect_certificate": self.cert, "connect_private_key": self.key,
                "enable_mtls": bool(self.mutual), "verify_name_on_connect": bool(self.verify_name)}


@dataclass
class ZenohAccessConfig:
    """The [zenoh.access] table: who may do what, by the common name (CN) of their TLS certificate.

    Everything not granted here is denied. `readers` may subscribe to the unit's streams, query its state
    and see that it is alive; `commanders` may do that and send calibration commands (cmd/*). A peer
    whose certificate's CN is in neither list can connect (its certificate is valid) but gets nothing.
    Needs [zenoh.tls] with mutual = true: without client certificates there is no name to check.
    """

    readers: list[str] = spec([], doc="certificate common names that may read streams and state")
    commanders: list[str] = spec([], doc="certificate common names that may also send cmd/* commands")

    @property
    def enabled(self) -> bool:
        return bool(self.readers or self.commanders)

    def validate(self, path: str) -> None:
        for name in ("readers", "commanders"):
            for i, cn in enumerate(getattr(self, name)):
                if not cn.strip() or len(cn) > 256:
                    raise ConfigError(f"{path}.{name}[{i}]: {cn!r} is not allowed (allowed: the common name of "
                                      f"a client certificate, 1-256 characters)")

    def zenoh_json(self, unit: str) -> dict[str, Any]:
        """Zenoh's access_control block for `unit` on this node (default deny; the flows are seen from here:
        ingress is what a remote sends us, egress what we send it)."""
        root = Keys(unit).root
        streams = [f"{root}/*", f"{root}/corrected/*"]          # raw, corrected, ..., state, alive; not cmd/*
        rules = [
            {"id": "read-ingress", "permission": "allow", "flows": ["ingress"],
             "messages": ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"],
             "key_exprs": streams + ["fluxcal/*/alive"]},
            {"id": "read-egress", "permission": "allow", "flows": ["egress"],
             "messages": ["put", "delete", "reply", "declare_queryable", "liveliness_token"],
             "key_exprs": streams},
            {"id": "command-ingress", "permission": "allow", "flows": ["ingress"],
             "messages": ["query"], "key_exprs": [f"{root}/cmd/*"]},
            {"id": "command-egress", "permission": "allow", "flows": ["egress"],
             "messages": ["reply", "declare_queryable"], "key_exprs": [f"{root}/cmd/*"]},
        ]
        subjects, policies = [], []
        readers = sorted(set(self.readers) | set(self.commanders))
        if readers:
            subjects.append({"id": "readers", "cert_common_names": readers})
            policies.append({"id": "readers", "rules": ["read-ingress", "read-egress"], "subjects": ["readers"]})
        if self.commanders:
            subjects.append({"id": "commanders", "cert_common_names": sorted(set(self.commanders))})
            policies.append({"id": "commanders", "rules": ["command-ingress", "command-egress"],
                             "subjects": ["commanders"]})
        return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
                "policies": policies}


@dataclass
class ZenohConfig:
    """The [zenoh] section. By default a peer that listens on loopback only, without multicast scouting."""

    mode: str = spec("peer", choices=("peer", "client", "router"),
                     doc="peer: listens and accepts dashboards; client: connects to a router; "
                         "router: routes between clients (sites normally run zenohd instead)")
    listen: list[str] = spec(list(DEFAULT_LISTEN), doc="endpoints to listen on (peer, router); a client listens on none")
    connect: list[str] = spec([], doc="endpoints to connect to, e.g. a zenohd router 'tcp/10.0.0.5:7447'")
    multicast_scouting: bool = spec(False, doc="discover peers by UDP multicast (off: explicit endpoints only)")
    per_probe: bool = spec(True, doc="also publish corrected/<probe>, one probe per message")
    express: bool = spec(False, doc="send each message at once instead of letting Zenoh batch (lower latency)")
    stall_close_ms: float = spec(500.0, min=10.0, max=60000.0,
                                 doc="a subscriber that takes nothing for this long is disconnected, so that it "
                                     "holds back no other subscriber longer; it reconnects by itself and counts "
                                     "the raw samples it missed by their seq (docs/zenoh.md)")
    tls: ZenohTlsConfig = spec(default_factory=ZenohTlsConfig)
    access: ZenohAccessConfig = spec(default_factory=ZenohAccessConfig)

    def validate(self, path: str) -> None:
        p = f"{path}." if path else ""
        if self.mode == "client":
            if self.listen == DEFAULT_LISTEN:
                self.listen = []          # the default is the peer's; a client listens on nothing
            elif self.listen:
                raise ConfigError(f"{p}listen: {self.listen!r} is not allowed with mode 'client' (a client listens "
                                  f"on nothing; use mode 'peer' to accept connections)")
            if not self.connect:
                raise ConfigError(f"{p}connect: a client needs at least one endpoint to connect to "
                                  f"(e.g. ['tcp/127.0.0.1:{DEFAULT_PORT}'])")
        for name in ("listen", "connect"):
            for i, ep in enumerate(getattr(self, name)):
                _check_endpoint(ep, f"{p}{name}[{i}]")
        if self.mode != "client" and not self.listen and not self.connect:
            raise ConfigError(f"{p}listen: nothing to listen on and nothing to connect to: no dashboard could "
                              f"reach this service (e.g. listen = ['tcp/127.0.0.1:{DEFAULT_PORT}'])")
        self.tls.validate(f"{p}tls")
        self.access.validate(f"{p}access")
        if self.tls.enabled:
            for name in ("listen", "connect"):
                for i, ep in enumerate(getattr(self, name)):
                    if ep.partition("/")[0] not in _SECURE_PROTOCOLS:
                        raise ConfigError(f"{p}{name}[{i}]: {ep!r} would carry the streams and commands in clear "
                                          f"text beside TLS (allowed with [{p}tls]: tls/HOST:PORT or quic/HOST:PORT)")
        if self.access.enabled and not (self.tls.enabled and self.tls.mutual):
            raise ConfigError(f"{p}access: access control names peers by their client certificate, so it needs "
                              f"[{p}tls] with root_ca, cert and key, and mutual = true")

    def exposed(self) -> list[str]:
        """Listen endpoints reachable from other hosts in clear text (for a warning at start)."""
        out = []
        for ep in self.listen:
            proto, _, addr = ep.partition("/")
            host = addr.split("#", 1)[0].split("?", 1)[0].rsplit(":", 1)[0]
            if proto not in _SECURE_PROTOCOLS and not _LOOPBACK_HOST.match(host) and not proto.startswith("unix"):
                out.append(ep)
        return out

    @staticmethod
    def client(*endpoints: str, tls: ZenohTlsConfig | None = None) -> "ZenohConfig":
        """A client connected to `endpoints` (a service's listen endpoint or a router), over TLS if given."""
        cfg = ZenohConfig(mode="client", listen=[], connect=list(endpoints), tls=tls or ZenohTlsConfig())
        cfg.validate("zenoh")
        return cfg


def make_zenoh_config(cfg: ZenohConfig, unit: str | None = None) -> zenoh.Config:
    """The zenoh.Config for a validated ZenohConfig: every key set explicitly, none left to zenoh's defaults
    that would listen on all interfaces (a peer's default is tcp/[::]:0). With TLS, only tls and quic links
    are accepted; with [zenoh.access], the access control of `unit` (which must then be given)."""
    cfg.validate("zenoh")
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(cfg.mode))
    c.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    c.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    c.insert_json5("scouting/multicast/enabled", json.dumps(bool(cfg.multicast_scouting)))
    # BLOCK streams wait for a full link at most this long, then zenoh closes that link (its default, 5 s, let one
    # frozen subscriber stall every other one, recorders included, for 5 s at a time)
    c.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                   json.dumps(int(cfg.stall_close_ms * 1000)))
    if cfg.tls.enabled:
        c.insert_json5("transport/link/tls", json.dumps(cfg.tls.zenoh_json()))
        c.insert_json5("transport/link/protocols", json.dumps(list(_SECURE_PROTOCOLS)))
    if cfg.access.enabled and cfg.mode != "client":
        if unit is None:
            raise ConfigError("zenoh.access: access control is per unit; the session needs the unit's name")
        c.insert_json5("access_control", json.dumps(cfg.access.zenoh_json(unit)))
    return c


def open_session(cfg: "ZenohConfig | zenoh.Config", unit: str | None = None) -> zenoh.Session:
    """Open a session; a failure (port taken, nothing to connect to) is a BusError naming the endpoints."""
    zc = make_zenoh_config(cfg, unit) if isinstance(cfg, ZenohConfig) else cfg
    try:
        return zenoh.open(zc)
    except zenoh.ZError as e:
        where = ""
        if isinstance(cfg, ZenohConfig):
            where = (f" (mode {cfg.mode}, listen {cfg.listen or '-'}, connect {cfg.connect or '-'})")
        msg = str(e).split(" at /", 1)[0]        # drop the Rust source location
        hint = ""
        low = msg.lower()
        tls_words = ("private key", "keys may not", "keymismatch", "certificate", "pem", "rustls")
        if isinstance(cfg, ZenohConfig) and cfg.tls.enabled and any(w in low for w in tls_words):
            hint = (": the TLS files were read but Zenoh refused them: does zenoh.tls.key belong to zenoh.tls.cert "
                    "(not swapped, not from another certificate), and did zenoh.tls.root_ca sign it? "
                    "(docs/security.md)")
        elif isinstance(cfg, ZenohConfig) and "in use" in low:
            raise BusError(f"zenoh.listen: {cfg.listen}: the port is already in use (another fluxcal, or another "
                           f"program, listens there): choose another port in [zenoh] listen") from None
        elif "listener" in low or "in use" in low:
            hint = ": is another fluxcal already listening there? choose another port in [zenoh] listen"
        elif "connect" in low:
            hint = ": is the service (or router) running and listening there?"
            if isinstance(cfg, ZenohConfig) and cfg.tls.enabled:
                hint += (" With TLS, also check the certificates: the other end's must be signed by this node's "
                         "root_ca and name the host in the endpoint, and with mutual TLS this node's must be "
                         "signed by the CA the other end trusts")
        raise BusError(f"zenoh session failed to open{where}: {msg}{hint}") from None


class SessionHolder:
    """Holds a zenoh session: one it opened from a configuration (closed with it) or one it was given
    (left open); a context manager that calls `close()`."""

    session: zenoh.Session
    _own_session: bool

    def _hold(self, zenoh_cfg: "ZenohConfig | zenoh.Config | zenoh.Session", unit: str | None = None) -> None:
        if isinstance(zenoh_cfg, zenoh.Session):
            self.session, self._own_session = zenoh_cfg, False
        else:
            self.session, self._own_session = open_session(zenoh_cfg, unit), True

    def _release(self) -> None:
        if self._own_session:
            self.session.close()

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
