"""The online RLS ellipsoid estimator against the batch fit and a known truth: agreement, offset-step
tracking at the rate λ states, no wind-up at rest, P probes at once equal P single estimators."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.errors import CalibrationRefused, DataError
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.rls import RlsEllipsoid

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.numerics.calib.rls_info",)

TOTAL_NT = 50000.0
M_TRUE = np.array([[1.02, 0.01, -0.005], [0.0, 0.98, 0.008], [0.0, 0.0, 1.01]])   # corrected = M (raw − o)
O_TRUE = np.array([200.0, -300.0, 100.0])


def tumble(n: int, *, rate_hz: float = 100.0, noise_nT: float = 1.0, seed: int = 0,
           m_true: np.ndarray = M_TRUE, o_true: np.ndarray = O_TRUE) -> np.ndarray:
    """(n, 3) raw samples of a probe turning about three axes at incommensurate rates (0.31, 0.13,
    0.071 turns/s): the field direction fills the probe's sphere within ~10 s, 1° per sample."""
    t = np.arange(n) / rate_hz
    a, b, c = 2 * np.pi * 0.31 * t, 2 * np.pi * 0.13 * t + 0.4, 2 * np.pi * 0.071 * t + 1.1
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    r = np.empty((n, 3, 3))                                   # R = Rz(a) Ry(b) Rx(c), body = Rᵀ B
    r[:, 0] = np.stack([ca * cb, ca * sb * sc - sa * cc, ca * sb * cc + sa * sc], axis=1)
    r[:, 1] = np.stack([sa * cb, sa * sb * sc + ca * cc, sa * sb * cc - ca * sc], axis=1)
    r[:, 2] = np.stack([-sb, cb * sc, cb * cc], axis=1)
    b_earth = TOTAL_NT * np.array([np.cos(np.radians(60.0)), 0.0, np.sin(np.radians(60.0))])
    body = np.einsum("nji,j->ni", r, b_earth)
    raw = np.linalg.solve(m_true, body.T).T + o_true
    return raw + np.random.default_rng(seed).normal(0.0, noise_nT, raw.shape)


def feed(est: RlsEllipsoid, raw: np.ndarray, block: int = 100, total=TOTAL_NT) -> RlsEllipsoid:
    for i in range(0, raw.shape[0], block):
        est.partial_fit(raw[i:i + block], total)
    return est


def test_without_forgetting_the_online_estimate_is_the_batch_fit():
    raw = tumble(6000)
    batch = fit_ellipsoid(raw, TOTAL_NT).calibration
    est = RlsEllipsoid(forgetting=1.0)
    for i in range(0, 6000, 173):                                   # uneven blocks on purpose
        est.partial_fit(raw[i:i + 173], TOTAL_NT)
    assert np.allclose(est.offset_, batch.offset_nT, atol=1e-6)
    assert np.allclose(est.matrix_, batch.matrix, atol=1e-10)
    assert np.allclose(est.offset_se_, batch.offset_se_nT, rtol=1e-3)
    assert np.allclose(est.matrix_se_, batch.matrix_se, rtol=1e-3, atol=1e-12)
    assert est.n_samples_ == 6000 and abs(est.condition_ - fit_ellipsoid(raw, TOTAL_NT).condition) < 1e-6


def test_with_forgetting_stationary_data_agree_with_the_batch_within_standard_errors():
    raw = tumble(20000, seed=1)
    batch = fit_ellipsoid(raw, TOTAL_NT).calibration
    est = feed(RlsEllipsoid(forgetting=0.9995), raw)
    snap = est.snapshot()
    # memory 1/(1 − λ) = 2000 samples: the estimate's own standard errors are ~3× the batch's
    assert np.all(np.abs(snap.offset_nT - batch.offset_nT) < 3 * snap.offset_se_nT), \
        (snap.offset_nT - batch.offset_nT, snap.offset_se_nT)
    assert np.all(np.abs(snap.matrix - batch.matrix) < 3 * snap.matrix_se + 1e-12)
    assert np.all(np.abs(snap.offset_nT - O_TRUE) < 4 * snap.offset_se_nT)
    assert abs(snap.params["memory_samples"]["value"] - 2000.0) < 1.0


@pytest.mark.parametrize("lam", [0.999, 0.998])
def test_an_offset_step_is_tracked_within_the_samples_lambda_states(lam):
    # After k samples the data from before a step weigh λ^k of the memory, so a step S is expected
    # within ε after k = ln(S / ε) / (−ln λ) samples. Stated (docs/service.md): within ε after 1.2 k samples,
    # the 20 % for motion that covers the sphere unevenly within one memory. 100 nT to 2 nT:
    # 4695 samples at λ = 0.999 (4.7 memories), 2346 at 0.998.
    step_nT, eps_nT = 100.0, 2.0
    k_expected = np.log(step_nT / eps_nT) / -np.log(lam)
    stated = int(np.ceil(1.2 * k_expected))
    step_at = 20000
    raw = tumble(step_at + 3 * stated, seed=2)
    raw[step_at:, 0] += step_nT
    est = RlsEllipsoid(forgetting=lam)
    track = []
    for i in range(0, raw.shape[0], 100):
        est.partial_fit(raw[i:i + 100], TOTAL_NT)
        if i + 100 > step_at:
            track.append((i + 100 - step_at, est.offset_[0] - (O_TRUE[0] + step_nT)))
    track = np.array(track)
    after = track[track[:, 0] >= stated, 1]
    assert np.all(np.abs(after) < eps_nT), after[:5]
    # and not much sooner: at 0.8 k the error is still above ε (λ^0.8k S ≈ 4.4 nT)
    early = track[np.argmin(np.abs(track[:, 0] - 0.8 * k_expected)), 1]
    assert abs(early) > eps_nT
    # after one memory (1/(1 − λ) samples) ~e⁻¹ of the step remains, as an exponential average's
    one = track[np.argmin(np.abs(track[:, 0] - 1.0 / (1.0 - lam))), 1]
    assert 0.25 * step_nT < abs(one) < 0.45 * step_nT


