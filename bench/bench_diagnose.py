"""Benchmark: `diagnose` of 100,000 samples from 4 probes with the full effect catalogue as candidates.

Run by hand: .venv/bin/python bench/bench_diagnose.py [--samples N] [--probes P]
Prints the wall time of each stage, the machine, and ratios against a baseline run in the same
process (one Gauss-Newton fit of the linear calibration alone on the same data), plus the CPU time of
this process (less sensitive than wall time to other work on a shared machine; run with
OPENBLAS_NUM_THREADS=1 there, or idle BLAS threads spinning for the cores inflate both). Target: <= 30 s.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
from _machine import cpu_model


def machine() -> str:
    return (f"{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}, "
            f"{platform.system()} {platform.release()}")


def world_data(n_samples: int, n_probes: int):
    from fluxcal.drivers.sim import Unit, load_sim_config
    from fluxcal.service.numerics.effects.base import EffectData

    rate = 200.0
    pos = [[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0], [0, 0, 0.2], [0, 0, -0.2], [0.3, 0.3, 0],
           [-0.3, -0.3, 0]]
    rng = np.random.default_rng(5)
    probes = []
    for k in range(n_probes):
        probes.append({"position_m": pos[k], "scale": (1 + 0.02 * rng.standard_normal(3)).tolist(),
                       "nonorth_deg": rng.uniform(-2, 2, 3).tolist(), "misalign_deg": rng.uniform(-3, 3, 3).tolist(),
                       "offset_nT": rng.uniform(-300, 300, 3).tolist(), "noise_nT": 1.0,
                       "temp_offset_nT_per_C": [2.0, -1.0, 0.5] if k == 0 else [0.0, 0.0, 0.0]})
    cfg = load_sim_config({
        "seed": 11, "rate_hz": rate, "duration_s": n_samples / rate,
        "field": {"total_nT": 52000.0, "inclination_deg": 58.0, "declination_deg": -4.0},
        "reference": {"enabled": True, "noise_nT": 0.05},
        "motion": {"kind": "tumble", "rate_deg_s": 25.0, "tumble_period_s": 10.0},
        "temperature": {"start_C": 20.0, "amplitude_C": 4.0, "period_s": n_samples / rate / 2.0},
        "probes": probes})
    s = Unit(cfg).digitise(0, cfg.n_samples)
    block = s.to_block()
    # the attitude as a turntable controller would log it: R = Rz(azimuth) Ry(pitch) Rx(heel)
    r = s.world.attitude
    block.extras["heel_deg"] = np.degrees(np.arctan2(r[:, 2, 1], r[:, 2, 2]))
    block.extras["pitch_deg"] = np.degrees(-np.arcsin(np.clip(r[:, 2, 0], -1, 1)))
    block.extras["azimuth_deg"] = np.degrees(np.arctan2(r[:, 1, 0], r[:, 0, 0]))
    return EffectData.from_block(block, positions_m=np.array(pos[:n_probes]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--probes", type=int, default=4)
    args = ap.parse_args()
    from fluxcal.service.numerics.diagnose import diagnose
    from fluxcal.service.numerics.engine import fit_with_effects

    print(f"machine: {machine()}")
    t0 = time.perf_counter()
    data = world_data(args.samples, args.probes)
    t_sim = time.perf_counter() - t0
    print(f"simulated {data.n_samples} samples x {data.n_probes} probes in {t_sim:.2f} s")

    t0 = time.perf_counter()
    fit, _ = fit_with_effects(data, [])
    t_base = time.perf_counter() - t0
    print(f"baseline: linear fit alone           {t_base:7.2f} s   (rms {fit.rms_nT:.3f} nT)")

    stages: dict[str, float] = {}
    last = [time.perf_counter(), "start"]

    def progress(frac: float, msg: str) -> None:
        now = time.perf_counter()
        stages[last[1]] = stages.get(last[1], 0.0) + now - last[0]
        last[0], last[1] = now, msg.split(" ")[0] if msg.startswith("trying") is False else msg

    t0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(data, progress=progress)
    t_diag, c_diag = time.perf_counter() - t0, time.process_time() - c0
    for name, dt in stages.items():
        print(f"  {name:<32} {dt:7.2f} s")
    tested = [c.effect for c in d.candidates if c.testable]
    print(f"diagnose, full catalogue ({len(d.candidates)} candidates, {len(tested)} testable): "
          f"{t_diag:7.2f} s = {t_diag / t_base:5.1f} x baseline (CPU {c_diag:.2f} s, load average "
          f"{os.getloadavg()[0]:.1f})   target <= 30 s: {'OK' if t_diag <= 30 else 'TOO SLOW'}")
    best = d.best
    print(f"result: rms {d.rms_nT:.3f} nT, noise {d.noise_nT:.3f} nT, best candidate "
          f"{best.effect if best else None} -> {best.rms_nT if best else float('nan'):.3f} nT")

    # the other reading of "the full catalogue": every effect in the model at once
    from fluxcal.service.numerics.effects import EFFECTS

    usable = [name for name, cls in EFFECTS.items() if cls().why_unavailable(data) is None]
    t0 = time.perf_counter()
    fit, _ = fit_with_effects(data, usable)
    t_all = time.perf_counter() - t0
    n_par = len(fit.parameters)
    print(f"fit with every effect these data allow in the model ({len(usable)} of {len(EFFECTS)}, {n_par} effect "
          f"parameters): {t_all:7.2f} s = "
          f"{t_all / t_base:5.1f} x baseline   (rms {fit.rms_nT:.3f} nT)")
    contract = ["temperature", "eddy", "lag", "nonlinearity", "drift"]
    t0 = time.perf_counter()
    d = diagnose(data, effects=contract)
    t_d5 = time.perf_counter() - t0
    print(f"diagnose --effects {','.join(contract)} (4 candidates left): {t_d5:7.2f} s = "
          f"{t_d5 / t_base:5.1f} x baseline   (rms {d.rms_nT:.3f} nT)")


if __name__ == "__main__":
    main()
