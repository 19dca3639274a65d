"""[SineFit] (non-orthogonality from a turntable rotation by sine fits): its simulation and Table 1.

The simulation (tests/sims_003_004.py): α = 1.5°, β = 32.5°, γ = 1.7°, B = 52000 nT, I = 47°, one
turn of 360 samples, initial phase 91° (which reproduces the paper's printed curves), noise read
as σ = n/2 per axis (the reading that reproduces the paper's σ column).
"""

from __future__ import annotations

import numpy as np
import pytest
from sims_003_004 import P003_CURVES, P003_TABLE1, paper003

from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.service.numerics.calib.sinefit import fit_sine_nonorthogonality, fit_sinefit

TRUTH = (1.5, 32.5, 1.7)


def angles(r):
    return np.array([r.alpha_deg, r.beta_deg, r.gamma_deg])


def test_noise_free_turn_gives_the_exact_angles_and_the_papers_curves():
    s = paper003(0.0)
    r = fit_sine_nonorthogonality(s.theta_rad, s.raw_nT)
    assert np.allclose(angles(r), TRUTH, atol=1e-9)
    # Table 1 row 0: φ = 88.566°, η = 89.050° (printed to 3 decimals), σ = 0
    a, b, g, phi, eta, sigma = P003_TABLE1[0]
    # (η = 89.04947°: the paper rounds it up to 89.050)
    assert abs(r.phi_deg - phi) < 6e-4 and abs(r.eta_deg - eta) < 6e-4
    assert abs(r.phi_deg - s.phi_deg) < 1e-9 and abs(r.eta_deg - s.eta_deg) < 1e-9
    corrected = r.calibration.apply(s.raw_nT)
    assert np.abs(corrected - s.field_nT).max() < 1e-7              # eq. 7 and 10 undo eq. 1
    assert r.residual_rms_nT < 1e-7
    # section 3.1's fitted curves: x = 35463.9 sin(t + 91), y = 35463.9 sin(t + 179.5),
    # z = A sin(t + 123.5) + 38013.7
    for k, axis in enumerate("xyz"):
        amp, phase, mean = P003_CURVES[axis]
        assert abs(r.phase_deg[k] - phase) < 1e-9
        assert abs(r.mean_nT[k] - mean) < 0.05
        if axis != "z":
            assert abs(r.amplitude_nT[k] - amp) < 0.05
    # the paper prints A_z = 10520.8; B cos I sin γ = 1052.08: the printed value is ten times too large
    assert abs(r.amplitude_nT[2] - 1052.08) < 0.01
    # with o_z = 0 (the paper's model) the mean of z gives the inclination back
    assert abs(r.inclination_deg - 47.0) < 1e-9


@pytest.mark.parametrize("noise_nT", [30, 50, 100])
def test_table1_angles_within_035_deg_and_residual_below_the_noise(noise_nT):
    s = paper003(noise_nT, seed=0)
    r = fit_sine_nonorthogonality(s.theta_rad, s.raw_nT)
    err = angles(r) - TRUTH
    # [SineFit]: "β and γ change by at most 0.35°"; measured (seed 0): β 0.03 / 0.05 / 0.09°, α and γ < 0.02°
    assert np.abs(err).max() < 0.35, err
    # each error within 4 of its own standard error: the standard errors are honest
    se = np.array([r.se_deg["alpha"], r.se_deg["beta"], r.se_deg["gamma"]])
    assert np.all(np.abs(err) < 4 * se), (err, se)
    # residual (eq. 13) against the true B: below the noise level, near the paper's σ column
    res = np.sqrt(np.mean((np.linalg.norm(r.calibration.apply(s.raw_nT), axis=1) - s.total_nT) ** 2))
    assert res < noise_nT
    paper_sigma = P003_TABLE1[noise_nT][5]
    assert abs(res - paper_sigma) / paper_sigma < 0.1, (res, paper_sigma)
    # φ, η: "the three inter-axis angles are off by at most 0.2°"
    assert abs(r.phi_deg - s.phi_deg) < 0.2 and abs(r.eta_deg - s.eta_deg) < 0.2


def test_standard_errors_match_the_scatter_over_seeds():
    est, se = [], []
    for seed in range(40):
        s = paper003(100, seed=seed)
        r = fit_sine_nonorthogonality(s.theta_rad, s.raw_nT)
        est.append(angles(r))
        se.append([r.se_deg["alpha"], r.se_deg["beta"], r.se_deg["gamma"]])
    ratio = np.std(est, axis=0) / np.mean(se, axis=0)
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio
    # β is the fragile angle (the z sine is only B cos I sin γ ≈ 1052 nT): σ_β ≈ 0.2° at 100 nT;
    # α moves too (σ ≈ 0.009°), which the paper's Table 1 ("α does not change") hides in rounding
    assert 0.15 < np.mean(se, axis=0)[1] < 0.25
    assert 0.005 < np.std(est, axis=0)[0] < 0.015


