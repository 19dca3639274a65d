"""Benchmark: what the wider library of discovery (issue 36: shapes, laws, the verdict per channel) costs `diagnose`,
against the code before it (a git revision, run from a copy of its tree in the same run): within 2x of its wall time
and 1.2x of its peak memory, on 100,000 samples x 4 probes and on a real recording of 50,000 rows with 25 columns.

Run by hand: OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_shape_cost.py [--baseline REV]
    [--samples N] [--probes P] [--real FILE.csv]

The baseline's tree is `git archive`d into a temporary folder and imported from there (PYTHONPATH) in a process of
its own; so is this checkout's. Each variant runs in a process of its own (wall time, CPU time, peak resident memory,
which is a process's maximum). Worlds:

- bench_discovery_cost.py's: a tumble of 4 probes at 200 Hz with a temperature effect the catalogue explains and three
  logged columns, discovery forced on; the same with a heater coupled into s2 through a lag of 60 s (discovery runs by
  itself and claims);
- a simulated array of 50,000 rows with 25 logged columns that wander (tests/shape_worlds.py), and a real recording
  (--real, default: ../shared/real-data/qmc5883l_suarez.csv, 19,745 rows) with 25 such columns added: diagnose as a
  user runs it, discovery forced. No public recording of a real magnetometer with 50,000 rows and 25 columns was found (a search of
  public repositories, 2026-12-06: the largest with 25 columns had 40,609 rows of a rocket's launch, the longest
  magnetometer logs fewer columns).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BASELINE = "9261922"          # main before issue 36 and 40 (stop 34's last commit)
#: a recording as wide as a user's flight log: rows and logged columns (no public recording of a real magnetometer
#: with 50,000 rows and 25 columns was found: the real one gets 25 wandering columns, the wide world is simulated)
WIDE_ROWS = 50_000
WIDE_COLUMNS = 25


class _OldNames:
    """A tree from before issue 39 has top-level `service` and `drivers`: its process imports them as
    `fluxcal.service` and `fluxcal.drivers` (the same module objects), so that the worlds of this checkout's tests/
    and this script, which use the package's names, run on the baseline's code alone."""

    def find_spec(self, name, path=None, target=None):
        import importlib.util

        if name == "fluxcal" or name.startswith(("fluxcal.service", "fluxcal.drivers")):
            return importlib.util.spec_from_loader(name, self, is_package=True)
        return None

    def create_module(self, spec):
        import importlib
        import types

        if spec.name == "fluxcal":
            return types.ModuleType("fluxcal")
        return importlib.import_module(spec.name.removeprefix("fluxcal."))

    def exec_module(self, module):
        pass


def one(world: str, samples: int, probes: int, real: str | None, worlds: str) -> dict:
    if not (HERE.parent / "fluxcal" / "__init__.py").is_file():
        sys.meta_path.insert(0, _OldNames())
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, worlds)                     # this checkout's tests/: the worlds, whichever code runs them
    import numpy as np

    from fluxcal.service.numerics.diagnose import diagnose

    if world == "real":
        from shape_worlds import wandering

        from fluxcal.service.io.recordings.load import load_data
        from fluxcal.service.numerics.engine import as_effect_data

        data, discover = as_effect_data(load_data(real)), True
        data.extras.update(wandering(data.t_s, WIDE_COLUMNS, 7))
    elif world == "wide":
        from shape_worlds import shape_world

        data, discover = shape_world(None, 5, n=WIDE_ROWS, wander=WIDE_COLUMNS - 6), True
    else:
        from bench_diagnose import world_data
        from discovery_worlds import _columns

        data = world_data(samples, probes)
        cols = _columns(data.t_s, np.random.default_rng(3))
        cols.pop("_noise")
        data.extras.update(cols)
        discover = True
        if world == "coupled":
            from fluxcal.service.numerics.effects.thermal import low_pass

            lag = low_pass(data.t_s, cols["heater_A"], 60.0)
            data.raw_nT[:, 1, :] += np.outer(lag - lag.mean(), [8.0, -6.0, 4.0])
            discover = None
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(data, discover=discover)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    f = d.discovery
    return {"code": str(Path(sys.modules[diagnose.__module__].__file__).parents[3]), "wall_s": wall, "cpu_s": cpu, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "before_mb": base_rss / 1024, "rows": int(data.n_samples), "columns": len(data.extras),
            "groups": None if f is None else f.tried, "params": None if f is None else f.tried_params,
            "claimed": None if f is None else f.claimed, "verdict": d.verdict["kind"]}


def tree(rev: str, into: Path) -> Path:
    """This repository's tree at `rev`, extracted into `into`."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", rev], check=True,
                             capture_output=True).stdout
    with tempfile.TemporaryFile() as f:
        f.write(archive)
        f.seek(0)
        with tarfile.open(fileobj=f) as tar:
            tar.extractall(into, filter="data")
    return into


