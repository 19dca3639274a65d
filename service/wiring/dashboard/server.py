"""The dashboard's HTTP side: the page and its plot code from the package (no CDN: field machines have no
internet), and a small JSON API the page polls. A page polls; a closed tab sends nothing and costs nothing.

    GET  /                      the page (it carries this server's session token, see below)
    GET  /static/<file>         its scripts and style
    GET  /api/units             {"connected", "endpoints", "units": [{"unit", "status", "status_text"}], "message",
                                 "read_only", "refused_requests", "connections" (guard.py: waiting, closed idle,
                                 evicted at the cap, cut off slow)}
    GET  /api/calibration?unit=U  the calibration in use as a calibration file, which `apply` takes back
    GET  /api/effect?unit=U     the term the last diagnosis discovered, as an effect module (diagnose --write-effect)
    GET  /api/view?unit=U&series=N&raw=N&error=N
                                one unit's view (fluxcal.service.wiring.dashboard.view.UnitView.view): the history
                                rows after the numbers given, and the rest whole
    POST /api/command           {"unit", "command", "payload"} -> the unit's answer, as `fluxcal command`
    POST /api/diagnose          {"unit"} -> starts a diagnosis of the raw samples kept here

Any web page the operator's browser shows can send requests here; what stops it (docs/dashboard.md, "Safety"):
- every request's Host must name this host (loopback, an IP address, this machine's name): a page of another
  name resolved to this address (DNS rebinding) gets nothing, not even the data;
- a POST needs `Content-Type: application/json` (another origin cannot send that without a CORS preflight,
  which this server never grants), no foreign `Origin` or cross-site `Sec-Fetch-Site`, and the header
  `X-Fluxcal-Token` with this server's session token, which only the page served from here can read (it is
  in the page itself; no CORS header lets another origin read a response);
- with --read-only every POST is refused: no command, no diagnosis (it takes a core for tens of seconds).
Refused requests change nothing and say why (403, 415).
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import secrets
import socket
import sys
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlparse

from fluxcal.drivers.errors import FluxcalError
from fluxcal.drivers.text import printable
from fluxcal.service.io.bus import COMMANDS

from .guard import Guard
from .hub import Hub

_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".png": "image/png"}
#: largest request body taken (a calibration JSON for `apply`)
MAX_BODY = 1 << 20
#: the request header that carries the session token
TOKEN_HEADER = "X-Fluxcal-Token"
#: where the page carries its token: index.html's placeholder, replaced when served
_TOKEN_SLOT = b"__FLUXCAL_TOKEN__"
#: the page may load only its own scripts and style, and no other page may frame it (clickjacking)
_SECURITY_HEADERS = (("Content-Security-Policy", "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'; "
                                                 "base-uri 'none'; form-action 'none'"),
                     ("X-Frame-Options", "DENY"), ("X-Content-Type-Options", "nosniff"),
                     ("Referrer-Policy", "no-referrer"), ("Cross-Origin-Resource-Policy", "same-origin"))
READ_ONLY_REASON = "this dashboard is read-only (started with --read-only): no commands, no diagnosis"


def _static(name: str) -> bytes | None:
    if "/" in name or name.startswith("."):
        return None
    f = resources.files("fluxcal.service.wiring.dashboard").joinpath("static", name)
    return f.read_bytes() if f.is_file() else None


def _host_name(host_header: str) -> str | None:
    """The name in a Host header (`name:port`, `[v6]:port`, or without the port), lower case; None if malformed.

    >>> _host_name("LocalHost:8090"), _host_name("[::1]:80"), _host_name("10.0.0.5"), _host_name("a b")
    ('localhost', '::1', '10.0.0.5', None)
    """
    h = host_header.strip().lower()
    if h.startswith("["):
        name, sep, rest = h[1:].partition("]")
        if not sep or (rest and not (rest.startswith(":") and rest[1:].isdigit())):
            return None
        return name
    name, _, port = h.partition(":")
    if (port and not port.isdigit()) or not name or any(c in name for c in " /\\@?#"):
        return None
    return name


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class _Handler(BaseHTTPRequestHandler):
    server: DashboardServer
    protocol_version = "HTTP/1.1"

    def log_message(self, fmt: str, *args: Any) -> None:      # quiet: the page polls several times a second
        pass

    def _send(self, status: int, body: bytes, ctype: str, extra: tuple[tuple[str, str], ...] = ()) -> None:
        self.close_connection = True          # one request a connection: no worker waits on a kept-alive socket
        self.send_response(status)
        self.send_header("Connection", "close")
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in _SECURITY_HEADERS + extra:
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj: Any, status: int = 200) -> None:
        self._send(status, json.dumps(obj, allow_nan=False, separators=(",", ":")).encode(), "application/json")

    def _download(self, unit: str, make: Callable[[str], str], ctype: str, filename: str) -> None:
        """A unit's file to save (its calibration, a discovered effect), or 409 with why there is none yet."""
        try:
            text = make(unit)
        except FluxcalError as e:
            self._json({"error": str(e)}, 409)
            return
        name = "".join(c for c in unit if c.isalnum() or c in "_-") or "unit"
        self._send(200, text.encode(), ctype,
                   (("Content-Disposition", f'attachment; filename="{filename.format(name)}"'),))

    def _refuse(self, status: int, why: str) -> None:
        self.server.count_refused(why)
        self._json({"ok": False, "error": why}, status)

    def _host_refusal(self) -> str | None:
        """Why this request's Host is not one of this server's names (DNS rebinding), or None."""
        host = self.headers.get("Host")
        if host is None:
            return "no Host header"
        name = _host_name(host)
        if name is None or not self.server.host_allowed(name):
            return (f"Host {host!r} is not this dashboard's address (allowed: an IP address, localhost or this "
                    f"machine's name {socket.gethostname()!r}): a page of another name is refused")
        return None

    def _post_refusal(self) -> tuple[int, str] | None:
        """Why this POST cannot be from this server's own page, or None: content type, origin, token."""
        if self.server.read_only:
            return 403, READ_ONLY_REASON
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return 415, f"Content-Type {ctype or 'none'!r} refused (allowed: application/json)"
        origin = self.headers.get("Origin")
        if origin is not None and origin != f"http://{self.headers.get('Host', '')}":
            return 403, f"a request from another origin ({origin}) is refused"
        site = (self.headers.get("Sec-Fetch-Site") or "same-origin").lower()
        if site not in ("same-origin", "none"):
            return 403, f"a {site} request is refused (Sec-Fetch-Site)"
        token = self.headers.get(TOKEN_HEADER) or ""
        if not hmac.compare_digest(token.encode(), self.server.token.encode()):
            return 403, (f"{'no' if not token else 'a wrong'} {TOKEN_HEADER} header: a request needs the token of "
                         f"the page this dashboard serves (reload the page after a restart of the dashboard)")
        return None

    def do_GET(self) -> None:
        self.server.guard.request_read(self.connection)      # the request is in: answered from here on
        why = self._host_refusal()
        if why is not None:
            self._refuse(403, why)
            return
        url = urlparse(self.path)
        q = {k: v[-1] for k, v in parse_qs(url.query).items()}
        hub = self.server.hub
        try:
            if url.path in ("/", "/index.html"):
                page = (_static("index.html") or b"").replace(_TOKEN_SLOT, self.server.token.encode())
                self._send(200, page, _TYPES[".html"])
            elif url.path.startswith("/static/"):
                name = url.path[len("/static/"):]
                body = _static(name)
                if body is None:
                    self._json({"error": f"no such file: {name}"}, 404)
                else:
                    self._send(200, body, _TYPES.get(name[name.rfind("."):], "application/octet-stream"))
            elif url.path == "/favicon.ico":
                self._send(204, b"", "image/x-icon")
            elif url.path == "/api/units":
                self._json({**hub.units(), "read_only": self.server.read_only,
                            "read_only_reason": READ_ONLY_REASON if self.server.read_only else "",
                            "refused_requests": dict(self.server.refused), "connections": self.server.guard.stats()})
            elif url.path == "/api/calibration":
                self._download(q.get("unit", ""), lambda u: json.dumps(hub.calibration_file(u), indent=1),
                               "application/json", "{}-calibration.json")
            elif url.path == "/api/effect":
                self._download(q.get("unit", ""), hub.discovered_effect, "text/x-python; charset=utf-8",
                               "{}_discovered.py")
            elif url.path == "/api/view":
                since = {k: int(q.get(k, 0) or 0) for k in ("series", "raw", "error")}
                self._json(hub.view(q.get("unit", ""), since))
            else:
                self._json({"error": f"no such page: {url.path}"}, 404)
        except KeyError as e:
            self._json({"error": f"unit {str(e)[:60]} is not followed by this dashboard"}, 404)
        except ValueError as e:
            self._json({"error": f"bad request: {e}"}, 400)
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as e:                    # noqa: BLE001 - a request never ends in a dropped connection
            self._failed(e)

    def _body(self) -> dict[str, Any] | None:
        """The request's JSON object, or None after answering why not (size, depth, shape)."""
        try:
            n = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            n = -1
        if n < 0 or n > MAX_BODY:
            self._refuse(413 if n > MAX_BODY else 400, f"request body of {self.headers.get('Content-Length')!r} "
                                                       f"bytes refused (allowed: 0 to {MAX_BODY})")
            return None
        raw = self.rfile.read(n) if n else b"{}"
        self.server.guard.request_read(self.connection)      # the whole request is in: answered from here on
        try:
            body = json.loads(raw)
        except (ValueError, RecursionError) as e:
            why = "nested too deeply" if isinstance(e, RecursionError) else str(e)
            self._refuse(400, f"bad request: the body is not JSON ({why})")
            return None
        if not isinstance(body, dict):
            self._refuse(400, f"bad request: expected a JSON object, got {type(body).__name__}")
            return None
        return body

    def do_POST(self) -> None:
        why = self._host_refusal()
        if why is not None:
            self._refuse(403, why)
            return
        refusal = self._post_refusal()
        if refusal is not None:
            self.close_connection = True              # the body, if any, is not read
            self._refuse(*refusal)
            return
        url = urlparse(self.path)
        hub = self.server.hub
        try:
            body = self._body()
            if body is None:
                return
            unit = body.get("unit", "")
            if not isinstance(unit, str):
                self._refuse(400, f"bad request: unit must be a name, got {type(unit).__name__}")
            elif url.path == "/api/command":
                name = body.get("command", "")
                if not isinstance(name, str) or name not in COMMANDS:
                    self._refuse(400, f"command {str(name)[:40]!r} is not allowed (allowed: {', '.join(COMMANDS)})")
                    return
                payload, why = command_payload(name, body.get("payload"))
                if why:
                    self._refuse(400, why)
                    return
                self._json(hub.command(unit, name, payload))
            elif url.path == "/api/diagnose":
                self._json(hub.diagnose(unit))
            else:
                self._json({"ok": False, "error": f"no such action: {url.path}"}, 404)
        except KeyError as e:
            self._json({"ok": False, "error": f"unit {str(e)[:60]} is not followed by this dashboard"}, 404)
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as e:                    # noqa: BLE001 - a request never ends in a dropped connection
            self._failed(e)

    def _failed(self, e: Exception) -> None:
        """A request the dashboard could not serve: a 500 that says why (and the first of each kind on stderr)."""
        try:
            self._refuse(500, f"the dashboard failed on this request: {type(e).__name__}: {str(e)[:200]}")
        except OSError:
            pass

    def _refuse_other(self) -> None:
        why = self._host_refusal()
        self.close_connection = True
        self._refuse(403 if why else 405, why or f"method {self.command} is not allowed here (GET and POST only; "
                                                  f"no cross-origin requests)")

    # a CORS preflight (OPTIONS) gets no Access-Control-Allow-* header: the browser then sends nothing
    do_OPTIONS = do_PUT = do_DELETE = do_PATCH = _refuse_other


