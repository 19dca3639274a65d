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

from tests.test_service_e2e import TOTAL_NT, free_port, stop, write_config

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]


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
    proc = subprocess.Popen([sys.executable, "-m", "service.wiring.cli", "dashboard", "--listen", "127.0.0.1:0",
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
    try:
        page.wait_for_function(expr, timeout=timeout_s * 1000)
    except Exception as e:
        banner = page.eval_on_selector("#banner", "b => b.textContent")
        raise AssertionError(f"{what} within {timeout_s} s (banner: {banner!r})") from e


def test_page_updates_shows_the_calibration_round_trips_commands_and_sees_the_unit_stop(tmp_path, browser):
    port = free_port()
    cfg = write_config(tmp_path, port)
    text = Path(cfg).read_text().replace("realtime = false", "realtime = true").replace("run_s = 40.0", "run_s = 90.0")
    Path(cfg).write_text(text)
    svc = subprocess.Popen([sys.executable, "-m", "service.wiring.cli", "run", "--config", cfg],
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
            page.wait_for_function(within, timeout=15000)
        except Exception:
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
