"""`fit` of hours of data in bounded memory (issue 17): the regression alignment solved from normal equations
summed over chunks of rows, and the residual channels reduced to their sums of squares chunk by chunk, give
the numbers of the whole-array path on data short enough to hold whole."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.numerics.calib.alignment import align_regression, regression_calibration
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.wiring.fitting import TotalField, channel_sums, residual_channels, rms, rms_all, uncalibrated_rms


def pink(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """(n, 3) 1/f noise of standard deviation sigma per axis."""
    f = np.fft.rfftfreq(n)
    f[0] = f[1]
    spec = (rng.standard_normal((f.size, 3)) + 1j * rng.standard_normal((f.size, 3))) / np.sqrt(f)[:, None]
    x = np.fft.irfft(spec, n, axis=0)
    return sigma * x / x.std(axis=0)


def two_probes(seed: int, n: int, coloured: bool):
    """Probe 1 calibrated (its output is the field), probe 2 raw: its matrix and offset are the truth."""
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    b = 50000.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    m_true = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
    o_true = rng.uniform(-400, 400, 3)
    noise = pink(rng, n, 1.0) if coloured else rng.standard_normal((n, 3))
    raw2 = b @ np.linalg.inv(m_true).T + o_true + noise
    ref = b + 0.5 * rng.standard_normal((n, 3))
    return ref, raw2, m_true, o_true


@pytest.mark.parametrize("seed, coloured", [(1, False), (2, True), (3, True)])
def test_the_regression_by_chunks_equals_lstsq_of_the_whole_design(seed, coloured):
    ref, raw, m_true, o_true = two_probes(seed, 600_000, coloured)          # > 2 chunks of 2**18 rows
    a0, c0 = align_regression(ref, raw)
    a1, c1 = align_regression(ref, raw, gram_rows=1000)
    np.testing.assert_allclose(a1, a0, rtol=0, atol=1e-11)
    np.testing.assert_allclose(c1, c0, rtol=0, atol=1e-7 * np.abs(c0).max())
    p0 = regression_calibration("s2", ref, raw)
    p1 = regression_calibration("s2", ref, raw, gram_rows=1000)
    np.testing.assert_allclose(p1.offset_nT, p0.offset_nT, rtol=0, atol=1e-8)
    np.testing.assert_allclose(p1.offset_se_nT, p0.offset_se_nT, rtol=1e-8)
    np.testing.assert_allclose(p1.matrix_se, p0.matrix_se, rtol=1e-8)
    rr = [p.params["vector_residual_rms_nT"]["value"] for p in (p0, p1)]
    assert rr[1] == pytest.approx(rr[0], rel=1e-10)
    # and the truth: the matrix and offset the data were made with (1/f noise's slow wander is not averaged
    # away as white noise is: 1 nT of it moves the offsets by tenths of a nT)
    np.testing.assert_allclose(p1.matrix, m_true, atol=1e-4)
    assert np.all(np.abs(p1.offset_nT - o_true) < (0.5 if coloured else 0.05))


def test_the_chunked_regression_refuses_a_single_turn_like_the_whole_one():
    rng = np.random.default_rng(4)
    ang = np.linspace(0, 2 * np.pi, 5000)
    raw = np.column_stack([30000 * np.cos(ang), 30000 * np.sin(ang), np.full(ang.size, 20000.0)])
    raw += 0.5 * rng.standard_normal(raw.shape)
    for rows in (10**9, 100):
        with pytest.raises(CalibrationRefused, match="do not span three directions"):
            align_regression(raw, raw, gram_rows=rows)


def lab(seed: int, n: int, with_ref: bool) -> tuple[LabData, ArrayCalibration]:
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    b = 50000.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    probes, raws = [], []
    for k in range(3):
        m = np.eye(3) + 0.03 * rng.standard_normal((3, 3))
        o = rng.uniform(-300, 300, 3)
        raws.append(b @ np.linalg.inv(m).T + o + rng.standard_normal((n, 3)))
        probes.append(ProbeCalibration(f"s{k + 1}", o, m))
    extras = {"ref_total": 50000.0 + 0.1 * rng.standard_normal(n)} if with_ref else {}
    block = SampleBlock(t_s=np.arange(n) / 100.0, seq=np.arange(n), field_nT=np.stack(raws, axis=1),
                        temp_C=np.full((n, 3), 20.0), flags=np.zeros(n, np.uint8), extras=extras)
    return LabData(block=block, probe_names=["s1", "s2", "s3"], path="mem"), ArrayCalibration("ellipsoid", None,
                                                                                             probes)


@pytest.mark.parametrize("total", ["ref_total", "config", "estimated"])
def test_channel_sums_give_the_rms_of_the_whole_channels(total):
    data, cal = lab(7, 10_001, with_ref=total == "ref_total")
    tf = {"ref_total": TotalField(data.ref_total, "ref_total"), "config": TotalField(50000.0, "config"),
          "estimated": TotalField(None, "estimated")}[total]
    whole = residual_channels(data, cal, tf)
    sums = channel_sums(data, cal, tf, chunk=997)                        # chunks that do not divide N
    assert list(sums) == list(whole)
    for name, v in whole.items():
        assert rms(sums[name]) == pytest.approx(rms(v), rel=1e-12), name
        assert sums[name].n == v.size
    assert rms_all(list(sums.values())) == pytest.approx(rms_all(list(whole.values())), rel=1e-12)
    assert 0.5 < rms_all(list(sums.values())) < 2.0                      # the calibration is the truth: noise
    before = uncalibrated_rms(data, tf)
    ident = ArrayCalibration("none", None, [ProbeCalibration(n, np.zeros(3), np.eye(3)) for n in data.probe_names])
    for name, v in residual_channels(data, ident, tf).items():
        assert before[name] == pytest.approx(rms(v), rel=1e-12)


def test_fit_gives_the_same_numbers_with_and_without_a_report(tmp_path, capsys):
    """The report takes the scalar residuals whole for its direction bins; the figures printed are the chunked
    sums either way."""
    import json
    from pathlib import Path

    from fluxcal.service.wiring import cli

    rec = str(Path(__file__).resolve().parents[2] / "recordings" / "grad1-sim-30s.mcap")
    assert cli.main(["fit", rec, "--json"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert cli.main(["fit", rec, "--json", "--report", str(tmp_path / "rep")]) == 0
    with_report = json.loads(capsys.readouterr().out)
    assert with_report == plain
    page = (tmp_path / "rep" / "index.html").read_text()
    assert "s1" in page and "s2" in page
