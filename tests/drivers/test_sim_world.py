"""The simulated world against its own truth and against [FastRotation]: field, motion, forward model, effects."""

from __future__ import annotations

import copy
import math
import warnings

import numpy as np
import pytest

from fluxcal.drivers.block import FLAG_SATURATED, FLAG_TEMP_INVALID
from fluxcal.drivers.errors import ConfigError
from fluxcal.drivers.sim import Unit, World, load_sim_config
from fluxcal.drivers.sim.config import GRADIOMETER
from fluxcal.drivers.sim.motion import (
    attitude_from_euler_deg,
    geomagnetic_field_nT,
    misalignment_matrix,
    nonorthogonality_matrix,
    rotation,
)

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.drivers.sim.physics",)

F, INC, DEC = 50000.0, 62.0, -4.0


def make(probes=None, **sim):
    table = {"seed": 7, "rate_hz": 100.0, "duration_s": 10.0,
             "field": {"total_nT": F, "inclination_deg": INC, "declination_deg": DEC},
             "motion": {"kind": "tumble", "rate_deg_s": 40.0, "tumble_period_s": 3.0}}
    table.update(sim)
    table["probes"] = probes if probes is not None else [{"position_m": [-0.25, 0, 0]}, {"position_m": [0.25, 0, 0]}]
    return World(load_sim_config(table))


def paper001_cross(noise_nT=1.0):
    """[FastRotation] section 5.1: four probes in a cross (d = 0.4 m), Table 1 errors, Table 3 misalignments,
    60000 nT, I = 57 deg, D = -5 deg, 12^3 attitudes (z fastest, then y, then x)."""
    phi = [3.56, -2.74, 1.86, -3.28]
    theta = [-1.85, 3.11, -2.95, 2.44]
    psi = [2.27, 1.66, 3.02, -1.88]
    c = [[1.253, 1.175, 0.859], [0.951, 1.202, 1.105], [1.110, 0.799, 1.308], [0.853, 1.235, 1.186]]
    i0 = [[357, 160, -213], [-253, 183, 97], [169, -364, 245], [256, 169, -166]]
    mis = [[-21.97, 12.88, 13.64], [12.51, -3.96, 21.42], [-11.77, 7.46, -13.03], [12.17, 13.39, 9.64]]
    pos = [[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]]
    probes = [{"position_m": pos[k], "scale": c[k], "nonorth_deg": [phi[k], theta[k], psi[k]],
               "misalign_deg": mis[k], "offset_nT": i0[k], "noise_nT": noise_nT} for k in range(4)]
    return World(load_sim_config({
        "seed": 1, "rate_hz": 10.0, "duration_s": 172.8,
        "field": {"total_nT": 60000.0, "inclination_deg": 57.0, "declination_deg": -5.0},
        "motion": {"kind": "grid", "axes": ["z", "y", "x"], "steps_per_turn": 12, "hold_s": 0.1},
        "probes": probes}))


# --- field and motion -------------------------------------------------------------------------------

def test_ideal_world_total_field_everywhere_and_ned_components():
    w = make(motion={"kind": "tumble", "rate_deg_s": 60.0})
    s = w.samples(0, w.n_samples)
    total = np.linalg.norm(s.field_platform_nT, axis=-1)
    assert np.max(np.abs(total - F)) < 1e-8
    # ideal probes output the field itself
    assert np.max(np.abs(s.output_nT - s.field_platform_nT)) < 1e-8
    # rotated back to NED, every sample gives the geomagnetic components
    i, d = math.radians(INC), math.radians(DEC)
    expect = F * np.array([math.cos(i) * math.cos(d), math.cos(i) * math.sin(d), math.sin(i)])
    ned = np.einsum("nij,nj->ni", s.attitude, s.field_platform_nT[:, 0])
    assert np.max(np.abs(ned - expect)) < 1e-8
    assert expect[0] > 0 and expect[1] < 0 and expect[2] > 0      # north, west of north (D < 0), down


