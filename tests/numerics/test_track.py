"""The reference field along a track (service/numerics/calib/track.py): the vectorised World Magnetic Model agrees
with pygeomag's own GeoMag.calculate at sample points (every model pygeomag ships, the poles included); the field
along the lat_deg, lon_deg, alt_m columns as ref_total and its direction, each sample at its date; and on a simulated
balloon climb from 0 to 25 km (drivers/sim [sim.track]) the residual is at the noise floor with it (within 1.3 x)
and far from it without, where diagnose says the residual follows alt_m."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pygeomag import GeoMag
from pygeomag.wmm import wmm_2010, wmm_2015v2, wmm_2020, wmm_2025

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import DataError
from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.numerics.calib.track import (
    DIRECTION,
    decimal_years,
    follows_height_note,
    model_for,
    track_reference,
    wmm_field,
)
from fluxcal.service.wiring import cli

WITHIN_FLOOR = 1.3


@pytest.mark.parametrize("model", [wmm_2010.WMM_2010, wmm_2015v2.WMM_2015v2, wmm_2020.WMM_2020, wmm_2025.WMM_2025],
                         ids=lambda m: m[0][1])
def test_vectorised_model_is_pygeomags(model):
    epoch = model[0][0]
    rng = np.random.default_rng(int(epoch))
    n = 300
    lat = np.concatenate([rng.uniform(-90, 90, n - 2), [90.0, -90.0]])
    lon = rng.uniform(-180, 180, n)
    alt = rng.uniform(-1000, 850_000, n)
    yr = rng.uniform(epoch, epoch + 5, n)
    gm = GeoMag(coefficients_data=model)
    ref = np.array([[r.x, r.y, r.z] for r in (gm.calculate(glat=a, glon=b, alt=c / 1000, time=y)
                                              for a, b, c, y in zip(lat, lon, alt, yr))])
    got = np.column_stack(wmm_field(lat, lon, alt, yr, epoch=epoch))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)
    assert model_for(epoch + 2.5) == (epoch, model[0][1])


def test_dates_and_models():
    assert decimal_years(np.array([1735689600.0]))[0] == 2025.0                       # 2025-01-01T00:00Z
    assert decimal_years(np.array([1735689600.0 + 365 * 86400 / 2]))[0] == pytest.approx(2025.5)
    with pytest.raises(DataError, match="outside every World Magnetic Model"):
        model_for(2001.0)


def _block(lat, lon, alt, t=None, **extras) -> SampleBlock:
    n = np.size(alt)
    t = np.arange(n, dtype=float) if t is None else t
    return SampleBlock(t_s=t, seq=np.arange(n), field_nT=np.zeros((n, 1, 3)), temp_C=np.zeros((n, 1)),
                       flags=np.zeros(n, np.uint8), extras={"lat_deg": np.broadcast_to(lat, n).copy(),
                                                            "lon_deg": np.broadcast_to(lon, n).copy(),
                                                            "alt_m": np.asarray(alt, float), **extras})


def test_track_reference_columns_and_note():
    alt = np.linspace(0, 25_000, 6)
    t0 = 1767225600.0                                                               # 2026-01-01
    tr = track_reference(_block(52.0, 13.0, alt, t=np.linspace(0, 86400 * 365 / 2, 6)), t0_unix_s=t0)
    gm = GeoMag()
    yrs = 2026.0 + np.linspace(0, 0.5, 6)
    want = np.array([[r.x, r.y, r.z, r.f] for r in (gm.calculate(glat=52.0, glon=13.0, alt=a / 1000, time=y)
                                                    for a, y in zip(alt, yrs))])
    got = np.column_stack([tr.block.extras[c] for c in (*DIRECTION, "ref_total")])
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.all(np.diff(tr.total_nT) < 0)                       # falls with height
    assert "WMM-2025 at every sample's lat_deg, lon_deg, alt_m and each sample's date (2026-01-01)" in tr.note
    # a measured reference is kept; the model only adds the direction
    measured = np.full(6, 50_000.0)
    tr2 = track_reference(_block(52.0, 13.0, alt, ref_total=measured), year=2026.0)
    np.testing.assert_array_equal(tr2.block.extras["ref_total"], measured)
    assert "the measured ref_total column kept" in tr2.note
    # no date: today's, said
    assert "does not say its date" in track_reference(_block(52.0, 13.0, alt)).notes[0]
    assert track_reference(SampleBlock(t_s=np.arange(3.0), seq=np.arange(3), field_nT=np.zeros((3, 1, 3)),
                                       temp_C=np.zeros((3, 1)), flags=np.zeros(3, np.uint8))) is None
    with pytest.raises(DataError, match="alt_m: 0 to 900000 m, outside the model's -1000 to 850000 m"):
        track_reference(_block(52.0, 13.0, np.array([0.0, 900_000.0])), year=2026.0)


def _climb(seed: int, pink: float) -> SampleBlock:
    cfg = load_sim_config({"seed": seed, "rate_hz": 10.0, "duration_s": 1000.0,
                           "track": {"enabled": True, "latitude_deg": 45.0 + 3 * seed, "longitude_deg": 7.0,
                                     "climb_m_s": 25.0, "year": 2026.0},
                           "motion": {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 11.0},
                           "probes": [{"position_m": [0, 0, 0], "offset_nT": [300, -200, 150],
                                       "scale": [1.01, 0.99, 1.0], "nonorth_deg": [0.5, -0.3, 0.2],
                                       "noise_nT": 1.0, "pink_nT_rtHz": [pink] * 3}]})
    return Unit(cfg).digitise(0, cfg.n_samples).to_block()


def _write(path, block: SampleBlock) -> None:
    cols = ["t", "s1_x", "s1_y", "s1_z", *sorted(block.extras)]
    rows = np.column_stack([block.t_s, block.field_nT[:, 0], *(block.extras[k] for k in sorted(block.extras))])
    np.savetxt(path, rows, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")


@pytest.mark.parametrize("seed, pink", [(1, 0.0), (2, 0.0), (3, 0.3)])
def test_simulated_climb_residual_vanishes_with_the_track_field(tmp_path, capsys, seed, pink):
    """White noise of 1 nT (and on seed 3 1/f noise of 0.3 nT/sqrt(Hz) besides, which the second-difference floor
    does not see)."""
    b = _climb(seed, pink)
    alt = b.extras["alt_m"]
    assert alt[0] == 0.0 and alt[-1] == pytest.approx(24_997.5)
    tr = track_reference(b, year=2026.0)
    assert tr.total_nT[0] - tr.total_nT[-1] > 400                    # the field the climb goes through falls
    _write(tmp_path / "plain.csv", b)                               # lat_deg, lon_deg, alt_m as a receiver logs them
    altitude_only = SampleBlock(t_s=b.t_s, seq=b.seq, field_nT=b.field_nT, temp_C=b.temp_C, flags=b.flags,
                                extras={"alt_m": b.extras["alt_m"]})
    _write(tmp_path / "altitude.csv", altitude_only)               # a height, but no position to take a model at
    lat = 45.0 + 3 * seed

    def diagnose(*args):
        capsys.readouterr()
        assert cli.main(["diagnose", *args, "--json", "--max-samples", "0"]) == 0
        return json.loads(capsys.readouterr().out)

    # the preparation takes the model along the track from the position columns by itself (and says so)
    with_track = diagnose(str(tmp_path / "plain.csv"), "--site", f"{lat},7,0,2026.0")
    ratio = with_track["rms_nT"] / with_track["noise_nT"]
    assert ratio <= WITHIN_FLOOR, ratio
    assert not any("the residual follows alt_m" in n for n in with_track["notes"])
    fixed = diagnose(str(tmp_path / "altitude.csv"), "--site", f"{lat},7,0,2026.0")
    ratio_fixed = fixed["rms_nT"] / fixed["noise_nT"]
    assert ratio_fixed > 20 * WITHIN_FLOOR, ratio_fixed
    where = fixed["where"]
    assert any(w["observable"] == "alt_m" and w["strength"] > 0.9 for w in where), where
    assert any(n.startswith("the residual follows alt_m") for n in fixed["notes"]), fixed["notes"]
    assert follows_height_note(with_track["where"], track_used=True) is None
    print(f"seed {seed}, 1/f {pink}: residual / floor {ratio:.3f} with the track field, {ratio_fixed:.1f} with --site at 0 m")
