"""Sweep: discovery beyond the catalogue (issue 30) on worlds made for it, effect-free controls and real recordings.

Run by hand, one at a time on a shared machine:

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_discovery.py [--part worlds|controls|real|all]

- worlds: the six kinds of tests/discovery_worlds.py (effects outside the catalogue) x 3 seeds, white and 1/f
  noise: found where the discovered groups bring the held-out error within 1.3x the noise floor and the verdict
  names the observable and the physical group (the acceptance asks 15 of 18);
- controls: effect-free worlds on the repository's configs and the discovery worlds' own, white and 1/f, with
  decoy columns logged, discovery forced on: claimed where it claims anything (the acceptance asks none in 29
  of 30);
- real: the public recordings of ../shared/real-data (or $FLUXCAL_REAL_DATA) with a logged column and an effect of
  it added, and their copy with the column but no effect: found, the held-out error within 1.1x the copy's, nothing
  claimed on it; each case sized by one rule (tests/real_effects.py: the model's held-out error grows 1.4 times);
- power: the same cases over 10 seeds of the columns, each sized for held-out growths of 1.2, 1.3, 1.4 and 1.5:
  how often found, and how often the untouched copy stays quiet.

Prints one line per world and the counts.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from discovery_worlds import KINDS, config_world, named, world  # noqa: E402

from fluxcal.service.numerics.diagnose import diagnose  # noqa: E402

FLOOR = 1.3


def run_worlds(seeds=(1, 2, 3), pinks=(0.0, 0.1)) -> None:
    for pink in pinks:
        ok = 0
        total = 0
        for kind in KINDS:
            for seed in seeds:
                t0 = time.perf_counter()
                d = diagnose(world(kind, seed, pink=pink))
                f = d.discovery
                ratio = (f.heldout_rms_nT / d.noise_nT) if (f is not None and f.claimed) else float("nan")
                names = named(d, kind)
                good = bool(f is not None and f.claimed and ratio <= FLOOR and names)
                ok += good
                total += 1
                reading = "; ".join(g.reading for g in f.groups)[:150] if f is not None and f.claimed else (
                    f.reason[:150] if f is not None else "discovery did not run: " + d.verdict["kind"])
                print(f"{'FOUND' if good else 'miss '} pink {pink:<4} {kind:<22} seed {seed}: held-out/floor "
                      f"{ratio:5.2f} (model {d.heldout_rms_nT / d.noise_nT:5.2f}) names {names}  "
                      f"{time.perf_counter() - t0:5.1f} s  {reading}", flush=True)
        print(f"== worlds, pink {pink}: found {ok} of {total}", flush=True)


CONTROLS = (
    [("discovery", s, 0.0) for s in range(101, 107)] + [("discovery", s, 0.3) for s in range(111, 117)]
    + [("sim-gradiometer.toml", s, p) for s, p in ((90005, 5.0), (90010, 5.0), (90014, 5.0), (90021, 1.0),
                                                      (90022, 1.0), (90023, 0.0), (90024, 0.0), (90025, 1.0),
                                                      (90026, 5.0), (90027, 0.3))]
    + [("sim-cross.toml", s, p) for s, p in ((90002, 1.0), (90004, 1.0), (90031, 0.0), (90032, 0.0),
                                               (90033, 1.0), (90034, 0.3), (90035, 5.0), (90036, 0.0))])


def run_controls() -> None:
    claimed = 0
    for config, seed, pink in CONTROLS:
        t0 = time.perf_counter()
        data = (world(None, seed, pink=pink) if config == "discovery" else
                config_world(config, seed, pink=pink, seconds=300.0 if config == "sim-gradiometer.toml" else None))
        d = diagnose(data, discover=True)
        f = d.discovery
        claimed += f.claimed
        what = "; ".join(g.reading for g in f.groups)[:160] if f.claimed else f.reason[:160]
        print(f"{'CLAIM' if f.claimed else 'none '} {config:<21} seed {seed} pink {pink:<4} "
              f"rms/floor {d.rms_nT / d.noise_nT:5.2f} {time.perf_counter() - t0:5.1f} s  {what}", flush=True)
    print(f"== controls: discovery claimed something in {claimed} of {len(CONTROLS)}", flush=True)


def run_real() -> None:
    from real_effects import cases, missing

    if missing():
        print("== real: " + "; ".join(missing()))
        return
    found = quiet = total = 0
    for name, kind, touched, control in cases():
        d0 = diagnose(control, discover=True)
        d1 = diagnose(touched, discover=True)
        f0, f1 = d0.discovery, d1.discovery
        ratio = f1.heldout_rms_nT / d0.heldout_rms_nT if f1.claimed else float("nan")
        good = f1.claimed and ratio <= 1.1 and named(d1, kind, probe="s1")
        found += bool(good)
        quiet += not f0.claimed
        total += 1
        print(f"{'FOUND' if good else 'miss '} {name:<30} {kind:<16} held-out with/untouched {ratio:5.3f} "
              f"(before {d1.heldout_rms_nT / d0.heldout_rms_nT:5.3f}); untouched: "
              f"{'CLAIM ' + f0.groups[0].reading[:80] if f0.claimed else 'nothing claimed'}; "
              f"{'weak held-out test; ' if d1.heldout_weak else ''}"
              f"{(f1.groups[0].reading if f1.claimed else f1.reason)[:140]}", flush=True)
    print(f"== real: found {found} of {total}; nothing claimed on the untouched copy in {quiet} of {total}",
          flush=True)


def run_power(growths=(1.2, 1.3, 1.4, 1.5), seeds=range(1, 11)) -> None:
    from real_data import find
    from real_effects import CASES, missing, size_for, with_effect

    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.numerics.engine import as_effect_data

    if missing():
        print("== power: " + "; ".join(missing()))
        return
    for name, kind, size in CASES:
        data = as_effect_data(load_data(find(f"{name}.csv")))
        quiet, found, t0 = 0, {g: 0 for g in growths}, time.perf_counter()
        for seed in seeds:
            d0 = diagnose(with_effect(data, kind, size, seed)[1], discover=True)
            quiet += not d0.discovery.claimed
            for g in growths:
                d1 = diagnose(with_effect(data, kind, size_for(data, kind, g, seed, start=size), seed)[0],
                              discover=True)
                f1 = d1.discovery
                found[g] += bool(f1.claimed and f1.heldout_rms_nT <= 1.1 * d0.heldout_rms_nT
                                 and named(d1, kind, probe="s1"))
        print(f"{name:30} {kind:14} untouched quiet {quiet}/{len(seeds)}; found at growth "
              + ", ".join(f"{g}: {found[g]}/{len(seeds)}" for g in growths)
              + f"  ({time.perf_counter() - t0:.0f} s)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("worlds", "controls", "real", "power", "all"), default="all")
    args = ap.parse_args()
    t0 = time.perf_counter()
    if args.part in ("worlds", "all"):
        run_worlds()
    if args.part in ("controls", "all"):
        run_controls()
    if args.part in ("real", "all"):
        run_real()
    if args.part == "power":                                    # 13 minutes: by itself
        run_power()
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
