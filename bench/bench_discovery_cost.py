"""Benchmark: what discovery beyond the catalogue adds to `diagnose` on 100,000 samples x 4 probes (issue 30: within
2x of diagnose without it; memory as today).

Run by hand: OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_discovery_cost.py [--samples N] [--probes P]

The world is bench_diagnose.py's (a tumble with a temperature effect the catalogue explains) with a heater, a fan
and a supply logged beside it, so that the library is as large as a user's with three columns; and the same world
with the heater coupled into s2 through a first-order lag of 60 s (outside the catalogue: discovery runs by itself,
selects, fits and claims); and with a core's loop on s2 (an offset following the sign of each axis' rate over 0.25 s:
its rate's window and its sign's width are then refined on all the data, discover.refine_loops). Each variant runs in a process of its own (wall time, CPU time, and peak resident memory,
which is a process's maximum): diagnose as today (discover=False), and with discovery (forced on in the first world,
where the catalogue explains everything; by itself in the second). Prints the ratios.
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


def one(samples: int, probes: int, discover: bool | None, coupled: str | None = None) -> dict:
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, str(HERE.parent / "tests"))
    import numpy as np
    from bench_diagnose import world_data
    from discovery_worlds import _columns

    from fluxcal.service.numerics.diagnose import diagnose

    data = world_data(samples, probes)
    cols = _columns(data.t_s, np.random.default_rng(3))
    cols.pop("_noise")
    data.extras.update(cols)
    if coupled == "coupled":
        from fluxcal.service.numerics.effects.thermal import low_pass

        lag = low_pass(data.t_s, cols["heater_A"], 60.0)
        data.raw_nT[:, 1, :] += np.outer(lag - lag.mean(), [8.0, -6.0, 4.0])
    elif coupled == "loop":
        from scipy.signal import savgol_filter

        win = int(0.25 / np.median(np.diff(data.t_s))) | 1
        rate = np.gradient(savgol_filter(data.raw_nT[:, 1, :], win, 2, axis=0), data.t_s, axis=0)
        data.raw_nT[:, 1, :] += np.array([4.0, -3.0, 3.0]) * np.tanh(rate / (0.05 * rate.std(0)))
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
    ap.add_argument("--one", choices=("with", "without", "coupled-with", "coupled-without", "loop-with",
                                      "loop-without"))
    args = ap.parse_args()
    if args.one:
        coupled = args.one.split("-")[0] if "-" in args.one else None
        discover = False if args.one.endswith("without") else (None if coupled else True)
        print(json.dumps(one(args.samples, args.probes, discover, coupled)))
        return
    from bench_diagnose import machine

    print(f"machine: {machine()}")
    for world, (without, with_) in (("catalogue-explained world, discovery forced", ("without", "with")),
                                    ("a heater coupled through a lag, discovery by itself",
                                     ("coupled-without", "coupled-with")),
                                    ("a core's loop, discovery by itself", ("loop-without", "loop-with"))):
        print(f"-- {world}")
        out = {}
        for variant in (without, with_):
            run = subprocess.run([sys.executable, __file__, "--samples", str(args.samples), "--probes",
                                  str(args.probes), "--one", variant], capture_output=True, text=True, check=True)
            out[variant] = r = json.loads(run.stdout.strip().splitlines()[-1])
            print(f"diagnose {'with' if variant == with_ else 'without':<7} discovery: {r['wall_s']:7.1f} s wall, "
                  f"{r['cpu_s']:7.1f} s CPU, peak memory {r['peak_mb']:6.0f} MB (data {r['before_mb']:5.0f} MB)"
                  + (f"; {r['groups']} groups of {r['params']} parameters tried, claimed: {r['claimed']}"
                     f"{'' if r['claimed'] else ' (' + str(r['reason'])[:90] + ')'}" if variant == with_ else ""))
        w, wo = out[with_], out[without]
        print(f"ratio with / without: wall {w['wall_s'] / wo['wall_s']:.2f}, CPU {w['cpu_s'] / wo['cpu_s']:.2f}, "
              f"peak memory {w['peak_mb'] / wo['peak_mb']:.2f}   target <= 2 wall: "
              f"{'OK' if w['wall_s'] <= 2 * wo['wall_s'] else 'TOO SLOW'}")


if __name__ == "__main__":
    main()
