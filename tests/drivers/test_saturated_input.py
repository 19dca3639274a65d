"""Saturated axes and invalid temperatures (ICD flags bit0, bit1) from `simulate` and `decode`: never a number in
a fit, left out per probe and counted by `fit` and `diagnose` (CSV and MCAP alike), the offsets still those of
the simulation; an invalid temperature blocks nothing; a truncated `simulate` MCAP keeps most of its samples."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fluxcal.drivers.block import FLAG_SATURATED, FLAG_TEMP_INVALID
from fluxcal.drivers.sim import Unit
from fluxcal.service.io.recordings.labdata import load_csv
from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.wiring.cli import main as cli
from fluxcal.service.wiring.commands.simulate import load_simulation

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.numerics.usable",)

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "sim-gradiometer.toml"


def _faulty_config(tmp_path: Path, *, ramp_C_per_h: float = 0.0, temp_nT_per_C: str = "") -> Path:
    """The built-in gradiometer with a 50,000 nT probe range (the 52,500 nT field saturates an axis near it)
    and one sample in ten flagged temperature-invalid; temp_nT_per_C: probe s1's offset change with temperature
    (a TOML list), where the temperature terms are to find one."""
    text = CONFIG.read_text()
    if temp_nT_per_C:
        text = text.replace("# temp_offset_nT_per_C = [0.0, 0.0, 0.0] ", f"temp_offset_nT_per_C = {temp_nT_per_C} ", 1)
    for old, new in (("# range_nT = 100000.0 ", "range_nT = 50000.0 "),
                     ("# temp_invalid_fraction = 0.0 ", "temp_invalid_fraction = 0.1 "),
                     ("ramp_C_per_h = 0.0 ", f"ramp_C_per_h = {ramp_C_per_h} "),
                     ('"../state/grad1-sim-cal.json"', '"state/cal.json"'),
                     ('"../recordings/live"', '"live"')):
        assert old in text
        text = text.replace(old, new)
    p = tmp_path / "faults.toml"
    p.write_text(text)
    return p


def _truth_counts(config: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per probe the saturated samples, the flags, and the truth of the run as the unit digitises it."""
    sim, _ = load_simulation(str(config))
    s = Unit(sim).digitise(0, sim.n_samples)
    return s.saturated.any(axis=2).sum(axis=0), s.flags, s


