"""diagnose outside the catalogue and under coloured noise (issue 14), each on several seeds:

- the ambient field changing over twenty minutes, common to all probes, no reference logged: no catalogue
  effect is named; the verdict is "unexplained" and says what is left: common to all probes, the
  differences at their floor, slow (minutes), and that a reference magnetometer would explain it;
  with the reference logged the same world is at the floor;
- 1/f probe noise and no effect: nothing significant in any seed (hysteresis steps no longer found in
  the wander); what is left is described as each probe's own slow noise;
- a hidden temperature effect under 1/f noise: first and significant, "explained by temperature", and
  with it added the residual within 1.3x the floor and nothing else significant.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose import TUMBLE, data_of, probe

from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.numerics.diagnose import diagnose, summary_text

#: discovery beside the catalogue's best, and the verdict said again (diagnose's step 6)
COVERS = ("fluxcal.service.numerics.diagnose.beyond",)

F_TOTAL = 51500.0
#: samples of the worlds where the catalogue holds the cause (ambient, a hidden temperature): 16,000 (800 s), on which
#: each figure keeps its margin (the error 1.90-2.42 times the floor before against 1.5, 1.002-1.042 after against
#: 1.3, the gains within 3 % of 1, the coefficient 0.5 % of its 5 %, the cause first at 5.8-11 standard errors); the
#: worlds without it keep world's 24,000: on 16,000 the ambient variation of seed 1 was taken as a significant drift
N_HELD = 16000


def world(seed: int, *, variation=0.0, pink=0.0, reference=False, extra=None, n=24000, rate=20.0, n_probes=3):
    probes = [probe(k) for k in range(n_probes)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    probes[0].update(extra or {})
    cfg = load_sim_config({
        "seed": seed, "rate_hz": rate, "duration_s": n / rate,
        "field": {"total_nT": F_TOTAL, "inclination_deg": 62.0, "declination_deg": -5.0,
                  "variation_nT": variation, "variation_min_period_s": 60.0},
        "reference": {"enabled": reference, "noise_nT": 0.05}, "motion": TUMBLE,
        "temperature": {"start_C": 21.0, "ramp_C_per_h": 10.0, "amplitude_C": 3.0, "period_s": 700.0},
        "probes": probes})
    return data_of(Unit(cfg).digitise(0, cfg.n_samples).to_block(), probes)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_ambient_variation_is_explained_by_the_other_probes_not_by_a_confident_wrong_name(seed):
    data = world(seed, variation=5.0, n=N_HELD)
    d = diagnose(data, total_nT=F_TOTAL)
    text = summary_text(d)
    assert d.rms_nT > 1.5 * d.noise_nT, text
    assert d.candidates[0].effect == "ambient" and d.verdict["kind"] == "explained", text
    assert [c.effect for c in d.candidates if c.significant] == ["ambient"], text
    d2 = diagnose(data, total_nT=F_TOTAL, effects=["ambient"])
    assert d2.rms_nT <= 1.3 * d2.noise_nT and not any(c.significant for c in d2.candidates), summary_text(d2)
    gains = [p.value for p in d2.parameters if p.name.endswith("ambient gain")]
    assert len(gains) == 3 and all(0.8 < g < 1.1 for g in gains)              # the same change in every probe


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_without_the_ambient_term_the_variation_is_unexplained_and_described(seed):
    # the catalogue less `ambient`: what a user sees for a cause the catalogue does not hold
    from fluxcal.service.numerics.effects import known_effects

    d = diagnose(world(seed, variation=5.0), total_nT=F_TOTAL,
                 candidates=[n for n in known_effects() if n != "ambient"])
    text = summary_text(d)
    assert not any(c.significant for c in d.candidates), text
    v = d.verdict
    assert v["kind"] == "unexplained" and v["effect"] is None, text
    sig = v["signature"]
    assert sig["shared_fraction"] > 0.8, text
    assert sig["difference_rms_nT"] < 1.1 * sig["difference_noise_nT"], text
    assert sig["half_power_period_s"] > 60.0, text
    assert "common to all probes" in v["left"] and "differences between probes are at their floor" in v["left"]
    assert "reference magnetometer" in v["advice"] and "--effects ambient" in v["advice"]
    assert "unexplained" in text and "what is left" in text and "what would explain it" in text
    assert d.as_dict()["verdict"]["kind"] == "unexplained"


@pytest.mark.slow
def test_ambient_variation_with_the_reference_logged_is_at_the_floor():
    d = diagnose(world(1, variation=5.0, reference=True))
    assert d.rms_nT <= 1.3 * d.noise_nT and d.verdict["kind"] == "at the floor", summary_text(d)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_over_f_noise_alone_raises_no_alarm_and_is_called_the_probes_own(seed):
    d = diagnose(world(seed, pink=0.3), total_nT=F_TOTAL)
    text = summary_text(d)
    assert not any(c.significant for c in d.candidates), text
    hyst = next(c for c in d.candidates if c.effect == "hysteresis")
    amb = next(c for c in d.candidates if c.effect == "ambient")
    assert not hyst.significant and not amb.significant
    v = d.verdict
    if v["kind"] != "at the floor":
        assert v["kind"] == "unexplained" and v["signature"]["shared_fraction"] < 0.25, text
        assert "each probe's own" in v["left"] and "flicker" in v["advice"], text


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_hidden_temperature_under_one_over_f_noise_is_explained_and_then_nothing_else(seed):
    data = world(seed, pink=0.1, extra={"temp_offset_nT_per_C": [2.0, -1.5, 1.0]}, n=N_HELD)
    d = diagnose(data, total_nT=F_TOTAL)
    text = summary_text(d)
    assert d.candidates[0].effect == "temperature" and d.candidates[0].significant, text
    assert d.verdict["kind"] == "explained" and d.verdict["effect"] == "temperature", text
    assert sum(c.significant for c in d.candidates) == 1 or all(
        "temperature" in c.indistinguishable_from for c in d.candidates[1:] if c.significant), text
    d2 = diagnose(data, total_nT=F_TOTAL, effects=["temperature"])
    assert d2.rms_nT <= 1.3 * d2.noise_nT, summary_text(d2)
    assert not any(c.significant for c in d2.candidates), summary_text(d2)
    # the coefficient is recovered: s1.x 2.0 nT/degC within 5 %
    p = next(p for p in d2.parameters if p.name == "s1.x nT/degC")
    assert np.isclose(p.value, 2.0, rtol=0.05)


def thermal_world(seed: int, tau_s: float, pink: float = 0.0):
    probes = [probe(0, temp_offset_nT_per_C=[2.5, -1.8, 1.0], temp_lag_s=tau_s), probe(1, temp_lag_s=tau_s),
              probe(2, temp_lag_s=tau_s)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    cfg = load_sim_config({
        "seed": seed, "rate_hz": 10.0, "duration_s": 1200.0,
        "field": {"total_nT": F_TOTAL, "inclination_deg": 62.0, "declination_deg": -5.0},
        "reference": {"enabled": True, "noise_nT": 0.05}, "motion": TUMBLE,
        "temperature": {"start_C": 21.0, "ramp_C_per_h": 6.0, "amplitude_C": 3.0, "period_s": 300.0},
        "probes": probes})
    return data_of(Unit(cfg).digitise(0, cfg.n_samples).to_block(), probes)


@pytest.mark.slow
@pytest.mark.parametrize("seed, tau_s, pink", [(1, 90.0, 0.0), (2, 150.0, 0.0), (3, 60.0, 0.1)])
def test_temperature_through_a_thermal_lag_is_explained_by_thermal_with_its_time_constant(seed, tau_s, pink):
    # the core follows the logged temperature with a time constant of a minute or two
    data = thermal_world(seed, tau_s, pink)
    d = diagnose(data)
    text = summary_text(d)
    assert d.candidates[0].effect == "thermal" and d.candidates[0].significant, text
    assert d.verdict["kind"] == "explained" and d.verdict["effect"] == "thermal", text
    d2 = diagnose(data, effects=["thermal"])
    assert d2.rms_nT <= 1.3 * d2.noise_nT, summary_text(d2)
    assert not any(c.significant for c in d2.candidates), summary_text(d2)
    p = {q.name: q for q in d2.parameters}
    assert abs(p["s1.thermal lag s"].value - tau_s) < 0.1 * tau_s
    assert np.isclose(p["s1.x nT/degC"].value, 2.5, rtol=0.05) and np.isclose(p["s1.y nT/degC"].value, -1.8, rtol=0.05)


def heater_world(seed: int, coupled: bool):
    from test_diagnose import sim_block

    probes = [probe(0), probe(1), probe(2)]
    block = sim_block(probes, n=12000, rate=20.0, motion=TUMBLE, seed=seed)
    t = block.t_s - block.t_s[0]
    on = 1.5 * ((t // 40) % 2)                       # a heater switched 0 / 1.5 A every 40 s
    block.extras["heater_A"] = on + 0.05 * np.random.default_rng(seed).standard_normal(t.size)
    if coupled:
        block.field_nT[:, 1, :] += on[:, None] * np.array([3.0, -2.0, 1.0])
    return data_of(block, probes)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_a_logged_current_coupled_into_a_probe_is_found_by_column_and_a_decoy_is_not(seed):
    d = diagnose(heater_world(seed, coupled=True))
    text = summary_text(d)
    assert d.candidates[0].effect == "column", text
    assert d.verdict["kind"] == "explained" and d.verdict["effect"] == "column", text
    d2 = diagnose(heater_world(seed, coupled=True), effects=["column"])
    assert d2.rms_nT <= 1.3 * d2.noise_nT and not any(c.significant for c in d2.candidates), summary_text(d2)
    p = {q.name: q.value for q in d2.parameters}
    assert [p[f"s2.{a} nT per heater_A"] for a in "xyz"] == pytest.approx([3.0, -2.0, 1.0], abs=0.1), text
    control = diagnose(heater_world(seed + 10, coupled=False))
    assert not any(c.significant for c in control.candidates), summary_text(control)


def test_a_tie_of_any_shape_to_a_logged_column_is_measured():
    # the correlation ratio catches what a polynomial misses: an oscillation in the column's value
    from fluxcal.service.numerics.diagnose.where import _eta2, _r2

    rng = np.random.default_rng(5)
    x = rng.uniform(0, 1, 4000)
    y = np.cos(6 * np.pi * x) + 0.3 * rng.standard_normal(x.size)
    assert _r2(y, np.column_stack([x, x ** 2])) < 0.2 and _eta2(y, x) > 0.6     # at most 0.85 with this noise
    assert _eta2(rng.standard_normal(x.size), x) < 0.01                       # no tie: nothing, after adjustment


@pytest.mark.slow
def test_where_it_fails_names_a_column_tied_in_no_polynomial_way():
    from test_diagnose import sim_block

    probes = [probe(0), probe(1)]
    block = sim_block(probes, n=8000, rate=50.0, motion=TUMBLE, seed=3)
    t = block.t_s - block.t_s[0]
    valve = 0.5 + 0.5 * np.sin(2 * np.pi * t / 37.0)            # a valve cycling slowly, position 0..1
    block.extras["valve"] = valve
    block.field_nT[:, 1, 0] += 3.0 * np.cos(6 * np.pi * valve)
    # where-it-fails and the verdict's 'left' are read from the model's residual before discovery (which would run
    # by itself here and change neither: both equal with and without it on this world and the two below)
    d = diagnose(data_of(block, probes), candidates=["column"], discover=False)
    top = d.where[0]
    assert top["observable"] == "valve" and top["strength"] > 0.5, d.where[:4]
    assert "valve" in d.verdict["left"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 4])
def test_where_it_fails_names_temperature_tied_in_no_polynomial_way(seed):
    # a coupling that turns over twice across the temperature range: T and T^2 miss it, the correlation ratio not
    from test_diagnose import sim_block

    probes = [probe(0), probe(1)]
    block = sim_block(probes, n=8000, rate=50.0, motion=TUMBLE, seed=seed)
    t = block.t_s - block.t_s[0]
    temp = 20.0 + 5.0 * np.sin(2 * np.pi * t / 53.0)
    block.temp_C[:] = temp[:, None]
    block.field_nT[:, 1, 0] += 3.0 * np.cos(4 * np.pi * (temp - 15.0) / 10.0)
    d = diagnose(data_of(block, probes), candidates=["temperature"], discover=False)   # where: before discovery
    top = d.where[0]
    assert top["observable"] == "temperature" and top["channel"].startswith("s2") and top["strength"] > 0.5, d.where[:4]
