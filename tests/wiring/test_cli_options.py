"""What a new user typed, taken as they meant it or refused naming what was wrong: a southern and western --site on
every command that takes one, a refusal naming the configuration or calibration file it is about (docs/cli.md,
docs/contracts.md)."""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest

from fluxcal.service.numerics.calib.site import site_field
from fluxcal.service.wiring import cli


def _sphere_csv(path, total_nT: float, n: int = 2000, seed: int = 0):
    """A probe turned over the whole sphere in a field of total_nT, with a scale error and an offset, no ref_total."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    raw = total_nT * d * [1.01, 0.99, 1.02] + [120.0, -40.0, 300.0] + rng.normal(scale=1.0, size=d.shape)
    np.savetxt(path, np.column_stack([np.arange(n) * 0.01, raw]), delimiter=",", header="t,s1_x,s1_y,s1_z",
               comments="")
    return path


@pytest.mark.parametrize("site", ["-75,-120,0,2026.5", "-75,-120"])
def test_a_southern_and_western_site_is_taken_as_its_value(tmp_path, capsys, site):
    """`--site -75,-120` is the site's value, not an option argparse does not know: the fit is scaled to the model's
    field there (the altitude left out: 0 m)."""
    lat, lon = -75.0, -120.0
    year = 2026.5 if site.count(",") == 3 else None
    want = site_field(lat, lon, 0.0, year)
    path = _sphere_csv(tmp_path / "south.csv", want.total_nT)
    assert cli.main(["fit", str(path), "--site", site, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["site"]["latitude_deg"], out["site"]["longitude_deg"], out["site"]["altitude_m"]) == (lat, lon, 0.0)
    assert abs(out["site"]["total_nT"] - want.total_nT) < 0.5       # today's date may turn between the two
    assert np.allclose(np.diag(out["sensors"][0]["matrix"]), [1 / 1.01, 1 / 0.99, 1 / 1.02], atol=2e-4)


@pytest.mark.parametrize("command", ["fit", "diagnose", "inspect"])
def test_every_command_that_takes_a_site_takes_a_negative_one(command):
    parser = cli.build_parser(command)
    for argv in (["--site", "-33.9,-70.6,500"], ["--site", "-.5,-0.5"], ["--site=-33.9,-70.6"]):
        args = parser.parse_args(cli._signed_values_joined([command, "d.csv", *argv]))
        assert args.site == argv[-1].removeprefix("--site="), argv
    # a value that is no number after the '-' is left to argparse, which says what it expected
    with pytest.raises(SystemExit):
        parser.parse_args(cli._signed_values_joined([command, "d.csv", "--site", "--json"]))


@pytest.mark.parametrize("command", ["fit", "diagnose", "inspect"])
def test_a_refused_configuration_or_calibration_is_the_refusals_file(tmp_path, capsys, command):
    """`--json --config bad.toml` (a typo'd key, a file that is not there) refuses bad.toml, not the data beside it;
    so does a calibration that is none (diagnose --calibration); bad data still refuse the data."""
    data = _sphere_csv(tmp_path / "lab.csv", 50_000.0, n=200)
    typo = tmp_path / "typo.toml"
    typo.write_text("[estimator]\ntotl_nT = 50000.0\n")
    cases = [(["--config", str(typo)], typo, "estimator.totl_nT: unknown key"),
             (["--config", str(tmp_path / "gone.toml")], tmp_path / "gone.toml", "not found")]
    if command == "diagnose":
        cal = tmp_path / "cal.json"
        cal.write_text("{}")
        cases.append((["--calibration", str(cal)], cal, "not a fluxcal calibration file"))
    for extra, file, why in cases:
        assert cli.main([command, str(data), "--json", *extra]) == 2
        refused = json.loads(capsys.readouterr().out)["refused"]
        assert refused["file"] == str(file) and why in refused["reason"], refused
    bad = tmp_path / "bad.csv"
    bad.write_text("t,s1_x,s1_y\n0,1,2\n")
    assert cli.main([command, str(bad), "--json", "--config", str(typo)]) == 2
    assert json.loads(capsys.readouterr().out)["refused"]["file"] == str(bad)


@pytest.mark.parametrize("toml, said", [
    ("[estimator]\ntotal_nT = true", "estimator.total_nT: expected a number, got true"),
    ("[[probes]]\nposition_m = [0.0, 0.0, false]", "probes[0].position_m[2]: expected a number, got false"),
    ("[estimator]\ntotal_nT = [true, 1.5, 'x', 2026-07-02]",
     "estimator.total_nT: expected a number, got [true, 1.5, 'x', 2026-07-02]"),
    ("[estimator]\nalign = false", "estimator.align: expected a string, got false"),
    ("[estimator]\ntotal_nT = 1979-05-27T07:32:00Z", "estimator.total_nT: expected a number, got 1979-05-27T07:32:00"),
    ("[estimator]\ntotal_nT = nan", "estimator.total_nT: expected a finite number, got nan"),
])
def test_a_value_in_a_configuration_error_is_spelled_as_toml(tmp_path, capsys, toml, said):
    """The value the error shows is the one the file holds, as TOML writes it (it said Python's `got True`)."""
    data = _sphere_csv(tmp_path / "lab.csv", 50_000.0, n=200)
    config = tmp_path / "c.toml"
    config.write_text(toml + "\n")
    assert cli.main(["fit", str(data), "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert f"{config}: {said}" in err and "True" not in err and "False" not in err


@pytest.mark.parametrize("command, sig, by", [("diagnose", signal.SIGINT, "Ctrl-C"), ("fit", signal.SIGTERM, "SIGTERM")])
def test_an_interrupted_command_says_so_in_one_line(tmp_path, capsys, monkeypatch, command, sig, by):
    """Ctrl-C (or SIGTERM) while diagnose read its data ended it with exit status 130 and not a word; now one line says
    which signal stopped which command on which data. The signal is a real one, sent while the second piece of the
    file is read."""
    from fluxcal.drivers import inputs

    data = _sphere_csv(tmp_path / "lab.csv", 50_000.0, n=6000)
    monkeypatch.setattr(inputs, "CHUNK_BYTES", 64 << 10)
    reads, read = [], inputs._read_chunk

    def read_and_signal(f, n):
        reads.append(n)
        if len(reads) == 2:
            os.kill(os.getpid(), sig)
        return read(f, n)

    monkeypatch.setattr(inputs, "_read_chunk", read_and_signal)
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    # Ctrl-C as a shell in the foreground delivers it: a test runner's worker may have inherited SIGINT ignored
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert cli.main([command, str(data)]) == 130
    finally:
        signal.signal(signal.SIGTERM, before[0])
        signal.signal(signal.SIGINT, before[1])
    out, err = capsys.readouterr()
    assert len(reads) == 2 and out == ""
    assert err == f"fluxcal {command}: interrupted by {by} on {data} before it finished\n"
