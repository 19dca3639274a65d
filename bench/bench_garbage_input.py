"""Benchmark (not a test): `fluxcal fit` on a garbage file of random bytes named as each input it reads, its peak
memory and how it ends, against a baseline `fluxcal fit --help` (the interpreter and the imports) in the same run.

Writes SIZE of random bytes once in a temporary folder (hard links give it the names .csv, .mcap, .ulg and .BIN),
runs `fluxcal fit FILE` in a subprocess for each, and prints its exit status, its last line on stderr and its peak
resident memory (ru_maxrss of that child, from os.wait4). Issue 38: refused with one line, peak under 200 MB
(before: the CSV read whole, then decoded, 2.06 GB at its peak for 1 GB).

Run by hand, under the shared lock:  .venv/bin/python bench/bench_garbage_input.py [--mb 1024] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import cpu_model

SUFFIXES = (".csv", ".mcap", ".ulg", ".BIN")


def run(args: list[str]) -> tuple[int, float, str, float]:
    """(exit status, peak RSS in MiB, the last line on stderr, wall s) of `fluxcal ARGS` in a child process."""
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", *args], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    err = p.stderr.read()
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    return p.returncode, usage.ru_maxrss / 1024, (lines[-1] if lines else ""), time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mb", type=int, default=1024, help="size of the garbage file, MiB")
    ap.add_argument("--out", help="also write the lines printed to this file")
    args = ap.parse_args()
    out = [f"machine: {cpu_model()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}, "
           f"{time.strftime('%Y-%m-%d')}", f"garbage: {args.mb:,} MiB of random bytes"]
    with tempfile.TemporaryDirectory() as d:
        first = Path(d) / f"garbage{SUFFIXES[0]}"
        with open(first, "wb") as f:
            for _ in range(args.mb):
                f.write(os.urandom(1 << 20))
        for s in SUFFIXES[1:]:
            os.link(first, Path(d) / f"garbage{s}")
        status, base, _, wall = run(["fit", "--help"])
        out.append(f"baseline `fluxcal fit --help`: exit {status}, peak {base:.0f} MiB, {wall:.2f} s")
        for s in SUFFIXES:
            status, peak, last, wall = run(["fit", str(Path(d) / f"garbage{s}")])
            out.append(f"fit garbage{s}: exit {status}, peak {peak:.0f} MiB ({peak / base:.2f}x the baseline), "
                       f"{wall:.2f} s: {last.replace(d, '<tmp>')}")
    print("\n".join(out))
    if args.out:
        Path(args.out).write_text("\n".join(out) + "\n")


if __name__ == "__main__":
    main()
