"""fit and diagnose of service recordings as they are: the configuration stored in them, a folder of one run's
rotated files, a continuation replayed alone, and fleets that carry each recording's read warnings."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import write_rotated

from fluxcal.service.io.recordings.runs import expand_inputs, linked_run
from fluxcal.service.wiring import cli

REPO = Path(__file__).resolve().parents[2]
LIVE = REPO / "recordings" / "grad1-sim-30s.mcap"        # `fluxcal run`: estimator.total_nT = 52500 stored


def run(argv, capsys):
    status = cli.main([str(a) for a in argv], install_signals=False)
    out = capsys.readouterr()
    return status, out.out, out.err


@pytest.fixture(scope="module")
def rotated(tmp_path_factory) -> Path:
    """LIVE written again as the service writes a long run: rotated into several files of one run."""
    d = tmp_path_factory.mktemp("rot")
    assert len(write_rotated(LIVE, d)) >= 3
    return d


def test_fit_takes_the_total_field_from_the_stored_configuration(capsys):
    status, out, _ = run(["fit", LIVE, "--json"], capsys)
    stored = json.loads(out)
    assert status == 0 and stored["configuration"] == "recording"
    status, out, _ = run(["fit", LIVE, "--json", "--config", REPO / "configs" / "sim-gradiometer.toml"], capsys)
    given = json.loads(out)
    assert status == 0 and "configuration" not in given
    for a, b in zip(stored["sensors"], given["sensors"]):            # the same fit as --config, to the bit
        assert a["matrix"] == b["matrix"] and a["offset_nT"] == b["offset_nT"]
    # the 52,500 nT stored, not the 52,772 estimated: s1's x scale 0.97982, where estimating gave 0.98490 (0.5 %)
    assert stored["sensors"][0]["matrix"][0][0] == pytest.approx(0.97982, abs=2e-5)
    status, out, _ = run(["fit", LIVE], capsys)
    assert "total field from the configuration; configuration from the recording" in out.splitlines()[0]


def test_diagnose_takes_the_probe_positions_and_total_field_from_the_recording(capsys):
    status, out, _ = run(["diagnose", LIVE, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and d["reference"] == "config"
    assert d["notes"][0] == ("configuration from the recording: total field 52,500 nT (estimator.total_nT); "
                             "probe positions of 2 probes")
    gradient = next(c for c in d["candidates"] if c["effect"] == "gradient")
    assert "probe positions" not in (gradient.get("reason") or "")          # it needs the attitude now, no more


def test_a_folder_of_one_runs_rotated_files_is_that_run(rotated, capsys):
    status, out, _ = run(["fit", LIVE, "--json"], capsys)
    whole = json.loads(out)
    for jobs in ([], ["--jobs", "2"]):                    # --jobs with one recording: run it, as without
        status, out, err = run(["fit", rotated, "--json", *jobs], capsys)
        assert status == 0, err
        got = json.loads(out)
        assert got["sensors"] == whole["sensors"] and got["configuration"] == "recording"
    status, out, err = run(["fit", rotated / "*.mcap", "--jobs", "2", "--json"], capsys)
    fleet = json.loads(out)                               # a pattern matching one run's files: that run, once
    assert status == 0 and fleet["recordings"] == 1
    assert fleet["results"][0]["result"]["sensors"] == whole["sensors"]
    status, out, err = run(["diagnose", rotated, "--max-samples", "2000"], capsys)
    assert status == 0 and out.splitlines()[0] == f"fluxcal diagnose {rotated} (configuration from the recording)"
    status, _, err = run(["fit", LIVE, "--jobs", "0"], capsys)
    assert status == 2 and "--jobs: 0 is not allowed" in err


def test_a_continuation_replayed_alone_says_so_and_names_the_folder(rotated, capsys):
    second = next(rotated.glob("*-0002.mcap"))
    status, _, err = run(["replay", second], capsys)
    assert f"{second.name} is file 2 of a run" in err and f"`fluxcal replay {rotated}`" in err
    status, out, err = run(["replay", rotated], capsys)
    assert status == 0 and "compared with the recording: 2000, bit-identical: " in out and "is file" not in err


def test_a_fleet_carries_the_lost_bytes_and_lists_what_it_skipped(tmp_path, capsys):
    folder = tmp_path / "recs"
    (folder / "live").mkdir(parents=True)
    shutil.copy(LIVE, folder / "good.mcap")
    shutil.copy(LIVE, folder / "live" / "grad1-20261126T020717-0001.mcap")
    cut = folder / "cut.mcap"
    cut.write_bytes(LIVE.read_bytes()[:500_000])
    status, out, _ = run(["fit", folder, "--jobs", "2", "--json"], capsys)
    s = json.loads(out)
    assert status == 0 and s["recordings"] == 2 and s["with_warnings"] == 1
    assert s["skipped"] == [{"path": str(folder / "live"), "reason": "a folder inside a folder given: not searched "
                             f"(give it too, or a pattern such as '{folder}/**/*.mcap')"}]
    by = {Path(r["recording"]).name: r for r in s["results"]}
    assert by["good.mcap"]["read_warnings"] == []
    (lost,) = by["cut.mcap"]["read_warnings"]
    assert lost.startswith(f"{cut}: cut inside a chunk record at byte 401216 of 500000") and \
        "the 98784 bytes of that record are lost" in lost
    status, out, _ = run(["fit", folder, "--jobs", "2"], capsys)
    rows = {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith(str(folder))}
    assert "ok, 1 warning " in rows[str(cut)] and rows[str(folder / "good.mcap")].split()[1] == "ok"
    assert f"  {lost}" in out.splitlines() and "skipped" in out.splitlines()
    # the two kinds of warning counted apart: the fits' (the column) and the reading's (listed above the line)
    fit_warned = sum(r["warnings"] > 0 for r in s["results"])
    assert s["fit_warned"] == fit_warned
    assert (f"2 recording(s), 0 failed, {fit_warned} whose fit warns (the warnings column; --json lists them), "
            f"1 read with warnings (above), 1 path(s) skipped") in out


def test_patterns_group_one_runs_files_and_folders_list_what_they_skip(tmp_path):
    for name in ("u-20261101T000000-0001.mcap", "u-20261101T001000-0002.mcap", "v-20261102T000000-0001.mcap",
                 "notes.txt", "capture.bin"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    got = expand_inputs([str(tmp_path / "*.mcap")])
    run, v = got.recordings
    assert v.path == str(tmp_path / "v-20261102T000000-0001.mcap") and v.parts == ()
    assert run.parts == (str(tmp_path / "u-20261101T000000-0001.mcap"), str(tmp_path / "u-20261101T001000-0002.mcap"))
    assert run.name == f"{tmp_path / 'u-20261101T000000-0001.mcap'} (+1 rotated)"
    linked = linked_run(run.parts, tmp_path / "links")          # where the job runs: a folder of the run's files
    assert sorted(f.name for f in linked.iterdir()) == ["u-20261101T000000-0001.mcap", "u-20261101T001000-0002.mcap"]
    skipped = expand_inputs([str(tmp_path)]).skipped
    assert [(Path(p).name, why.split(":")[0]) for p, why in skipped] == [
        ("capture.bin", "not a recording"), ("links", "a folder inside a folder given"),
        ("notes.txt", "not a recording (allowed"), ("sub", "a folder inside a folder given")]
    assert "a .bin that is no ArduPilot log" in skipped[0][1]
    assert np.all([Path(p).exists() for p, _ in skipped])


def test_every_format_fluxcal_reads_is_a_recording_of_a_folder_and_a_bag_is_one(tmp_path, monkeypatch, capsys):
    """Flight logs and ROS 2 bags are recordings of a folder (they were 'skipped ... not a recording', and a folder
    holding only a .ulg was refused); a bag's folder is one recording, its .db3 never one of its own; paths as
    the user named them, sent absolute; an item that names nothing is one line with its reason."""
    from fluxcal.service.io.recordings.formats import DATAFLASH_HEAD
    from fluxcal.service.wiring.fleet_cli import _is_fleet, _one

    logs = tmp_path / "logs"
    (logs / "bag").mkdir(parents=True)
    (logs / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (logs / "bag" / "bag_0.db3").write_bytes(b"x")
    (logs / "flight.ulg").write_bytes(b"ULog")
    (logs / "00000012.BIN").write_bytes(DATAFLASH_HEAD + b"x")
    (tmp_path / "empty").mkdir()
    monkeypatch.chdir(tmp_path)
    got = expand_inputs(["logs", "logs/bag", "nothere.csv", "empty", "none-*.mcap"])
    assert [(r.name, r.path) for r in got.recordings] == [
        (f"logs/{n}", str(tmp_path / "logs" / n)) for n in ("00000012.BIN", "bag", "flight.ulg")]
    assert got.skipped == []
    assert [(item, why.split(" (")[0]) for item, why in got.unreadable] == [
        ("nothere.csv", "no such file or folder"), ("empty", "holds no recording"), ("none-*.mcap", "matches no file")]
    assert not _is_fleet(["logs/bag"]) and _one("logs/bag", "fit") == "logs/bag" and _is_fleet(["logs"])
    assert capsys.readouterr().err == ""                      # nothing of the bag said skipped


def test_one_rotated_file_fitted_alone_says_it_is_part_of_a_run(rotated, capsys):
    """fit and diagnose of one file of a rotated run use its samples alone; that is said first, naming the folder
    (these pieces, a few seconds each, are then refused on their own: too few directions)."""
    from fluxcal.service.wiring.prepare import part_of_run
    from fluxcal.service.wiring.result import Said

    files = sorted(rotated.glob("*.mcap"))
    for k, f in enumerate(files[1:], 2):
        _, _, err = run(["fit", f, "--json"], capsys)
        note = f"{f.name} is file {k} of {len(files)} of one run the service rotated"
        assert note in err and f"`fluxcal fit {rotated}` takes the whole run" in err
    assert note in part_of_run(Said("diagnose"), str(files[-1])) and part_of_run(Said("fit"), str(rotated)) is None
    capsys.readouterr()
    status, out, err = run(["fit", rotated, "--json"], capsys)
    assert status == 0 and "of one run the service rotated" not in err


def test_inspect_says_the_time_the_commands_and_skip_take(tmp_path, capsys):
    """A recording whose time does not start at its first sample (a unit's clock 5 s in): inspect said "t: seconds
    from the first sample" where fit's --skip and diagnose's segments take the unit's own time (a field trial
    planned a --skip from it and cut the wrong stretch). It now gives the time as the commands take it."""
    text = (REPO / "configs" / "sim-gradiometer.toml").read_text().replace("duration_s = 60.0", "duration_s = 10.0")
    (tmp_path / "sim.toml").write_text(text.replace("[sim]\n", "[sim]\nt_us_start = 5000000\n"))
    csv = tmp_path / "late.csv"
    assert run(["simulate", "--config", tmp_path / "sim.toml", "--out", csv], capsys)[0] == 0
    status, out, _ = run(["inspect", csv, "--json"], capsys)
    clock = json.loads(out)["clock"]["t_s"]
    assert status == 0 and clock == "seconds of the data's own time, 5-14.995 s (--skip takes these)", clock
    _, _, err = run(["fit", csv, "--skip", "5-6", "--json"], capsys)                  # its first second, as said
    assert "--skip left out 201 of 2,000 samples (5-6 s: 201)" in err, err
    status, out, _ = run(["inspect", LIVE, "--json"], capsys)                          # a recording from 0: as before
    assert json.loads(out)["clock"]["t_s"] == "seconds from the first sample"
