"""`fluxcal dashboard` in a real browser: headless Chromium (Debian's package) driven by Playwright, against
a running simulated unit. The page must load, keep updating, show a calibration, round-trip commands and
show their effect, and say when the unit stops or cannot be reached.

Chromium is installed by .ci/run; elsewhere, without /usr/bin/chromium these tests skip and say so, but
under CI (the CI environment variable set) a missing browser fails them.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from test_service_e2e import TOTAL_NT, free_port, stop, write_config

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync",
        # a name of an attacker's that resolves to this host: DNS rebinding without a DNS server
        "--host-resolver-rules=MAP evil.example.com 127.0.0.1"]


def _need_browser():
    try:
        import playwright  # noqa: F401
    except ImportError:
        reason = "playwright is not installed (pip install -e '.[test]')"
    else:
        if os.path.exists(CHROMIUM):
            return
        reason = "Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)"
    if os.environ.get("CI"):
        pytest.fail(f"browser tests must run in CI: {reason}")
    pytest.skip(reason)


pytestmark = pytest.mark.slow


def start_dashboard(*argv: str) -> tuple[subprocess.Popen, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "dashboard", "--listen", "127.0.0.1:0",
                             "--seconds", "120", *argv], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                            text=True, env=env)
    line = proc.stderr.readline()
    m = re.search(r"(http://127\.0\.0\.1:\d+/)", line)
    assert m, f"the dashboard did not say where it serves: {line!r}"
    return proc, m.group(1)


def stop_dashboard(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.fixture
def browser():
    _need_browser()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            yield b
        finally:
            b.close()


def _wait(page, expr: str, timeout_s: float, what: str):
    """Poll `expr` in the page until it is true. Not page.wait_for_function: it evaluates a string inside the page,
    which the dashboard's Content-Security-Policy (no eval) forbids, as it should."""
    import time

    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expr):
        if time.monotonic() > deadline:
            banner = page.evaluate("(document.getElementById('banner') || {}).textContent")
            raise AssertionError(f"{what} within {timeout_s} s (banner: {banner!r})")
        page.wait_for_timeout(100)