def _fit_json(path: Path, capsys, *extra: str) -> dict:
    assert cli(["fit", str(path), "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def _offsets_within_errors(result: dict, truth_file: Path) -> None:
    truth = json.loads(truth_file.read_text())
    for got, want in zip(result["sensors"], truth["sensors"]):
        off, se = np.array(got["offset_nT"]), np.array(got["offset_se_nT"])
        assert np.all(se > 0) and np.all(se < 1.0)
        assert np.all(np.abs(off - np.array(want["offset_nT"])) < 4 * se), (off, want["offset_nT"], se)


def test_simulated_csv_carries_saturation_as_nan_and_fit_leaves_it_out(tmp_path, capsys):
    cfg = _faulty_config(tmp_path)
    sat, flags, _ = _truth_counts(cfg)
    assert sat[0] > 500 and sat[1] > 100                             # both probes saturate somewhere
    out = tmp_path / "faults.csv"
    assert cli(["simulate", "--config", str(cfg), "--out", str(out)]) == 0
    said = capsys.readouterr().err                                   # simulate counts what it saturated
    assert f"s1: {sat[0]} samples saturated (beyond range_nT 50000 nT)" in said
    assert f"s2: {sat[1]} samples saturated" in said
    n_invalid = int(np.count_nonzero(flags & FLAG_TEMP_INVALID))
    assert 900 < n_invalid < 1500 and f"{n_invalid} samples with the temperature marked invalid" in said
    body = [ln for ln in out.read_text().splitlines() if not ln.startswith("#")][1:]
    assert not any("2147483" in ln for ln in body)                   # the rails are never written as numbers
    blk = load_csv(out).block
    np.testing.assert_array_equal(np.isnan(blk.field_nT).any(axis=2).sum(axis=0), sat)
    np.testing.assert_array_equal(np.isnan(blk.temp_C[:, 0]), (flags & FLAG_TEMP_INVALID) != 0)

    result = _fit_json(out, capsys)
    any_sat = int(np.count_nonzero(flags & FLAG_SATURATED))
    assert f"s1: {sat[0]} saturated samples left out" in result["warnings"]
    assert f"s2: {sat[1]} saturated samples left out" in result["warnings"]
    assert any(w.startswith(f"{any_sat} of 12000 samples left out in all") for w in result["warnings"])
    assert not any("_temp" in w for w in result["warnings"])        # no temperature term: nothing to say
    _offsets_within_errors(result, tmp_path / "faults.truth.json")
    assert result["rms_nT"] < 1.2                                    # the noise, 0.6-0.8 nT per axis

    assert cli(["diagnose", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"note: s1: {sat[0]} saturated samples left out" in text
    # the temperature terms are among those diagnose tries: the invalid temperatures of the samples kept, said
    kept = ~np.isnan(blk.field_nT).any(axis=(1, 2))
    bad_temp = int(np.count_nonzero(((flags & FLAG_TEMP_INVALID) != 0) & kept))
    assert f"note: s1_temp: {bad_temp} samples without a valid temperature" in text
    rms, floor = (float(x) for x in text.split("residual RMS ")[1].split(" nT (")[0].split(" nT against a noise floor of "))
    assert rms < 1.2 * floor


def test_decoded_capture_with_invalid_temperatures_fits(tmp_path, capsys):
    """The user's path: simulate a capture, decode it to CSV (NaN temperatures and axes), fit it."""
    cfg = _faulty_config(tmp_path)
    sat, flags, _ = _truth_counts(cfg)
    cap, csv = tmp_path / "faults.bin", tmp_path / "d.csv"
    assert cli(["simulate", "--config", str(cfg), "--out", str(cap)]) == 0
    assert cli(["decode", str(cap), "--probes", "2", "--lsb-nT", "0.001", "--out", str(csv)]) == 0
    capsys.readouterr()
    assert np.count_nonzero(np.isnan(load_csv(csv).block.temp_C[:, 0])) == np.count_nonzero(flags & FLAG_TEMP_INVALID)
    result = _fit_json(csv, capsys)
    assert f"s1: {sat[0]} saturated samples left out" in result["warnings"]
    _offsets_within_errors(result, tmp_path / "faults.truth.json")


def test_mcap_fit_leaves_saturated_samples_out_like_diagnose(tmp_path, capsys):
    cfg = _faulty_config(tmp_path)
    sat, _, _ = _truth_counts(cfg)
    out = tmp_path / "faults.mcap"
    assert cli(["simulate", "--config", str(cfg), "--out", str(out)]) == 0
    capsys.readouterr()
    result = _fit_json(out, capsys)
    assert f"s1: {sat[0]} saturated samples left out" in result["warnings"]
    assert f"s2: {sat[1]} saturated samples left out" in result["warnings"]
    _offsets_within_errors(result, tmp_path / "faults.truth.json")
    assert cli(["fit", str(out)]) == 0                               # the text says it too
    assert f"s1: {sat[0]} saturated samples left out" in capsys.readouterr().out


def test_invalid_temperatures_are_counted_for_the_temperature_terms_only(tmp_path, capsys):
    # a temperature the data show (s1's offsets move 1.7 nT over the ramp's 0.33 degC): fit refuses an effect they
    # do not show, as the service's add-effect does
    cfg = _faulty_config(tmp_path, ramp_C_per_h=20.0, temp_nT_per_C="[5.0, -4.0, 3.0]")
    _, flags, _ = _truth_counts(cfg)
    out = tmp_path / "ramp.csv"
    assert cli(["simulate", "--config", str(cfg), "--out", str(out)]) == 0
    capsys.readouterr()
    kept = (flags & FLAG_SATURATED) == 0
    invalid = int(np.count_nonzero((flags[kept] & FLAG_TEMP_INVALID) != 0))
    result = _fit_json(out, capsys, "--effects", "temperature")
    assert (f"s1_temp: {invalid} samples without a valid temperature: the temperature terms take s1's "
            f"temperature there interpolated in time from the valid ones") in result["warnings"]
    coefficients = result["effect_params"]["temperature"]
    for axis, want in zip("xyz", (5.0, -4.0, 3.0)):                 # the truth, within 4 standard errors
        got = coefficients[f"s1.{axis} nT/degC"]
        assert abs(got["value"] - want) < 4 * got["se"], (axis, got)


def test_csv_flags_column_is_honoured_when_the_rails_are_numbers(tmp_path):
    """An older `simulate` CSV wrote a saturated axis as its rail (2147483.647 nT at 0.001 nT): the flags say so."""
    rows = ["t,s1_x,s1_y,s1_z,s2_x,s2_y,s2_z,s1_temp,s2_temp,flags",
            "0.0,1.0,2.0,3.0,4.0,5.0,6.0,20.0,20.0,0",
            "0.1,2147483.647,2.0,3.0,4.0,5.0,6.0,20.0,20.0,1",
            "0.2,1.0,2.0,3.0,4.0,-2147483.648,6.0,20.0,20.0,3",
            "0.3,1.0,2.0,3.0,4.0,5.0,6.0,20.0,20.0,1",             # flagged, no rail: the flag cannot say which
            "0.4,1.0,2.0,nan,4.0,5.0,6.0,inf,20.0,0"]
    p = tmp_path / "old.csv"
    p.write_text("\n".join(rows) + "\n")
    b = load_csv(p).block
    assert np.isnan(b.field_nT).any(axis=2).tolist() == [[False, False], [True, False], [False, True],
                                                        [True, True], [True, False]]
    assert np.isnan(b.field_nT).sum() == 1 + 1 + 6 + 1
    assert np.isnan(b.temp_C).tolist() == [[False, False], [False, False], [True, True], [False, False],
                                           [True, False]]


def test_too_few_usable_samples_is_a_clear_error(tmp_path, capsys):
    t = np.arange(40) * 0.01
    v = np.column_stack([t] + [1000.0 + 10.0 * k + t * (k + 1) for k in range(6)])   # no two rows alike (no holds)
    v[5:, 1] = np.nan
    p = tmp_path / "few.csv"
    np.savetxt(p, v, delimiter=",", header="t,s1_x,s1_y,s1_z,s2_x,s2_y,s2_z", comments="", fmt="%.3f")
    assert cli(["fit", str(p)]) == 2
    err = capsys.readouterr().err
    assert f"{p}: only 5 of 40 samples are usable (s1: 35 samples with a non-finite axis left out" in err
    assert "too few to fit" in err


def test_a_simulated_mcap_cut_to_80_percent_keeps_most_samples(tmp_path, capsys):
    out = tmp_path / "sim.mcap"
    assert cli(["simulate", "--out", str(out)]) == 0
    whole = read_recording(out).raw
    data = out.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 8 // 10])
    rec = read_recording(cut)
    n = rec.raw.n_samples
    assert rec.truncated and 0.7 * whole.n_samples < n < 0.8 * whole.n_samples
    np.testing.assert_array_equal(rec.raw.field_nT, whole.field_nT[:n])   # what is kept is the file's start
    capsys.readouterr()
    assert cli(["fit", str(cut), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["sensors"]


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_non_finite_time_or_reference_is_still_refused(tmp_path, bad):
    p = tmp_path / "x.csv"
    p.write_text(f"t,s1_x,s1_y,s1_z,ref_total\n0,1,2,3,50000\n1,1,2,3,{bad}\n")
    from fluxcal.drivers.errors import DataError

    with pytest.raises(DataError, match=r"line 3, column 'ref_total'.*only probe axes and temperatures may be NaN"):
        load_csv(p)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_flagged_samples_without_a_rail_are_left_out_for_every_probe(tmp_path, seed):
    """A logger that flags saturation but writes no rail: the flag does not say which axis, so a flagged sample
    is left out for every probe, never one real measurement taken for a rail (it was: 499 and 500 of 500)."""
    rng = np.random.default_rng(seed)
    n = 2000
    field = rng.normal(0.0, 30000.0, size=(n, 6))
    flags = np.zeros(n, int)
    flagged = rng.choice(n, 500, replace=False)
    flags[flagged] = 1
    t = np.arange(n) * 0.01
    p = tmp_path / "flagged.csv"
    np.savetxt(p, np.column_stack([t, field, flags]), delimiter=",", comments="",
               header="t,s1_x,s1_y,s1_z,s2_x,s2_y,s2_z,flags", fmt=["%.3f"] + ["%.6f"] * 6 + ["%d"])
    b = load_csv(p).block
    gone = np.isnan(b.field_nT).all(axis=2)
    assert gone[:, 0].sum() == gone[:, 1].sum() == 500 and set(np.flatnonzero(gone[:, 0])) == set(flagged.tolist())
    assert not np.isnan(b.field_nT[~gone[:, 0]]).any()
