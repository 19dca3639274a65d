"""Output files that cannot be written are refused before any work (exit 2, naming the flag and the path),
and a write that fails later is said (exit 1), never a traceback nor a "written to" over nothing: a replay's
--out naming a folder used to print "written to" and exit 0 with no file made."""

from __future__ import annotations

from pathlib import Path

import pytest

from fluxcal.service.wiring.cli import main

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.wiring.commands.notes",)

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "recordings" / "grad1-sim-30s.mcap"


@pytest.mark.parametrize("command", [["replay", str(SAMPLE)], ["simulate"]])
def test_an_output_that_is_a_folder_or_in_no_folder_is_refused_first(tmp_path, capsys, command):
    folder = tmp_path / "out"
    folder.mkdir()
    assert main([*command, "--out", str(folder)]) == 2
    assert f"--out {folder}: is a folder; give a file name in it" in capsys.readouterr().err
    assert list(folder.iterdir()) == []
    missing = tmp_path / "nowhere" / "x.mcap"
    assert main([*command, "--out", str(missing)]) == 2
    assert f"folder {missing.parent} does not exist" in capsys.readouterr().err
    beside_a_file = tmp_path / "plain.txt"
    beside_a_file.write_text("x")
    assert main([*command, "--out", str(beside_a_file / "x.mcap")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_fit_refuses_its_output_before_fitting(tmp_path, capsys):
    csv = tmp_path / "grad.csv"
    assert main(["simulate", "--out", str(csv)]) == 0
    capsys.readouterr()
    assert main(["fit", str(csv), "--out", str(tmp_path / "none" / "cal.json")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "--out" in err and "does not exist" in err       # nothing fitted, nothing printed


def test_a_write_that_fails_later_is_said_without_a_traceback(tmp_path, capsys, monkeypatch):
    csv = tmp_path / "grad.csv"
    assert main(["simulate", "--out", str(csv)]) == 0
    capsys.readouterr()

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device", str(tmp_path / "cal.json"))

    monkeypatch.setattr("fluxcal.service.wiring.commands.fit.save_calibration", full_disk)
    assert main(["fit", str(csv), "--out", str(tmp_path / "cal.json")]) == 1
    err = capsys.readouterr().err
    assert f"fluxcal fit: {tmp_path / 'cal.json'}: No space left on device" in err and "Traceback" not in err


def test_a_replay_whose_output_fails_says_so_and_fails(tmp_path, capsys, monkeypatch):
    """The recording logger never raises (a live service keeps running on a full disk); replay asks it."""
    from fluxcal.service.io.recordings import files

    def no_space(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(files.McapFiles, "flush", no_space)
    monkeypatch.setattr(files.McapFiles, "finish", no_space)
    out = tmp_path / "again.mcap"
    assert main(["replay", str(SAMPLE), "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert "written to" not in captured.out
    assert f"fluxcal replay: {out}: the replay could not be written" in captured.err and "lost" in captured.err


def test_replay_out_that_is_no_recording_or_the_input_is_refused(tmp_path, capsys):
    """A trial's cases: a missing folder written with a trailing slash became a file of that name, '--out x.csv'
    got MCAP bytes, and '--out' equal to the input overwrote the recording; all silently."""
    import shutil

    rec = tmp_path / "rec.mcap"
    shutil.copy(SAMPLE, rec)
    before = rec.read_bytes()
    for out, said in ((f"{tmp_path / 'missing'}/", "is a folder"), (str(tmp_path / "x.csv"), "allowed: FILE.mcap"),
                      (str(rec), "is the input itself")):
        assert main(["replay", str(rec), "--out", out]) == 2
        assert said in capsys.readouterr().err
    assert rec.read_bytes() == before and not (tmp_path / "missing").exists() and not (tmp_path / "x.csv").exists()


def test_report_and_fleet_output_folders_are_checked_before_any_work(tmp_path, capsys):
    csv = tmp_path / "grad.csv"
    assert main(["simulate", "--out", str(csv)]) == 0
    capsys.readouterr()
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    for command in (["fit", str(csv)], ["diagnose", str(csv)]):
        assert main([*command, "--report", str(plain / "r")]) == 2
        out, err = capsys.readouterr()
        assert out == "" and f"--report {plain / 'r'}: {plain} is a file, not a folder" in err
        assert main([*command, "--report", str(plain)]) == 2
        assert f"--report {plain}: is a file; give a folder" in capsys.readouterr().err
    assert main(["fit", str(csv), str(csv), "--out", str(plain / "o")]) == 2
    assert f"--out {plain / 'o'}: {plain} is a file, not a folder" in capsys.readouterr().err


def test_report_refuses_a_missing_folder_as_out_does_and_makes_only_its_own(tmp_path, capsys):
    """`fit --report /nonexistent/x` made the whole tree where `--out` refuses a missing folder: a typo in the path
    grew folders. The report's own folder is made (as --out makes its file), in a folder that must exist."""
    csv = tmp_path / "grad.csv"
    assert main(["simulate", "--out", str(csv)]) == 0
    capsys.readouterr()
    tree = tmp_path / "nonexistent" / "x"
    for command in (["fit", str(csv)], ["diagnose", str(csv)], ["fit", str(csv), str(csv)]):
        assert main([*command, "--report", str(tree)]) == 2
        out, err = capsys.readouterr()
        assert out == "" and f"--report {tree}: folder {tree.parent} does not exist" in err
        assert not tree.parent.exists()
    # the --out of a fit says the same of the same path
    assert main(["fit", str(csv), "--out", str(tree / "cal.json")]) == 2
    assert f"folder {tree} does not exist" in capsys.readouterr().err
    assert main(["fit", str(csv), "--report", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep" / "index.html").is_file()


def test_run_with_a_dashboard_port_in_use_says_so_before_starting(tmp_path, capsys):
    """The service ran on without its dashboard, which named an option (--listen) the user never typed."""
    import socket

    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        cfg = ROOT / "configs" / "sim-gradiometer.toml"
        assert main(["run", "--config", str(cfg), "--dashboard", f"127.0.0.1:{port}"], install_signals=False) == 1
    err = capsys.readouterr().err
    assert f"--dashboard 127.0.0.1:{port}: cannot serve there (Address already in use)" in err
    assert "--listen" not in err
