"""The web dashboard's HTTP API against requests that are not its own page's (issue 27), in raw HTTP: another
origin, a text/plain "simple" POST, no or a wrong token, a Host of another name (DNS rebinding), a preflight,
bodies too deep or too large, a path as `apply`'s payload, and a read-only dashboard. Each must change
nothing: no command reaches the unit (a stand-in that records what it receives and answers ok) and the
dashboard's own command log stays empty. Its own page's requests, the positive control, still go through.
The same from a real browser on another origin: tests/e2e/test_dashboard_browser.py."""

from __future__ import annotations

import http.client
import json
import time
from urllib.parse import urlparse

import numpy as np
import pytest
from test_dashboard import page_token
from test_watch import Publisher, corrected_block

from fluxcal.drivers.block import SampleBlock
from fluxcal.service.wiring.dashboard import DashboardServer, Hub

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.wiring.dashboard.guard",)


class RecordingUnit(Publisher):
    """The service stand-in of tests/wiring/test_watch.py that also takes commands: each one is recorded and answered ok,
    as a unit that applies everything would."""

    def __init__(self, **kw) -> None:
        self.received: list[tuple[str, str]] = []
        super().__init__(**kw)

    def run(self) -> None:
        i = 0
        while not self.stop.wait(0.05):
            for cmd in self.bus.pending_commands():
                self.received.append((cmd.name, cmd.payload))
                cmd.reply({"ok": True})
            cb = corrected_block(i)
            self.bus.publish_raw(SampleBlock(t_s=cb.t_s, seq=cb.seq, field_nT=cb.corrected_nT * 1.1,
                                             temp_C=np.zeros((10, 2)), flags=np.zeros(10, np.uint8)))
            self.bus.publish_corrected(cb)
            i += 1


@pytest.fixture
def dashboard():
    """(unit, server, hub) of a dashboard following a recording unit; read_only as asked."""
    made = []

    def make(read_only: bool = False):
        unit = RecordingUnit()
        hub = Hub([unit.ep], ["u1"]).start()
        server = DashboardServer(hub, "127.0.0.1", 0, read_only=read_only).start()
        made.append((unit, server, hub))
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not hub.view("u1", {})["series"]:
            time.sleep(0.1)                                         # connected: a command could reach the unit
        assert hub.view("u1", {})["series"], "the dashboard never received the stand-in's data"
        return unit, server, hub

    yield make
    for unit, server, hub in made:
        server.stop()
        hub.close()
        unit.close()


def request(server: DashboardServer, method: str, path: str, body: bytes | None = None,
            headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], dict]:
    """One raw HTTP request with exactly the headers given (Host too: none unless given), and Content-Length."""
    u = urlparse(server.url)
    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=10)
    try:
        hdrs = dict(headers or {})
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        for k, v in hdrs.items():
            conn.putheader(k, v)
        if body is not None:
            conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        r = conn.getresponse()
        raw = r.read()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, json.loads(raw) if raw.startswith(b"{") else {}
    finally:
        conn.close()


def own_headers(server: DashboardServer, token: str) -> dict[str, str]:
    """What the dashboard's own page sends with a POST (Chromium adds Origin and Sec-Fetch-Site)."""
    host = server.url.split("/")[2]
    return {"Host": host, "Origin": f"http://{host}", "Sec-Fetch-Site": "same-origin",
            "Content-Type": "application/json", "X-Fluxcal-Token": token}


FREEZE = json.dumps({"unit": "u1", "command": "freeze"}).encode()


def assert_nothing_reached_the_unit(unit: RecordingUnit, hub: Hub) -> None:
    time.sleep(0.5)                                                  # a command would have arrived by now
    assert unit.received == [], unit.received
    assert hub.view("u1", {})["commands"] == []


