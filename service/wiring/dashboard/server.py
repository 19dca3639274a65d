"""The dashboard's HTTP side: the page and its plot code from the package (no CDN: field machines have no
internet), and a small JSON API the page polls. A page polls; a closed tab sends nothing and costs nothing.

    GET  /                      the page
    GET  /static/<file>         its scripts and style
    GET  /api/units             {"connected", "endpoints", "units": [{"unit", "status", "status_text"}], "message"}
    GET  /api/calibration?unit=U  the calibration in use as a calibration file, which `apply` takes back
    GET  /api/view?unit=U&series=N&raw=N&error=N
                                one unit's view (service.wiring.dashboard.view.UnitView.view): the history
                                rows after the numbers given, and the rest whole
    POST /api/command           {"unit", "command", "payload"} -> the unit's answer, as `fluxcal command`
    POST /api/diagnose          {"unit"} -> starts a diagnosis of the raw samples kept here
"""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlparse

from drivers.errors import FluxcalError
from service.io.bus import COMMANDS

from .hub import Hub

_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".png": "image/png"}
#: largest request body taken (a calibration JSON for `apply`)
MAX_BODY = 1 << 20


def _static(name: str) -> bytes | None:
    if "/" in name or name.startswith("."):
        return None
    f = resources.files("service.wiring.dashboard").joinpath("static", name)
    return f.read_bytes() if f.is_file() else None


class _Handler(BaseHTTPRequestHandler):
    server: DashboardServer
    protocol_version = "HTTP/1.1"

    def log_message(self, fmt: str, *args: Any) -> None:      # quiet: the page polls several times a second
        pass

    def _send(self, status: int, body: bytes, ctype: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj: Any, status: int = 200) -> None:
        self._send(status, json.dumps(obj, allow_nan=False, separators=(",", ":")).encode(), "application/json")

    def do_GET(self) -> None:
        url = urlparse(self.path)
        q = {k: v[-1] for k, v in parse_qs(url.query).items()}
        hub = self.server.hub
        try:
            if url.path in ("/", "/index.html"):
                self._send(200, _static("index.html") or b"", _TYPES[".html"])
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
                self._json({**hub.units(), "read_only": self.server.read_only})
            elif url.path == "/api/calibration":
                unit = q.get("unit", "")
                try:
                    cal = hub.calibration_file(unit)
                except FluxcalError as e:
                    self._json({"error": str(e)}, 409)
                    return
                body = json.dumps(cal, indent=1).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Disposition", f'attachment; filename="{unit}-calibration.json"')
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
            elif url.path == "/api/view":
                since = {k: int(q.get(k, 0) or 0) for k in ("series", "raw", "error")}
                self._json(hub.view(q.get("unit", ""), since))
            else:
                self._json({"error": f"no such page: {url.path}"}, 404)
        except KeyError as e:
            self._json({"error": f"unit {e} is not followed by this dashboard"}, 404)
        except ValueError as e:
            self._json({"error": f"bad request: {e}"}, 400)
        except (BrokenPipeError, ConnectionResetError):
            pass

    def do_POST(self) -> None:
        url = urlparse(self.path)
        hub = self.server.hub
        try:
            n = int(self.headers.get("Content-Length") or 0)
            if n > MAX_BODY:
                self._json({"error": f"request body of {n} bytes (at most {MAX_BODY})"}, 413)
                return
            body = json.loads(self.rfile.read(n) or b"{}")
            unit = str(body.get("unit", ""))
            if self.server.read_only and url.path in ("/api/command",):
                self._json({"ok": False, "error": "this dashboard is read-only (started with --read-only)"}, 403)
            elif url.path == "/api/command":
                name = str(body.get("command", ""))
                if name not in COMMANDS:
                    self._json({"ok": False, "error": f"command {name!r} is not allowed (allowed: "
                                                      f"{', '.join(COMMANDS)})"}, 400)
                    return
                self._json(hub.command(unit, name, str(body.get("payload") or "")))
            elif url.path == "/api/diagnose":
                self._json(hub.diagnose(unit))
            else:
                self._json({"error": f"no such action: {url.path}"}, 404)
        except KeyError as e:
            self._json({"ok": False, "error": f"unit {e} is not followed by this dashboard"}, 404)
        except (ValueError, AttributeError) as e:
            self._json({"ok": False, "error": f"bad request: {e}"}, 400)
        except (BrokenPipeError, ConnectionResetError):
            pass


class DashboardServer(ThreadingHTTPServer):
    """Serves the page and the API for `hub` on (host, port); port 0 takes a free one (see `url`)."""

    daemon_threads = True

    def __init__(self, hub: Hub, host: str = "127.0.0.1", port: int = 8090, read_only: bool = False) -> None:
        self.hub = hub
        self.read_only = read_only
        super().__init__((host, port), _Handler)
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{port}/"

    def start(self) -> DashboardServer:
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True,
                                        name="fluxcal-dashboard-http")
        self._thread.start()
        return self

    def stop(self) -> None:
        self.shutdown()
        self.server_close()
