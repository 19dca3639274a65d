"""Benchmark (not a test): the batch calibration of one probe, against the bare least squares of its design.

Run by hand:  .venv/bin/python bench/bench_fit.py [--samples N]
Prints, for a simulated tumble (a fluxgate: offset small next to the field) and the same data moved by
six fields (a hobby board's hard-iron offset), the time of `fit_ellipsoid` (the model order chosen on
held-out blocks, standard errors, warnings), of the full nine-term order alone, and of the bare
`numpy.linalg.lstsq` of the centred nine-term design in the same process: the ratios are what to
compare between versions, not the seconds.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np
from _machine import best_of, cpu_model

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluxcal.drivers.sim.config import load_sim_config  # noqa: E402
from fluxcal.drivers.sim.world import World  # noqa: E402
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.quadric import normalise, quadric_design


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=12000)
    args = ap.parse_args()
    cfg = load_sim_config({"duration_s": args.samples / 200.0, "rate_hz": 200.0, "probes": [
        {"offset_nT": [200.0, -300.0, 100.0], "scale": [1.02, 0.98, 1.01], "nonorth_deg": [0.5, -0.3, 0.8]}]})
    raw = World(cfg).samples(0, cfg.n_samples).raw_nT[:, 0]
    print(f"machine: {cpu_model()} ({platform.machine()}), os.cpu_count() = {os.cpu_count()}, "
          f"Python {platform.python_version()}, numpy {np.__version__}")
    for label, data in (("fluxgate (offset ~ 0.01 field)", raw),
                        ("hard iron (offset 6 fields)", raw + np.array([3.0, -4.0, 2.0]) * 52500.0)):
        def bare() -> None:
            c, s = normalise(data)
            np.linalg.lstsq(quadric_design((data - c) / s), np.ones(data.shape[0]), rcond=None)

        base = best_of(5, bare)
        auto = best_of(5, lambda: fit_ellipsoid(data))
        full = best_of(5, lambda: fit_ellipsoid(data, order="full"))
        order = fit_ellipsoid(data).order
        print(f"{label:32s} {data.shape[0]} samples: lstsq {base * 1e3:6.2f} ms; fit_ellipsoid (order {order}) "
              f"{auto * 1e3:6.2f} ms = {auto / base:4.1f}x; full order only {full * 1e3:6.2f} ms = {full / base:4.1f}x")


if __name__ == "__main__":
    main()
