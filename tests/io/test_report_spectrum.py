"""The band `diagnose` names and the spectrum its report draws come from one computation
(numerics.diagnose.where.excess_spectrum), and the report draws every channel.

The report drew its first six channels only (a three-probe array has nine) from a Welch spectrum, while the
text named the strongest of twelve log-spaced bands at fixed edges: a hump at 0.9-1.8 Hz, 50 Hz for 370 s, was
named "1.19-2.55 Hz", the fixed band holding most of it. The band now slides to where the excess lies."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt

from fluxcal.service.numerics.diagnose.where import excess_spectrum

ROOT = Path(__file__).resolve().parents[2]
PUMP = ROOT / "recordings" / "grad3-pump.mcap"


def pink(rng, n: int, dt: float, density_at_1hz: float) -> np.ndarray:
    """1/f noise: its one-sided density density_at_1hz²/f nT²/Hz."""
    f = np.fft.rfftfreq(n, dt)
    amp = np.zeros(f.size)
    amp[1:] = density_at_1hz / np.sqrt(f[1:])
    spec = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * np.sqrt(n / (4 * dt))
    return np.fft.irfft(spec, n)


def hump(rng, n: int, fs: float, lo: float = 0.9, hi: float = 1.8, rms: float = 2.0) -> np.ndarray:
    sos = butter(4, [lo, hi], btype="band", fs=fs, output="sos")
    h = sosfiltfilt(sos, rng.standard_normal(n))
    return h * rms / h.std()


@pytest.mark.parametrize("fs, seconds", [(50.0, 370.0), (10.0, 600.0), (200.0, 60.0)])
@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("coloured", [False, True])
def test_a_hump_is_named_where_it_lies(fs, seconds, seed, coloured):
    rng = np.random.default_rng(seed)
    n, dt, sigma = int(fs * seconds), 1.0 / fs, 0.6
    y = sigma * rng.standard_normal(n) + hump(rng, n, fs)
    if coloured:
        y += pink(rng, n, dt, 0.05)
    ex = excess_spectrum(y, dt, sigma)
    lo, hi = ex.band_hz
    # the hump's half-power edges 0.9 and 1.8 Hz, within a twentieth of the band's width of each (a factor
    # 1.87-2.2 here: the record's span of log frequency in twelve)
    assert abs(np.log(lo / 0.9)) < 0.2 and abs(np.log(hi / 1.8)) < 0.2, ex.band
    assert ex.band == f"{lo:.3g}-{hi:.3g} Hz"
    # its share is the variance above the floor in that band, from the periodogram itself
    spec = np.abs(np.fft.rfft(y - y.mean())) ** 2 / n
    f = np.fft.rfftfreq(n, dt)
    inside = (f >= lo) & (f < hi)
    total = np.mean((y - y.mean()) ** 2)
    assert ex.share == pytest.approx((2 / n) * (spec[inside].sum() - sigma ** 2 * inside.sum()) / total, abs=1e-9)
    # 4 nT² of a hump over 0.36 nT² of white noise (and the 1/f's): most of the variance
    assert ex.share > 0.8
    # the spectrum drawn has the floor where the white noise is: the median density above 3.5 Hz
    assert np.median(ex.density[ex.freq_hz > 3.5]) == pytest.approx(ex.floor, rel=0.25)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_line_is_named_by_the_band_centred_on_it(seed):
    rng = np.random.default_rng(seed)
    n, fs = 4000, 25.0
    t = np.arange(n) / fs
    y = 0.6 * rng.standard_normal(n) + 4.0 * np.sin(2 * np.pi * 1.51 * t + seed)
    ex = excess_spectrum(y, 1.0 / fs, 0.6)
    lo, hi = ex.band_hz
    assert lo < 1.51 < hi and abs(np.log(np.sqrt(lo * hi) / 1.51)) < 0.05, ex.band
    assert ex.share == pytest.approx(8.0 / (8.0 + 0.36), abs=0.02)          # the line's share of the variance


def test_white_noise_names_no_strong_band():
    rng = np.random.default_rng(7)
    ex = excess_spectrum(0.6 * rng.standard_normal(20000), 0.02, 0.6)
    assert ex.share < 0.02


@pytest.mark.skipif(not PUMP.exists(), reason="recordings/grad3-pump.mcap is not in this checkout")
def test_the_report_draws_every_channel_and_shades_the_bands_the_text_names(tmp_path, monkeypatch, capsys):
    pytest.importorskip("matplotlib")
    import json

    from fluxcal.service.io.report import diagnose as report
    from fluxcal.service.wiring import cli

    drawn: dict[str, object] = {}
    real_png = report.png

    def keep(fig):
        if "spectrum" not in drawn and any(ax.get_yscale() == "log" and "Hz" in ax.get_xlabel()
                                           for ax in fig.axes if ax.get_visible()):
            drawn["spectrum"] = [(ax.get_title(), [ln.get_label() for ln in ax.get_lines()],
                                  [p.get_label() for p in ax.patches], [p.get_x() for p in ax.patches],
                                  [p.get_x() + p.get_width() for p in ax.patches])
                                 for ax in fig.axes if ax.get_visible()]
        return real_png(fig)

    monkeypatch.setattr(report, "png", keep)
    assert cli.main(["diagnose", str(PUMP), "--report", str(tmp_path / "rep"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    names = [c["name"] for c in d["channels"]]
    assert len(names) == 9                                  # three probes: 3 scalar channels, 6 differences
    panels = drawn["spectrum"]
    lines = [label for _, labels, *_ in panels for label in labels]
    assert sorted(x for x in lines if not x.startswith("_") and not x.startswith("line at")) == sorted(names)
    assert [title for title, *_ in panels] == ["scalar residuals", "s2-s1", "s3-s1"]
    # every band the text names is shaded, with its edges and its share as the text gives them
    named = {(w["band"], round(100 * w["strength"])): w["band_hz"] for w in d["where"]
             if w["observable"] == "frequency"}
    assert named
    shaded = {label: (x0, x1) for _, _, labels, x0s, x1s in panels for label, x0, x1 in zip(labels, x0s, x1s)}
    for (band, pct), (lo, hi) in named.items():
        assert shaded[f"{band} ({pct} %)"] == pytest.approx((lo, hi), rel=1e-12)
    # the pump turns at 1.51 Hz beside s2: the band named in what is left is centred on it
    lo, hi = named[next(iter(named))]
    assert lo < 1.51 < hi and abs(np.log(np.sqrt(lo * hi) / 1.51)) < 0.05
    assert f"it follows frequency {next(iter(named))[0]} in s2.scalar" in d["verdict"]["left"]
    html = (tmp_path / "rep" / "index.html").read_text()
    assert "each of the 9 channels" in html
