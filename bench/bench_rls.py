"""Benchmark (not a test): the online RLS ellipsoid estimator in probe-samples/s on one core.

Run by hand:  .venv/bin/python bench/bench_rls.py   (sets OPENBLAS_NUM_THREADS=1 itself)
Prints the throughput of `RlsEllipsoid.partial_fit` on simulated data of 4 probes in blocks, all
probes at once (`n_probes=4`) and one estimator per probe, and the ratio of each against a textbook
per-sample RLS in covariance form (K = Pφ/(λ + φᵀPφ), θ += K(y − φᵀθ), P = (P − K φᵀ P)/λ, a Python
loop over samples with numpy) run in the same process on the same data. Target: ≥ 1,000,000
probe-samples/s. The estimates are checked against each other so the speed is not bought with a
wrong answer.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import platform  # noqa: E402

import numpy as np
from _machine import best_of, cpu_model  # noqa: E402

from fluxcal.drivers.sim.config import load_sim_config  # noqa: E402
from fluxcal.drivers.sim.world import World  # noqa: E402
from fluxcal.service.numerics.calib.quadric import quadric_design, quadric_to_calibration
from fluxcal.service.numerics.calib.rls import RlsEllipsoid  # noqa: E402

LAMBDA = 0.9995
TOTAL_NT = 52500.0


def textbook_rls(raw: np.ndarray, scale: float, lam: float) -> np.ndarray:
    """Per-sample covariance-form RLS of the same nine-term quadric (u = r / s, r about the block RLS's origin,
    right side 1)."""
    phi_all = quadric_design(raw / scale)
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
    raw = World(cfg).samples(0, cfg.n_samples).raw_nT           # (N, P, 3)
    n = raw.shape[0]
    print(f"machine: {cpu_model()} ({platform.machine()}), os.cpu_count() = {os.cpu_count()}, "
          f"Python {platform.python_version()}, numpy {np.__version__}, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    print(f"data: {n} samples x {n_probes} probes (simulated unit, {rate:.0f} Hz, {seconds:.0f} s), lambda = {LAMBDA}")

    results = {}
    for block in (50, 200, 1000):
        multi = RlsEllipsoid(forgetting=LAMBDA, total_nT=TOTAL_NT, n_probes=n_probes)

        def run_multi() -> None:
            multi.reset()
            for i in range(0, n, block):
                multi.partial_fit(raw[i:i + block])
            multi.snapshots()                          # include the solves the service asks for

        singles = [RlsEllipsoid(forgetting=LAMBDA, total_nT=TOTAL_NT) for _ in range(n_probes)]

        def run_singles() -> None:
            for est in singles:
                est.reset()
            for i in range(0, n, block):
                for k, est in enumerate(singles):
                    est.partial_fit(raw[i:i + block, k])
            for est in singles:
                est.snapshot()

        results[("all probes at once", block)] = n * n_probes / best_of(3, run_multi)
        results[("one estimator per probe", block)] = n * n_probes / best_of(3, run_singles)
        assert np.allclose(multi.offset_, np.stack([e.offset_ for e in singles]), atol=1e-6)

    m = 20000
    # the block RLS accumulates about its first samples' mean (origin_) in units of scale_: the textbook
    # runs in the same coordinates, so the two must hold the same information
    ref = RlsEllipsoid(forgetting=LAMBDA, total_nT=TOTAL_NT, forget_deg=None).fit(raw[:m, 0])
    origin, scale = ref.origin_, ref.scale_
    theta_tb = None

    def run_textbook() -> None:
        nonlocal theta_tb
        theta_tb = textbook_rls(raw[:m, 0] - origin, scale, LAMBDA)

    base = m / best_of(2, run_textbook)
    # the same least squares on the same samples (textbook starts from P = 1e6 I, a negligible prior)
    o_tb = quadric_to_calibration(theta_tb, scale, TOTAL_NT ** 2, origin)[0]
    o_ref = quadric_to_calibration(np.linalg.solve(ref.info_, ref.eta_), scale, TOTAL_NT ** 2, origin)[0]
    print(f"textbook per-sample RLS ({m} samples, 1 probe): {base:12,.0f} probe-samples/s   "
          f"(offset agrees with the block RLS within {np.abs(o_tb - o_ref).max():.2g} nT)")
    for (kind, block), speed in results.items():
        print(f"block RLS, {kind:24s} {block:5d}-sample blocks: {speed:12,.0f} probe-samples/s   "
              f"ratio {speed / base:6.1f}x")


if __name__ == "__main__":
    main()