def test_static_platform_reads_the_ned_components_directly():
    w = make(motion={"kind": "static"})
    s = w.samples(0, 5)
    np.testing.assert_allclose(s.field_platform_nT[:, 1], np.tile(geomagnetic_field_nT(F, INC, DEC), (5, 1)),
                               atol=1e-9)
    assert geomagnetic_field_nT(F, INC, DEC)[2] == pytest.approx(F * math.sin(math.radians(INC)))


@pytest.mark.parametrize("motion", [
    {"kind": "tumble", "rate_deg_s": 45.0, "tumble_period_s": 2.0, "initial_deg": [10, -20, 30]},
    {"kind": "turntable", "axes": ["z", "y", "x"], "rate_deg_s": 90.0, "dwell_s": 0.2, "ramp_s": 0.5},
])
def test_angular_rate_matches_the_attitude_derivative(motion):
    w = make(motion=motion)
    t = np.linspace(0.05, 12.0, 1500)
    h = 1e-5
    r0, r1, r2 = (w.motion.attitude(t + d) for d in (-h, 0.0, h))
    # dR/dt = R [w]x  ->  [w]x = R^T dR/dt
    wx = np.einsum("nji,njk->nik", r1, (r2 - r0) / (2 * h))
    fd = np.stack([wx[:, 2, 1], wx[:, 0, 2], wx[:, 1, 0]], axis=1)
    np.testing.assert_allclose(w.motion.angular_rate(t), fd, atol=1e-6)
    # attitudes are proper rotations
    np.testing.assert_allclose(np.einsum("nji,njk->nik", r1, r1), np.broadcast_to(np.eye(3), r1.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r1), 1.0, atol=1e-12)