#: the kinds refusals are counted by, from how their reasons begin: a fixed set, so that a request's own words (a
#: Host, a Content-Type, a command's name) never become a key and the counts cannot grow without bound
_REFUSAL_KINDS = (("no Host header", "host"), ("Host ", "host"), ("Content-Type ", "content type"),
                  ("a request from another origin", "origin"), ("request body of", "body size"),
                  ("bad request:", "bad request"), ("command ", "command"), ("apply", "apply payload"),
                  ("the dashboard failed", "failed"), ("method ", "method"))


def refusal_kind(why: str) -> str:
    """The kind a refusal's reason is counted by (one of a fixed set; "other" for a reason of no known kind)."""
    for start, kind in _REFUSAL_KINDS:
        if why.startswith(start):
            return kind
    if why.endswith("(Sec-Fetch-Site)"):
        return "fetch site"
    if TOKEN_HEADER in why.split(":")[0]:
        return "token"
    if "the payload must be" in why:
        return "payload"
    return "other"


def command_payload(name: str, payload: Any) -> tuple[str, str]:
    """(the payload text sent to the unit, why it is refused or ""). `apply` carries a calibration itself, as a
    JSON object or its text, never a path: the dashboard's host and the unit's may differ, and a path would have
    the unit open a file of its host's choosing (issue 27)."""
    if payload is None:
        payload = ""
    if name == "apply":
        if isinstance(payload, dict):
            try:
                return json.dumps(payload, allow_nan=True), ""
            except (ValueError, RecursionError):
                return "", "apply: the calibration cannot be written as JSON (nested too deeply)"
        if not isinstance(payload, str) or not payload.strip():
            return "", "apply takes a calibration: the JSON text of a calibration file (choose or paste one)"
        try:
            cal = json.loads(payload)
        except RecursionError:
            return "", "apply: the calibration is not JSON (nested too deeply)"
        except ValueError as e:
            looks_like_path = not payload.lstrip().startswith(("{", "["))
            return "", ("apply takes the calibration itself (the JSON text of a calibration file), not a path: "
                        "choose the file in the page or paste its text" if looks_like_path
                        else f"apply: the calibration is not JSON ({e})")
        if not isinstance(cal, dict):
            return "", f"apply: a calibration is a JSON object, got {type(cal).__name__}"
        return payload, ""
    if not isinstance(payload, str):
        return "", f"{name}: the payload must be text, got {type(payload).__name__}"
    return payload, ""


