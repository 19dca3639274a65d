"""PX4 ULog as lab data (service/io/recordings/px4.py): a ULog built from the format's specification and read by
pyulog gives every sensor_mag instance as a probe (gauss -> nT), its temperature, the attitude, the track and the
battery current as columns; `fit` fits it with both compasses as probes and `diagnose` finds the current; a real
flight log (pyulog's own sample, BSD-3-Clause) is read end to end where ../shared/real-data or $FLUXCAL_REAL_DATA
has it (tests/real_data.py)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyulog", reason="the PX4 reader's optional package: pip install 'fluxcal[px4]'")

from flightlogs import CURRENT_COUPLING_NT_A, simulated_flight, write_ulog
from real_data import needs_real, real

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.io.recordings.px4 import Px4Mapping, inspect_px4
from fluxcal.service.wiring import cli

BOOT_US = 20_000_000                      # the log starts 20 s after boot
UTC_AT_BOOT_US = 1_700_000_000_000_000    # 2023-11-14


def _ulog_topics(d: dict) -> list:
    n = d["t_s"].size
    us = BOOT_US + np.round(d["t_s"] * 1e6).astype(np.int64)
    mag_fields = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
                  ("float", "x"), ("float", "y"), ("float", "z"), ("float", "temperature"),
                  ("uint32_t", "error_count")]
    topics = []
    for k in range(2):
        g = d["field_nT"][:, k] / 1e5                                              # gauss
        topics.append(("sensor_mag", k, mag_fields,
                       {"timestamp": us + 150, "timestamp_sample": us, "device_id": np.full(n, 0x30000 + k),
                        "x": g[:, 0], "y": g[:, 1], "z": g[:, 2], "temperature": d["temp_C"][:, k],
                        "error_count": np.zeros(n, int)}))
    att = slice(None, None, 2)                                                     # attitude at half the rate
    topics.append(("vehicle_attitude", 0, [("uint64_t", "timestamp"), ("float[4]", "q")],
                   {"timestamp": us[att] + 37, "q": d["q"][att]}))
    gps = slice(0, None, 10)                                                      # 5 Hz
    topics.append(("vehicle_gps_position", 0,
                   [("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec"), ("int32_t", "lat"), ("int32_t", "lon"),
                    ("int32_t", "alt"), ("int32_t", "alt_ellipsoid"), ("uint8_t", "fix_type")],
                   {"timestamp": us[gps], "time_utc_usec": UTC_AT_BOOT_US + us[gps],
                    "lat": np.round(d["lat"][gps] * 1e7), "lon": np.round(d["lon"][gps] * 1e7),
                    "alt": np.round((d["alt"][gps] - 48.0) * 1e3), "alt_ellipsoid": np.round(d["alt"][gps] * 1e3),
                    "fix_type": np.full(us[gps].size, 3)}))
    topics.append(("battery_status", 0, [("uint64_t", "timestamp"), ("float", "current_a")],
                   {"timestamp": us, "current_a": d["current_a"]}))
    return topics


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    d = simulated_flight()
    path = tmp_path_factory.mktemp("px4") / "flight.ulg"
    write_ulog(path, _ulog_topics(d), info={"sys_name": "PX4", "ver_hw": "SIMULATED"})
    return path, d


def test_every_compass_a_probe_with_its_columns(flight):
    path, d = flight
    lab = load_data(path)
    b = lab.block
    assert lab.probe_names == ["s1", "s2"]
    # each row's instant on the boot clock, from where t = 0 lies in UTC: the simulator's sample it is
    boot_s = float(lab.metadata["t0_unix_s"]) - UTC_AT_BOOT_US / 1e6 + b.t_s
    sel = np.rint((boot_s - BOOT_US / 1e6) * 50.0).astype(int)
    np.testing.assert_allclose(d["t_s"][sel], boot_s - BOOT_US / 1e6, atol=2e-6)
    # the attitude starts 37 us after the first compass sample and the GPS ends before the last ones: those rows go
    assert sel[0] == 1 and d["t_s"].size - 12 <= sel[-1] + 1 < d["t_s"].size
    np.testing.assert_allclose(b.field_nT, d["field_nT"][sel], rtol=1e-6, atol=0.01)     # float32 gauss
    np.testing.assert_allclose(b.temp_C, d["temp_C"][sel], rtol=1e-6)
    np.testing.assert_allclose(b.extras["battery_current_a"], d["current_a"][sel], rtol=1e-6)
    for c, col in enumerate(("heel_deg", "pitch_deg", "azimuth_deg")):
        # interpolated between attitude samples 40 ms apart: within the turn of half an interval's curvature
        err = (b.extras[col] - d["euler"][sel, c] + 180.0) % 360.0 - 180.0
        assert np.percentile(np.abs(err), 99) < 0.05, col
    np.testing.assert_allclose(b.extras["alt_m"], d["alt"][sel], atol=2e-3)                 # mm, linear climb
    np.testing.assert_allclose(b.extras["lat_deg"], d["lat"][sel], atol=2e-7)
    assert float(lab.metadata["t0_unix_s"]) == pytest.approx((UTC_AT_BOOT_US + BOOT_US) / 1e6 + 0.02, abs=1e-5)
    src = json.loads(lab.metadata["sources"])
    assert src["s1"] == "sensor_mag[0]" and src["s2_temp"] == "sensor_mag[1].temperature"
    assert any("alt_m from vehicle_gps_position: above the WGS84 ellipsoid" in n for n in lab.notes)
    said = " ".join(lab.warnings)
    assert "1 before its first sample" in said and "after its last" in said


def test_fit_and_diagnose_take_the_log(flight, capsys):
    path, d = flight
    capsys.readouterr()
    assert cli.main(["fit", str(path), "--json", "--effects", "column"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["name"] for s in out["sensors"]] == ["s1", "s2"]
    # the current's field on the first compass, nT per A, as simulated (the column effect on the logged current)
    col = out["effect_params"]["column"]
    for a, want in zip("xyz", CURRENT_COUPLING_NT_A):
        got = col[f"s1.{a} nT per battery_current_a"]
        assert abs(got["value"] - want) < 4 * got["se"], (a, got, want)
        got2 = col[f"s2.{a} nT per battery_current_a"]
        assert abs(got2["value"]) < 4 * got2["se"], (a, got2)
    assert cli.main(["diagnose", str(path), "--json"]) == 0
    diag = json.loads(capsys.readouterr().out)
    text = json.dumps(diag)
    assert "battery_current_a" in text
    assert diag["candidates"][0]["effect"] == "column", [c["effect"] for c in diag["candidates"]]


def test_mapping_and_inspect(flight, capsys):
    path, _ = flight
    lab = load_data(path, mapping=Px4Mapping(mags=[1], attitude=False, position=False, currents=False))
    assert lab.probe_names == ["s1"] and lab.block.extras == {} and lab.warnings == []
    assert json.loads(lab.metadata["sources"])["s1"] == "sensor_mag[1]"
    with pytest.raises(DataError, match=r"mags: instance\(s\) \[4\] not in .*its sensor_mag instances: \[0, 1\]"):
        load_data(path, mapping=Px4Mapping(mags=[4]))
    i = inspect_px4(path)
    by = {s.name: s for s in i.streams}
    assert by["sensor_mag[0]"].maps_to.startswith("probe s1") and "s1_temp" in by["sensor_mag[0]"].maps_to
    assert by["sensor_mag[1]"].rate_hz == pytest.approx(50.0, rel=1e-6)
    assert by["vehicle_gps_position"].maps_to == "lat_deg, lon_deg, alt_m"
    assert by["battery_status"].maps_to == "battery_current_a"
    assert cli.main(["inspect", str(path)]) == 0
    assert "PX4 flight log (ULog)" in capsys.readouterr().out


def test_the_advice_on_cut_rows_is_an_option_that_keeps_them(flight, capsys):
    """The GPS ends 9 rows before the compasses, the attitude begins 1 row after them and lacks the last of those 9:
    each warning names its stream as inspect does and the --topics that keeps the rows, and --topics takes it for a
    PX4 log (it was refused: 'not a ROS 2 bag'), keeping them."""
    path, _ = flight
    said = load_data(path).warnings
    assert len(said) == 2
    assert said[0].startswith("lat_deg (vehicle_gps_position (3D fix), 400 samples): no value at 9 rows")
    assert "leave the stream and attitude, which lacks some of them too, out of the mapping (--topics gps=none," \
           "imu=none) to keep them" in said[0]
    assert said[1].startswith("attitude (heel_deg, pitch_deg, azimuth_deg) (vehicle_attitude q") and \
        "out of the mapping (--topics imu=none) to keep them" in said[1]
    capsys.readouterr()
    assert cli.main(["inspect", str(path), "--json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert cli.main(["inspect", str(path), "--topics", "gps=none,imu=none,battery=none", "--json"]) == 0
    narrow = json.loads(capsys.readouterr().out)
    assert narrow["samples"] == whole["samples"] + 10 and set(narrow["columns"]) == {"s1_temp", "s2_temp"}
    assert {s["name"]: s["maps_to"] for s in narrow["streams"]}["battery_status"] == ""
    assert cli.main(["inspect", str(path), "--topics", "gps=none", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] == whole["samples"] + 8
    for wrong in ("battery=/battery", "s1=/mag"):
        assert cli.main(["fit", str(path), "--topics", wrong]) == 2
        assert f"--topics: {wrong} is not allowed for {path} (a PX4 log" in capsys.readouterr().err


#: what PX4's own calibration left on the second compass in the simulated vehicle_magnetometer, nT
LEFT_BY_PX4_NT = np.array([120.0, -75.0, 40.0])


def test_vehicle_magnetometer_taken_only_when_asked_one_compass_and_calibration(tmp_path, capsys):
    """A log whose sensor_mag is sparse while vehicle_magnetometer is rich could only be refused: vehicle_magnetometer
    is PX4's output after its own calibration, which a fit must not take for the raw field unasked. Asked for
    (`--topics mag=vehicle_magnetometer`), it is the probe, said as PX4's output, and a fit finds what PX4's
    calibration left (LEFT_BY_PX4_NT). PX4 switched to another compass for the last quarter: those samples are left
    out and said (one probe is one compass under one calibration)."""
    d = simulated_flight()
    n = d["t_s"].size
    us = BOOT_US + np.round(d["t_s"] * 1e6).astype(np.int64)
    vm = (d["field_nT"][:, 1] - d["offsets_nT"][1] + LEFT_BY_PX4_NT) / 1e5           # gauss, PX4's offsets out
    device = np.where(np.arange(n) < 3 * n // 4, 0x30001, 0x30002)
    topics = _ulog_topics(d) + [("vehicle_magnetometer", 0,
                                 [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
                                  ("float[3]", "magnetometer_ga"), ("uint8_t", "calibration_count")],
                                 {"timestamp": us + 400, "timestamp_sample": us + 300, "device_id": device,
                                  "magnetometer_ga": vm, "calibration_count": np.ones(n)})]
    path = tmp_path / "vm.ulg"
    write_ulog(path, topics, info={"sys_name": "PX4"})
    assert load_data(path).probe_names == ["s1", "s2"]                            # unasked: sensor_mag, as before
    lab = load_data(path, mapping=Px4Mapping(compass="vehicle_magnetometer"))
    assert lab.probe_names == ["s1"] and json.loads(lab.metadata["sources"])["s1"] == "vehicle_magnetometer[0]"
    assert any("PX4's output after its own calibration" in note for note in lab.notes)
    assert 2_950 <= lab.block.n_samples <= 3_000                                  # the first compass's samples alone
    said = " ".join(lab.warnings)                                                 # samples left out: a warning
    assert "the 3,000 samples of device 0x30001 calibration 1 taken, 1,000 of device 0x30002 calibration 1 left " \
           "out" in said
    by = {st.name: st for st in inspect_px4(path, Px4Mapping(compass="vehicle_magnetometer")).streams}
    assert by["vehicle_magnetometer"].maps_to.startswith("probe s1") and by["sensor_mag[0]"].maps_to == ""
    capsys.readouterr()
    assert cli.main(["fit", str(path), "--topics", "mag=vehicle_magnetometer", "--json"]) == 0
    out, err = capsys.readouterr()
    assert "PX4's output after its own calibration" in err and "on top of PX4's, not the sensor's own" in err
    s1 = json.loads(out)["sensors"][0]
    for got, se, want in zip(s1["offset_nT"], s1["offset_se_nT"], LEFT_BY_PX4_NT):
        assert abs(got - want) < max(4 * se, 5.0), (got, se, want)
    assert cli.main(["fit", str(path), "--topics", "mag=vehicle_attitude"]) == 2
    assert "mag=sensor_mag or mag=vehicle_magnetometer the topic the probes come from" in capsys.readouterr().err


@needs_real("px4_sample_log_small.ulg")
def test_real_px4_log_end_to_end(capsys):
    """A real flight (CubeOrange, 2021-04-21): two compasses logged at 1 Hz, two batteries, GPS. Read end to end:
    both compasses as probes in the Earth's field, the date from the GPS; too few samples to fit (6), which fit
    says instead of fitting."""
    capsys.readouterr()
    path = real("px4_sample_log_small.ulg")
    lab = load_data(path)
    assert lab.probe_names == ["s1", "s2"] and lab.block.n_samples == 6
    total = np.linalg.norm(lab.block.field_nT, axis=2)
    assert np.all((total > 20_000) & (total < 80_000))                  # gauss x 1e5: the Earth's field in nT
    assert {"battery_current_a", "battery1_current_a", "lat_deg", "heel_deg"} <= set(lab.block.extras)
    assert 63.4 < float(np.mean(lab.block.extras["lat_deg"])) < 63.5
    import datetime as dt
    day = dt.datetime.fromtimestamp(float(lab.metadata["t0_unix_s"]), dt.timezone.utc).date()
    assert day == dt.date(2021, 4, 21)
    assert cli.main(["fit", str(path)]) == 2
    err = capsys.readouterr().err
    assert "s1: 5 samples; the fit needs at least 10" in err       # one of the 6 a logger's hold, left out: said
    # the log's 319 samples of vehicle_magnetometer, PX4's output after its calibration: said, and why not taken
    assert "sensor_mag holds 6, 6 sample(s) (the logging profile's rate) where vehicle_magnetometer holds 319" in err
    assert "s1: 1 of 6 samples (17%) repeat the previous one exactly" in err
    quoted = re.search(r'`fit` says "([^"]+)"', (Path(__file__).parents[2] / "docs" / "px4.md").read_text()).group(1)
    assert quoted in err                                               # docs/px4.md quotes what fit says


@needs_real("px4_pyulog_sample.ulg")
def test_a_real_flight_of_an_older_px4_is_read_and_its_cone_refused(capsys):
    """pyulog's sample.ulg: a real flight of 69 s whose one magnetometer an older PX4 logged in sensor_combined
    (17,070 rows at the gyroscope's rate, 6,750 magnetometer samples). Read end to end; fitted with the total field
    estimated, its cone of directions gave a matrix no sensor has (condition 9.4, 62 degrees of non-orthogonality)
    which passed the cone check on its own shape: refused now, saying which turn is missing."""
    path = real("px4_pyulog_sample.ulg")
    lab = load_data(path)
    assert lab.probe_names == ["s1"] and lab.block.n_samples == 6750
    total = np.linalg.norm(lab.block.field_nT[:, 0], axis=1)
    assert 45_000 < np.median(total) < 51_000                          # the Earth's field, in nT
    assert {"heel_deg", "pitch_deg", "azimuth_deg"} <= set(lab.block.extras)
    capsys.readouterr()
    assert cli.main(["fit", str(path)]) == 2
    err = capsys.readouterr().err
    assert "the fitted calibration is no sensor's (fails the condition check" in err and "turn about" in err
    assert cli.main(["fit", str(path), "--site", "47.4,8.5,500"]) == 2               # the total given: the cone
    assert "one cone about" in capsys.readouterr().err
