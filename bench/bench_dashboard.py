"""Benchmark (not a test): what the web dashboard costs the service, and whether the page keeps up.

The service runs the simulated unit at 1 kHz with 4 probes (ICD frames through a pty, paced by the wall
clock). Its CPU time is read from /proc in alternating segments of the same run: without a dashboard
(the baseline), then with `fluxcal dashboard` and a page open in headless Chromium, and again. It prints
the service's CPU in % of one core in each, the difference against the baseline, the dashboard's own
CPU, and how far the page's newest point lags the service's unit time at the end of each segment.

Run by hand:  .venv/bin/python bench/bench_dashboard.py [--segment-s 60] [--pairs 2]
              (the acceptance run: --segment-s 600 --pairs 1, ten minutes with the page open)
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import cpu_model

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def config(tmp: Path, port: int) -> Path:
    text = (REPO / "configs" / "sim-cross.toml").read_text()
    text = re.sub(r"(?m)^rate_hz = .*$", "rate_hz = 1000.0", text)
    text = re.sub(r'(?m)^kind = "grid".*$', 'kind = "tumble"', text)
    text = text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
    text = re.sub(r'(?m)^dir = .*$', f'dir = "{tmp / "rec"}"', text)
    text = re.sub(r'(?m)^file = .*$', f'file = "{tmp / "cal.json"}"', text)
    path = tmp / "bench.toml"
    path.write_text(text)
    return path


def unit_now(port: int) -> float:
    """The unit time of the newest corrected sample on the bus, s."""
    from fluxcal.service.io.bus import BusClient, ZenohConfig

    with BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "cross1", streams=["corrected"], lossless=False) as c:
        msg = c.recv(timeout=5.0)
        return float(msg.value.t_s[-1])


def segment(svc: subprocess.Popen, seconds: float) -> float:
    """The service's CPU over `seconds`, % of one core."""
    c0, t0 = cpu_seconds(svc.pid), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (cpu_seconds(svc.pid) - c0) / (time.monotonic() - t0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--segment-s", type=float, default=60.0)
    ap.add_argument("--pairs", type=int, default=2)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    print(f"machine: {cpu_model()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        port = free_port()
        cfg = config(tmp, port)
        svc = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "run", "--config", str(cfg)],
                               stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
        time.sleep(20.0)                                       # start-up and the first calibration
        base, withd, dash_cpu, lags = [], [], [], []
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                    "--disable-sync"])
                for _ in range(args.pairs):
                    base.append(segment(svc, args.segment_s))
                    dash = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "dashboard", "--connect",
                                             f"tcp/127.0.0.1:{port}", "--listen", "127.0.0.1:0"],
                                            stderr=subprocess.PIPE, text=True)
                    url = re.search(r"http://\S+/", dash.stderr.readline()).group(0)
                    page = browser.new_page()
                    page.goto(url)
                    # a selector, not wait_for_function: the page's Content-Security-Policy forbids eval
                    page.wait_for_selector("body[data-status='live']", state="attached", timeout=30000)
                    d0 = cpu_seconds(dash.pid)
                    t0 = time.monotonic()
                    withd.append(segment(svc, args.segment_s))
                    dash_cpu.append(100.0 * (cpu_seconds(dash.pid) - d0) / (time.monotonic() - t0))
                    unit_t = unit_now(port)
                    newest = page.evaluate("hist.series ? hist.series.t[hist.series.t.length - 1] : null")
                    updates = int(page.evaluate("document.body.dataset.updates"))
                    lags.append((unit_t, newest, updates))
                    page.close()
                    dash.send_signal(signal.SIGTERM)
                    dash.wait(15)
                browser.close()
        finally:
            svc.send_signal(signal.SIGTERM)
            svc.wait(30)
    print(f"service: simulated unit, 4 probes at 1 kHz through a pty; segments of {args.segment_s:.0f} s")
    for k, (b, w, dc, (ut, newest, n)) in enumerate(zip(base, withd, dash_cpu, lags)):
        print(f"  pair {k + 1}: service CPU {b:.1f} % of a core without the dashboard (baseline), {w:.1f} % with it "
              f"and a page open: {w - b:+.1f} points, ratio {w / b:.3f}; dashboard process {dc:.1f} %; the page polled "
              f"{n} times; its newest point {ut - newest:.2f} s behind the unit's newest sample (a 0.1-s mean is "
              f"shown once the interval ends; the page polls every 0.5 s)")
    mb, mw = sum(base) / len(base), sum(withd) / len(withd)
    print(f"mean: baseline {mb:.1f} %, with the dashboard {mw:.1f} % ({mw - mb:+.1f} points of a core)")


if __name__ == "__main__":
    main()
