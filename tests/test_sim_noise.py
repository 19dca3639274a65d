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

from drivers.sim import Unit, load_sim_config


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
