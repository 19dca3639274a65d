"""`fluxcal fit` end to end: simulate → fit → compare with the simulator's truth (docs/cli.md, docs/contracts.md)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fluxcal.service.io.calfile import load_calibration
from fluxcal.service.wiring.cli import main


@pytest.fixture(scope="module")
def gradiometer(tmp_path_factory):
    d = tmp_path_factory.mktemp("fit")
    out = d / "grad.csv"
    assert main(["simulate", "--config", "configs/sim-gradiometer.toml", "--out", str(out)]) == 0
    return out, json.loads((d / "grad.truth.json").read_text())


def _a(m):
    m = np.asarray(m)
    return m.T @ m


@pytest.mark.parametrize("method", ["ellipsoid", "rls"])
def test_fit_json_matches_truth(gradiometer, capsys, method):
    path, truth = gradiometer
    capsys.readouterr()
    assert main(["fit", str(path), "--method", method, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"method", "align", "effects", "sensors", "differential_rms_nT", "rms_nT", "warnings",
                        "effect_params", "determinacy"}
    assert [d["probe"] for d in out["determinacy"]] == [s["name"] for s in out["sensors"]]
    assert all(d["determined"] and d["reason"] is None for d in out["determinacy"])
    assert out["effect_params"] == {}
    assert out["method"] == method and out["effects"] == []
    # what the text shows, in the JSON too (docs/contracts.md): standard errors, order, coverage
    for s in out["sensors"]:
        assert len(s["offset_se_nT"]) == 3 and all(0 < se < 0.5 for se in s["offset_se_nT"])
        # a minute of tumbling saw 12 of the 26 direction bins about each fitted offset: usable, and said
        assert s["model_order"] == "full" and s["coverage"]["usable"] and s["coverage"]["fraction"] > 0.4
        assert s["params"]["offset_nT"]["unit"] == "nT"
        assert all(f"{s['name']}: only" in w or "standard error exceeds" in w for w in out["warnings"]
                   if w.startswith(s["name"] + ":"))
    for got, want in zip(out["sensors"], truth["sensors"]):
        assert got["name"] == want["name"]
        assert np.allclose(got["offset_nT"], want["offset_nT"], atol=0.5)
        # matrices agree up to the common frame's rotation: compare MᵀM
        assert np.allclose(_a(got["matrix"]), _a(want["matrix"]), atol=1e-4)
        assert got["scalar_rms_nT"] < 1.1 * np.mean(want["noise_nT"]) + 0.05
    noise = np.hypot(np.mean(truth["sensors"][0]["noise_nT"]), np.mean(truth["sensors"][1]["noise_nT"]))
    assert out["differential_rms_nT"] < 1.1 * noise


def test_fit_writes_a_calibration_file_and_prints_a_summary(gradiometer, tmp_path, capsys):
    path, truth = gradiometer
    cal_path = tmp_path / "cal.json"
    assert main(["fit", str(path), "--align", "rotation", "--out", str(cal_path)]) == 0
    text = capsys.readouterr().out
    assert "residual RMS" in text and "coverage" in text and str(cal_path) in text
    cal = load_calibration(cal_path)
    assert cal.method == "ellipsoid" and cal.align == "rotation" and cal.probe_names == ["s1", "s2"]
    assert np.allclose(cal.probes[1].offset_nT, truth["sensors"][1]["offset_nT"], atol=0.5)


def test_fit_refuses_a_single_axis_turn(tmp_path, capsys):
    cfg = tmp_path / "turn.toml"
    cfg.write_text('[unit]\nn_probes = 1\n[sim]\nduration_s = 15\n[sim.motion]\nkind = "turntable"\naxes = ["z"]\n'
                   'rate_deg_s = 30.0\n[sim.reference]\nenabled = true\n[[sim.probes]]\noffset_nT = [100.0, 0.0, 0.0]\n')
    out = tmp_path / "turn.csv"
    assert main(["simulate", "--config", str(cfg), "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["fit", str(out)]) == 2
    err = capsys.readouterr().err
    assert "one plane" in err and "turn about the x or y axis" in err
    # (a noise-free dwell repeats samples exactly: said as holds and left out, one line; the refusal is one line)
    assert len([ln for ln in err.strip().splitlines() if "repeat the previous one exactly" not in ln]) == 1


def test_fit_bad_csv_names_line_and_column(tmp_path, capsys):
    p = tmp_path / "bad.csv"
    p.write_text("# lab export\nt,s1_x,s1_y,s1_z\n0,1,2,3\n1,1,oops,3\n")
    assert main(["fit", str(p)]) == 2
    err = capsys.readouterr().err
    assert "line 4" in err and "'s1_y'" in err and "oops" in err


def test_a_blank_cell_says_how_a_missing_value_is_written(tmp_path, capsys):
    """pandas' to_csv writes a missing value as an empty cell, which the CSV contract does not read: said with what to
    write (nan, where the column may miss a value), where it said only "'' is not a number" (a field trial)."""
    p = tmp_path / "blank.csv"
    p.write_text("t,s1_x,s1_y,s1_z,s1_temp,heater_A\n0,1,2,3,,0.5\n")
    assert main(["fit", str(p)]) == 2
    assert ("line 2, column 's1_temp': '' is not a number: a missing value is written nan, where it may be one (a "
            "probe's axis or temperature; pandas: to_csv(na_rep='nan'))") in capsys.readouterr().err
    p.write_text("t,s1_x,s1_y,s1_z,s1_temp,heater_A\n0,1,2,3,20,\n")
    assert main(["fit", str(p)]) == 2
    assert "column 'heater_A': '' is not a number: this column takes no missing value" in capsys.readouterr().err


def test_fit_row_with_another_delimiter_says_so(tmp_path, capsys):
    p = tmp_path / "semi.csv"
    p.write_text("t,s1_x,s1_y,s1_z\n0,1,2,3\n1;1;2;3\n")
    assert main(["fit", str(p)]) == 2
    err = capsys.readouterr().err
    assert "line 3: 1 values, expected 4 (as in the header); values must be separated by ',' and this line uses ';'" in err


def test_fit_missing_file(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "nope.csv")]) == 2
    assert "no such file" in capsys.readouterr().err


def _keys(x) -> set[str]:
    """Every key of a JSON document, at any depth."""
    if isinstance(x, dict):
        return set(x) | {k for v in x.values() for k in _keys(v)}
    if isinstance(x, list):
        return {k for v in x for k in _keys(v)}
    return set()


@pytest.mark.parametrize("align", ["regression", "rotation"])
def test_scale_is_the_sensors_scale_of_every_probe_in_text_json_and_the_file(gradiometer, tmp_path, capsys, align):
    """"scale" had two names and two meanings: fit printed the sensor's scale (1.021) for s1 and called the same figure
    "sensitivity" for s2, which was besides [TwoFluxgate]'s column gain (1.3e-3 off the sensor's where the axes are not
    orthogonal), while the dashboard's "scale x" was the correction matrix's diagonal (0.979). One name, one meaning:
    the sensor's scale factor per axis, above 1 where the simulated sensor reads high."""
    import re

    path, truth = gradiometer
    want = {s["name"]: np.array(s["scale"]) for s in truth["sensors"]}
    assert want["s1"][0] > 1 > want["s2"][0]                       # the configuration reads high and low
    cal_path = tmp_path / "cal.json"
    capsys.readouterr()
    assert main(["fit", str(path), "--align", align, "--out", str(cal_path)]) == 0
    text = capsys.readouterr().out
    assert main(["fit", str(path), "--align", align, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    file_json = json.loads(cal_path.read_text())
    for doc in (text, cal_path.read_text(), json.dumps(out)):
        assert "sensitivit" not in doc
    assert "sensitivity" not in _keys(out) | _keys(file_json)
    blocks = dict(re.findall(r"\n(s\d)\n(.*?)(?=\n\n)", text, flags=re.S))
    cal = load_calibration(cal_path)
    for k, s in enumerate(out["sensors"]):
        c = want[s["name"]]
        printed = re.search(r"^  scale +\[([^]]+)\]", blocks[s["name"]], flags=re.M)
        assert printed, blocks[s["name"]]
        got_text = np.array([float(v) for v in printed[1].split(",")])
        got_json = np.array(s["params"]["scale"]["value"])
        got_file = cal.probes[k].value("scale")
        assert s["params"]["scale"]["names"] == ["c_x", "c_y", "c_z"]
        for got in (got_text, got_json, got_file):
            np.testing.assert_allclose(got, c, atol=2e-4)              # the sensor's, within 2e-4 of the truth
            assert np.array_equal(got > 1, c > 1)                      # > 1 where the sensor reads high
        # and not the correction matrix's diagonal, which is about 1/scale (0.979 for s1's 1.021)
        assert np.all(np.abs(np.diag(np.array(s["matrix"])) - got_json) > 5e-3)
    # the dashboard's API: the same file applied to a unit shows the same figures as "sensor scale", whether it
    # reads params["scale"] or decomposes the matrix (a calibration learned online has no params)
    from fluxcal.service.wiring.dashboard.view import UnitView

    for keep_params in (True, False):
        view = UnitView("grad1")
        view.update_state({"usable": True, "cal_id": 1, "probes": [
            {"name": p["name"], "offset_nT": p["offset_nT"], "matrix": p["matrix"],
             "params": p["params"] if keep_params else {}} for p in file_json["probes"]]})
        shown = {r["name"]: np.array(r["scale"]) for r in json.loads(json.dumps(view.view({})))["sensor_scales"]}
        for s in out["sensors"]:
            np.testing.assert_allclose(shown[s["name"]], s["params"]["scale"]["value"], atol=1e-9 if keep_params
                                       else 2e-4)


def test_every_residual_is_printed_with_what_it_is(gradiometer, capsys):
    """s2's block printed "residual_rms_nT 0.997414 nT" and the table 0.811 for s2.scalar, neither saying which
    residual: the first is the vector residual against the aligned reference s1, the second the scalar one."""
    import re

    path, truth = gradiometer
    capsys.readouterr()
    assert main(["fit", str(path)]) == 0
    text = capsys.readouterr().out
    assert main(["fit", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    s1, s2 = out["sensors"]
    assert "residual_rms_nT" not in text
    # the scalar residual once, in the table (a real board's fit with the total estimated printed 245.266 in the
    # probe's block, against its own assumed total, and 245.248 in the table: now the table's alone)
    assert not re.search(r"^  residual .*the scalar residual", text, flags=re.M), text
    scalar = re.search(r"^  s1\.scalar +[\d.]+ +([\d.]+)$", text, flags=re.M)
    vector = re.search(r"\ns2\n.*?^  residual +([\d.]+) nT RMS: the vector residual against the aligned reference, "
                       r"corrected s2 − corrected s1", text, flags=re.S | re.M)
    assert scalar and vector, text
    assert float(scalar[1]) == pytest.approx(s1["params"]["residual_rms_nT"]["value"], rel=1e-3)   # a total given
    assert float(scalar[1]) == pytest.approx(s1["scalar_rms_nT"], abs=5e-4)              # printed to 3 decimals
    assert float(vector[1]) == pytest.approx(s2["params"]["vector_residual_rms_nT"]["value"], rel=1e-5)
    # the vector residual is the RMS over s2-s1's three axes, which the table lists: one set of numbers
    axes = [float(re.search(rf"^  s2-s1\.{a} +[\d.]+ +([\d.]+)$", text, flags=re.M)[1]) for a in "xyz"]
    assert float(vector[1]) == pytest.approx(np.sqrt(np.mean(np.square(axes))), abs=2e-3)
    # against the noise the simulation put in: s1 0.6 nT; s2 - s1 per axis hypot(0.6, 0.8) = 1.0 nT
    assert float(scalar[1]) == pytest.approx(np.mean(truth["sensors"][0]["noise_nT"]), rel=0.05)
    assert float(vector[1]) == pytest.approx(1.0, rel=0.05)
    assert "<probe>.scalar: the scalar residual" in text and "<probe>-s1.<axis>: the vector residual" in text


def test_fit_with_effects_says_why_the_matrix_has_no_errors(capsys):
    """`fit --effects` printed the matrix's standard errors as 'n/a' with no reason (new-user trial): the line after
    the matrix says why, and where they are to be had; the header names the reference in words."""
    assert main(["fit", "recordings/grad1-hidden-effect.mcap", "--effects", "temperature"]) == 0
    out = capsys.readouterr().out
    assert "± n/a" in out
    assert "(± n/a: the fit with effects gives the effects' and the offsets' errors, not the matrix's: `fit` without " \
           "--effects gives them)" in out
    assert "total field from the ref_total column" in out.splitlines()[0]


def test_an_effect_a_real_board_does_not_show_is_refused_as_the_service_refuses_it(capsys):
    """`fit --effects drift` on 106 s of a real HMC5883L gave a quadratic drift of 1.4e6 ± 3.3e6 nT/h² (tens of
    Earth fields an hour later), exit 0 without a warning: refused now, with the service's add-effect words, and
    the parameters of an effect the data show that they do not determine are said (the temperature of the hidden
    effect's recording: 9 of its 12 within one standard error of zero)."""
    from real_data import real

    board = str(real("hmc5883l_sensorfusion_sphere.csv"))
    assert main(["fit", board, "--effects", "drift", "--json"]) == 2
    refused = json.loads(capsys.readouterr().out)["refused"]
    assert "do not show drift: none of its 8 parameters is 3 standard errors from zero" in refused["reason"]
    assert refused["advice"].startswith("fit without it")
    recording = str(Path(__file__).resolve().parents[2] / "recordings" / "grad1-hidden-effect.mcap")
    assert main(["fit", recording, "--effects", "temperature", "--json"]) == 0
    said = [w for w in json.loads(capsys.readouterr().out)["warnings"] if w.startswith("temperature: ")]
    assert len(said) == 1 and "the standard errors of 9 of its 12 parameters exceed their size" in said[0], said


def test_a_temperature_borrowed_from_another_probe_is_said_by_fit_as_by_diagnose(tmp_path, capsys):
    """A probe whose temperature column holds no value takes the other probes' mean in the temperature terms: diagnose
    said so, `fit --effects temperature` fitted s1's coefficient on s2's temperature without a word (a field trial,
    through `fluxcal.fit` as from the command line). fit now says it in the same words, and its Python result's
    warnings are the ones it prints."""
    import fluxcal

    rec = Path(__file__).resolve().parents[2] / "recordings" / "grad1-hidden-effect.mcap"
    frame = fluxcal.read(str(rec)).to_dataframe()
    frame["s1_temp"] = np.nan
    path = tmp_path / "no_s1_temp.csv"
    frame.to_csv(path, index=False, na_rep="nan")
    said = ("s1 has no temperature of its own: the temperature terms take the mean of s2's (borrowed); a coefficient "
            "fitted for s1 is a coefficient on its temperature")
    assert main(["fit", str(path), "--effects", "temperature", "--json"]) == 0
    assert said in json.loads(capsys.readouterr().out)["warnings"]
    result = fluxcal.fit(frame, effects=["temperature"])
    assert said in [w.text for w in result.warnings]
    assert [w.text for w in result.warnings][-len(result.to_dict()["warnings"]):] == result.to_dict()["warnings"]
    assert main(["diagnose", str(path), "--json"]) == 0
    assert said in json.loads(capsys.readouterr().out)["notes"]
    assert main(["fit", str(path), "--json"]) == 0                    # no temperature term: nothing borrowed to say
    assert said not in json.loads(capsys.readouterr().out)["warnings"]


def _fit_json(capsys, *args):
    assert main(["fit", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_probe_aligned_by_regression_is_told_what_it_took_from_the_reference(gradiometer, capsys):
    """grad3-flap: a flap's magnet closes on s2, and on s1 at 0.15 of it. Aligned by regression onto s1, the clean s3
    follows s1's corrected vector and takes on what s1's calibration lacks: its scalar residual grows from what its
    own fit leaves (rotation keeps that calibration: the same figure) by 1.24 times. Said, with the way out; s2's
    error is its own (1.02 times: not said); a clean simulated gradiometer says nothing of it."""
    flap = "recordings/grad3-flap.mcap"
    rot = {s["name"]: s["scalar_rms_nT"] for s in _fit_json(capsys, flap, "--align", "rotation")["sensors"]}
    reg = _fit_json(capsys, flap)
    said = [w for w in reg["warnings"] if "by regression, its scalar residual" in w]
    assert len(said) == 1 and said[0].startswith("s3: aligned to s1 by regression"), said
    s3 = {s["name"]: s["scalar_rms_nT"] for s in reg["sensors"]}["s3"]
    assert f"its scalar residual is {s3:.3f} nT where its own ellipsoid leaves {rot['s3']:.3f}" in said[0]
    assert s3 / rot["s3"] > 1.2 and "--align rotation keeps s3's own calibration" in said[0]
    rls = [w for w in _fit_json(capsys, flap, "--method", "rls")["warnings"] if "by regression, its scalar" in w]
    assert len(rls) == 1 and rls[0].startswith("s3: aligned to s1 by regression"), rls       # every method alike
    grad = _fit_json(capsys, str(gradiometer[0]))
    assert not [w for w in grad["warnings"] if "by regression, its scalar residual" in w]
