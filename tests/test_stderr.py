"""Standard errors that hold on coloured noise (issue 14): over several seeds the stated standard errors
cover the truth at their stated rate, within a factor 1.5, under white and under 1/f probe noise. The
white-noise formula alone understated temperature coefficients 9-fold under 1/f noise (rms z 9.2); the
block jackknife over time blocks brings them to about 0.9. A drift cannot be told from the noise's own
wander at periods as long as the record, which no estimate from the record alone sees: under 1/f noise
its errors are still about twice the stated ones, and diagnose says to take them as lower bounds."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim import Unit, load_sim_config
from service.numerics.diagnose import diagnose
from service.numerics.engine import fit_with_effects
from test_diagnose import TUMBLE, data_of, probe

TEMP = {"s1.x nT/degC": 2.0, "s1.y nT/degC": -1.5, "s1.z nT/degC": 1.0,
        "s2.x nT/degC": 0.0, "s2.y nT/degC": 0.0, "s2.z nT/degC": 0.0}
DRIFT = {"s1.x drift nT/h": 30.0, "s1.y drift nT/h": -20.0, "s1.z drift nT/h": 10.0, "s2.x drift nT/h": 0.0}


def world(seed: int, pink: float, effect: str):
    extra = ({"temp_offset_nT_per_C": [2.0, -1.5, 1.0]} if effect == "temperature"
             else {"drift_offset_nT_per_h": [30.0, -20.0, 10.0]})
    probes = [probe(0, **extra), probe(1)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    cfg = load_sim_config({
        "seed": 100 + seed, "rate_hz": 20.0, "duration_s": 900.0,
        "field": {"total_nT": 51500.0, "inclination_deg": 62.0, "declination_deg": -5.0},
        "reference": {"enabled": True, "noise_nT": 0.05}, "motion": TUMBLE,
        "temperature": {"start_C": 21.0, "ramp_C_per_h": 4.0, "amplitude_C": 3.0, "period_s": 300.0},
        "probes": probes})
    return data_of(Unit(cfg).digitise(0, cfg.n_samples).to_block(), probes)


def z_scores(pink: float, effect: str, seeds: range) -> np.ndarray:
    truth = TEMP if effect == "temperature" else DRIFT
    z = []
    for seed in seeds:
        ef, _ = fit_with_effects(world(seed, pink, effect), [effect])
        got = {p.name: p for p in ef.parameters}
        z += [(got[n].value - v) / got[n].stderr for n, v in truth.items()]
    return np.array(z)


@pytest.mark.slow
@pytest.mark.parametrize("pink, effect", [(0.0, "temperature"), (0.3, "temperature"), (0.0, "drift")])
def test_standard_errors_cover_the_truth_at_their_stated_rate(pink, effect):
    z = z_scores(pink, effect, range(6))
    rms = float(np.sqrt(np.mean(z ** 2)))
    assert 1 / 1.5 <= rms <= 1.5, (rms, z.round(2))
    assert np.mean(np.abs(z) < 2) >= 0.85


@pytest.mark.slow
def test_under_one_over_f_noise_drift_rates_are_said_to_be_lower_bounds():
    z = z_scores(0.3, "drift", range(4))
    # measured, not hidden: the record cannot show the noise's wander at its own length
    assert float(np.sqrt(np.mean(z ** 2))) > 1.5
    d = diagnose(world(0, 0.3, "drift"), effects=["drift"])
    assert any("lower bounds" in n for n in d.notes) and any("block jackknife" in n for n in d.notes)
