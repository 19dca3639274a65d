"""The calibration core against the simulated unit's truth: ellipsoid, RLS, coverage, alignment,
tensor and the calibration file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fluxcal.drivers.errors import CalibrationRefused, DataError
from fluxcal.drivers.sim.config import load_sim_config
from fluxcal.drivers.sim.world import World
from fluxcal.service.io.calfile import load_calibration, save_calibration
from fluxcal.service.numerics.calib.alignment import align_probes, angles_from_rotation, rotation_from_angles
from fluxcal.service.numerics.calib.coverage import coverage
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.model import ArrayCalibration
from fluxcal.service.numerics.calib.rls import RlsEllipsoid
from fluxcal.service.numerics.calib.tensor import invariants, tensor_cross, tensor_from_positions

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.numerics.calib.order",)

PROBE = {"scale": [1.02, 0.98, 1.01], "nonorth_deg": [1.0, 2.0, -1.0], "misalign_deg": [2.0, 1.0, 3.0],
         "offset_nT": [200.0, -300.0, 100.0], "noise_nT": 1.0}


def world(duration_s=120.0, motion=None, probes=None, **kw):
    table = {"duration_s": duration_s, "reference": {"enabled": True, "noise_nT": 0.05},
             "probes": probes or [PROBE], **kw}
    if motion:
        table["motion"] = motion
    cfg = load_sim_config(table)
    w = World(cfg)
    return w, w.samples(0, cfg.n_samples)


def a_matrix(m):
    return m.T @ m


def test_ellipsoid_recovers_truth_within_standard_errors():
    w, s = world()
    truth = w.truth()["sensors"][0]
    fit = fit_ellipsoid(s.raw_nT[:, 0], s.ref_total_nT)
    cal = fit.calibration
    err = cal.offset_nT - np.array(truth["offset_nT"])
    assert np.all(np.abs(err) < 4 * cal.offset_se_nT + 0.02), (err, cal.offset_se_nT)
    # the triangular matrix is the truth up to a rotation: compare A = MᵀM
    m_true = np.array(truth["matrix"])
    assert np.abs(a_matrix(cal.matrix) - a_matrix(m_true)).max() < 2e-5
    assert abs(fit.residual_rms_nT - 1.0) < 0.1                      # the noise, 1 nT
    assert np.allclose(np.tril(cal.matrix, -1), 0)


def test_single_axis_turn_is_refused_with_the_missing_motion():
    w, s = world(duration_s=20.0, motion={"kind": "turntable", "axes": ["z"], "rate_deg_s": 30.0})
    with pytest.raises(CalibrationRefused, match=r"one plane.*turn about the x or y axis"):
        fit_ellipsoid(s.raw_nT[:, 0], s.ref_total_nT)
    cov = coverage(s.raw_nT[:, 0])
    assert cov.planarity < 0.02 and not cov.usable


def test_nan_rows_are_refused_by_row():
    w, s = world(duration_s=10.0)
    raw = s.raw_nT[:, 0].copy()
    raw[[5, 17], 1] = np.nan
    with pytest.raises(DataError, match="rows 5, 17"):
        fit_ellipsoid(raw, s.ref_total_nT)


def test_rls_equals_batch_without_forgetting_and_agrees_within_se_with_it():
    w, s = world()
    raw, ref = s.raw_nT[:, 0], s.ref_total_nT
    batch = fit_ellipsoid(raw, ref).calibration
    exact = RlsEllipsoid(forgetting=1.0)
    forget = RlsEllipsoid(forgetting=0.9995)
    for i in range(0, len(raw), 137):                               # uneven blocks on purpose
        exact.partial_fit(raw[i:i + 137], ref[i:i + 137])
        forget.partial_fit(raw[i:i + 137], ref[i:i + 137])
    e = exact.snapshot()
    assert np.allclose(e.offset_nT, batch.offset_nT, atol=1e-5)
    assert np.allclose(e.offset_se_nT, batch.offset_se_nT, rtol=1e-3)
    f = forget.snapshot()
    # the forgetting estimate sees ~2000 recent samples: agree within its own standard errors
    assert np.all(np.abs(f.offset_nT - batch.offset_nT) < 4 * f.offset_se_nT)


def test_block_update_equals_sample_by_sample():
    """The same sums in another order: equal up to rounding, and rounding bounded by the conditioning (the bound
    replay uses across machines, docs/recording.md "Replay equality"). The information Λ = Σ w φφᵀ of n samples:
    two orders of summing differ by at most n·u of Σ w |φ_i φ_j| <= sqrt(Λ_ii Λ_jj); the solve turns that into at
    most κ²·n·u of the parameters (κ the column-scaled condition the estimator reports; 12,867 here, where 20 s
    of one turn leave the offset ill-determined), so at most |B|·κ²·n·u nT of an offset. Measured on an AVX-512
    machine: Λ 4.0e-15 of its scaling (the bound 4.4e-13), offsets 0.0124 nT apart (the bound 3.8 nT); on an
    AVX2-only one 0.0126 nT, which the former atol of 1e-6 nT refused."""
    from fluxcal.service.wiring.commands.replay import UNIT_ROUNDOFF, rounding_tolerance_nT

    w, s = world(duration_s=20.0)
    raw, ref = s.raw_nT[:, 0], s.ref_total_nT
    kw = dict(forgetting=0.999, forget_deg=None, max_condition=1e6)
    a, b = RlsEllipsoid(**kw), RlsEllipsoid(**kw)
    a.partial_fit(raw[:50], ref[:50])                                # the first block fixes the scaling
    b.partial_fit(raw[:50], ref[:50])
    a.partial_fit(raw[50:], ref[50:])
    for i in range(50, len(raw)):
        b.partial_fit(raw[i:i + 1], ref[i:i + 1])
    n = len(raw)
    scaling = np.sqrt(np.outer(np.diag(a.info_), np.diag(a.info_)))
    assert np.all(np.abs(a.info_ - b.info_) <= n * UNIT_ROUNDOFF * scaling)
    kappa = a.condition_
    assert 1e4 < kappa < 2e4                                          # the ill-conditioned case this test is about
    sa, sb = a.snapshot(), b.snapshot()
    field = float(np.linalg.norm(raw, axis=1).max())
    assert np.abs(sa.offset_nT - sb.offset_nT).max() <= rounding_tolerance_nT(field, kappa, n)
    assert np.abs(sa.matrix - sb.matrix).max() <= kappa ** 2 * n * UNIT_ROUNDOFF


def test_rls_tracks_an_offset_step_within_stated_samples():
    # memory 1/(1-λ) = 1000 samples; stated (docs/service.md): after 10 memories the offset is within 2 nT of
    # a 100 nT step. Mixed data from before and after the step fit a compromise ellipsoid, so the
    # approach is slower than an exponential average's (measured: 47% after 1, 67% after 5 memories)
    lam = 0.999
    w, s = world(duration_s=200.0)
    raw, ref = s.raw_nT[:, 0].copy(), s.ref_total_nT
    step_at = 20000
    raw[step_at:, 0] += 100.0
    est = RlsEllipsoid(forgetting=lam)
    track = []
    for i in range(0, len(raw), 100):
        est.partial_fit(raw[i:i + 100], ref[i:i + 100])
        if i + 100 > step_at:
            track.append((i + 100 - step_at, est.snapshot().offset_nT[0]))
    before = 200.0
    stated = 10 * int(1 / (1 - lam))
    after = [x for n, x in track if n >= stated]
    assert all(abs(x - (before + 100.0)) < 2.0 for x in after), after[:5]
    early = [x for n, x in track if n <= 200]
    assert early[0] < before + 50.0                                 # not instantaneous: it is a filter


def test_rls_survives_a_long_rest_without_wind_up_or_nan():
    w, s = world(duration_s=60.0)
    raw, ref = s.raw_nT[:, 0], s.ref_total_nT
    est = RlsEllipsoid(forgetting=0.999)
    est.partial_fit(raw, ref)
    good = est.snapshot()
    rest = np.repeat(raw[-1:], 100000, axis=0) + np.random.default_rng(3).normal(0, 1.0, (100000, 3))
    for i in range(0, len(rest), 1000):
        est.partial_fit(rest[i:i + 1000], np.full(1000, ref[-1]))
        snap = est.snapshot()
        assert snap.is_finite()
    # the unobserved directions kept their last good value
    assert np.abs(snap.offset_nT - good.offset_nT).max() < 5.0
    est.partial_fit(raw, ref)                                       # motion returns: recovers
    assert np.abs(est.snapshot().offset_nT - np.array(PROBE["offset_nT"])).max() < 1.0


def test_rotation_alignment_recovers_relative_misalignment():
    p2 = {**PROBE, "misalign_deg": [-4.0, 3.0, 7.0], "offset_nT": [-100.0, 50.0, 300.0], "position_m": [0.3, 0, 0]}
    p1 = {**PROBE, "position_m": [-0.3, 0, 0]}
    w, s = world(probes=[p1, p2])
    truth = w.truth()["sensors"]
    fits = [fit_ellipsoid(s.raw_nT[:, k], s.ref_total_nT, name=f"s{k + 1}").calibration for k in range(2)]
    aligned = align_probes(fits, s.raw_nT, method="rotation")
    # each aligned frame is the platform frame turned by one common rotation C_k = M_true,k M_k⁻¹
    c = [np.array(truth[k]["matrix"]) @ np.linalg.inv(aligned[k].matrix) for k in range(2)]
    assert np.abs(c[0] - c[1]).max() < 2e-4
    assert np.allclose(c[0] @ c[0].T, np.eye(3), atol=2e-4)
    corr = np.stack([p.apply(s.raw_nT[:, k]) for k, p in enumerate(aligned)], axis=1)
    assert np.sqrt(np.mean((corr[:, 1] - corr[:, 0]) ** 2)) < 2.0   # noise of the two probes, ~1.4 nT


def test_euler_angles_round_trip():
    a, b, g = 0.3, -0.2, 1.1
    assert np.allclose(angles_from_rotation(rotation_from_angles(a, b, g)), (a, b, g))


def test_tensor_of_a_linear_field_and_the_cross():
    g_true = np.array([[10.0, 3.0, -2.0], [3.0, -4.0, 5.0], [-2.0, 5.0, -6.0]])
    pos = np.array([[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]])
    b0 = np.array([20000.0, 1000.0, 45000.0])
    fields = (b0 + pos @ g_true)[None].repeat(5, axis=0)            # B(r) = B0 + Gᵀ r
    g = tensor_from_positions(fields, pos)
    assert np.allclose(g, g_true[None], atol=1e-9)
    assert np.allclose(tensor_cross(fields, 0.4), g_true[None], atol=1e-9)
    inv = invariants(g)
    assert np.allclose(inv["I0"], 0.0, atol=1e-9)


def test_calibration_file_round_trip_and_refusals(tmp_path):
    w, s = world(duration_s=30.0)
    cal = fit_ellipsoid(s.raw_nT[:, 0], s.ref_total_nT).calibration
    arr = ArrayCalibration(method="ellipsoid", align=None, probes=[cal], total_nT=52500.0, span=(0.0, 30.0, 6000))
    path = tmp_path / "cal.json"
    save_calibration(arr, path)
    import os

    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask              # readable as the user's files are, not 0600
    back = load_calibration(path)
    assert np.array_equal(back.probes[0].matrix, cal.matrix)
    assert np.array_equal(back.probes[0].offset_nT, cal.offset_nT)
    d = json.loads(path.read_text())
    d["version"] = 99
    (tmp_path / "v99.json").write_text(json.dumps(d))
    with pytest.raises(DataError, match="version 99"):
        load_calibration(tmp_path / "v99.json")
    (tmp_path / "cut.json").write_text(path.read_text()[:200])
    with pytest.raises(DataError, match="damaged"):
        load_calibration(tmp_path / "cut.json")
    d["version"] = 1
    d["probes"][0]["matrix"] = [[1, 0], [0, 1]]
    (tmp_path / "shape.json").write_text(json.dumps(d))
    with pytest.raises(DataError, match="shape"):
        load_calibration(tmp_path / "shape.json")
