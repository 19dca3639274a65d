"""`diagnose` of a long recording keeps every k-th sample (--max-samples, or the default budget of probe-samples),
reads only those from the file, and says so; what it finds agrees, within the standard errors of the samples
used, with the diagnosis of every sample (issue 17: results equal within their standard errors to the
in-memory path on shorter data)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.io.recordings.labdata import keep_every, load_csv
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.io.recordings.reader import read_recording, read_samples
from fluxcal.service.numerics.diagnose import diagnose, summary_text
from fluxcal.service.numerics.engine import fit_with_effects
from fluxcal.service.wiring import cli

sys.path.insert(0, str(Path(__file__).parent))
from test_diagnose import TUMBLE, data_of, probe  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
RECORDINGS = sorted((REPO / "recordings").glob("*.mcap"))
F_TOTAL = 51500.0


def test_keep_every_is_the_smallest_stride_within_both_limits():
    assert keep_every(24000, 2, None, None) == 1
    assert keep_every(24000, 2, 0, 0) == 1
    assert keep_every(24000, 2, 8000, None) == 3
    assert keep_every(24000, 2, 7999, None) == 4
    assert keep_every(24000, 2, None, 48000) == 1
    assert keep_every(24000, 2, None, 47999) == 2
    assert keep_every(24000, 4, 20000, 24000) == 4            # the tighter of the two decides
    assert keep_every(10, 3, None, 10) == 4                   # ceil(10 / 3) = 4 rows x 3 > 10: one more
    for n, p, m in [(1, 1, 1000), (999, 3, 1000), (3_600_000, 4, None)]:
        k = keep_every(n, p, m, 500_000)
        assert len(range(0, n, k)) * p <= 500_000 and (k == 1 or len(range(0, n, k - 1)) * p > 500_000
                                                          or len(range(0, n, k - 1)) > (m or n))


@pytest.mark.parametrize("path", RECORDINGS, ids=lambda p: p.name)
@pytest.mark.parametrize("share", [2.5, 7.3])
def test_read_samples_keeps_every_kth_sample_of_the_whole_recording(path, share):
    whole = read_recording(path).raw                      # blocks of many sizes: the stride runs across them
    limit = int(whole.n_samples / share)
    rec = read_samples(path, max_samples=limit)
    k = keep_every(whole.n_samples, whole.n_probes, limit, None)
    assert rec.every == k > 1 and rec.n_read == whole.n_samples
    got = rec.raw
    assert got.n_samples == len(range(0, whole.n_samples, k)) <= limit
    np.testing.assert_array_equal(got.t_s, whole.t_s[::k])
    np.testing.assert_array_equal(got.seq, whole.seq[::k])
    np.testing.assert_array_equal(got.field_nT, whole.field_nT[::k])
    np.testing.assert_array_equal(got.temp_C, whole.temp_C[::k])
    np.testing.assert_array_equal(got.flags, whole.flags[::k])
    assert set(got.extras) == set(whole.extras)
    for name, v in whole.extras.items():
        np.testing.assert_array_equal(got.extras[name], v[::k])
    assert read_samples(path).every == 1                  # no limit: every sample


def test_a_csv_is_thinned_the_same_way(tmp_path):
    rng = np.random.default_rng(5)
    n = 5000
    t = np.arange(n) / 50.0
    f = rng.normal(0, 30000, (n, 6))
    path = tmp_path / "lab.csv"
    rows = "\n".join(",".join(f"{v:.3f}" for v in (t[i], *f[i])) for i in range(n))
    path.write_text("t,s1_x,s1_y,s1_z,s2_x,s2_y,s2_z\n" + rows + "\n")
    whole = load_csv(path).block
    lab = load_data(path, max_probe_samples=2 * 1200)
    assert (lab.every, lab.n_read) == (5, n)
    np.testing.assert_array_equal(lab.block.field_nT, whole.field_nT[::5])
    np.testing.assert_array_equal(lab.block.t_s, whole.t_s[::5])
    assert lab.block.field_nT.base is None                 # a copy: the whole file's arrays can go
    assert load_data(path).every == 1 and load_data(path).n_read == n


def world(seed: int, pink: float):
    probes = [probe(k) for k in range(3)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    probes[0]["temp_offset_nT_per_C"] = [2.0, -1.5, 1.0]
    n, rate = 24000, 100.0
    cfg = load_sim_config({
        "seed": seed, "rate_hz": rate, "duration_s": n / rate,
        "field": {"total_nT": F_TOTAL, "inclination_deg": 62.0, "declination_deg": -5.0},
        "reference": {"enabled": False}, "motion": TUMBLE,
        "temperature": {"start_C": 21.0, "ramp_C_per_h": 30.0, "amplitude_C": 3.0, "period_s": 150.0},
        "probes": probes})
    return data_of(Unit(cfg).digitise(0, cfg.n_samples).to_block(), probes)


@pytest.mark.slow
@pytest.mark.parametrize("seed, pink", [(1, 0.0), (2, 0.1), (3, 0.1)])
def test_one_sample_in_four_finds_what_every_sample_finds_within_its_standard_errors(seed, pink):
    data = world(seed, pink)
    thin = data.subset(np.arange(0, data.n_samples, 4))
    d_all, d_thin = diagnose(data, total_nT=F_TOTAL), diagnose(thin, total_nT=F_TOTAL)
    for d in (d_all, d_thin):
        assert d.verdict["kind"] == "explained" and d.verdict["effect"] == "temperature", summary_text(d)
    # the noise floor and the error are those of the same samples: thinning keeps them
    assert d_thin.noise_nT == pytest.approx(d_all.noise_nT, rel=0.1)
    assert d_thin.rms_nT == pytest.approx(d_all.rms_nT, rel=0.1)
    # with the effect in the model, the coefficients agree within the thinned fit's standard errors, and
    # both cover the simulated truth. The model's fit alone: diagnose(effects=["temperature"]).parameters are this very
    # fit's (fit_with_effects, bit for bit); the candidates diagnose would try beside it are not read here
    f_all, _ = fit_with_effects(data, ["temperature"], total_nT=F_TOTAL)
    f_thin, _ = fit_with_effects(thin, ["temperature"], total_nT=F_TOTAL)
    truth = {"s1.x nT/degC": 2.0, "s1.y nT/degC": -1.5, "s1.z nT/degC": 1.0}
    by_all = {p.name: p for p in f_all.parameters}
    for p in f_thin.parameters:
        if p.name not in truth:
            continue
        q = by_all[p.name]
        assert abs(p.value - q.value) <= 3.0 * p.stderr, (p, q)
        assert abs(p.value - truth[p.name]) <= 4.0 * p.stderr, p
        assert abs(q.value - truth[q.name]) <= 4.0 * q.stderr, q
        # fewer samples: no smaller error claimed under white noise. Under 1/f noise the error is the wander's,
        # which thinning does not lose, but the thinned record's white density is k times higher and can hide the
        # colour from the power-law test (engine/coloured.is_coloured): it then states the jackknife's errors,
        # down to half the whole record's (seed 3); both cover the truth (rms z over seeds 1-6: 0.93 whole,
        # 1.06 thinned, measured)
        assert p.stderr >= (1.0 if pink == 0 else 0.4) * q.stderr, (p, q)


@pytest.mark.slow
def test_the_command_reads_one_sample_in_k_and_says_so(capsys):
    rec = REPO / "recordings" / "grad1-hidden-effect.mcap"
    assert cli.main(["diagnose", str(rec), "--json"]) == 0                     # 24,000 x 2: within the budget
    d_all = json.loads(capsys.readouterr().out)
    assert "thinned" not in d_all and d_all["n_samples"] == 24000
    assert cli.main(["diagnose", str(rec), "--json", "--max-samples", "8000"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["thinned"]["every"] == 3 and d["thinned"]["n_read"] == 24000 and d["n_samples"] == 8000
    assert d["thinned"]["rate_hz"] == pytest.approx(200.0 / 3)
    assert d["notes"][0].startswith("thinned: one sample in 3 diagnosed (8,000 of 24,000")
    assert d["verdict"]["kind"] == d_all["verdict"]["kind"] == "explained"
    assert d["verdict"]["effect"] == d_all["verdict"]["effect"] == "temperature"
    full = {p["name"]: p for p in d_all["candidates"][0]["parameters"]}
    for p in d["candidates"][0]["parameters"]:
        assert abs(p["value"] - full[p["name"]]["value"]) <= 3.0 * p["stderr"], (p, full[p["name"]])
    assert cli.main(["diagnose", str(rec), "--max-samples", "8000"]) == 0
    assert "thinned: one sample in 3 diagnosed" in capsys.readouterr().out


@pytest.mark.parametrize("bad", ["12", "-5", "many"])
def test_a_bad_max_samples_is_refused_with_what_is_allowed(bad, capsys):
    rec = REPO / "recordings" / "grad1-hidden-effect.mcap"
    with pytest.raises(SystemExit) as e:
        cli.main(["diagnose", str(rec), "--max-samples", bad])
    assert e.value.code == 2
    assert "at least 1000 (0: all samples)" in capsys.readouterr().err


@pytest.mark.slow
def test_fit_with_effects_beyond_the_budget_fits_them_on_one_sample_in_k(monkeypatch, capsys):
    import fluxcal.service.wiring.commands.fit as fit_cmd

    rec = str(REPO / "recordings" / "grad1-hidden-effect.mcap")               # 24,000 samples of 2 probes
    assert cli.main(["fit", rec, "--effects", "temperature", "--json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    monkeypatch.setattr(fit_cmd, "NONLINEAR_PROBE_SAMPLES", 16_000)            # one sample in 3
    assert cli.main(["fit", rec, "--effects", "temperature", "--json"]) == 0
    thin = json.loads(capsys.readouterr().out)
    assert not any("one sample in" in w for w in whole["warnings"])
    assert any(w.startswith("effects fitted on one sample in 3 (8,000 of 24,000), the linear calibration refitted")
               for w in thin["warnings"])
    a, b = whole["effect_params"]["temperature"], thin["effect_params"]["temperature"]
    assert set(a) == set(b)
    fitted = {name: p for name, p in b.items() if p["se"] is not None}               # not the reference constants
    assert len(fitted) == 12
    for name, p in fitted.items():
        assert p["se"] >= a[name]["se"]
        assert abs(p["value"] - a[name]["value"]) <= 3.0 * p["se"], (name, p, a[name])
    assert b["s1.x nT/degC"]["value"] == pytest.approx(2.0, abs=4 * b["s1.x nT/degC"]["se"])
    # the linear calibration, refitted with the effects on those samples, agrees within its standard errors
    for sw, st in zip(whole["sensors"], thin["sensors"]):
        assert np.all(np.abs(np.subtract(st["offset_nT"], sw["offset_nT"])) <= 4 * np.array(st["offset_se_nT"]))
    assert thin["rms_nT"] == pytest.approx(whole["rms_nT"], rel=0.05)