def test_requests_not_from_the_dashboards_own_page_change_nothing(dashboard):
    unit, server, hub = dashboard()
    token = page_token(server.url)
    own = own_headers(server, token)
    host = own["Host"]
    port = host.rsplit(":", 1)[1]
    attempts = {
        # the "simple" cross-origin POST any web page can send without a preflight: text/plain, another origin
        "text/plain from another origin": (415, {"Host": host, "Origin": "http://evil.example.com",
                                                 "Sec-Fetch-Site": "cross-site", "Content-Type": "text/plain"}),
        "text/plain, no origin": (415, {**own, "Content-Type": "text/plain;charset=UTF-8"}),
        "form-encoded": (415, {**own, "Content-Type": "application/x-www-form-urlencoded"}),
        "no content type": (415, {k: v for k, v in own.items() if k != "Content-Type"}),
        "JSON from another origin, right token": (403, {**own, "Origin": "http://evil.example.com"}),
        "JSON, Origin null (a sandboxed frame)": (403, {**own, "Origin": "null"}),
        "JSON, cross-site fetch": (403, {**own, "Sec-Fetch-Site": "cross-site"}),
        "JSON, same-site fetch of another port": (403, {**own, "Sec-Fetch-Site": "same-site"}),
        "JSON, no token": (403, {k: v for k, v in own.items() if k != "X-Fluxcal-Token"}),
        "JSON, wrong token": (403, {**own, "X-Fluxcal-Token": token[:-2] + "xx"}),
        "JSON, empty token": (403, {**own, "X-Fluxcal-Token": ""}),
        # DNS rebinding: a name of the attacker's resolved to 127.0.0.1; to the browser it is the same origin
        "rebound name, right token": (403, {**own, "Host": f"evil.example.com:{port}",
                                            "Origin": f"http://evil.example.com:{port}"}),
        "no Host": (403, {k: v for k, v in own.items() if k != "Host"}),
        "malformed Host": (403, {**own, "Host": "a b:1"}),
    }
    for what, (status, headers) in attempts.items():
        code, hdrs, body = request(server, "POST", "/api/command", FREEZE, headers)
        assert code == status, (what, code, body)
        assert body["ok"] is False and body["error"], what
        assert "access-control-allow-origin" not in hdrs, what
    for what, headers in (("no token", {k: v for k, v in own.items() if k != "X-Fluxcal-Token"}),
                          ("text/plain from another origin", attempts["text/plain from another origin"][1])):
        code, _, _ = request(server, "POST", "/api/diagnose", json.dumps({"unit": "u1"}).encode(), headers)
        assert code in (403, 415), what
    assert hub.view("u1", {})["diagnosis"]["status"] == "none"
    # a CORS preflight gets no permission: the browser then sends nothing
    code, hdrs, _ = request(server, "OPTIONS", "/api/command", None, {
        "Host": host, "Origin": "http://evil.example.com", "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "content-type,x-fluxcal-token"})
    assert code == 405 and not any(k.startswith("access-control-") for k in hdrs)
    assert_nothing_reached_the_unit(unit, hub)
    # a rebound name reads nothing either: not the page (its token), not the data
    for path in ("/", "/api/view?unit=u1", "/api/units", "/api/calibration?unit=u1"):
        code, _, body = request(server, "GET", path, None, {"Host": f"evil.example.com:{port}"})
        assert code == 403 and "not this dashboard's address" in body["error"], path
    code, _, units = request(server, "GET", "/api/units", None, {"Host": host})
    assert code == 200 and sum(units["refused_requests"].values()) >= len(attempts) + 2 + 1 + 4
    # counted by kind, from a fixed set: the requests' own Hosts, types and origins are no keys (review, stop 32)
    from fluxcal.service.wiring.dashboard.server import _REFUSAL_KINDS

    kinds = {k for _, k in _REFUSAL_KINDS} | {"fetch site", "token", "payload", "other"}
    assert set(units["refused_requests"]) <= kinds, units["refused_requests"]
    assert units["refused_requests"]["host"] >= 4
    # the positive control: the page's own request goes through, once
    code, _, body = request(server, "POST", "/api/command", FREEZE, own)
    assert code == 200 and body["ok"] is True and body["command"] == "freeze"
    assert unit.received == [("freeze", "")]
    # names of this host are its own: localhost, an IP address; the page and the data come back
    for name in ("localhost", "127.0.0.1", "LOCALHOST"):
        code, hdrs, _ = request(server, "GET", "/api/units", None, {"Host": f"{name}:{port}"})
        assert code == 200, name
    code, hdrs, _ = request(server, "GET", "/", None, {"Host": host})
    assert code == 200 and "frame-ancestors 'none'" in hdrs["content-security-policy"]
    assert hdrs["x-frame-options"] == "DENY"


def test_bad_bodies_and_path_payloads_are_refused_and_the_dashboard_keeps_serving(dashboard):
    unit, server, hub = dashboard()
    own = own_headers(server, page_token(server.url))
    deep = b'{"unit": "u1", "command": "apply", "payload": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    bad = {
        "nested 100,000 deep": (deep, 400, "nested too deeply"),
        "not JSON": (b"freeze", 400, "not JSON"),
        "a list": (b"[1, 2]", 400, "expected a JSON object"),
        "unit a number": (json.dumps({"unit": 3, "command": "freeze"}).encode(), 400, "unit must be a name"),
        "command not allowed": (json.dumps({"unit": "u1", "command": "shutdown"}).encode(), 400, "not allowed"),
        "command a list": (json.dumps({"unit": "u1", "command": ["freeze"]}).encode(), 400, "not allowed"),
        "apply of a path": (json.dumps({"unit": "u1", "command": "apply", "payload": "/etc/shadow"}).encode(), 400,
                            "not a path"),
        "apply of a relative path": (json.dumps({"unit": "u1", "command": "apply", "payload": "cal.json"}).encode(),
                                     400, "not a path"),
        "apply of nothing": (json.dumps({"unit": "u1", "command": "apply"}).encode(), 400, "apply takes a calibration"),
        "apply of a JSON list": (json.dumps({"unit": "u1", "command": "apply", "payload": "[1]"}).encode(), 400,
                                 "a JSON object"),
        "apply of broken JSON": (json.dumps({"unit": "u1", "command": "apply", "payload": "{\"probes\": "}).encode(),
                                 400, "not JSON"),
        "apply of a deep payload": (json.dumps({"unit": "u1", "command": "apply",
                                                "payload": "[" * 50_000 + "]" * 50_000}).encode(), 400,
                                    "nested too deeply"),
        "add-effect of a number": (json.dumps({"unit": "u1", "command": "add-effect", "payload": 7}).encode(), 400,
                                   "must be text"),
        "unknown unit": (json.dumps({"unit": "nobody", "command": "freeze"}).encode(), 404, "not followed"),
    }
    for what, (body, status, says) in bad.items():
        code, _, answer = request(server, "POST", "/api/command", body, own)
        assert code == status and says in answer["error"], (what, code, answer)
    # a body too large is refused from its announced length, before it is read
    code, _, answer = request(server, "POST", "/api/command", None, {**own, "Content-Length": str(2 << 20)})
    assert code == 413 and "allowed: 0 to 1048576" in answer["error"]
    code, _, answer = request(server, "POST", "/api/command", None, {**own, "Content-Length": "-5"})
    assert code == 400
    assert_nothing_reached_the_unit(unit, hub)
    # still serving, and a calibration given as content (text or an object) reaches the unit as that content
    cal = {"format": "fluxcal-calibration", "probes": [{"name": "s1", "offset_nT": [1, 2, 3]}]}
    for payload in (json.dumps(cal), cal):
        code, _, answer = request(server, "POST", "/api/command",
                                  json.dumps({"unit": "u1", "command": "apply", "payload": payload}).encode(), own)
        assert code == 200 and answer["ok"] is True, answer
    assert [name for name, _ in unit.received] == ["apply", "apply"]
    assert all(json.loads(text) == cal for _, text in unit.received)


def test_a_read_only_dashboard_refuses_commands_and_diagnosis_even_from_its_own_page(dashboard):
    unit, server, hub = dashboard(read_only=True)
    own = own_headers(server, page_token(server.url))
    reset = json.dumps({"unit": "u1", "command": "reset"}).encode()
    for path, body in (("/api/command", FREEZE), ("/api/command", reset),
                       ("/api/diagnose", json.dumps({"unit": "u1"}).encode())):
        code, _, answer = request(server, "POST", path, body, own)
        assert code == 403 and "read-only (started with --read-only)" in answer["error"], (path, answer)
    time.sleep(0.3)
    assert hub.view("u1", {})["diagnosis"]["status"] == "none"       # no diagnosis started
    assert_nothing_reached_the_unit(unit, hub)
    code, _, units = request(server, "GET", "/api/units", None, {"Host": own["Host"]})
    assert units["read_only"] is True and "no diagnosis" in units["read_only_reason"]


# --- idle and slow clients (issue 38, build 6) ---------------------------------------------------------------

def _get_units(port: int, timeout: float = 3.0) -> tuple[int, dict]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        conn.request("GET", "/api/units", headers={"Host": f"127.0.0.1:{port}"})
        r = conn.getresponse()
        return r.status, json.loads(r.read())
    finally:
        conn.close()


@pytest.mark.slow
def test_real_users_are_served_while_1000_idle_sockets_are_open_under_1024_descriptors():
    """`fluxcal dashboard` in a process limited to 1,024 descriptors; 1,000 sockets connect and send nothing. Before,
    every real request timed out while they lasted (one thread each, no timeout), and nothing was said."""
    import resource
    import socket
    import subprocess
    import sys

    from test_zenoh_security import free_port

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "dashboard", "--connect",
                             f"tcp/127.0.0.1:{free_port()}", "--listen", f"127.0.0.1:{port}", "--seconds", "60"],
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024)))
    idle: list[socket.socket] = []
    try:
        assert "fluxcal dashboard: http://127.0.0.1" in proc.stderr.readline()
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft < 1200:                                          # this test's own 1,000 sockets
            resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, 4096), hard))
        for _ in range(1000):
            idle.append(socket.create_connection(("127.0.0.1", port), timeout=5))
        served, slowest = 0, 0.0
        for _ in range(20):
            t0 = time.monotonic()
            status, units = _get_units(port)
            served += status == 200
            slowest = max(slowest, time.monotonic() - t0)
        assert served == 20 and slowest < 2.0, (served, slowest)
        c = units["connections"]
        assert c["evicted"] >= 900 and c["waiting"] <= c["max_waiting"] == 64, c
    finally:
        for s in idle:
            s.close()
        proc.terminate()
        err = proc.communicate(timeout=20)[1]
    assert "more than 64 connections waited without sending a request: the oldest are closed" in err, err


def test_idle_and_slow_clients_are_closed_counted_and_the_page_still_served(dashboard):
    import socket

    unit, server, hub = dashboard()
    g = server.guard
    g.idle_s, g.request_s = 0.3, 0.6
    port = int(server.url.rsplit(":", 1)[1].strip("/"))
    idle = socket.create_connection(("127.0.0.1", port))
    slow = socket.create_connection(("127.0.0.1", port))
    slow.sendall(b"GET /api/units HTTP/1.1\r\n")               # then a byte now and then: never the whole request
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and not (g.stats()["idle_closed"] and g.stats()["slow_closed"]):
        try:
            slow.sendall(b"X")
        except OSError:
            pass
        time.sleep(0.1)
    stats = g.stats()
    assert stats["idle_closed"] >= 1 and stats["slow_closed"] == 1, stats
    assert idle.recv(10) == b""                                    # closed by the dashboard
    status, units = _get_units(port)
    assert status == 200 and units["connections"]["slow_closed"] == 1
    idle.close()
    slow.close()
