"""diagnose on every public recording of a real magnetometer in ../shared/real-data (issue 14; found by
tests/real_data.py): it runs on each, bursty time base included (2 ms bursts with 20-60 ms between them were
taken for 2,958 gaps and left nothing to fit), and says what its residual follows."""

from __future__ import annotations

import json

import pytest
from real_data import real, real_nT

from fluxcal.service.wiring.cli import main

NAMES = ["qmc5883l_suarez", "imu_freeimucal", "hmc5883l_sensorfusion_sphere"]
TURNS = {"hmc5883l_nliaudat": "z", "hmc5883l_sensorfusion_turn_x": "x", "hmc5883l_sensorfusion_turn_y": "y",
         "hmc5883l_sensorfusion_turn_z": "z"}


def _diagnose(name: str, capsys, *extra: str) -> dict:
    capsys.readouterr()
    assert main(["diagnose", str(real_nT(f"{name}.csv")), "--json", *extra]) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_diagnose_runs_on_every_real_recording_and_describes_what_is_left(name, capsys):
    d = _diagnose(name, capsys)
    v = d["verdict"]
    assert v["kind"] in ("at the floor", "explained", "partly explained", "unexplained",
                         "explained beyond the catalogue")
    from fluxcal.service.io.recordings.load import load_data

    assert d["n_samples"] >= 0.9 * load_data(real(f"{name}.csv")).block.n_samples     # the samples are kept
    if v["kind"] in ("partly explained", "unexplained", "explained beyond the catalogue"):
        assert v["left"] and v["advice"], v            # what is left (or what the catalogue leaves) is described


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(TURNS))
def test_a_real_single_axis_turn_is_refused_unless_a_calibration_is_held(name, capsys, tmp_path):
    """A single-axis turn does not fix the linear part it would refit (fit refuses it): diagnose said a real turn
    was 'explained by crossfield' and sent the user to a refused fit. Refused alike, naming the cone and the way
    out; with the board's own sphere calibration held, the turn is diagnosed."""
    capsys.readouterr()
    assert main(["diagnose", str(real(f"{name}.csv"))]) == 2
    err = capsys.readouterr().err
    axis = TURNS[name]
    assert f"one cone about {axis} (a turn about {axis})" in err and "--calibration CAL.json" in err
    if name.startswith("hmc5883l_sensorfusion"):
        cal = tmp_path / "sphere.json"
        assert main(["fit", str(real("hmc5883l_sensorfusion_sphere.csv")), "--out", str(cal)]) == 0
        capsys.readouterr()
        d = _diagnose(name, capsys, "--calibration", str(cal))
        assert d["linear"] == "fixed" and d["verdict"]["kind"] in ("at the floor", "explained", "partly explained",
                                                                    "unexplained", "explained beyond the catalogue")


@pytest.mark.slow
def test_the_bursty_recording_keeps_its_samples(capsys):
    """Every sample, but the 239 that repeat the one before exactly (18.8 expected by chance): the board's driver read
    the sensor faster than it measured (bursts of ~8 samples 2-3 ms apart), a logger's hold, left out and said."""
    d = _diagnose("hmc5883l_sensorfusion_sphere", capsys)
    assert d["n_samples"] == 8190 - 239
    assert d["rms_nT"] < 2 * d["noise_nT"]                # hand-turned hobby board: ~250 against ~140 nT


@pytest.mark.slow
def test_a_band_at_the_rates_the_board_turns_is_a_misfit_that_follows_its_direction(capsys):
    """The hand-turned sphere's residual is strongest at 0.09-0.19 Hz, where the field the board reads changes as it is
    turned: it was advised as 'a narrow-band disturbance (something turning near the probe)' with a request to log
    the phase of what turns, though its gyros are logged (two field trials). The band's share of the field's own
    variation says it is the turning's."""
    d = _diagnose("hmc5883l_sensorfusion_sphere", capsys)
    band = next(w for w in d["where"] if w["observable"] == "frequency")
    assert band["turning_share"] >= 0.3, band
    advice = d["verdict"]["advice"]
    assert "a misfit at the rates the probe turns" in advice and "it follows the direction the probe points" in advice
    assert "narrow-band disturbance" not in advice and "log the phase" not in advice, advice


@pytest.mark.slow
def test_an_hour_long_recording_whose_residual_follows_time_says_so(capsys):
    d = _diagnose("imu_freeimucal", capsys)
    v = d["verdict"]
    assert v["kind"] == "unexplained"
    assert v["signature"]["follows"][0]["observable"] == "time"
    assert "second probe or a reference magnetometer" in v["advice"]