def test_sigma_equal_to_the_noise_level_leaves_the_residual_at_the_noise_not_below():
    # the other reading of "noise n nT" (σ = n per axis): |B| errs by the noise along B, ≈ n
    s = paper003(100, seed=0, noise_sd_per_level=1.0)
    r = fit_sine_nonorthogonality(s.theta_rad, s.raw_nT, total_nT=s.total_nT, inclination_deg=47.0)
    assert 90.0 < r.residual_rms_nT < 105.0


def test_unknown_table_angle_is_estimated_from_a_constant_rate():
    s = paper003(0.0)
    t = 7.0 + s.t_s / 5.0                                   # 5°/s, clock starting at 7 s
    r = fit_sine_nonorthogonality(None, s.raw_nT, t_s=t)
    assert abs(r.rate_rad_s - np.radians(5.0)) < 1e-9
    assert np.allclose(angles(r), TRUTH, atol=1e-6)
    noisy = paper003(50, seed=1)
    known = fit_sine_nonorthogonality(noisy.theta_rad, noisy.raw_nT)
    unknown = fit_sine_nonorthogonality(None, noisy.raw_nT)          # sample index as time
    assert np.abs(angles(known) - angles(unknown)).max() < 0.01


def test_a_table_angle_read_the_other_way_is_reversed_not_misread():
    s = paper003(0.0)
    r = fit_sine_nonorthogonality(-s.theta_rad, s.raw_nT)
    assert r.angle_reversed and r.calibration.params["angle_reversed"] is True
    assert np.allclose(angles(r), TRUTH, atol=1e-9)


def test_offsets_and_scales_with_the_field_known():
    offset, scale = np.array([120.0, -80.0, 45.0]), np.array([1.012, 0.991, 1.012])   # k_z = k_x (assumed)
    s = paper003(0.0, offset_nT=offset, scale=scale)
    r = fit_sine_nonorthogonality(s.theta_rad, s.raw_nT, total_nT=52000.0, inclination_deg=47.0)
    cal = r.calibration
    assert np.allclose(cal.offset_nT, offset, atol=1e-6)
    assert np.allclose(cal.value("scale"), scale, atol=1e-9)
    assert np.allclose(angles(r), TRUTH, atol=1e-9)
    assert np.abs(cal.apply(s.raw_nT) - s.field_nT).max() < 1e-6
    # without the inclination, o_z = 0 is assumed and the z offset goes into the estimated inclination
    r2 = fit_sine_nonorthogonality(s.theta_rad, s.raw_nT, total_nT=52000.0)
    assert r2.calibration.offset_nT[2] == 0.0 and any("o_z = 0" in a for a in r2.assumed)
    assert np.allclose(angles(r2), TRUTH, atol=1e-9)               # the angles do not need it


def test_half_a_turn_is_refused_with_what_to_do():
    s = paper003(0.0)
    keep = s.theta_rad < np.radians(180.0)
    with pytest.raises(CalibrationRefused, match=r"gap of 181°.*one full turn"):
        fit_sine_nonorthogonality(s.theta_rad[keep], s.raw_nT[keep])


def test_method_entry_point_returns_a_probe_calibration():
    s = paper003(30, seed=2)
    cal = fit_sinefit(s.theta_rad, s.raw_nT, inclination_deg=47.0, total_nT=52000.0, name="s3")
    assert cal.name == "s3" and cal.is_finite()
    a, b, g = cal.value("nonorth_deg")
    assert abs(b - 32.5) < 0.35 and abs(a - 1.5) < 0.05 and abs(g - 1.7) < 0.05
    assert np.all(cal.offset_se_nT[:2] > 0) and np.all(np.isfinite(cal.matrix_se))


def test_fluxcal_fit_sinefit_from_a_lab_csv(tmp_path, capsys):
    # docs/csv.md, docs/cli.md: a lab CSV with the table angle in an 'angle_deg' column
    import json

    from fluxcal.service.wiring.cli import main

    s = paper003(30, seed=0)
    path = tmp_path / "turntable.csv"
    rows = [f"{t:.1f},{x:.4f},{y:.4f},{z:.4f},{np.degrees(a):.4f}"
            for t, (x, y, z), a in zip(s.t_s, s.raw_nT, s.theta_rad)]
    path.write_text("# 003 simulation, 30 nT\nt,s1_x,s1_y,s1_z,angle_deg\n" + "\n".join(rows) + "\n")
    capsys.readouterr()
    assert main(["fit", str(path), "--method", "sinefit", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    m = np.array(out["sensors"][0]["matrix"])
    direct = fit_sine_nonorthogonality(s.theta_rad, s.raw_nT).calibration.matrix
    assert out["method"] == "sinefit" and np.allclose(m, direct, atol=1e-6)
    assert out["sensors"][0]["scalar_rms_nT"] < 30.0
