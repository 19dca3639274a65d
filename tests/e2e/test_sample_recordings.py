"""The sample recordings shipped in recordings/ stay readable and replay to their recorded output."""

from __future__ import annotations

from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.wiring.cli import main


def test_sample_recording_replays_within_the_rounding_tolerance_of_its_conditioning(capsys):
    """It was recorded on another machine, before recordings named their arithmetic: its replay is never assumed
    bit for bit (on a machine without AVX-512 not one sample was, issue 28), but equal within the tolerance the
    estimator's conditioning gives rounding (docs/recording.md), which replay prints with the largest difference."""
    import re

    rec = read_recording("recordings/grad1-sim-30s.mcap")
    assert rec.n_probes == 2 and rec.probe_names == ["s1", "s2"] and not rec.truncated
    assert sum(b.n_samples for b in rec.raw_blocks) == 6000 and rec.arithmetic == {}
    # exit 0: every corrected sample both runs produced equal within the tolerance, and the calibration replaced
    # at the same samples; when the gate's rules change, replay may start correcting later, never differently
    assert main(["replay", "recordings/grad1-sim-30s.mcap"]) == 0
    out = capsys.readouterr().out
    compared, identical = map(int, re.search(r"compared with the recording: (\d+), bit-identical: (\d+)", out).groups())
    assert compared >= 1000 and "the arithmetic it was recorded with: unknown" in out
    if identical < compared:
        largest, tol = map(float, re.search(r"equal within (\S+) nT .*tolerance (\S+) nT", out).groups())
        assert largest <= tol < rec.lsb_nT                    # rounding: below one step of the unit's ADC


def test_guided_example_finds_the_hidden_effect_and_the_error_falls(capsys):
    import json

    path = "recordings/grad1-hidden-effect.mcap"
    capsys.readouterr()
    assert main(["diagnose", path, "--json"]) == 0
    before = json.loads(capsys.readouterr().out)
    top = before["candidates"][0]
    assert top["effect"] == "temperature" and top["significant"]
    assert not any(c["significant"] for c in before["candidates"][1:])
    assert main(["diagnose", path, "--effects", "temperature", "--json"]) == 0
    after = json.loads(capsys.readouterr().out)
    assert before["rms_nT"] > 3 * before["noise_nT"]
    assert after["rms_nT"] < 1.2 * after["noise_nT"]
    assert not any(c["significant"] for c in after["candidates"])


def test_a_directory_of_several_runs_is_not_replayed_as_one(tmp_path, capsys):
    """Each run of a folder is replayed on its own (a fleet), never one run's state carried into the next."""
    import re
    import shutil

    for stamp in ("20261101T100000", "20261102T100000"):
        shutil.copy("recordings/grad1-sim-30s.mcap", tmp_path / f"grad1-{stamp}-0001.mcap")
    assert main(["replay", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert len(re.findall(r"grad1-2026110[12]T100000-0001\.mcap\s+ok .* compared with the recording: 2000, "
                          r"bit-identical: \d+", out)) == 2, out
    assert "2 recording(s), 0 failed" in out
    assert main(["replay", str(tmp_path / "grad1-20261102T100000-0001.mcap")]) == 0     # one of them: fine