def test_page_updates_shows_the_calibration_round_trips_commands_and_sees_the_unit_stop(tmp_path, browser):
    port = free_port()
    cfg = write_config(tmp_path, port)
    text = Path(cfg).read_text().replace("realtime = false", "realtime = true").replace("run_s = 40.0", "run_s = 90.0")
    Path(cfg).write_text(text)
    svc = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "run", "--config", cfg],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
    dash, url = start_dashboard("--connect", f"tcp/127.0.0.1:{port}")
    try:
        page = browser.new_page(viewport={"width": 1300, "height": 1800})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url)
        _wait(page, "document.body.dataset.status === 'live'", 30, "the page did not show the unit live")
        # the page keeps updating: the poll counter and the newest sample's time both advance
        n0 = int(page.evaluate("document.body.dataset.updates"))
        _wait(page, f"Number(document.body.dataset.updates) >= {n0 + 4}", 10, "the page stopped updating")
        # a usable calibration: |B| of every probe within 1 % of the site's field, the offsets with errors
        _wait(page, "document.querySelector('#calibration .good') !== null", 60, "no usable calibration shown")
        _wait(page, "document.querySelector('td[data-col=\"s1.total\"]') !== null && "
                    "document.querySelector('td[data-col=\"s1.total\"]').textContent !== '–'", 20, "no |B| shown")
        # the |B| column is the newest 0.1-s mean of the corrected stream, which may still hold samples corrected
        # before the gate's acceptance reached the page: within a few seconds every probe's is within 1 %
        within = " && ".join(f"Math.abs(Number(document.querySelector('td[data-col=\"s{k}.total\"]').textContent) - "
                             f"{TOTAL_NT}) < {0.01 * TOTAL_NT}" for k in range(1, 5))
        try:
            _wait(page, within, 15, "|B| within 1 %")
        except AssertionError:
            totals = {p: page.eval_on_selector(f'td[data-col="{p}.total"]', "td => td.textContent")
                      for p in ("s1", "s2", "s3", "s4")}
            raise AssertionError(f"|B| not within 1 % of {TOTAL_NT} nT for 15 s after a usable calibration: {totals}")
        for p in ("s1", "s2", "s3", "s4"):
            total = float(page.eval_on_selector(f'td[data-col="{p}.total"]', "td => td.textContent"))
            assert abs(total - TOTAL_NT) < 0.01 * TOTAL_NT, (p, total)
        table = page.eval_on_selector("#calibration table", "t => t.textContent")
        assert "±" in table and "s4" in table
        assert page.eval_on_selector("#chart-tensor", "c => c.width") > 0
        cov = page.eval_on_selector("#coverage", "d => d.textContent")
        assert "% of directions seen" in cov
        # a command round-trips and its effect shows: freeze -> FROZEN, unfreeze -> gone
        page.click("button[data-cmd=freeze]")
        _wait(page, "document.querySelector('#command-log li[data-command=freeze][data-ok=true]') !== null", 15,
              "freeze did not come back ok")
        _wait(page, "document.querySelector('#frozen') !== null", 10, "the unit's state did not show FROZEN")
        page.click("button[data-cmd=unfreeze]")
        _wait(page, "document.querySelector('#command-log li[data-command=unfreeze][data-ok=true]') !== null", 15,
              "unfreeze did not come back ok")
        _wait(page, "document.querySelector('#frozen') === null", 10, "FROZEN stayed after unfreeze")
        # save the calibration in use, apply it back: the unit takes it (a new cal_id)
        saved = page.evaluate("fetch(document.getElementById('save-calibration').href).then(r => r.text())")
        cal = json.loads(saved)
        assert cal["format"] and [p["name"] for p in cal["probes"]] == ["s1", "s2", "s3", "s4"]
        page.fill("#apply-payload", saved)
        page.click("button[data-cmd=apply]")
        _wait(page, "document.querySelector('#command-log li[data-command=apply][data-ok=true]') !== null", 15,
              "apply of the saved calibration did not come back ok")
        # a refused command comes back refused, with the unit's reason
        page.fill("#effect-name", "no-such-effect")
        page.click("button[data-cmd='add-effect']")
        _wait(page, "document.querySelector('#command-log li[data-command=\"add-effect\"][data-ok=false]') !== null",
              15, "a bad add-effect did not come back refused")
        # a diagnosis of the raw samples the dashboard kept, in its own process: a verdict and the candidates
        page.click("#diagnose")
        _wait(page, "document.getElementById('diagnosis').dataset.status === 'done'", 90, "the diagnosis did not finish")
        verdict = page.eval_on_selector("#verdict", "p => p.textContent")
        assert re.match(r"(at the floor|explained|partly explained|unexplained)", verdict), verdict
        assert page.eval_on_selector_all("#diagnosis table tr", "rows => rows.length") >= 4     # head + candidates
        page.screenshot(path=str(tmp_path / "dashboard.png"), full_page=True)
        assert not errors, errors
        # the unit stops: the page says so
        stop(svc)
        _wait(page, "['stopped', 'silent'].includes(document.body.dataset.status)", 15,
              "the page did not say that the unit stopped")
        assert "not running" in page.eval_on_selector("#banner", "b => b.textContent") or \
            "no data" in page.eval_on_selector("#banner", "b => b.textContent")
    finally:
        stop(svc)
        stop_dashboard(dash)


def test_an_unreachable_unit_is_shown_as_such(browser):
    port = free_port()                                  # nobody listens here
    dash, url = start_dashboard("--connect", f"tcp/127.0.0.1:{port}", "--unit", "ghost")
    try:
        page = browser.new_page()
        page.goto(url)
        _wait(page, "document.getElementById('banner').dataset.state === 'unreachable'", 15,
              "an unreachable endpoint was not shown")
        text = page.eval_on_selector("#banner", "b => b.textContent")
        assert f"cannot reach tcp/127.0.0.1:{port}" in text
    finally:
        stop_dashboard(dash)


