"""Standard errors that hold on coloured noise (issue 14): over several seeds the stated standard errors
cover the truth at their stated rate, within a factor 1.5, under white and under 1/f probe noise. The
white-noise formula alone understated temperature coefficients 9-fold under 1/f noise (rms z 9.2); the
block jackknife over time blocks brings them to about 0.9. A drift and the noise's own wander at periods as
long as the record look alike, and the jackknife does not see that wander (rms z 1.98 under 1/f noise): the
drift's errors come from a power-law model of each probe's noise spectrum, extended below the fitted band at
least as steeply as flicker noise (engine/coloured.py). So do every effect's parameters (a step, a heater's
coupling, a thermal lag: the jackknife alone left them 2 to 2.5 times too small), and `fit`'s linear calibration
gets the same from weights of its own (numerics/calib/offset_noise.py)."""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose import TUMBLE, data_of, probe

from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.numerics.diagnose import diagnose, summary_text
from fluxcal.service.numerics.engine import fit_with_effects

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
@pytest.mark.parametrize("pink, effect", [(0.0, "temperature"), (0.3, "temperature"), (0.0, "drift"), (0.1, "drift"),
                                          (0.3, "drift")])
def test_standard_errors_cover_the_truth_at_their_stated_rate(pink, effect):
    z = z_scores(pink, effect, range(6))
    rms = float(np.sqrt(np.mean(z ** 2)))
    assert 1 / 1.5 <= rms <= 1.5, (rms, z.round(2))
    assert np.mean(np.abs(z) < 2) >= 0.8


@pytest.mark.slow
def test_under_one_over_f_noise_diagnose_says_where_the_drift_errors_come_from():
    d = diagnose(world(0, 0.3, "drift"), effects=["drift"])
    assert any("block jackknife" in n for n in d.notes)
    assert any("power law" in n and "flicker" in n for n in d.notes), d.notes
    white = diagnose(world(0, 0.0, "drift"), effects=["drift"])
    assert not any("power law" in n for n in white.notes)


