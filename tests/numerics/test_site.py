"""The site's field from the World Magnetic Model: published test values, the key, the errors."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pygeomag import GeoMag
from pygeomag.wmm.wmm_2010 import WMM_2010
from pygeomag.wmm.wmm_2015v2 import WMM_2015v2
from pygeomag.wmm.wmm_2020 import WMM_2020
from pygeomag.wmm.wmm_2025 import WMM_2025

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.numerics.calib.site import parse_site, site_field, site_from_text
from fluxcal.service.wiring.config import config_from_dict

ROOT = Path(__file__).resolve().parents[2]

# NOAA NCEI, "The US/UK World Magnetic Model for 2025-2030", test values (year, height km, lat, lon,
# X, Y, Z, F nT, I, D deg): the model's own published check figures
WMM2025_TEST_VALUES = [
    (2025.0, 0.0, 80.0, 0.0, 6521.6, 145.9, 54791.5, 55178.5, 83.21, 1.28),
    (2025.0, 0.0, 0.0, 120.0, 39677.8, -109.6, -10580.2, 41064.3, -14.93, -0.16),
    (2025.0, 100.0, -80.0, 240.0, 5907.6, 14780.3, -49540.7, 52035.0, -72.19, 68.21),
    (2027.5, 0.0, -80.0, 240.0, 6200.7, 15730.3, -51783.7, 54474.2, -71.92, 68.49),
    (2027.5, 100.0, 0.0, 120.0, 37711.5, -148.7, -9969.8, 39007.4, -14.81, -0.23),
]


@pytest.mark.parametrize("year, h_km, lat, lon, x, y, z, f, inc, dec", WMM2025_TEST_VALUES)
def test_the_site_field_matches_the_published_test_values(year, h_km, lat, lon, x, y, z, f, inc, dec):
    s = site_field(lat, lon, h_km * 1000.0, year)
    assert np.allclose([s.north_nT, s.east_nT, s.down_nT, s.total_nT], [x, y, z, f], atol=0.051)
    assert abs(s.inclination_deg - inc) < 0.0051 and abs(s.declination_deg - dec) < 0.0051
    assert s.model == "WMM-2025"


def test_a_date_as_day_or_decimal_year_and_today_by_default():
    assert parse_site("46.5, 6.6, 400, 2026-07-02") == (46.5, 6.6, 400.0, pytest.approx(2026.5, abs=0.003))
    assert parse_site("46.5,6.6,400,2026.5")[3] == 2026.5 and parse_site("46.5,6.6,400")[3] is None
    assert 2025.0 <= site_from_text("46.5,6.6,400").year < 2031.0


def test_the_altitude_left_out_is_the_ground_and_costs_a_few_nT():
    """LAT,LON (as fluxcal's own advice writes it) is the site at 0 m; the field falls by 8-32 nT a km of height at
    these sites (0.035-0.06 %), far below the model's 0.1-1 % at a site."""
    assert parse_site("46,6") == (46.0, 6.0, 0.0, None) and parse_site("-75,-120") == (-75.0, -120.0, 0.0, None)
    for lat, lon in [(46.0, 6.0), (-75.0, 120.0), (0.0, 0.0), (-30.0, -60.0)]:
        ground, km = site_field(lat, lon, 0.0, 2026.0), site_field(lat, lon, 1000.0, 2026.0)
        assert site_from_text(f"{lat},{lon},0,2026.0") == ground
        assert -35.0 < km.total_nT - ground.total_nT < -5.0
        assert abs(km.total_nT - ground.total_nT) / ground.total_nT < 7e-4


@pytest.mark.parametrize("year, model", [(2012.5, WMM_2010), (2017.0, WMM_2015v2), (2021.3, WMM_2020),
                                         (2026.0, WMM_2025)])
def test_the_model_of_the_date_is_taken_as_along_a_track(year, model):
    """The model whose five-year life holds the date (a 2021 flight log's track is given WMM-2020; its --site too),
    equal to pygeomag's own evaluation of that model."""
    s = site_field(-33.9, -70.6, 500.0, year)
    r = GeoMag(coefficients_data=model).calculate(glat=-33.9, glon=-70.6, alt=0.5, time=year)
    assert s.model == str(model[0][1])
    assert np.allclose([s.north_nT, s.east_nT, s.down_nT, s.total_nT], [r.x, r.y, r.z, r.f], atol=1e-6)
    assert abs(s.inclination_deg - r.i) < 1e-9 and abs(s.declination_deg - r.d) < 1e-9


@pytest.mark.parametrize("text, why", [("1", "1 field"), ("a,b,c", "must be numbers"), ("95,0,0", "latitude"),
                                       ("0,0,900000", "altitude"), ("0,0,0,2009-01-01", "2010 to 2030"),
                                       ("0,0,0,soon", "neither")])
def test_a_bad_site_is_named_with_what_is_allowed(text, why):
    with pytest.raises(ConfigError, match=f"--site: .*{why}"):
        site_from_text(text)
    with pytest.raises(ConfigError, match="allowed: "):
        site_from_text(text)


def test_a_date_outside_every_model_says_what_to_give_instead():
    with pytest.raises(ConfigError, match=r"2031.00 is not allowed .*give a date within those years, or the total "
                                          r"field itself \(a ref_total column, or estimator.total_nT"):
        site_from_text("46,6,0,2031.0")


def test_the_config_key_gives_the_estimator_its_total_field():
    cfg = config_from_dict({"estimator": {"site": "80,0,0,2025.0"}})
    assert abs(cfg.estimator.total_nT - 55178.5) < 0.051
    with pytest.raises(ConfigError, match="estimator.site: .* beside estimator.total_nT"):
        config_from_dict({"estimator": {"site": "80,0,0,2025.0", "total_nT": 50000.0}})
    with pytest.raises(ConfigError, match="estimator.site: '80' is not allowed"):
        config_from_dict({"estimator": {"site": "80"}})


def test_fit_takes_the_site_for_a_method_that_needs_a_total_field(tmp_path):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    f = site_field(80.0, 0.0, 0.0, 2025.0).total_nT
    raw = f * d * [1.01, 0.99, 1.02] + [120.0, -40.0, 300.0] + rng.normal(scale=1.0, size=d.shape)
    path = tmp_path / "lab.csv"
    np.savetxt(path, np.column_stack([np.arange(2000) * 0.01, raw]), delimiter=",", header="t,s1_x,s1_y,s1_z",
               comments="")
    run = [sys.executable, "-m", "fluxcal.service.wiring.cli", "fit", str(path), "--method", "tmi", "--json"]
    refused = subprocess.run(run, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert refused.returncode == 2 and "tmi needs a scalar reference" in refused.stderr
    assert "--site LAT,LON" in refused.stderr          # the way out it needs, said where it is refused
    done = subprocess.run(run + ["--site", "80,0,0,2025.0"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert abs(out["site"]["total_nT"] - 55178.5) < 0.051
    scale = np.diag(np.asarray(out["sensors"][0]["matrix"]))
    assert np.allclose(scale, [1 / 1.01, 1 / 0.99, 1 / 1.02], atol=2e-4)
    assert out["sensors"][0]["scalar_rms_nT"] < 1.5
    # diagnose of the same file at the same site says where its total field came from as fit does
    diag = subprocess.run([sys.executable, "-m", "fluxcal.service.wiring.cli", "diagnose", str(path), "--site",
                           "80,0,0,2025.0"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    fitted = subprocess.run(run[:-3] + ["--site", "80,0,0,2025.0"], capture_output=True, text=True, cwd=ROOT,
                            timeout=120)
    assert diag.returncode == 0 and fitted.returncode == 0, diag.stderr + fitted.stderr
    said = re.search(r"total field from (the site \([^)]*\))", fitted.stdout).group(1)
    assert said.startswith("the site (WMM") and f"total field from {said})" in diag.stdout, diag.stdout