def test_tumble_rate_is_near_the_configured_rate_and_covers_directions():
    w = make(motion={"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 5.0}, duration_s=120.0)
    rms = w.rms_rate_deg_s()
    assert 20.0 < rms < 40.0
    s = w.samples(0, w.n_samples)
    unit = s.field_platform_nT[:, 0] / F
    # every octant of the sphere of field directions is visited
    octants = {tuple(v) for v in (unit > 0).astype(int)}
    assert len(octants) == 8


def test_turntable_turns_about_one_platform_axis_at_a_time():
    w = make(motion={"kind": "turntable", "axes": ["z", "y"], "rate_deg_s": 90.0, "turns": 1, "dwell_s": 1.0},
             rate_hz=50.0, duration_s=10.0)
    s = w.samples(0, w.n_samples)
    b = s.field_origin_nT
    z_turn = (s.t_s > 1.0) & (s.t_s < 5.0)        # dwell 1 s, then 4 s for 360 deg about z
    y_turn = (s.t_s > 6.0) & (s.t_s < 10.0)
    ned = geomagnetic_field_nT(F, INC, DEC)
    assert np.ptp(b[z_turn, 2]) < 1e-8 and np.ptp(b[z_turn, 0]) > 1000
    assert np.ptp(b[y_turn, 1]) < 1e-8 and np.ptp(b[y_turn, 2]) > 1000
    # rate 90 deg/s about z
    np.testing.assert_allclose(s.angular_rate_rad_s[z_turn][:, 2], math.radians(90.0))
    # after whole turns the platform is back where it started
    np.testing.assert_allclose(w.motion.attitude(np.array([5.0 + 0.5]))[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(b[0], ned, atol=1e-9)


def test_grid_has_the_paper_12_cubed_attitudes():
    w = paper001_cross()
    j = w.motion.index(w.times(0, 1728))
    assert np.array_equal(j, np.arange(1728))       # one sample per attitude, i / rate_hz lands exactly
    r = w.motion.attitude(w.times(0, 1728))
    # first 12: 30 degree steps about z
    np.testing.assert_allclose(r[1], rotation("z", math.radians(30)), atol=1e-12)
    np.testing.assert_allclose(r[12], rotation("y", math.radians(30)), atol=1e-12)
    np.testing.assert_allclose(r[144], rotation("x", math.radians(30)), atol=1e-12)


# --- the probe model ---------------------------------------------------------------------------------

def test_forward_model_inverts_with_the_truth_matrix_to_the_noise():
    cfg = copy.deepcopy(GRADIOMETER)
    cfg["duration_s"] = 20.0
    w = World(load_sim_config(cfg))
    s = w.samples(0, w.n_samples)
    truth = w.truth()
    for k, sensor in enumerate(truth["sensors"]):
        m, off = np.array(sensor["matrix"]), np.array(sensor["offset_nT"])
        exact = (s.output_nT[:, k] - off) @ m.T
        np.testing.assert_allclose(exact, s.field_platform_nT[:, k], atol=1e-7)
        noisy = (s.raw_nT[:, k] - off) @ m.T
        resid = noisy - s.field_platform_nT[:, k]
        # matrix ~ identity, so the residual is the probe noise (0.6 / 0.8 nT), to within a few percent
        expect = np.array(sensor["noise_nT"])
        np.testing.assert_allclose(resid.std(axis=0), expect, rtol=0.06)
    # the errors are realistic: a few hundred nT of offset and percent scale errors change |B| a lot
    assert np.sqrt(np.mean((np.linalg.norm(s.raw_nT[:, 0], axis=-1) - 52500.0) ** 2)) > 300


def test_matrices_are_paper001_eq11_and_eq5():
    phi, theta, psi = np.radians([3.56, -1.85, 2.27])
    a = nonorthogonality_matrix(phi, theta, psi)
    c = np.array([1.253, 1.175, 0.859])
    # [FastRotation] eq. 12: (C A)^-1 is upper triangular with k_x = 1/(c_x cosφ cosθ), k_y = 1/(c_y cosψ), k_z = 1/c_z,
    # m k_y = -tanθ k_y, n k_z = -tanψ k_z
    inv = np.linalg.inv(c[:, None] * a)
    kx, ky, kz = 1 / (c[0] * math.cos(phi) * math.cos(theta)), 1 / (c[1] * math.cos(psi)), 1 / c[2]
    assert inv[0, 0] == pytest.approx(kx) and inv[1, 1] == pytest.approx(ky) and inv[2, 2] == pytest.approx(kz)
    assert inv[0, 1] == pytest.approx(-math.tan(theta) * ky) and inv[1, 2] == pytest.approx(-math.tan(psi) * kz)
    assert abs(inv[1, 0]) < 1e-15 and abs(inv[2, 0]) < 1e-15 and abs(inv[2, 1]) < 1e-15
    # [FastRotation] eq. 6 written out: first row of T = (cosβcosγ, cosβsinγ, -sinβ)
    al, be, ga = np.radians([-21.97, 12.88, 13.64])
    t = misalignment_matrix(al, be, ga)
    np.testing.assert_allclose(t[0], [math.cos(be) * math.cos(ga), math.cos(be) * math.sin(ga), -math.sin(be)])
    np.testing.assert_allclose(t[1, 2], math.sin(al) * math.cos(be))
    np.testing.assert_allclose(t @ t.T, np.eye(3), atol=1e-12)


def test_paper001_table2_and_table4_before_calibration():
    """Our forward model on [FastRotation]'s simulation gives the paper's uncalibrated errors (Tables 2, 4)."""
    w = paper001_cross(noise_nT=1.0)
    s = w.samples(0, 1728)
    tmi_rmse = np.sqrt(np.mean((np.linalg.norm(s.raw_nT, axis=-1) - 60000.0) ** 2, axis=0))
    np.testing.assert_allclose(tmi_rmse, [8994.31, 6714.99, 9041.56, 8723.06], atol=0.5)
    b, d = s.raw_nT, 0.4
    d13, d24 = (b[:, 0] - b[:, 2]) / d, (b[:, 1] - b[:, 3]) / d
    rms = lambda x: float(np.sqrt(np.mean(x ** 2)))  # noqa: E731
    # Table 4 "before" row, columns in the paper's order
    got = [rms(d13[:, 0]), rms(d24[:, 0]), rms(d13[:, 2]), rms(d13[:, 1]), rms(d24[:, 1]), rms(d24[:, 2])]
    np.testing.assert_allclose(got, [52171, 28115, 42346, 53898, 21816, 30940], atol=2.0)


def test_gradient_difference_between_probes_is_g_times_baseline():
    g = np.array([[12.0, 5.0, -3.0], [5.0, -20.0, 7.0], [-3.0, 7.0, 8.0]])      # symmetric, traceless
    w = make(field={"total_nT": F, "inclination_deg": INC, "declination_deg": DEC, "gradient_nT_m": g.tolist()},
             probes=[{"position_m": [-0.25, 0.1, 0.0]}, {"position_m": [0.25, 0.0, 0.05]}])
    s = w.samples(0, w.n_samples)
    dr = np.array([0.5, -0.1, 0.05])
    diff_platform = s.field_platform_nT[:, 1] - s.field_platform_nT[:, 0]
    # in the platform frame: R^T G^T R dr (G fixed in the earth frame while the platform turns)
    expect = np.einsum("nji,jk,nkl,l->ni", s.attitude, g, s.attitude, dr)
    np.testing.assert_allclose(diff_platform, expect, atol=1e-8)
    # in the earth frame it is G^T dr_earth with dr_earth = R dr, the baseline turning with the platform
    diff_earth = np.einsum("nij,nj->ni", s.attitude, diff_platform)
    dr_earth = np.einsum("nij,j->ni", s.attitude, dr)
    np.testing.assert_allclose(diff_earth, dr_earth @ g, atol=1e-8)
    assert np.ptp(diff_earth[:, 0]) > 5.0
    assert "gradient" in w.active_effects


def test_non_physical_gradient_warns_naming_the_key():
    with pytest.warns(UserWarning, match=r"sim.field.gradient_nT_m"):
        load_sim_config({"field": {"gradient_nT_m": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_sim_config({"field": {"gradient_nT_m": [[1, 2, 0], [2, -1, 0], [0, 0, 0]]}})


# --- effects -----------------------------------------------------------------------------------------

def two_worlds(probe_extra, **sim):
    base = {"position_m": [0.3, 0.0, 0.0], "scale": [1.02, 0.97, 1.01], "nonorth_deg": [1, -2, 1.5],
            "misalign_deg": [2, -1, 3], "offset_nT": [100, -200, 50]}
    plain = make(probes=[dict(base)], **sim)
    with_effect = make(probes=[{**base, **probe_extra}], **sim)
    return plain, with_effect


def test_lag_probe_sees_the_instant_t_plus_lag():
    plain, lagged = two_worlds({"lag_s": 0.0123})
    t = plain.times(0, plain.n_samples)
    got = lagged.evaluate(t).output_nT
    np.testing.assert_allclose(got, plain.evaluate(t + 0.0123).output_nT, atol=1e-8)
    # against the no-lag samples: linear interpolation between the 10 ms samples, within its error
    ref = plain.samples(0, plain.n_samples, noise=False).output_nT[:, 0]
    inner = (t > 0.1) & (t < t[-1] - 0.1)
    interp = np.stack([np.interp(t + 0.0123, t, ref[:, a]) for a in range(3)], axis=1)
    err = np.abs(got[inner, 0] - interp[inner]).max()
    effect = np.abs(got[inner, 0] - ref[inner]).max()
    assert effect > 100.0 and err < 0.02 * effect
    assert lagged.active_effects == ["lag"] and plain.active_effects == []


def test_eddy_adds_e_times_db_dt_and_scales_with_rate():
    e = [[2e-3, 0.0, 0.0], [0.0, 1e-3, 5e-4], [0.0, 0.0, -1.5e-3]]
    motion = {"kind": "turntable", "axes": ["z", "x"], "rate_deg_s": 60.0, "dwell_s": 0.5}
    plain, eddy = two_worlds({"eddy_s": e}, motion=motion)
    t = plain.times(0, plain.n_samples)
    a, b = plain.evaluate(t), eddy.evaluate(t)
    ca = plain.probes.scale[0][:, None] * plain.probes.nonorth[0]
    expect = np.einsum("ij,jk,nk->ni", ca, np.array(e), a.dsensor_dt_nT_s[:, 0])
    np.testing.assert_allclose(b.output_nT[:, 0] - a.output_nT[:, 0], expect, atol=1e-8)
    # dB/dt is the derivative of the sensor-frame field
    h = 1e-5
    fd = (plain.evaluate(t + h).field_sensor_nT - plain.evaluate(t - h).field_sensor_nT) / (2 * h)
    moving = np.abs(a.angular_rate_rad_s).sum(axis=1) > 0
    np.testing.assert_allclose(a.dsensor_dt_nT_s[moving], fd[moving], atol=1e-3)
    # while turning at 60 deg/s |dB/dt| reaches |B_perp| * 1.047 rad/s; standing still: nothing
    assert np.abs(expect[~moving]).max() < 1e-9
    assert np.abs(expect[moving]).max() > 50.0
    _, fast = two_worlds({"eddy_s": e}, motion={**motion, "rate_deg_s": 120.0})
    peak_fast = np.abs(fast.evaluate(t / 2).output_nT - make(probes=[{"position_m": [0.3, 0, 0],
                       "scale": [1.02, 0.97, 1.01], "nonorth_deg": [1, -2, 1.5], "misalign_deg": [2, -1, 3],
                       "offset_nT": [100, -200, 50]}], motion={**motion, "rate_deg_s": 120.0}).evaluate(t / 2)
                       .output_nT).max()
    assert peak_fast == pytest.approx(2 * np.abs(expect).max(), rel=0.02)


def test_temperature_coefficients_give_the_offset_and_scale_change():
    temp = {"start_C": 15.0, "ramp_C_per_h": 36.0, "amplitude_C": 2.0, "period_s": 4.0, "reference_C": 20.0}
    plain, hot = two_worlds({"temp_offset_nT_per_C": [1.5, -0.8, 0.3], "temp_scale_ppm_per_C": [0, 0, 0],
                             "temp_offset_C": 1.0}, temperature=temp)
    t = plain.times(0, plain.n_samples)
    a, b = plain.evaluate(t), hot.evaluate(t)
    expect_temp = 15.0 + 36.0 * t / 3600.0 + 2.0 * np.sin(2 * np.pi * t / 4.0) + 1.0
    np.testing.assert_allclose(b.temp_C[:, 0], expect_temp)
    np.testing.assert_allclose(b.output_nT[:, 0] - a.output_nT[:, 0],
                               np.outer(expect_temp - 20.0, [1.5, -0.8, 0.3]), atol=1e-8)
    _, scaled = two_worlds({"temp_scale_ppm_per_C": [200.0, 0.0, -100.0]}, temperature=temp)
    c = scaled.evaluate(t)
    u = a.output_nT[:, 0] - plain.probes.offset_nT[0]
    dtemp = (15.0 + 36.0 * t / 3600.0 + 2.0 * np.sin(2 * np.pi * t / 4.0) - 20.0)[:, None]
    np.testing.assert_allclose(c.output_nT[:, 0] - a.output_nT[:, 0], u * 1e-6 * np.array([200, 0, -100]) * dtemp,
                               atol=1e-8)


def test_nonlinearity_is_u_plus_q_u2_plus_c_u3():
    q, c = [1e-7, 0.0, -2e-7], [2e-12, -1e-12, 0.0]
    plain, nl = two_worlds({"nonlin_quadratic_per_nT": q, "nonlin_cubic_per_nT2": c})
    t = plain.times(0, 200)
    u = plain.evaluate(t).output_nT[:, 0] - plain.probes.offset_nT[0]
    got = nl.evaluate(t).output_nT[:, 0] - plain.probes.offset_nT[0]
    np.testing.assert_allclose(got, u + np.array(q) * u ** 2 + np.array(c) * u ** 3, atol=1e-8)
    assert np.abs(got - u).max() > 50.0        # 2e-12 * (5e4)^3 = 250 nT: a visible effect


def test_drift_of_offsets_and_of_the_ambient_field():
    plain, drifting = two_worlds({"drift_offset_nT_per_h": [36.0, 0.0, -72.0]})
    t = plain.times(0, plain.n_samples)
    np.testing.assert_allclose(drifting.evaluate(t).output_nT[:, 0] - plain.evaluate(t).output_nT[:, 0],
                               np.outer(t / 3600.0, [36.0, 0.0, -72.0]), atol=1e-8)
    w = make(field={"total_nT": F, "inclination_deg": INC, "declination_deg": DEC, "drift_nT_per_h": [0, 0, 360.0]},
             reference={"enabled": True, "noise_nT": 0.0})
    s = w.samples(0, w.n_samples)
    np.testing.assert_allclose(s.field_earth_nT[:, 2] - s.field_earth_nT[0, 2], 0.1 * s.t_s, atol=1e-9)
    np.testing.assert_allclose(s.ref_total_nT, np.linalg.norm(s.field_earth_nT, axis=1))
    assert w.active_effects == ["drift"]


def test_reference_noise_and_probe_noise_are_gaussian_with_the_configured_sigma():
    w = make(probes=[{"noise_nT": [0.5, 1.0, 2.0]}], reference={"enabled": True, "noise_nT": 0.2},
             duration_s=100.0)
    s = w.samples(0, w.n_samples)
    np.testing.assert_allclose(s.noise_nT[:, 0].std(axis=0), [0.5, 1.0, 2.0], rtol=0.03)
    np.testing.assert_allclose((s.ref_total_nT - np.linalg.norm(s.field_earth_nT, axis=1)).std(), 0.2, rtol=0.03)
    assert abs(s.noise_nT[:, 0].mean(axis=0)).max() < 0.05


def test_samples_do_not_depend_on_how_the_run_is_cut():
    cfg = copy.deepcopy(GRADIOMETER)
    cfg["duration_s"] = 50.0
    w = World(load_sim_config(cfg))
    whole = w.samples(0, 10000)
    cuts = [0, 1, 17, 4095, 4097, 9000, 10000]
    parts = [World(load_sim_config(cfg)).samples(a, b) for a, b in zip(cuts, cuts[1:])]
    np.testing.assert_array_equal(np.concatenate([p.raw_nT for p in parts]), whole.raw_nT)
    np.testing.assert_array_equal(np.concatenate([p.ref_total_nT for p in parts]), whole.ref_total_nT)
    other_seed = World(load_sim_config({**cfg, "seed": 99})).samples(0, 100)
    assert not np.array_equal(other_seed.noise_nT, whole.noise_nT[:100])


# --- digitisation --------------------------------------------------------------------------------------

def test_quantisation_saturation_and_flags():
    unit = Unit(load_sim_config({"rate_hz": 50.0, "duration_s": 4.0, "lsb_nT": 1e-5,
                                 "field": {"total_nT": 50000.0, "inclination_deg": 60.0},
                                 "motion": {"kind": "turntable", "axes": ["y"], "rate_deg_s": 90.0, "dwell_s": 0},
                                 "faults": {"temp_invalid_fraction": 0.25},
                                 "probes": [{"noise_nT": 0.5}]}))
    s = unit.digitise(0, 200)
    # 1e-5 nT per count: the int32 range is +-21475 nT, so big components rail
    big = np.abs(s.world.raw_nT) > 2147483647 * 1e-5
    assert big.any() and (~big).any()
    assert np.array_equal(s.saturated, big)
    assert np.all(s.counts[big & (s.world.raw_nT > 0)] == 2147483647)
    assert np.all(s.counts[big & (s.world.raw_nT < 0)] == -2147483648)
    assert np.array_equal((s.flags & FLAG_SATURATED) != 0, big.any(axis=(1, 2)))
    ok = ~big
    assert np.abs(s.counts[ok] * 1e-5 - s.world.raw_nT[ok]).max() <= 0.5e-5 + 1e-9
    invalid = (s.flags & FLAG_TEMP_INVALID) != 0
    assert 20 < invalid.sum() < 80
    blk = s.to_block()
    assert np.isnan(blk.field_nT[big]).all() and np.isfinite(blk.field_nT[ok]).all()
    assert np.isnan(blk.temp_C[invalid]).all() and np.isfinite(blk.temp_C[~invalid]).all()
    np.testing.assert_allclose(blk.temp_C[~invalid], s.world.temp_C[~invalid], atol=0.005)


def test_range_nT_saturates_like_the_probe_would():
    unit = Unit(load_sim_config({"duration_s": 1.0, "range_nT": 30000.0,
                                 "field": {"total_nT": 50000.0, "inclination_deg": 70.0},
                                 "motion": {"kind": "static"}}))
    s = unit.digitise(0, 10)
    assert np.all(s.saturated[:, :, 2]) and not s.saturated[:, :, :2].any()
    assert np.all(s.flags & FLAG_SATURATED)


def test_counters_wrap_from_the_configured_start():
    unit = Unit(load_sim_config({"rate_hz": 1000.0, "duration_s": 1.0, "seq_start": 65530,
                                 "t_us_start": 2**32 - 3000}))
    s = unit.digitise(0, 10)
    assert s.seq_raw.tolist() == [65530, 65531, 65532, 65533, 65534, 65535, 0, 1, 2, 3]
    assert s.t_us_raw[:4].tolist() == [2**32 - 3000, 2**32 - 2000, 2**32 - 1000, 0]
    assert np.all(np.diff(s.to_block().t_s) == pytest.approx(1e-3))
    assert s.to_block().seq[-1] == 65539


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match=r"sim\.probes\[1\]\.scael: unknown key"):
        load_sim_config({"probes": [{}, {"scael": [1, 1, 1]}]})
    with pytest.raises(ConfigError, match=r"sim\.motion\.kind: 'spin' is not allowed"):
        load_sim_config({"motion": {"kind": "spin"}})
    with pytest.raises(ConfigError, match=r"sim\.rate_hz: -5.0 is below the minimum"):
        load_sim_config({"rate_hz": -5.0})
    with pytest.raises(ConfigError, match=r"sim\.probes\[0\]\.eddy_s: expected a 3x3 matrix"):
        load_sim_config({"probes": [{"eddy_s": [[0, 0], [0, 0]]}]})
    with pytest.raises(ConfigError, match=r"sim\.probes: 9 \[\[sim\.probes\]\] tables \(allowed: 1\.\.8\)"):
        load_sim_config({"probes": [{}] * 9})
    with pytest.raises(ConfigError, match=r"sim\.probes\[0\]\.noise_nT: expected a list of 3 values"):
        load_sim_config({"probes": [{"noise_nT": [1.0, 2.0]}]})
    with pytest.raises(ConfigError, match=r"sim\.faults\.outage_at_s"):
        load_sim_config({"faults": {"outage_at_s": [2.0, 1.0]}})
    cfg = load_sim_config({"probes": [{"noise_nT": 0.3}]})
    assert cfg.probes[0].noise_nT == [0.3, 0.3, 0.3]
    assert load_sim_config(cfg.as_dict()) == cfg


def test_truth_lists_every_parameter():
    table = copy.deepcopy(GRADIOMETER)
    table["probes"][1].update({"lag_s": 0.002, "eddy_s": [[1e-3, 0, 0], [0, 0, 0], [0, 0, 0]]})
    w = World(load_sim_config(table))
    truth = w.truth()
    assert truth["effects"] == ["lag", "eddy"]
    s2 = truth["sensors"][1]
    assert s2["name"] == "s2" and s2["position_m"] == [0.25, 0.0, 0.0]
    assert s2["effects"]["lag"] == {"lag_s": 0.002}
    assert s2["effects"]["eddy"]["matrix_s"][0][0] == 1e-3
    np.testing.assert_allclose(np.array(s2["matrix"]) @ np.array(s2["forward_matrix"]), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(truth["field"]["vector_nT"], geomagnetic_field_nT(52500.0, 52.8, -3.6))
    # the truth rebuilds the world
    again = World(load_sim_config(truth["config"]))
    np.testing.assert_array_equal(again.samples(0, 50).raw_nT, w.samples(0, 50).raw_nT)
    assert attitude_from_euler_deg(0, 0, 90) @ np.array([1.0, 0, 0]) == pytest.approx([0, 1, 0])