def run(code: Path, world: str, args: argparse.Namespace) -> dict:
    env = {**os.environ, "PYTHONPATH": str(code)}
    out = subprocess.run([sys.executable, str(code / "bench" / "bench_shape_cost.py"), "--one", world, "--samples",
                          str(args.samples), "--probes", str(args.probes), "--worlds", str(ROOT / "tests")]
                         + (["--real", args.real] if args.real else []),
                         env=env, capture_output=True, text=True, check=True, cwd=str(code))
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default=BASELINE, help="the git revision to compare with")
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--probes", type=int, default=4)
    ap.add_argument("--real", default=None, help="a real recording (CSV, MCAP, log) to diagnose")
    ap.add_argument("--one", choices=("explained", "coupled", "wide", "real"))
    ap.add_argument("--worlds", default=str(ROOT / "tests"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.samples, args.probes, args.real, args.worlds)))
        return
    from bench_diagnose import machine

    if args.real is None:
        sys.path.insert(0, str(ROOT / "tests"))
        from real_data import find

        found = find("qmc5883l_suarez.csv")
        args.real = str(found) if found is not None else None
    print(f"machine: {machine()}")
    print(f"baseline: {args.baseline}; this: {subprocess.run(['git', '-C', str(ROOT), 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True).stdout.strip()} (work tree)")
    with tempfile.TemporaryDirectory() as tmp:
        old = tree(args.baseline, Path(tmp))
        # the baseline runs this very script (its tree may not have it), importing the baseline's service
        (old / "bench" / "bench_shape_cost.py").write_text(Path(__file__).read_text())
        worlds = [("explained", "catalogue-explained world, discovery forced"),
                  ("coupled", "a heater coupled through a lag, discovery by itself"),
                  ("wide", f"a simulated array of {WIDE_ROWS:,} rows with {WIDE_COLUMNS} logged columns, as a user runs "
                           f"it, discovery forced")]
        if args.real:
            worlds.append(("real", f"the real recording {Path(args.real).name} with {WIDE_COLUMNS} logged columns "
                                   f"(wandering) added, discovery forced"))
        else:
            print("no real recording: give --real FILE (../shared/real-data/qmc5883l_suarez.csv by default)")
        for world, label in worlds:
            b, n = run(old, world, args), run(ROOT, world, args)
            assert b["code"] == str(old) and n["code"] == str(ROOT), (b["code"], n["code"])
            print(f"-- {label} ({n['rows']} rows, {n['columns']} columns)")
            for name, r in (("baseline", b), ("this", n)):
                print(f"   {name:<9} {r['wall_s']:7.1f} s wall, {r['cpu_s']:7.1f} s CPU, peak {r['peak_mb']:6.0f} MB "
                      f"(data {r['before_mb']:5.0f} MB); {r['groups']} groups of {r['params']} parameters, claimed "
                      f"{r['claimed']}, verdict {r['verdict']}")
            print(f"   ratio this / baseline: wall {n['wall_s'] / b['wall_s']:.2f}, CPU {n['cpu_s'] / b['cpu_s']:.2f}, "
                  f"peak memory {n['peak_mb'] / b['peak_mb']:.2f}   targets: wall <= 2 "
                  f"{'OK' if n['wall_s'] <= 2 * b['wall_s'] else 'TOO SLOW'}, memory <= 1.2 "
                  f"{'OK' if n['peak_mb'] <= 1.2 * b['peak_mb'] else 'TOO BIG'}", flush=True)


if __name__ == "__main__":
    main()