class DashboardServer(ThreadingHTTPServer):
    """Serves the page and the API for `hub` on (host, port); port 0 takes a free one (see `url`).
    `token` is this server's session token (a new random one by default); `refused` counts refused requests
    by kind of reason (and with `say_refusals` the first of each kind is said on stderr). Its connections are
    watched by a Guard (guard.py: idle and slow clients closed, a cap with a counter, one request each)."""

    daemon_threads = True
    request_queue_size = 128          # a burst of connections waits in the kernel, not refused, while the guard takes them

    def __init__(self, hub: Hub, host: str = "127.0.0.1", port: int = 8090, read_only: bool = False,
                 token: str | None = None, say_refusals: bool = False) -> None:
        self.hub = hub
        self.read_only = read_only
        self.token = token or secrets.token_urlsafe(32)
        self.refused: dict[str, int] = {}
        self.say_refusals = say_refusals
        self._refused_lock = threading.Lock()
        self.address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._names = {"localhost", "localhost.", socket.gethostname().lower(), socket.getfqdn().lower()}
        if not _is_ip(host):
            self._names.add(host.lower())
        super().__init__((host, port), _Handler)
        self._thread: threading.Thread | None = None
        self.guard = Guard(self, self._say if say_refusals else None)

    @staticmethod
    def _say(text: str) -> None:
        print(f"fluxcal dashboard: {text}", file=sys.stderr, flush=True)

    def serve_forever(self, poll_interval: float = 0.2) -> None:
        self.guard.run(poll_interval)

    def shutdown(self) -> None:
        self.guard.stop()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(10)

    def server_close(self) -> None:
        super().server_close()
        self.guard.close()

    def host_allowed(self, name: str) -> bool:
        """A Host name this server answers to: an IP address (a page cannot rebind a name to one), localhost,
        this machine's names or the name it was told to listen on. The port is not checked: `ssh -L` may forward
        another local port, and a page of another origin on this host is refused by Origin and token instead."""
        return _is_ip(name) or name in self._names or name.endswith(".localhost")

    def count_refused(self, why: str) -> None:
        """Count a refused request by the kind of reason; the first of each kind is said on stderr (a page of
        another origin trying its luck is worth an operator's attention, its hundredth try is not)."""
        key = refusal_kind(why)
        with self._refused_lock:
            self.refused[key] = self.refused.get(key, 0) + 1
            first = self.refused[key] == 1
        if first and self.say_refusals:
            print(f"fluxcal dashboard: refused a request: {printable(why[:200])} (further ones of this kind are "
                  f"counted in /api/units)", file=sys.stderr, flush=True)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        host = {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(host, host)
        return f"http://{f'[{host}]' if ':' in host else host}:{port}/"

    def start(self) -> DashboardServer:
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True,
                                        name="fluxcal-dashboard-http")
        self._thread.start()
        return self

    def stop(self) -> None:
        self.shutdown()
        self.server_close()
