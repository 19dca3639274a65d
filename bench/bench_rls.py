"""Benchmark (not a test): the online RLS ellipsoid estimator in probe-samples/s on one core.

Run by hand:  OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_rls.py
Prints throughput of `RlsEllipsoid.partial_fit` over 4 probes in blocks, and a ratio against a
textbook per-sample RLS (covariance form, P ← (P − K φᵀ P) / λ) run in the same process on the
same data. Target: ≥ 1,000,000 probe-samples/s.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import platform  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from drivers.sim.config import load_sim_config  # noqa: E402
from drivers.sim.world import World  # noqa: E402
from service.calib.ellipsoid import quadric_design  # noqa: E402
from service.calib.rls import RlsEllipsoid  # noqa: E402


def textbook_rls(raw: np.ndarray, total: float, lam: float) -> np.ndarray:
    """Per-sample covariance-form RLS of the same nine-term quadric (u = r / s, right side 1)."""
    s = float(np.median(np.linalg.norm(raw, axis=1)))
    phi_all = quadric_design(raw / s)
    theta = np.zeros(9)
    p = np.eye(9) * 1e6
    for phi in phi_all:
        pphi = p @ phi
        k = pphi / (lam + phi @ pphi)          # K = P φ / (λ + φᵀ P φ)
        theta = theta + k * (1.0 - phi @ theta)
        p = (p - np.outer(k, pphi)) / lam     # P = (P − K φᵀ P) / λ
    return theta


def main() -> None:
    n_probes, seconds, rate = 4, 300.0, 200.0
    probes = [{"offset_nT": [100.0 * k, -50.0, 30.0], "scale": [1.01, 0.99, 1.02], "noise_nT": 0.5}
              for k in range(n_probes)]
    cfg = load_sim_config({"duration_s": seconds, "rate_hz": rate, "probes": probes,
                           "reference": {"enabled": True}})
    s = World(cfg).samples(0, cfg.n_samples)
    raw = s.raw_nT
    n = raw.shape[0]
    block = 200                                    # one second of the unit at 200 Hz
    best = float("inf")
    for _ in range(3):
        ests = [RlsEllipsoid(forgetting=0.9995, total_nT=52500.0) for _ in range(n_probes)]
        t0 = time.perf_counter()
        for i in range(0, n, block):
            for k, est in enumerate(ests):
                est.partial_fit(raw[i:i + block, k])
        for est in ests:
            est.snapshot()                         # include the solves the service would ask for
        best = min(best, time.perf_counter() - t0)
    ours = n * n_probes / best
    m = 20000
    t0 = time.perf_counter()
    textbook_rls(raw[:m, 0], 52500.0, 0.9995)
    base = m / (time.perf_counter() - t0)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    print(f"block RLS ({block}-sample blocks, {n_probes} probes, {n} samples): {ours:,.0f} probe-samples/s")
    print(f"textbook per-sample RLS (same quadric, {m} samples):       {base:,.0f} probe-samples/s")
    print(f"ratio: {ours / base:.1f}x")


if __name__ == "__main__":
    main()
