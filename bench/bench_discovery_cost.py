"""Benchmark: what discovery beyond the catalogue adds to `diagnose` on 100,000 samples x 4 probes (issue 30: within
2x of diagnose without it; memory as today).

Run by hand: OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_discovery_cost.py [--samples N] [--probes P]

The world is bench_diagnose.py's (a tumble with a temperature effect the catalogue explains) with a heater, a fan
and a supply logged beside it, so that the library is as large as a user's with three columns. Each variant runs
in a process of its own (wall time, CPU time, and peak resident memory, which is a process's maximum):
diagnose as today (discover=False), and with discovery forced on (discover=True: the catalogue explains this world,
so discovery would not run by itself). Prints the ratios.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def one(samples: int, probes: int, discover: bool) -> dict:
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, str(HERE.parent / "tests"))
    import numpy as np
    from bench_diagnose import world_data
    from discovery_worlds import _columns

    from service.numerics.diagnose import diagnose

    data = world_data(samples, probes)
    cols = _columns(data.t_s, np.random.default_rng(3))
    cols.pop("_noise")
    data.extras.update(cols)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(data, discover=discover)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    f = d.discovery
    return {"wall_s": wall, "cpu_s": cpu, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "before_mb": base_rss / 1024, "groups": None if f is None else f.tried,
            "params": None if f is None else f.tried_params, "claimed": None if f is None else f.claimed,
            "reason": None if f is None else f.reason}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--probes", type=int, default=4)
    ap.add_argument("--one", choices=("with", "without"))
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.samples, args.probes, args.one == "with")))
        return
    from bench_diagnose import machine

    print(f"machine: {machine()}")
    out = {}
    for variant in ("without", "with"):
        run = subprocess.run([sys.executable, __file__, "--samples", str(args.samples), "--probes", str(args.probes),
                              "--one", variant], capture_output=True, text=True, check=True)
        out[variant] = json.loads(run.stdout.strip().splitlines()[-1])
        r = out[variant]
        print(f"diagnose {variant:<7} discovery: {r['wall_s']:7.1f} s wall, {r['cpu_s']:7.1f} s CPU, peak memory "
              f"{r['peak_mb']:6.0f} MB (data {r['before_mb']:5.0f} MB)"
              + (f"; {r['groups']} groups of {r['params']} parameters tried, claimed: {r['claimed']}"
                 f"{'' if r['claimed'] else ' (' + str(r['reason'])[:90] + ')'}" if variant == "with" else ""))
    w, wo = out["with"], out["without"]
    print(f"ratio with / without: wall {w['wall_s'] / wo['wall_s']:.2f}, CPU {w['cpu_s'] / wo['cpu_s']:.2f}, "
          f"peak memory {w['peak_mb'] / wo['peak_mb']:.2f}   target <= 2 wall: "
          f"{'OK' if w['wall_s'] <= 2 * wo['wall_s'] else 'TOO SLOW'}")


if __name__ == "__main__":
    main()
