"""The Zenoh side of fluxcal: what the service publishes, answers and obeys, and the client that listens.

Key expressions, all under ``fluxcal/<unit>/`` (docs/zenoh.md has the full table):

    raw                binary SampleBlock      BLOCK  (never dropped)
    corrected          binary CorrectedBlock   BLOCK  all probes, diff, centre and tensor included
    corrected/<probe>  binary CorrectedBlock   BLOCK  one probe (P = 1), if ZenohConfig.per_probe
    diff               binary series           BLOCK  probe k minus probe 1, (N, P-1, 3) nT
    tensor             binary series           BLOCK  G[i, j] = dB_j/dx_i, (N, 3, 3) nT/m
    calibration        JSON                    BLOCK  every calibration event and the state after it
    health             JSON                    DROP   source counters and the bus's own counters, ~1 Hz
    error              JSON                    DROP   model-vs-measurement rms_nT per channel, per block
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

import itertools
import json
import math
import queue
import re
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import zenoh

from drivers.block import SampleBlock
from drivers.config import spec
from drivers.errors import ConfigError, DataError, FluxcalError

from service.io.encoding import decode_corrected, decode_raw, encode_corrected, encode_raw, json_ready
from service.numerics.outputs import CorrectedBlock

__all__ = [
    "BusClient", "BusError", "Command", "COMMANDS", "Keys", "Message", "Series", "ServiceBus",
    "STREAMS", "ZenohAccessConfig", "ZenohConfig", "ZenohTlsConfig", "discover_units", "make_zenoh_config", "open_session",
    "decode_series", "encode_series", "DEFAULT_PORT", "DEFAULT_LISTEN",
]


class BusError(FluxcalError):
    """The Zenoh session cannot open, or the service does not answer a query or command."""


# --------------------------------------------------------------------------------------------
# Binary encodings of the block streams
# --------------------------------------------------------------------------------------------

# raw and corrected layouts: drivers/encoding.py and service/io/encoding.py (shared with the MCAP logger)


@dataclass(frozen=True)
class Series:
    """A per-sample array stream (`diff`, `tensor`): values[i] belongs to sample seq[i] at t_s[i]."""

    t_s: np.ndarray         # (N,) float64, unit time, s
    seq: np.ndarray         # (N,) int64, unwrapped sample counter
    values: np.ndarray      # (N, ...) float64: diff (N, P-1, 3) nT, tensor (N, 3, 3) nT/m
    cal_id: int             # calibration that produced it


_SERIES_HEAD = struct.Struct("<4sBIq")        # magic b"FXS1", ndim of one sample, n_samples, cal_id


def encode_series(t_s: np.ndarray, seq: np.ndarray, values: np.ndarray, cal_id: int) -> bytes:
    """`diff`/`tensor` payload: header, u32 dims of one sample, then t_s f8[N], seq i8[N], values f8[N, ...].

    >>> s = decode_series(encode_series(np.array([0.5]), np.array([7]), np.ones((1, 3, 3)), 2))
    >>> (s.values.shape, int(s.seq[0]), s.cal_id)
    ((1, 3, 3), 7, 2)
    """
    values = np.ascontiguousarray(values, "<f8")
    n = values.shape[0]
    if np.shape(t_s) != (n,) or np.shape(seq) != (n,):
        raise ValueError(f"series: expected t_s and seq of shape ({n},), got {np.shape(t_s)} and {np.shape(seq)}")
    tail = values.shape[1:]
    return b"".join([_SERIES_HEAD.pack(b"FXS1", len(tail), n, int(cal_id)),
                     struct.pack(f"<{len(tail)}I", *tail),
                     np.ascontiguousarray(t_s, "<f8").tobytes(), np.ascontiguousarray(seq, "<i8").tobytes(),
                     values.tobytes()])


def decode_series(data: bytes) -> Series:
    """Inverse of `encode_series`; a malformed payload is a DataError."""
    try:
        magic, ndim, n, cal_id = _SERIES_HEAD.unpack_from(data, 0)
        if magic != b"FXS1":
            raise ValueError(f"not a series (magic {magic!r})")
        off = _SERIES_HEAD.size
        tail = struct.unpack_from(f"<{ndim}I", data, off)
        off += 4 * ndim
        t_s = np.frombuffer(data, "<f8", n, off).astype(float)
        off += 8 * n
        seq = np.frombuffer(data, "<i8", n, off).astype(np.int64)
        off += 8 * n
        count = n * math.prod(tail)
        values = np.frombuffer(data, "<f8", count, off).astype(float).reshape((n, *tail))
        if off + 8 * count != len(data):
            raise ValueError(f"{len(data) - off - 8 * count} trailing bytes")
    except (struct.error, ValueError) as e:
        raise DataError(f"series: {e}") from None
    return Series(t_s=t_s, seq=seq, values=values, cal_id=int(cal_id))


def _json_bytes(obj: Any) -> bytes:
    return json.dumps(json_ready(obj), allow_nan=False, separators=(",", ":")).encode()


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------

DEFAULT_PORT = 7447
DEFAULT_LISTEN = [f"tcp/127.0.0.1:{DEFAULT_PORT}"]
_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "vsock", "serial")
_HOST_PORT = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):(\d{1,5})$")
_UNIT_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")
_KEY_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


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
        elif "listener" in low or "in use" in low:
            hint = ": is another fluxcal already listening there? choose another port in [zenoh] listen"
        elif "connect" in low:
            hint = ": is the service (or router) running and listening there?"
            if isinstance(cfg, ZenohConfig) and cfg.tls.enabled:
                hint += (" With TLS, also check the certificates: the other end's must be signed by this node's "
                         "root_ca and name the host in the endpoint, and with mutual TLS this node's must be "
                         "signed by the CA the other end trusts")
        raise BusError(f"zenoh session failed to open{where}: {msg}{hint}") from None


# --------------------------------------------------------------------------------------------
# Key expressions and streams
# --------------------------------------------------------------------------------------------

JSON = zenoh.Encoding.APPLICATION_JSON
RAW_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("fluxcal.raw.v1")
CORRECTED_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("fluxcal.corrected.v1")
SERIES_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("fluxcal.series.v1")


@dataclass(frozen=True)
class StreamSpec:
    """How one stream is encoded and what Zenoh may do with it under congestion."""

    encoding: zenoh.Encoding
    lossless: bool            # CongestionControl.BLOCK (True) or DROP
    priority: zenoh.Priority
    decode: Callable[[bytes], Any]


def _decode_json(data: bytes) -> Any:
    try:
        return json.loads(data)
    except (ValueError, UnicodeDecodeError) as e:
        raise DataError(f"JSON payload: {e}") from None


#: stream name -> spec. BLOCK for data that must not be lost, DROP for status that the next message replaces.
#: Separate priorities also keep the DROP streams from queueing behind a blocked BLOCK stream.
STREAMS: dict[str, StreamSpec] = {
    "raw": StreamSpec(RAW_ENCODING, True, zenoh.Priority.DATA, decode_raw),
    "corrected": StreamSpec(CORRECTED_ENCODING, True, zenoh.Priority.DATA, decode_corrected),
    "diff": StreamSpec(SERIES_ENCODING, True, zenoh.Priority.DATA, decode_series),
    "tensor": StreamSpec(SERIES_ENCODING, True, zenoh.Priority.DATA, decode_series),
    "calibration": StreamSpec(JSON, True, zenoh.Priority.INTERACTIVE_LOW, _decode_json),
    "health": StreamSpec(JSON, False, zenoh.Priority.DATA_LOW, _decode_json),
    "error": StreamSpec(JSON, False, zenoh.Priority.DATA_LOW, _decode_json),
}

#: commands the service accepts under fluxcal/<unit>/cmd/<name>, and whether they need a payload
COMMANDS: dict[str, str | None] = {
    "freeze": None,                      # stop updating the online estimate; keep the calibration in use
    "unfreeze": None,
    "reset": None,                       # restart the online estimate from nothing
    "apply": "calibration JSON text, or the path of a calibration file on the service's host",
    "add-effect": "effect name, e.g. temperature",
}


class Keys:
    """The key expressions of one unit.

    >>> Keys("grad1").stream("corrected")
    'fluxcal/grad1/corrected'
    >>> Keys("grad1").cmd("freeze")
    'fluxcal/grad1/cmd/freeze'
    """

    def __init__(self, unit: str) -> None:
        if not _UNIT_NAME.match(unit or ""):
            raise ConfigError(f"unit name {unit!r} is not allowed (allowed: 1-64 letters, digits, '_' or '-')")
        self.unit = unit
        self.root = f"fluxcal/{unit}"
        self.alive = f"{self.root}/alive"
        self.state = f"{self.root}/state"

    def stream(self, name: str) -> str:
        return f"{self.root}/{name}"

    def probe(self, probe_name: str) -> str:
        return f"{self.root}/corrected/{probe_name}"

    def cmd(self, name: str) -> str:
        return f"{self.root}/cmd/{name}"


# --------------------------------------------------------------------------------------------
# Service side
# --------------------------------------------------------------------------------------------

class Command:
    """A command from the bus, applied by the service's own thread; `reply` answers the client once.

    `payload` is the query's payload as text ("" when none). `expires_at` (time.monotonic()) is when the
    bus withdraws it unapplied if the service has not taken it by then (the client is told so).
    """

    def __init__(self, id: int, name: str, payload: str, key: str, query: zenoh.Query | None,
                 expires_at: float = math.inf) -> None:
        self.id = id
        self.name = name
        self.payload = payload
        self.key = key
        self.received_unix_s = time.time()
        self.expires_at = expires_at
        self._query = query
        self._lock = threading.Lock()

    @property
    def answered(self) -> bool:
        return self._query is None

    def reply(self, result: Mapping[str, Any]) -> bool:
        """Send {"id", "command", **result} as JSON on the command's own key; False if already answered or the
        client has gone (its timeout passed)."""
        with self._lock:
            q, self._query = self._query, None
        if q is None:
            return False
        try:
            q.reply(self.key, _json_bytes({"id": self.id, "command": self.name, **result}), encoding=JSON)
            return True
        except zenoh.ZError:
            return False
        finally:
            try:
                q.drop()                  # sends the final reply marker: the client stops waiting now
            except zenoh.ZError:
                pass

    def __repr__(self) -> str:
        return f"Command(id={self.id}, name={self.name!r}, payload={self.payload[:40]!r})"


#: a command waits at most this long for the service's thread (a client may ask for less with ?wait_s=)
COMMAND_WAIT_S = 5.0
#: a state query the service's thread has not answered within this long is answered from the last state
STATE_GRACE_S = 0.25
#: without queries, the service's thread refreshes the cached state this often (for those late answers)
STATE_REFRESH_S = 1.0
#: messages waiting for the bus's sender thread, at most (bytes); beyond it the oldest are dropped, counted
SEND_BACKLOG_BYTES = 16 << 20


class ServiceBus:
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
                 send_backlog_bytes: int = SEND_BACKLOG_BYTES) -> None:
        self.keys = Keys(unit)
        self.unit = unit
        self.state_fn = state_fn
        self.probe_names = list(probe_names) if probe_names is not None else None
        for name in self.probe_names or []:
            if not _KEY_CHUNK.match(name):
                raise ConfigError(f"probe name {name!r} cannot be a key segment (allowed: letters, digits, '_', '-', '.')")
        cfg_obj = zenoh_cfg if isinstance(zenoh_cfg, ZenohConfig) else None
        self.per_probe = per_probe if per_probe is not None else (cfg_obj.per_probe if cfg_obj else True)
        express = express if express is not None else (cfg_obj.express if cfg_obj else False)
        self.command_wait_s = float(command_wait_s)
        self.state_grace_s = float(state_grace_s)
        self.stats: dict[str, int] = {"commands_received": 0, "commands_refused": 0, "commands_expired": 0,
                                      "state_queries": 0, "state_queries_stale": 0, "publish_errors": 0}
        self.stats.update({f"published_{name}": 0 for name in STREAMS})
        self.stats["published_corrected_probe"] = 0
        self.stats["send_dropped"] = 0
        # what the service's thread publishes waits here for the sender thread, which alone calls put():
        # a slow or frozen subscriber (Zenoh's BLOCK congestion control) then holds back the sender, never
        # the service's reading, recording and processing
        self._outbox: deque[tuple[str, zenoh.Publisher, bytes]] = deque()
        self._outbox_bytes = 0
        self._sending = False
        self._out_cond = threading.Condition()
        self._send_backlog_bytes = int(send_backlog_bytes)
        self._sender: threading.Thread | None = None
        # commands and state queries wait here for the service's thread; one lock, one condition
        self._cond = threading.Condition()
        self._commands: deque[Command] = deque()
        self._command_queue_size = int(command_queue_size)
        self._state_queries: deque[tuple[float, zenoh.Query]] = deque()
        self._state_queue_size = 16
        self._state_cache: tuple[float, dict[str, Any]] | None = None
        self._ids = itertools.count(1)
        self._last_calibration: dict[str, Any] | None = None
        self._last_health: dict[str, Any] | None = None
        self._closed = False
        self._close_lock = threading.Lock()
        self._stop = threading.Event()
        self._watchdog: threading.Thread | None = None
        self._entities: list[Any] = []
        self._probe_pubs: dict[str, zenoh.Publisher] = {}
        if isinstance(zenoh_cfg, zenoh.Session):
            self.session, self._own_session = zenoh_cfg, False
        else:
            self.session, self._own_session = open_session(zenoh_cfg, self.keys.unit), True
        self._express = bool(express)
        try:
            self._pubs = {name: self._declare_pub(self.keys.stream(name), s) for name, s in STREAMS.items()}
            for name in (self.probe_names or []) if self.per_probe else []:
                self._probe_pubs[name] = self._declare_pub(self.keys.probe(name), STREAMS["corrected"])
            self._watchdog = threading.Thread(target=self._watch_late, daemon=True, name=f"fluxcal-bus-{unit}-late")
            self._watchdog.start()
            self._sender = threading.Thread(target=self._send_loop, daemon=True, name=f"fluxcal-bus-{unit}-send")
            self._sender.start()
            self._entities.append(self.session.declare_queryable(self.keys.state, self._on_state_query))
            for name in COMMANDS:
                self._entities.append(self.session.declare_queryable(self.keys.cmd(name), self._command_callback(name)))
            self._token = self.session.liveliness().declare_token(self.keys.alive)
        except BaseException:
            self.close()
            raise

    def _declare_pub(self, key: str, s: StreamSpec) -> zenoh.Publisher:
        pub = self.session.declare_publisher(
            key, encoding=s.encoding, priority=s.priority, express=self._express,
            congestion_control=zenoh.CongestionControl.BLOCK if s.lossless else zenoh.CongestionControl.DROP)
        self._entities.append(pub)
        return pub

    # --- zenoh callbacks: never block, never call zenoh except to refuse a query ------------------

    def _on_state_query(self, query: zenoh.Query) -> None:
        with self._cond:
            if len(self._state_queries) < self._state_queue_size and not self._closed:
                self._state_queries.append((time.monotonic(), query))
                self._cond.notify_all()
                return
        query.reply_err(_json_bytes({"error": "busy: too many state queries pending"}), encoding=JSON)

    def _command_callback(self, name: str) -> Callable[[zenoh.Query], None]:
        key = self.keys.cmd(name)

        def on_query(query: zenoh.Query) -> None:
            self.stats["commands_received"] += 1
            if self._closed:
                return self._refuse(query, name, "the service is stopping")
            try:
                payload = query.payload.to_bytes().decode("utf-8").strip() if query.payload is not None else ""
            except UnicodeDecodeError:
                return self._refuse(query, name, "payload is not UTF-8 text")
            if COMMANDS[name] is not None and not payload:
                return self._refuse(query, name, f"needs a payload: {COMMANDS[name]}")
            if name == "add-effect" and not re.fullmatch(r"[a-z][a-z0-9_\-]{0,63}", payload):
                return self._refuse(query, name, f"{payload!r} is not an effect name")
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
        query.reply_err(_json_bytes({"command": name, "ok": False, "error": why}), encoding=JSON)

    # --- the bus's own thread: late answers (never a zenoh callback) ----------------------------

    def _watch_late(self) -> None:
        while not self._stop.wait(0.02):
            now = time.monotonic()
            with self._cond:
                late_q = [q for t, q in self._state_queries if now - t >= self.state_grace_s]
                for _ in late_q:
                    self._state_queries.popleft()         # oldest first: the late ones are at the front
                expired = [c for c in self._commands if now >= c.expires_at]
                for c in expired:
                    self._commands.remove(c)
            for q in late_q:
                self.stats["state_queries_stale"] += 1
                self._reply_state(q, self._stale_state(now))
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
        st.setdefault("unit", self.unit)
        st["bus"] = dict(self.stats)
        st["time_unix_s"] = time.time()
        st["stale"] = True
        st["state_age_s"] = age
        return st

    # --- the service's thread ------------------------------------------------------------------

    def pending_commands(self) -> list[Command]:
        """Commands received since the last call, oldest first; answers pending `state` queries on the way.

        Call it from the service's loop between blocks; answer each command with `cmd.reply({...})`."""
        self._answer_state_queries()
        with self._cond:
            out = list(self._commands)
            self._commands.clear()
        return out

    def next_command(self, timeout: float | None = None) -> Command | None:
        """Wait up to `timeout` s for one command (for a service thread that only serves commands)."""
        self._answer_state_queries()
        with self._cond:
            self._cond.wait_for(lambda: self._commands or self._closed, timeout)
            return self._commands.popleft() if self._commands else None

    def _published_state(self) -> dict[str, Any]:
        st = dict((self._last_calibration or {}).get("state") or {"usable": False})
        if self._last_health is not None:
            st["health"] = self._last_health.get("counters")
        return st

    def state(self) -> dict[str, Any]:
        """What a `state` query answers: state_fn() (or the last calibration and health published) + identity."""
        st = dict(self.state_fn()) if self.state_fn is not None else self._published_state()
        st.setdefault("unit", self.unit)
        if self.probe_names is not None:
            st.setdefault("probe_names", self.probe_names)
        st["bus"] = dict(self.stats)
        st["time_unix_s"] = time.time()
        st["stale"] = False
        st["state_age_s"] = 0.0
        return st

    def _reply_state(self, q: zenoh.Query, st: dict[str, Any] | Exception) -> None:
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

    def _answer_state_queries(self) -> None:
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
            self._reply_state(q, st)

    # --- publishing (the service's thread) -------------------------------------------------------

    def _put(self, name: str, pub: zenoh.Publisher, payload: bytes) -> None:
        """Hand a message to the sender thread (counted as published_<name>). If the backlog is over its
        bound (subscribers that cannot keep up), the oldest waiting messages are dropped and counted."""
        if self._closed:
            raise BusError(f"publish on {self.keys.root}/{name} after the bus was closed")
        with self._out_cond:
            self._outbox.append((name, pub, payload))
            self._outbox_bytes += len(payload)
            while self._outbox_bytes > self._send_backlog_bytes and len(self._outbox) > 1:
                _, _, old = self._outbox.popleft()
                self._outbox_bytes -= len(old)
                self.stats["send_dropped"] += 1
            self.stats[f"published_{name}"] += 1
            if not self._sending:
                self._out_cond.notify()      # wake the sender only when idle: one wake-up per block, not per message

    def _send_loop(self) -> None:
        """The sender thread: put() every message in order, taking what waits in one go; ends when
        closing and nothing waits."""
        while True:
            with self._out_cond:
                while not self._outbox and not self._stop.is_set():
                    self._sending = False
                    self._out_cond.notify_all()           # flush() waits for this
                    self._out_cond.wait(0.5)
                if not self._outbox:
                    self._sending = False
                    self._out_cond.notify_all()
                    return
                self._sending = True
                name, pub, payload = self._outbox.popleft()
                self._outbox_bytes -= len(payload)
            try:
                pub.put(payload)
            except zenoh.ZError:
                self.stats["publish_errors"] += 1

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every message handed to the bus has been put (True) or `timeout` passed (False)."""
        deadline = time.monotonic() + timeout
        with self._out_cond:
            while self._outbox or self._sending:
                left = deadline - time.monotonic()
                if left <= 0 or self._sender is None or not self._sender.is_alive():
                    return not (self._outbox or self._sending)
                self._out_cond.wait(left)
        return True

    def publish_raw(self, block: SampleBlock) -> None:
        if block.n_samples:
            self._put("raw", self._pubs["raw"], encode_raw(block))

    def publish_corrected(self, block: CorrectedBlock) -> None:
        """`corrected` (everything), and `diff`, `tensor`, `corrected/<probe>` when they exist."""
        if not block.n_samples:
            return
        self._put("corrected", self._pubs["corrected"], encode_corrected(block))
        if block.diff_nT is not None:
            self._put("diff", self._pubs["diff"], encode_series(block.t_s, block.seq, block.diff_nT, block.cal_id))
        if block.tensor_nT_m is not None:
            self._put("tensor", self._pubs["tensor"],
                      encode_series(block.t_s, block.seq, block.tensor_nT_m, block.cal_id))
        if self.per_probe:
            names = self.probe_names or [f"s{k + 1}" for k in range(block.n_probes)]
            if len(names) != block.n_probes:
                raise DataError(f"corrected block has {block.n_probes} probes, the bus knows {len(names)}: {names}")
            for k, name in enumerate(names):
                pub = self._probe_pubs.get(name)
                if pub is None:
                    pub = self._probe_pubs[name] = self._declare_pub(self.keys.probe(name), STREAMS["corrected"])
                one = CorrectedBlock(t_s=block.t_s, seq=block.seq, corrected_nT=block.corrected_nT[:, k:k + 1],
                                     diff_nT=None, tensor_nT_m=None, center_nT=None, cal_id=block.cal_id)
                self._put("corrected_probe", pub, encode_corrected(one))

    def publish_calibration(self, record: Mapping[str, Any]) -> None:
        """A calibration event (kind, seq, t_s, ..., "state": {...}) as JSON; kept for `state` queries."""
        self._last_calibration = dict(record)
        self._put("calibration", self._pubs["calibration"],
                  _json_bytes({**record, "unit": self.unit, "time_unix_s": time.time()}))

    def publish_health(self, counters: Mapping[str, Any]) -> None:
        """{"counters": source counters, "bus": this bus's counters} as JSON; may be dropped under congestion."""
        msg = {"unit": self.unit, "time_unix_s": time.time(), "counters": dict(counters), "bus": dict(self.stats)}
        self._last_health = msg
        self._put("health", self._pubs["health"], _json_bytes(msg))

    def publish_error(self, rms_nT: Mapping[str, float], *, seq: int | None = None, t_s: float | None = None) -> None:
        """The model-vs-measurement error metric of a block, {"rms_nT": {channel: nT}}; may be dropped."""
        self._put("error", self._pubs["error"], _json_bytes({"unit": self.unit, "time_unix_s": time.time(),
                                                            "seq": seq, "t_s": t_s, "rms_nT": dict(rms_nT)}))

    def has_subscribers(self, stream: str) -> bool:
        """Whether any subscriber anywhere matches `stream` ("raw", ..., "corrected/<probe>"), e.g. to wait for
        a dashboard before a burst."""
        pub = self._probe_pubs.get(stream[10:]) if stream.startswith("corrected/") else self._pubs[stream]
        return pub is not None and bool(pub.matching_status.matching)

    # --- lifetime ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Answer what is pending, undeclare everything, close the session if the bus opened it. Idempotent."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self.flush(2.0)                              # what was published goes out first, if it can
        self._stop.set()
        with self._out_cond:
            self._out_cond.notify_all()
        for t in (self._watchdog, self._sender):
            if t is not None and t is not threading.current_thread():
                t.join(2.0)
        with self._out_cond:
            self.stats["send_dropped"] += len(self._outbox)   # a subscriber frozen past the flush: not sent
            self._outbox.clear()
        with self._cond:
            commands, self._commands = list(self._commands), deque()
            states, self._state_queries = [q for _, q in self._state_queries], deque()
            self._cond.notify_all()                  # a next_command() waiting returns None
        for cmd in commands:
            cmd.reply({"ok": False, "error": "the service is stopping; the command was not applied"})
        for q in states:                             # not state_fn(): the source may be closed already
            self._reply_state(q, BusError("the service is stopping"))
        token = getattr(self, "_token", None)
        for ent in [token, *self._probe_pubs.values(), *reversed(self._entities)]:
            if ent is None:
                continue
            try:
                ent.undeclare()
            except zenoh.ZError:
                pass
        self._entities.clear()
        self._probe_pubs.clear()
        if self._own_session:
            self.session.close()

    def __enter__(self) -> "ServiceBus":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------------
# Client side: dashboards, recorders, tests
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Message:
    """One decoded message: `value` is a SampleBlock (raw), CorrectedBlock (corrected, corrected/<probe>),
    Series (diff, tensor) or dict (calibration, health, error)."""

    stream: str
    key: str
    value: Any
    received_s: float = field(default=0.0)     # time.monotonic() when the reader thread took it


_STOP = object()


class BusClient:
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
        self.stats: dict[str, int] = {"decode_errors": 0, "dropped": 0, **{f"received_{s}": 0 for s in names}}
        self.last_decode_error = ""
        self._queue: queue.Queue[Message] = queue.Queue(maxsize=capacity)
        self._closed = threading.Event()
        self._subs: list[Any] = []
        self._threads: list[threading.Thread] = []
        if isinstance(zenoh_cfg, zenoh.Session):
            self.session, self._own_session = zenoh_cfg, False
        else:
            self.session, self._own_session = open_session(zenoh_cfg), True
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
        kwargs: dict[str, Any] = {"timeout": float(timeout)}
        if payload:
            kwargs["payload"] = payload.encode()
        replies = list(self.session.get(f"{key}?{parameters}" if parameters else key, **kwargs))
        for r in replies:
            if r.ok is not None:
                return _decode_json(r.ok.payload.to_bytes())
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
        if self._own_session:
            self.session.close()

    def __enter__(self) -> "BusClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def discover_units(session: zenoh.Session, timeout: float = 1.0) -> list[str]:
    """Names of the units whose liveliness token `fluxcal/<unit>/alive` is visible from `session`."""
    units = set()
    for r in session.liveliness().get("fluxcal/*/alive", timeout=timeout):
        if r.ok is not None:
            parts = str(r.ok.key_expr).split("/")
            if len(parts) == 3:
                units.add(parts[1])
    return sorted(units)
