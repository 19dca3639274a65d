"""The versioned calibration file: round trip, atomic write, and refusal of other versions and damage."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from paper_sims import paper001

from fluxcal.drivers.errors import DataError
from fluxcal.service.io import calfile
from fluxcal.service.io.calfile import FORMAT, VERSION, load_calibration, save_calibration
from fluxcal.service.numerics.calib.alignment import align_rotation
from fluxcal.service.numerics.calib.model import ArrayCalibration, scalar_residual_summary
from fluxcal.service.numerics.calib.tmi import fit_tmi


@pytest.fixture(scope="module")
def cal() -> ArrayCalibration:
    sim = paper001(seed=2)
    sel = sim.spread(40)
    probes = [fit_tmi(sim.raw_nT[sel, q], sim.total_nT, name=f"s{q + 1}") for q in range(4)]
    corr = [p.apply(sim.raw_nT[sel, q]) for q, p in enumerate(probes)]
    probes = align_rotation(corr).apply(probes)
    probes[3].offset_se_nT[1] = np.nan                       # "unknown" must survive the round trip
    arr = ArrayCalibration(method="tmi", align="rotation", probes=probes, total_nT=sim.total_nT,
                           span=(12.5, 52.25, int(sel.size)))
    arr.diagnostics["scalar_rms"] = scalar_residual_summary(arr, sim.raw_nT[sel], sim.total_nT)
    arr.diagnostics["condition"] = [float(p.params["condition"]["value"]) for p in probes]
    return arr


def _params_equal(a: dict, b: dict) -> bool:
    return json.dumps(calfile._jsonable(a), sort_keys=True) == json.dumps(calfile._jsonable(b), sort_keys=True)


def test_round_trip_is_exact(tmp_path, cal):
    path = tmp_path / "sub" / "cal.json"
    save_calibration(cal, path)
    back = load_calibration(path)
    assert (back.method, back.align, back.total_nT, back.span, back.effects) == \
        (cal.method, cal.align, cal.total_nT, cal.span, cal.effects)
    assert back.probe_names == cal.probe_names == ["s1", "s2", "s3", "s4"]
    for p, q in zip(back.probes, cal.probes):
        assert np.array_equal(p.matrix, q.matrix) and np.array_equal(p.offset_nT, q.offset_nT)
        assert np.array_equal(p.offset_se_nT, q.offset_se_nT, equal_nan=True)
        assert np.array_equal(p.matrix_se, q.matrix_se, equal_nan=True)
        assert _params_equal(p.params, q.params)
    assert np.isnan(back.probes[3].offset_se_nT[1])
    assert _params_equal(back.diagnostics, cal.diagnostics)
    raw = np.random.default_rng(0).normal(0, 30000, (5, 4, 3))
    assert np.array_equal(back.apply(raw), cal.apply(raw))
    d = json.loads(path.read_text())
    assert d["format"] == FORMAT and d["version"] == VERSION and d["fluxcal"] and d["created"].endswith("+00:00")
    assert d["probes"][0]["params"]["nonorth_deg"]["se"] is not None
    assert "misalign_deg" in d["probes"][0]["params"]
    assert d["span"] == {"t0_s": 12.5, "t1_s": 52.25, "n_samples": 40}


def test_write_is_atomic(tmp_path, cal, monkeypatch):
    path = tmp_path / "cal.json"
    save_calibration(cal, path)
    before = path.read_bytes()

    def fail(src, dst):
        raise OSError("disk full")

    from fluxcal.drivers import outputs

    monkeypatch.setattr(outputs.os, "replace", fail)                  # the one helper every writer goes through
    with pytest.raises(OSError, match="disk full"):
        save_calibration(cal, path)
    assert path.read_bytes() == before                        # the old file is intact
    assert os.listdir(tmp_path) == ["cal.json"]               # and no temporary file is left


def _write(tmp_path, name: str, d) -> str:
    p = tmp_path / name
    p.write_text(d if isinstance(d, str) else json.dumps(d))
    return str(p)


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d.update(version=2), r"version 2; this fluxcal reads version 1"),
    (lambda d: d.update(format="other.tool"), r"not a fluxcal calibration file"),
    (lambda d: d.pop("probes"), r"damaged.*'probes'"),
    (lambda d: d.pop("method"), r"damaged.*'method'"),
    (lambda d: d["probes"][1].pop("matrix"), r"damaged.*'matrix'"),
    (lambda d: d["probes"][0].update(matrix=[[1, 0], [0, 1]]), r"probes\[0\]\.matrix: expected shape \(3, 3\)"),
    (lambda d: d["probes"][2].update(offset_nT=[1.0, None, 3.0]), r"probes\[2\]\.offset_nT: holds non-finite"),
    (lambda d: d["probes"][2].update(offset_nT=[1.0, "x", 3.0]), r"probes\[2\]\.offset_nT: expected numbers"),
    (lambda d: d["probes"][1].update(matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 0]]), r"probes\[1\]\.matrix is singular"),
    (lambda d: d.update(probes=[]), r"non-empty list"),
    (lambda d: d["probes"][1].update(name="s1"), r"probe names repeat"),
    (lambda d: d.update(total_nT="52000"), r"total_nT: expected a positive number"),
    (lambda d: d.update(span={"t0_s": "soon"}), r"damaged"),
])
def test_damaged_or_foreign_files_are_refused(tmp_path, cal, mutate, match):
    d = calfile.calibration_to_dict(cal)
    mutate(d)
    path = _write(tmp_path, "bad.json", d)
    with pytest.raises(DataError, match=match) as e:
        load_calibration(path)
    assert str(path) in str(e.value)                           # names the file


def test_truncated_nan_and_missing_files_are_refused(tmp_path, cal):
    good = tmp_path / "good.json"
    save_calibration(cal, good)
    text = good.read_text()
    for cut in (0, 1, len(text) // 3, len(text) - 3):
        path = _write(tmp_path, f"cut{cut}.json", text[:cut])
        with pytest.raises(DataError, match=r"cut\d+\.json: damaged calibration file \(not JSON"):
            load_calibration(path)
    # Python's json reads a bare NaN; a NaN matrix is still refused
    nan_text = text.replace(json.dumps(cal.probes[0].matrix[0, 0]), "NaN", 1)
    assert nan_text != text
    with pytest.raises(DataError, match=r"matrix: holds non-finite"):
        load_calibration(_write(tmp_path, "nan.json", nan_text))
    with pytest.raises(DataError, match=r"missing\.json: calibration file not found"):
        load_calibration(tmp_path / "missing.json")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(DataError, match="bin.json"):
        load_calibration(tmp_path / "bin.json")


def test_a_fit_json_report_reads_as_its_calibration_file_does(tmp_path, capsys):
    """`fluxcal.load_calibration` (and `command apply`) refused the JSON of `fit --json`, which `diagnose --calibration`
    takes: one file, two answers. Now both read it through one conversion, checked as a calibration file is: the same
    offsets and matrix as `fit --out` writes of the same fit (a real HMC5883L sphere); a report of a fit with effects
    is refused where the whole calibration is applied, and gives its linear part where only that is held."""
    from real_data import real

    from fluxcal.service.wiring.cli import main
    from fluxcal.service.wiring.prepare import held_calibration

    csv = real("hmc5883l_sensorfusion_sphere.csv")
    out = tmp_path / "cal.json"
    assert main(["fit", str(csv), "--json", "--out", str(out)]) == 0
    report = tmp_path / "report.json"
    report.write_text(capsys.readouterr().out)
    from_report, from_file = load_calibration(report), load_calibration(out)
    assert [p.name for p in from_report.probes] == [p.name for p in from_file.probes] == ["s1"]
    for a, b in zip(from_report.probes, from_file.probes):
        np.testing.assert_allclose(a.offset_nT, b.offset_nT, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(a.matrix, b.matrix, rtol=1e-12, atol=1e-15)
    linear, effects = held_calibration(str(report), 1)
    np.testing.assert_allclose(linear.offset_nT[0], from_file.probes[0].offset_nT, rtol=1e-12)
    assert effects == []
    obj = json.loads(report.read_text())
    with_effects = tmp_path / "effects.json"
    with_effects.write_text(json.dumps({**obj, "effects": ["temperature"]}))
    with pytest.raises(DataError, match=r"report of a fit with effects \(temperature\).*--out FILE"):
        load_calibration(with_effects)
    assert held_calibration(str(with_effects), 1)[1] == ["temperature"]
    bad = tmp_path / "bad.json"
    obj["sensors"][0]["offset_nT"] = [1.0, None, 2.0]
    bad.write_text(json.dumps(obj))
    for read in (load_calibration, lambda p: held_calibration(str(p), 1)):
        with pytest.raises(DataError, match=r"probes\[0\]\.offset_nT: holds non-finite values"):
            read(bad)


def test_a_loaded_calibration_corrects_bit_for_bit_as_the_one_in_memory(tmp_path, cal):
    """A saved and loaded calibration corrected up to 1.5e-11 nT differently from the one in memory (a new user): the
    same numbers, laid out otherwise in memory, summed in another order by einsum. apply now rounds as the service's
    pipeline does, element by element, whatever the layout: bit for bit the same, and the same as the pipeline's."""
    from fluxcal.service.numerics.calib.model import ProbeCalibration
    from fluxcal.service.wiring.pipeline import Pipeline

    save_calibration(cal, tmp_path / "c.json")
    loaded = load_calibration(tmp_path / "c.json")
    field = np.random.default_rng(5).normal(size=(5000, 4, 3)) * 3e4
    assert np.array_equal(cal.apply(field), loaded.apply(field))
    strided = ArrayCalibration(method=cal.method, align=cal.align, total_nT=cal.total_nT, probes=[
        ProbeCalibration(p.name, p.offset_nT, np.asfortranarray(p.matrix), p.offset_se_nT, p.matrix_se, p.params)
        for p in cal.probes])
    assert np.array_equal(cal.apply(field), strided.apply(field))
    pipe = Pipeline(n_probes=4, probe_names=[p.name for p in cal.probes], positions_m=None, initial=loaded)
    from fluxcal.drivers.block import SampleBlock

    block = SampleBlock(t_s=np.arange(5000) * 1e-3, seq=np.arange(5000), field_nT=field,
                        temp_C=np.zeros((5000, 4)), flags=np.zeros(5000, np.uint8))
    assert np.array_equal(pipe.process(block).corrected.corrected_nT, cal.apply(field))
