"""Make docs/dashboard.png: the web dashboard of the simulated four-probe cross (configs/sim-cross.toml) in
headless Chromium, once the calibration is usable and a diagnosis of the kept samples has run.

The service and `fluxcal dashboard` run as in tests/e2e/test_dashboard_browser.py: loopback on a free port, the
calibration file and recordings in a temporary directory. Needs Chromium (/usr/bin/chromium) and Playwright
(`pip install -e '.[test]'`). About a minute: the unit runs in real time at 10 Hz and the gate needs 300 samples.

Run by hand:  .venv/bin/python tools/dashboard_screenshot.py [--out docs/dashboard.png] [--width 1050]
"""

from __future__ import annotations

import argparse
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def config(tmp: Path, port: int) -> Path:
    """configs/sim-cross.toml on a free loopback port, its state and recordings in `tmp`."""
    text = (REPO / "configs" / "sim-cross.toml").read_text()
    text = text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
    text = re.sub(r"(?m)^dir = .*$", f'dir = "{tmp / "rec"}"', text)
    text = re.sub(r"(?m)^file = .*$", f'file = "{tmp / "cal.json"}"', text)
    path = tmp / "cross.toml"
    path.write_text(text)
    return path


def wait(page, expr: str, timeout_s: float, what: str) -> None:
    """Poll `expr` in the page (not wait_for_function: the page's Content-Security-Policy forbids eval)."""
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expr):
        if time.monotonic() > deadline:
            raise SystemExit(f"dashboard_screenshot: {what} within {timeout_s:.0f} s")
        page.wait_for_timeout(200)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def shrink(path: str) -> None:
    """128 colours, no dithering: a third of the size, the same to the eye (Pillow comes with matplotlib)."""
    try:
        from PIL import Image
    except ImportError:
        return
    im = Image.open(path).convert("RGB")
    im.quantize(colors=128, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(REPO / "docs" / "dashboard.png"))
    ap.add_argument("--width", type=int, default=1050)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        port = free_port()
        svc = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "run", "--config", str(config(tmp, port))],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        dash = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "dashboard", "--connect",
                                 f"tcp/127.0.0.1:{port}", "--listen", "127.0.0.1:0"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            url = re.search(r"http://\S+/", dash.stderr.readline()).group(0)
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                    "--disable-sync"])
                page = browser.new_page(viewport={"width": args.width, "height": 1400})
                page.goto(url)
                wait(page, "document.body.dataset.status === 'live'", 60, "the page did not show the unit live")
                wait(page, "document.querySelector('#calibration .good') !== null", 120, "no usable calibration shown")
                page.wait_for_timeout(5000)                     # a few seconds of corrected output in the plots
                page.click("#diagnose")
                wait(page, "document.getElementById('diagnosis').dataset.status === 'done'", 120,
                     "the diagnosis did not finish")
                page.screenshot(path=args.out, full_page=True)
                browser.close()
            shrink(args.out)
        finally:
            stop(dash)
            stop(svc)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