EVIL_PAGE = """<!doctype html><html><body><iframe name="sink"></iframe><script>
// A page of another origin open in the operator's browser: every way a web page can send the dashboard a command
const DASH = "%(dash)s", CMD = JSON.stringify({ unit: "u1", command: "freeze" });
const out = {};
async function attempt(name, f) {
  try {
    const r = await f();
    out[name] = r && r.type !== undefined ? "response " + r.type + " " + r.status : String(r);
  }
  catch (e) { out[name] = "failed: " + e.message; }
}
async function run() {
  // "simple" requests: no preflight, the browser sends them and hides the answer
  await attempt("no-cors text/plain", () => fetch(DASH + "api/command", {
    method: "POST", mode: "no-cors", headers: { "Content-Type": "text/plain" }, body: CMD }));
  await attempt("no-cors diagnose", () => fetch(DASH + "api/diagnose", { method: "POST", mode: "no-cors",
                                                                           body: JSON.stringify({ unit: "u1" }) }));
  await attempt("beacon", () => navigator.sendBeacon(DASH + "api/command", new Blob([CMD], { type: "text/plain" })));
  // preflighted: JSON and a guessed token need the dashboard's permission, which it never gives
  await attempt("cors json", () => fetch(DASH + "api/command", { method: "POST", headers: {
    "Content-Type": "application/json", "X-Fluxcal-Token": "guess" }, body: CMD }).then(r => r.text()));
  // the token is in the dashboard's page: another origin cannot read it
  await attempt("read the page", () => fetch(DASH).then(r => r.text()));
  // a form posted into a frame, its body shaped as JSON
  await new Promise(done => {
    document.querySelector("iframe").onload = done; setTimeout(done, 5000);
    const f = document.createElement("form");
    f.method = "POST"; f.enctype = "text/plain"; f.action = DASH + "api/command"; f.target = "sink";
    const i = document.createElement("input");
    i.name = '{"unit": "u1", "command": "freeze", "pad": "'; i.value = '"}';
    f.appendChild(i); document.body.appendChild(f); f.submit();
  });
  out.form = "submitted";
  window.results = out;
  document.title = "done";
}
run();
</script></body></html>"""


