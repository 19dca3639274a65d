"""The simulator's coloured noise and ambient variation: what tests of the statistics stand on.

- probe 1/f noise (`pink_nT_rtHz`): the spectrum falls as 1/f with the density asked for at 1 Hz, on
  several seeds; a run cut anywhere gives the same numbers; off by default (old runs unchanged);
- ambient variation (`field.variation_nT`): a field change common to every probe, with the RMS asked
  for, followed by the scalar reference.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import welch

from fluxcal.drivers.sim import Unit, load_sim_config


def unit(seed: int, *, pink=0.0, variation=0.0, duration=2000.0, rate=50.0, reference=False) -> Unit:
    return Unit(load_sim_config({
        "seed": seed, "rate_hz": rate, "duration_s": duration,
        "field": {"total_nT": 50000.0, "variation_nT": variation, "variation_min_period_s": 60.0},
        "reference": {"enabled": reference, "noise_nT": 0.0},
        "motion": {"kind": "tumble", "rate_deg_s": 20.0},
        "probes": [{"noise_nT": 0.0, "pink_nT_rtHz": pink, "position_m": [-0.5, 0, 0]},
                   {"noise_nT": 0.0, "pink_nT_rtHz": pink, "position_m": [0.5, 0, 0]}]}))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_pink_noise_has_a_one_over_f_spectrum_of_the_density_asked_for(seed):
    u = unit(seed, pink=0.05)
    n = u.world.samples(0, u.n_samples).noise_nT                   # (N, 2, 3)
    f, p = welch(n.reshape(n.shape[0], -1), fs=50.0, nperseg=2**14, axis=0)
    p = p.mean(axis=1)                                             # six channels
    band = (f > 0.01) & (f < 10.0)
    slope = np.polyfit(np.log(f[band]), np.log(p[band]), 1)[0]
    assert -1.15 < slope < -0.85
    # density at 1 Hz: sqrt(S f) is flat for 1/f noise; within 20 % of 0.05 nT/sqrt(Hz) in each decade
    for lo in (0.01, 0.1, 1.0):
        m = (f > lo) & (f < 10 * lo)
        assert 0.8 * 0.05 < np.sqrt(np.mean(p[m] * f[m])) < 1.2 * 0.05
    # the channels are independent
    c = np.corrcoef(n.reshape(n.shape[0], -1).T)
    assert np.max(np.abs(c - np.eye(6))) < 0.5


def test_pink_noise_is_the_same_however_the_run_is_cut():
    whole = unit(4, pink=0.05, duration=400.0).world.samples(0, 20000).noise_nT
    u = unit(4, pink=0.05, duration=400.0)
    later = u.world.samples(13000, 13100).noise_nT                   # asked for out of order, first
    parts = np.concatenate([u.world.samples(a, min(a + 777, 20000)).noise_nT for a in range(0, 20000, 777)])
    assert np.array_equal(parts, whole) and np.array_equal(later, whole[13000:13100])


def test_off_by_default_leaves_the_noise_white():
    u = unit(5)
    assert u.world._pink is None and u.world.field.variation is None and "ambient" not in u.world.active_effects


@pytest.mark.parametrize("seed", [1, 2])
def test_ambient_variation_is_common_to_all_probes_with_its_rms(seed):
    u = unit(seed, variation=4.0, duration=3600.0, rate=5.0, reference=True)
    s = u.world.samples(0, u.n_samples, noise=False)
    v = s.field_earth_nT - u.world.field.vector_nT
    assert np.allclose(np.std(v, axis=0).mean(), 4.0, rtol=0.35)   # one hour of a process with 4 h periods
    assert "ambient" in u.world.active_effects
    # both probes see it: their platform fields differ only by the gradient (none here)
    assert np.allclose(s.field_platform_nT[:, 0], s.field_platform_nT[:, 1], atol=1e-6)
    assert np.allclose(s.ref_total_nT, np.linalg.norm(s.field_earth_nT, axis=1))
    # structure on minutes: little power at periods shorter than 60 s
    f, p = welch(v[:, 0], fs=5.0, nperseg=4096)
    assert p[f > 1 / 30.0].sum() < 1e-3 * p.sum()


def test_thermal_lag_core_temperature_solves_its_equation():
    from fluxcal.drivers.sim.config import TemperatureConfig
    from fluxcal.drivers.sim.world import TemperatureProfile

    prof = TemperatureProfile(TemperatureConfig(start_C=20.0, ramp_C_per_h=30.0, amplitude_C=4.0, period_s=500.0))
    t = np.arange(0.0, 3000.0, 0.05)
    temp, core = prof.at(t), np.empty_like(t)
    core[0] = temp[0]
    a = np.exp(-0.05 / 90.0)
    for i in range(1, t.size):            # dT_c/dt = (T - T_c) / tau, stepped exactly for a linear T
        core[i] = a * core[i - 1] + (1 - a) * 0.5 * (temp[i] + temp[i - 1])
    assert np.max(np.abs(core - prof.core(t, 90.0))) < 1e-5
    assert np.array_equal(prof.core(t, 0.0), temp)


def test_thermal_lag_acts_on_the_effect_not_on_the_logged_temperature():
    cfg = {"seed": 1, "rate_hz": 5.0, "duration_s": 600.0, "motion": {"kind": "static"},
           "temperature": {"start_C": 20.0, "amplitude_C": 3.0, "period_s": 200.0},
           "probes": [{"temp_offset_nT_per_C": [2.0, 0.0, 0.0], "temp_lag_s": 60.0}]}
    lagged = Unit(load_sim_config(cfg)).world.samples(0, 3000, noise=False)
    cfg["probes"][0]["temp_lag_s"] = 0.0
    plain = Unit(load_sim_config(cfg)).world.samples(0, 3000, noise=False)
    assert np.array_equal(lagged.temp_C, plain.temp_C)                       # the log is the probe's
    x_lag, x = lagged.output_nT[:, 0, 0], plain.output_nT[:, 0, 0]
    # the lagged response: the same swing, later and smaller (first order: 1 / sqrt(1 + (w tau)^2))
    w = 2 * np.pi / 200.0
    assert np.isclose(np.ptp(x_lag[1500:]) / np.ptp(x[1500:]), 1 / np.sqrt(1 + (w * 60) ** 2), rtol=0.03)