def test_a_long_rest_neither_winds_up_nor_publishes_nan():
    raw = tumble(6000, seed=3)
    rest = raw[-1] + np.random.default_rng(4).normal(0.0, 1.0, (200_000, 3))    # 2000 s at rest
    for forget_deg in (0.05, None):            # motion-gated forgetting, and plain forgetting + anchor
        est = feed(RlsEllipsoid(forgetting=0.999, forget_deg=forget_deg), raw)
        good = est.snapshot()
        info_before = None
        for i in range(0, rest.shape[0], 1000):
            est.partial_fit(rest[i:i + 1000], TOTAL_NT)
            if info_before is None:
                # the motion from the last turn's segments to the rest point is forgotten as motion; what
                # must not decay is the information from there on, through the whole rest
                info_before = np.linalg.eigvalsh(est.info_)[0]
            assert np.all(np.isfinite(est.offset_)) and np.all(np.isfinite(est.matrix_))
            if i % 20000 == 0:                         # the standard errors too, now and then
                assert np.all(np.isfinite(est.snapshot().offset_se_nT))
        snap = est.snapshot()
        assert snap.is_finite() and np.all(np.isfinite(snap.offset_se_nT))
        # the last good estimate holds where the rest brings no information
        assert np.abs(snap.offset_nT - good.offset_nT).max() < 2.0, (forget_deg, snap.offset_nT - good.offset_nT)
        if forget_deg is not None:
            # nothing forgotten at rest: the information matrix did not decay (no wind-up)
            assert np.linalg.eigvalsh(est.info_)[0] >= 0.99 * info_before
            assert est.condition_ < 1e3
        else:
            # plain forgetting lost ~all of it (λ^200000): only the anchor holds the estimate
            assert np.linalg.eigvalsh(est.info_)[0] < 1e-50
        feed(est, tumble(6000, seed=5))                               # motion returns: recovers
        assert np.abs(est.offset_ - O_TRUE).max() < 1.0


def test_p_probes_at_once_equal_p_single_estimators_including_nan_rows():
    raws = [tumble(3000, seed=10 + k, o_true=O_TRUE + 50.0 * k) for k in range(3)]
    field = np.stack(raws, axis=1)                                      # (N, 3 probes, 3)
    field[500:520, 1] = np.nan                                          # a dropout on probe 2 only
    multi = RlsEllipsoid(forgetting=0.999, n_probes=3)
    singles = [RlsEllipsoid(forgetting=0.999) for _ in range(3)]
    for i in range(0, 3000, 100):
        multi.partial_fit(field[i:i + 100], TOTAL_NT)
        for k, s in enumerate(singles):
            s.partial_fit(field[i:i + 100, k], TOTAL_NT)
    assert multi.offset_.shape == (3, 3) and multi.matrix_.shape == (3, 3, 3)
    for k, s in enumerate(singles):
        assert np.allclose(multi.info_[k], s.info_, rtol=1e-12)
        assert np.allclose(multi.offset_[k], s.offset_, atol=1e-8)
        assert np.allclose(multi.offset_se_[k], s.offset_se_, rtol=1e-8)
        assert np.abs(multi.offset_[k] - (O_TRUE + 50.0 * k)).max() < 1.0
    assert list(multi.n_samples_) == [3000, 2980, 3000]
    assert [c.name for c in multi.snapshots(["a", "b", "c"])] == ["a", "b", "c"]


def test_unfitted_and_wrong_shapes_say_what_is_expected():
    est = RlsEllipsoid()
    with pytest.raises(CalibrationRefused, match="not determined yet"):
        est.snapshot()
    with pytest.raises(DataError, match=r"expected shape \(N, 3\), got \(10, 2\)"):
        est.partial_fit(np.zeros((10, 2)))
    with pytest.raises(DataError, match=r"expected shape \(N, 2, 3\)"):
        RlsEllipsoid(n_probes=2).partial_fit(np.zeros((10, 3)))
    # a single turn (one plane) never becomes an estimate: refused, not NaN
    t = np.linspace(0, 2 * np.pi, 500)
    flat = np.column_stack([30000 * np.cos(t), 30000 * np.sin(t), np.full_like(t, 40000.0)])
    est.fit(flat, TOTAL_NT)
    with pytest.raises(CalibrationRefused, match="keep rotating"):
        est.snapshot()
