"""Benchmark (not a test): many recordings through the process pool against one worker, in the same run.

Simulates N recordings of the built-in gradiometer (seeds differ), then runs `fluxcal diagnose` (or `fit`)
over all of them with --jobs 1 (the baseline) and with one process per core, and prints the wall times,
their ratio and the peak memory of the largest worker.

Run by hand:  .venv/bin/python bench/bench_fleet.py [--recordings 20] [--seconds 30] [--command diagnose]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

from _machine import cpu_model

from fluxcal.service.wiring import cli

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--recordings", type=int, default=20)
    ap.add_argument("--seconds", type=float, default=120.0, help="length of each simulated recording")
    ap.add_argument("--command", default="diagnose", choices=("diagnose", "fit"))
    args = ap.parse_args()
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        text = (REPO / "configs" / "sim-gradiometer.toml").read_text()
        for k in range(args.recordings):
            cfg = tmp / f"sim{k}.toml"
            cfg.write_text(re.sub(r"(?m)^duration_s = [\d.]+", f"duration_s = {args.seconds}",
                                  re.sub(r"(?m)^seed = \d+", f"seed = {100 + k}", text)))
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                cli.main(["simulate", "--config", str(cfg), "--out", str(tmp / f"rec{k:02d}.csv")], install_signals=False)
        walls = {}
        for jobs in (1, os.cpu_count() or 1):
            out = io.StringIO()
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(out):
                status = cli.main([args.command, str(tmp / "rec*.csv"), "--jobs", str(jobs), "--json"],
                                  install_signals=False)
            walls[jobs] = time.perf_counter() - t0
            summary = json.loads(out.getvalue())
            assert status == 0 and summary["failed"] == 0, summary
            busy = sum(r["seconds"] for r in summary["results"])
            peak = max(r["peak_rss_mb"] for r in summary["results"])
            print(f"{args.command} of {args.recordings} recordings ({args.seconds:.0f} s at 200 Hz, 2 probes) with "
                  f"--jobs {jobs}: {walls[jobs]:.1f} s wall, {busy:.1f} s of work in the workers, largest worker's "
                  f"peak memory {peak:.0f} MB")
    n = os.cpu_count() or 1
    print(f"speed-up, {n} processes against one: {walls[1] / walls[n]:.2f}x")


if __name__ == "__main__":
    main()