def _serve_dir(path: Path):
    """A plain web server of `path` on a free 127.0.0.1 port (another origin than the dashboard's)."""
    import functools
    import threading
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    srv = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(path)))
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def test_a_page_of_another_origin_cannot_command_the_dashboard(tmp_path, browser):
    """Issue 27: a cross-origin "simple" POST (text/plain) to /api/command was applied. From a page on another
    origin: fetch without CORS, a beacon, a preflighted JSON fetch, a text/plain form shaped as JSON; and after
    DNS rebinding (a name of the page's resolved to the dashboard's address). Nothing reaches the unit, while
    the dashboard's own page still commands it."""
    from test_dashboard_security import RecordingUnit

    from fluxcal.service.wiring.dashboard import DashboardServer, Hub

    unit = RecordingUnit()
    hub = Hub([unit.ep], ["u1"]).start()
    server = DashboardServer(hub, "127.0.0.1", 0).start()
    (tmp_path / "evil.html").write_text(EVIL_PAGE % {"dash": server.url})
    evil = _serve_dir(tmp_path)
    try:
        page = browser.new_page()
        page.goto(server.url)                                    # the operator's own page is open too
        _wait(page, "document.body.dataset.status === 'live'", 20, "the dashboard's page did not show the unit live")
        attacker = browser.new_page()
        attacker.goto(f"http://127.0.0.1:{evil.server_address[1]}/evil.html")
        _wait(attacker, "document.title === 'done'", 20, "the page of another origin did not finish its attempts")
        results = attacker.evaluate("window.results")
        assert results["cors json"].startswith("failed") and results["read the page"].startswith("failed"), results
        attacker.wait_for_timeout(1000)                          # anything sent has arrived by now
        assert unit.received == [], unit.received
        # DNS rebinding: evil.example.com resolves to 127.0.0.1 (--host-resolver-rules), so a page of that name on
        # the dashboard's port is the same origin as the dashboard for the browser
        rebound = f"http://evil.example.com:{server.server_address[1]}/"
        resp = attacker.goto(rebound)
        assert resp.status == 403 and "not this dashboard's address" in resp.text()
        same_origin = attacker.evaluate("""async () => {
            const page = await fetch("/").then(r => r.status);
            const cmd = await fetch("/api/command", { method: "POST", headers: {
                "Content-Type": "application/json", "X-Fluxcal-Token": "guess" },
                body: JSON.stringify({ unit: "u1", command: "reset" }) });
            return [page, cmd.status];
        }""")
        assert same_origin == [403, 403]
        attacker.wait_for_timeout(1000)
        assert unit.received == [], unit.received
        assert hub.view("u1", {})["commands"] == [] and hub.view("u1", {})["diagnosis"]["status"] == "none"
        refused = server.refused
        # counted by kind (a fixed set: the request's own Content-Type is no key): fetch, beacon and form arrived
        # as text/plain, one with none
        assert refused.get("content type", 0) >= 4, refused
        # the operator's own page still commands the unit
        page.click("button[data-cmd=freeze]")
        _wait(page, "document.querySelector('#command-log li[data-command=freeze][data-ok=true]') !== null", 15,
              "the page's own freeze did not come back ok")
        assert unit.received == [("freeze", "")]
    finally:
        evil.shutdown()
        evil.server_close()
        server.stop()
        hub.close()
        unit.close()


def test_a_read_only_dashboard_says_why_its_buttons_are_greyed(browser):
    """Issue 28: a read-only dashboard greyed its buttons without saying why. Issue 27: it refuses diagnose."""
    from test_dashboard_security import RecordingUnit

    from fluxcal.service.wiring.dashboard import DashboardServer, Hub

    unit = RecordingUnit()
    hub = Hub([unit.ep], ["u1"]).start()
    server = DashboardServer(hub, "127.0.0.1", 0, read_only=True).start()
    try:
        page = browser.new_page()
        page.goto(server.url)
        _wait(page, "document.body.dataset.status === 'live' && !document.getElementById('read-only-note').hidden", 20,
              "the read-only page did not say so")
        note = page.eval_on_selector("#read-only-note", "p => p.textContent")
        assert "read-only (started with --read-only)" in note
        assert "read-only (started with --read-only)" in page.eval_on_selector("#diagnose-note", "p => p.textContent")
        disabled = page.eval_on_selector_all("button[data-cmd], #diagnose, #apply-file, #apply-payload",
                                             "bs => bs.map(b => [b.disabled, b.title])")
        assert len(disabled) == 8 and all(d and "--read-only" in title for d, title in disabled), disabled
        # the page's own request, token and all, is refused by a read-only server
        answer = page.evaluate("""() => fetch("/api/diagnose", { method: "POST", headers: {
            "Content-Type": "application/json",
            "X-Fluxcal-Token": document.querySelector('meta[name="fluxcal-token"]').content },
            body: JSON.stringify({ unit: "u1" }) }).then(r => r.json().then(b => [r.status, b.error]))""")
        assert answer[0] == 403 and "read-only" in answer[1]
        assert hub.view("u1", {})["diagnosis"]["status"] == "none" and unit.received == []
        # text from the network is shown escaped, its control characters never acting (issue 38)
        shown = page.evaluate("() => esc('s1\\ncommand apply: applied\\x1b[2J<b>\\u202e')")
        assert shown == "s1\\ncommand apply: applied\\x1b[2J&lt;b&gt;\\u202e", shown
    finally:
        server.stop()
        hub.close()
        unit.close()
