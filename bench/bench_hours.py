"""Benchmark (not a test): `fit` and `diagnose` on long recordings, time and peak memory, against the same
commands on a recording a tenth as long in the same run (the baseline): how they scale with length. `diagnose`
keeps one sample in k beyond its budget of probe-samples (--max-samples); the lines say which k.

Simulates the four-probe cross array (configs/sim-cross.toml) at 1 kHz for --seconds (default 600 s; the
acceptance size of issue 17 is --seconds 3600: 14.4 M probe-samples) and for a tenth of that, then runs each
command as its own process and reads its peak RSS from wait4.

Run by hand:  .venv/bin/python bench/bench_hours.py [--seconds 3600] [--skip-diagnose]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import cpu_model

REPO = Path(__file__).resolve().parents[1]


def run(argv: list[str], out: Path) -> tuple[float, float, dict]:
    """(wall s, peak RSS MB, its JSON) of `fluxcal ARGV --json` as a process of its own."""
    t0 = time.perf_counter()
    with open(out, "wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", *argv], stdout=f,
                                stderr=subprocess.DEVNULL, env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"fluxcal {' '.join(argv)} failed with status {os.waitstatus_to_exitcode(status)}")
    return wall, usage.ru_maxrss / 1024, json.loads(out.read_text())


def simulate(tmp: Path, seconds: float) -> tuple[Path, Path]:
    text = (REPO / "configs" / "sim-cross.toml").read_text()
    text = re.sub(r"(?m)^rate_hz = .*$", "rate_hz = 1000.0", text)
    text = re.sub(r"(?m)^duration_s = .*$", f"duration_s = {seconds}", text)
    cfg = tmp / f"cross-{seconds:.0f}.toml"
    cfg.write_text(text)
    out = tmp / f"cross-{seconds:.0f}.mcap"
    subprocess.run([sys.executable, "-m", "fluxcal.service.wiring.cli", "simulate", "--config", str(cfg), "--out", str(out)],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return out, cfg


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--skip-diagnose", action="store_true")
    args = ap.parse_args()
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}")
    commands = ["fit"] + ([] if args.skip_diagnose else ["diagnose"])
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        lengths = (args.seconds / 10, args.seconds)
        recs = {s: simulate(tmp, s) for s in lengths}
        for cmd in commands:
            rows = []
            for s in lengths:
                rec, cfg = recs[s]
                wall, mb, out = run([cmd, str(rec), "--config", str(cfg), "--json"], tmp / "out.json")
                rows.append((s, wall, mb))
                thin = out.get("thinned")
                said = (f"; diagnosed one sample in {thin['every']} ({thin['n_used']:,} of {thin['n_read']:,}): "
                        f"rms {out['rms_nT']:.3f} nT, floor {out['noise_nT']:.3f} nT" if thin else "")
                print(f"{cmd}, 4 probes at 1 kHz, {s:.0f} s ({s * 4000 / 1e6:.2f} M probe-samples): {wall:.1f} s, "
                      f"peak {mb:.0f} MB ({1e3 * mb / (s * 1000):.2f} kB per sample of 4 probes){said}")
            (s0, w0, m0), (s1, w1, m1) = rows
            print(f"{cmd}: {s1 / s0:.0f}x the samples took {w1 / w0:.1f}x the time and {m1 / m0:.1f}x the memory "
                  f"(baseline: the shorter recording, same run)")


if __name__ == "__main__":
    main()