def test_the_spectral_variance_of_a_trend_under_flicker_noise_matches_simulation():
    """The formula alone (engine/coloured.py): the slope of a line fitted to 1/f noise, 300 records drawn from
    a process 16 times as long, against the variance the spectrum gives."""
    from fluxcal.service.numerics.engine.coloured import power_law, spectral_variance

    rng = np.random.default_rng(0)
    n, dt = 4000, 0.05
    t = np.arange(n) * dt
    u = (t - t.mean()) / np.sum((t - t.mean()) ** 2)                      # the slope's weights
    m = 16 * n
    f = np.fft.rfftfreq(m, dt)
    s = np.zeros_like(f)
    s[1:] = 0.05 / f[1:]                                                  # one-sided, nT^2/Hz
    scale = np.sqrt(s * m / (4 * dt))                                      # E x^2 = sum S df
    slopes, fits = [], []
    for _ in range(300):
        x = np.fft.irfft((rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * scale, n=m)[:n]
        slopes.append(u @ x)
        if len(fits) < 20:
            fits.append(power_law(x + 0.3 * rng.standard_normal(n), dt))
    want = spectral_variance(u[:, None], np.arange(n), [(0.0, 0.05, -1.0)], dt)
    assert np.var(slopes) == pytest.approx(want, rel=0.2)
    alphas = np.array([a for _, _, a in fits])
    assert np.all((alphas > -1.4) & (alphas < -0.6)), alphas              # flicker found as flicker
    amps = np.array([a for _, a, _ in fits])
    assert np.median(amps) == pytest.approx(0.05, rel=0.3)


def _fit_pair(seed: int, pink: float, tmp_path, capsys) -> tuple[dict, np.ndarray]:
    """`fluxcal fit --json` of test_diagnose's pair (900 s at 20 Hz, a tumble); with the truth of each probe's
    offsets over the record: the static offset plus the 1/f noise's mean over the record (which no record can
    tell from an offset; the white noise's mean is in the white-noise errors)."""
    import json

    from test_diagnose import _write_csv

    from fluxcal.service.wiring import cli

    unit = pair_unit(seed, pink)
    n = unit.config.n_samples
    csv = tmp_path / f"lab{seed}.csv"
    _write_csv(csv, unit.digitise(0, n).to_block())
    assert cli.main(["fit", str(csv), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    truth = np.array([s["offset_nT"] for s in unit.world.truth()["sensors"]])
    if pink:
        truth = truth + unit.world._pink.draw(0, n).mean(axis=0)     # the 1/f part's mean over the record, (P, 3)
    return out, truth


def pair_unit(seed: int, pink: float) -> Unit:
    probes = [probe(0), probe(1)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    return Unit(load_sim_config({
        "seed": 100 + seed, "rate_hz": 20.0, "duration_s": 900.0,
        "field": {"total_nT": 51500.0, "inclination_deg": 62.0, "declination_deg": -5.0},
        "reference": {"enabled": True, "noise_nT": 0.05}, "motion": TUMBLE, "probes": probes}))


@pytest.mark.slow
@pytest.mark.parametrize("pink", [0.1, 0.3])
def test_fit_offsets_standard_errors_cover_the_record_truth_under_one_over_f_noise(pink, tmp_path, capsys):
    """`fit`'s linear calibration under 1/f noise: at 0.3 nT/sqrt(Hz) the white-noise errors alone were off 30
    times (rms z, probe 1's offsets against their static truth) and 3 to 7 times (its matrix's named
    parameters); with the wander within the record from the residual's power law (numerics/calib/
    offset_noise.py), both probes' offsets (ellipsoid, regression) and probe 1's angles and scale factors within
    1.5 on six seeds (measured: offsets 0.86 and 1.03, shape 0.96 and 1.00), and the warning says what the
    figure covers and how far the offsets wander beyond the record."""
    from fluxcal.service.numerics.calib.model import triangular_params
    from fluxcal.service.numerics.calib.quadric import triangular_factor

    z, z_shape = [], []
    for seed in range(6):
        out, truth = _fit_pair(seed, pink, tmp_path, capsys)
        for k, s in enumerate(out["sensors"]):
            z += list((np.array(s["offset_nT"]) - truth[k]) / np.array(s["offset_se_nT"]))
        # probe 1's non-orthogonality angles and scale factors: the truth's from its matrix's triangular factor
        m = np.array(pair_unit(seed, pink).world.truth()["sensors"][0]["matrix"])
        named = out["sensors"][0]["params"]
        got = np.array(named["nonorth_deg"]["value"] + named["scale"]["value"])
        se = np.array(named["nonorth_deg"]["se"] + named["scale"]["se"])
        z_shape += list((got - np.concatenate(triangular_params(triangular_factor(m.T @ m)))) / se)
        said = [w for w in out["warnings"] if "standard errors include that wander within the record" in w]
        assert {w.split(":")[0] for w in said} == {"s1", "s2"}, out["warnings"]
        assert all("nT per decade of time" in w and "spectrum ~ f^-" in w for w in said)
    for zs in (np.array(z), np.array(z_shape)):
        rms = float(np.sqrt(np.mean(zs ** 2)))
        assert 1 / 1.5 <= rms <= 1.5, (rms, zs.round(2))
        assert np.mean(np.abs(zs) < 2) >= 0.8, zs.round(2)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_fit_on_white_noise_keeps_the_white_noise_errors(seed, tmp_path, capsys):
    """White noise: no coloured warning, probe 1's (ellipsoid) errors the white-noise ones, and probe 2's
    (regression onto probe 1) those of the regression plus probe 1's offset errors, which it inherits."""
    from fluxcal.service.numerics.calib.alignment import regression_calibration
    from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid

    out, truth = _fit_pair(seed, 0.0, tmp_path, capsys)
    assert not any("coloured" in w for w in out["warnings"]), out["warnings"]
    s1, s2 = out["sensors"]
    assert np.all(np.abs(np.array(s1["offset_nT"]) - truth[0]) < 4 * np.array(s1["offset_se_nT"]))
    unit = pair_unit(seed, 0.0)
    block = unit.digitise(0, unit.config.n_samples).to_block()
    fit = fit_ellipsoid(block.field_nT[:, 0], block.extras["ref_total"])
    assert np.allclose(s1["offset_se_nT"], fit.calibration.offset_se_nT, rtol=1e-6)
    reg = regression_calibration("s2", fit.calibration.apply(block.field_nT[:, 0]), block.field_nT[:, 1])
    carry = np.linalg.solve(reg.matrix, fit.calibration.matrix)
    inherited = np.sqrt(np.diag(carry @ np.diag(fit.calibration.offset_se_nT ** 2) @ carry.T))
    assert np.allclose(s2["offset_se_nT"], np.hypot(reg.offset_se_nT, inherited), rtol=1e-3)



@pytest.mark.slow
@pytest.mark.parametrize("pink", [0.0, 0.3])
def test_perming_step_sizes_cover_the_truth_under_white_and_one_over_f_noise(pink):
    """A step is a slow term (a function of time alone): its size against the noise's wander on either side,
    which the block jackknife sees only between its blocks; under 1/f noise of 0.3 nT/sqrt(Hz) step sizes
    were off by 2.25 times their errors (rms z, the steps found on seeds 40-45). With the power law's errors
    (engine/coloured.py, as the drift's), on ten seeds: measured 1.06 white, 0.88 under 1/f; a step found
    within 5 s of the true instant is compared with the true jump. Under 1/f noise of this size the 7.8 nT
    step is found in 9 of these ten worlds (in 6 of seeds 10-19): perming is harder to tell from a wander
    there, and what is not found is not judged here."""
    from test_diagnose_crossfit import JUMP, stepped

    z, found = [], 0
    for seed in range(20, 30):
        ef, _ = fit_with_effects(stepped(seed, wander=False, pink=pink), ["hysteresis"])
        for p in ef.parameters:
            if "step@" not in p.name:
                continue
            at = float(p.name.split("@")[1].split("s")[0])
            near = p.name.startswith("s2.") and abs(at - 61.7) < 5.0
            found += near
            z.append((p.value - (JUMP["xyz".index(p.name.split(".")[1][0])] if near else 0.0)) / p.stderr)
    z = np.array(z)
    assert found >= (30 if pink == 0 else 27), found          # every world (white), nine of ten (1/f)
    rms = float(np.sqrt(np.mean(z ** 2)))
    assert 1 / 1.5 <= rms <= 1.5, (rms, z.round(2))


def heater_or_thermal(kind: str, seed: int, pink: float):
    """test_diagnose_beyond's worlds: a heater current switched every 40 s coupled into probe 2 (`column`), or
    probe 1 following the temperature through a 90-s lag (`thermal`); with the truth of their parameters."""
    from test_diagnose import sim_block
    from test_diagnose_beyond import thermal_world

    if kind == "thermal":
        return thermal_world(seed, 90.0, pink), {"s1.x nT/degC": 2.5, "s1.y nT/degC": -1.8, "s1.z nT/degC": 1.0,
                                                 "s1.thermal lag s": 90.0}
    probes = [probe(0), probe(1), probe(2)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    block = sim_block(probes, n=12000, rate=20.0, motion=TUMBLE, seed=seed)
    on = 1.5 * (((block.t_s - block.t_s[0]) // 40) % 2)
    block.extras["heater_A"] = on + 0.05 * np.random.default_rng(seed).standard_normal(on.size)
    block.field_nT[:, 1, :] += on[:, None] * np.array([3.0, -2.0, 1.0])
    return data_of(block, probes), {f"s2.{a} nT per heater_A": v for a, v in zip("xyz", (3.0, -2.0, 1.0))}


@pytest.mark.slow
@pytest.mark.parametrize("kind, pink", [("column", 0.0), ("column", 0.3), ("thermal", 0.0), ("thermal", 0.1)])
def test_every_effects_errors_cover_the_truth_under_one_over_f_noise(kind, pink):
    """Not only a drift or a step: a heater switched every 40 s and a thermal lag of 90 s vary at periods where
    1/f noise wanders too. With the block jackknife alone their errors were 2.48 (column, 1/f 0.3 nT/sqrt(Hz))
    and 2.07 (thermal, 0.1) times too small (rms z, six seeds); with every effect's errors also from the power
    law (engine/coloured.py), measured 0.90 and 1.35 (white: 1.10 and 0.96)."""
    z = []
    for seed in range(1, 7):
        data, truth = heater_or_thermal(kind, seed, pink)
        ef, _ = fit_with_effects(data, [kind])
        got = {p.name: p for p in ef.parameters}
        z += [(got[n].value - v) / got[n].stderr for n, v in truth.items()]
    z = np.array(z)
    rms = float(np.sqrt(np.mean(z ** 2)))
    assert 1 / 1.5 <= rms <= 1.5, (rms, z.round(2))


def test_a_bursty_time_base_is_laid_out_in_the_samples_order_at_its_mean_interval():
    """Bursts of samples 2-3 ms apart with 40-60 ms between them (a hobby board), and a pause of 5 s: the spectra are
    taken over the samples in their order, so the weights are laid out the same way, at the mean interval outside
    the pause, and the pause keeps its length."""
    from fluxcal.service.numerics.effects.timebase import sample_grid

    rng = np.random.default_rng(3)
    steps = np.tile([0.002, 0.003, 0.002, 0.05], 500) + rng.uniform(0, 0.01, 2000) * np.tile([0, 0, 0, 1], 500)
    steps[1000] = 5.0
    t = np.concatenate([[0.0], np.cumsum(steps)])
    grid, dt = sample_grid(t)
    usual = np.delete(steps, 1000)
    assert dt == pytest.approx(usual.mean(), rel=1e-9)
    assert np.all(np.diff(grid) >= 1) and np.sum(np.diff(grid) != 1) == 1
    assert grid[1001] - grid[1000] == round(5.0 / dt)
    steady = np.arange(100) * 0.02
    assert np.array_equal(sample_grid(steady)[0], np.arange(100)) and sample_grid(steady)[1] == pytest.approx(0.02)


@pytest.mark.slow
def test_a_real_bursty_boards_errors_match_the_spread_over_random_heater_histories():
    """The hand-turned sensorfusion sphere (106 s, 8,190 samples in bursts 2-58 ms apart; its residual's law is f^-2.5
    above 16 cycles per record, the hand's turning, and 260 times below that law at 1-2 cycles): an offset that
    follows a logged heater switched at random (lagged 5 s), fitted by `column`. Its stated errors against the
    spread of its coefficients over 24 random heater histories: 0.76-1.47 (were 9-17 times: the law read at 4 times
    its frequencies, on the median interval, and carried below its band at -2.5)."""
    from real_data import real

    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.numerics.effects.thermal import low_pass
    from fluxcal.service.numerics.engine import as_effect_data

    data = as_effect_data(load_data(real("hmc5883l_sensorfusion_sphere.csv")))
    s = data.t_s - data.t_s[0]
    values, stated = [], []
    for seed in range(24):
        rng = np.random.default_rng(seed)
        heater = 1.5 * (np.searchsorted(np.cumsum(rng.uniform(s[-1] / 40, s[-1] / 12, 200)), s) % 2)
        data.extras["heater_A"] = low_pass(data.t_s, heater, 5.0)
        data._cache.clear()
        ef, _ = fit_with_effects(data, ["column"])
        got = [p for p in ef.parameters if p.term == "column" and "heater_A" in p.name]
        values.append([p.value for p in got])
        stated.append([p.stderr for p in got])
    ratio = np.median(stated, axis=0) / np.std(values, axis=0, ddof=1)
    assert np.all((ratio > 1 / 1.6) & (ratio < 1.6)), ratio.round(2)


@pytest.mark.slow
def test_under_a_random_walk_the_steep_law_is_kept_below_its_band_and_drift_is_not_claimed():
    """A law steeper than flicker is carried on below its band at flicker's slope only where the residual's own power
    at 1-2 cycles per record refutes the steep law (coloured.low_frequency_knee; a hand-turned board: 260 times below
    it). Under a random walk of the offsets it is not refuted: with the knee taken regardless, a drift's stated errors
    fell 2-4 fold (rms z 4.8, worst -18.5) and diagnose called a drift that is not there significant. Measured with
    the steep law kept: rms z 1.31 over six seeds."""
    from fluxcal.service.numerics.effects.timebase import sample_grid
    from fluxcal.service.numerics.engine.coloured import low_frequency_knee, welch_spectra

    z = []
    for seed in range(6):
        data = world(seed, 0.0, "drift")
        rng = np.random.default_rng(1000 + seed)
        data.raw_nT[:] += np.cumsum(rng.normal(0.0, 0.15, data.raw_nT.shape), axis=0)
        data._cache.clear()
        ef, ch = fit_with_effects(data, ["drift"])
        got = {p.name: p for p in ef.parameters}
        z += [(got[n].value - v) / got[n].stderr for n, v in DRIFT.items()]
        _, dt = sample_grid(ch.t_s)
        assert low_frequency_knee(ch.values, dt, welch_spectra(ch.values, dt)) is None
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 1 / 1.5 <= rms <= 1.5, (rms, np.round(z, 2))
    for seed in (2, 3):                               # where the knee taken regardless made a drift 'significant'
        data = world(seed, 0.0, "temperature")
        rng = np.random.default_rng(2000 + seed)
        data.raw_nT[:] += np.cumsum(rng.normal(0.0, 0.15, data.raw_nT.shape), axis=0)
        data._cache.clear()
        d = diagnose(data, candidates=["drift"], discover=False)
        assert not d.candidates[0].significant, summary_text(d)
