"""Fleets: fit, diagnose and replay over several recordings on a process pool or a Dask cluster, one summary,
failures isolated (a malformed file, a worker that dies)."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest

from drivers.errors import ConfigError
from service.wiring import cli
from service.wiring.fleet import expand_inputs, run_pool

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("service.wiring.fleet_cli",)

REPO = Path(__file__).resolve().parents[2]


def simulate(tmp: Path, seed: int, seconds: float = 20.0) -> Path:
    text = (REPO / "configs" / "sim-gradiometer.toml").read_text()
    text = re.sub(r"(?m)^seed = \d+", f"seed = {seed}", text)
    text = re.sub(r"(?m)^duration_s = [\d.]+", f"duration_s = {seconds}", text)
    cfg = tmp / f"sim{seed}.toml"
    cfg.write_text(text)
    out = tmp / f"grad-{seed}.csv"
    assert cli.main(["simulate", "--config", str(cfg), "--out", str(out)], install_signals=False) == 0
    return out


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    for seed in (11, 12, 13):
        simulate(d, seed)
    (d / "broken.csv").write_text("t,s1_x,s1_y\n0,1,2\n1,oops\n")
    return d


def test_folders_globs_and_runs_of_rotated_files_expand_to_recordings(tmp_path):
    for name in ("a.csv", "u-20261101T000000-0001.mcap", "u-20261101T001000-0002.mcap",
                 "u-20261102T000000-0001.mcap", "notes.txt", "single.mcap"):
        (tmp_path / name).write_bytes(b"x")
    links = tmp_path / "links"
    got = expand_inputs([str(tmp_path)], links)
    assert got[0] == str(tmp_path / "a.csv")             # in name order
    assert got[1] == str(tmp_path / "single.mcap")
    run = Path(got[2])                                   # two rotated files of one run: a folder of links
    assert run.parent == links and sorted(f.name for f in run.iterdir()) == [
        "u-20261101T000000-0001.mcap", "u-20261101T001000-0002.mcap"]
    assert got[3] == str(tmp_path / "u-20261102T000000-0001.mcap") and len(got) == 4
    assert expand_inputs([str(tmp_path / "*.csv"), str(tmp_path / "a.csv")], links) == [str(tmp_path / "a.csv")]
    with pytest.raises(ConfigError, match="matches no file"):
        expand_inputs([str(tmp_path / "*.nothing")], links)


def test_each_recording_gets_the_shared_options_and_its_own_outputs():
    from service.wiring.commands.fit import FitOptions
    from service.wiring.fleet import job_for

    shared = FitOptions(effects=["drift"], site="1,2,3")
    job = job_for("fit", "survey/a.csv", shared, {"out": "cals", "report": "reports"})
    assert job.options == FitOptions(effects=["drift"], site="1,2,3", out="cals/a.cal.json", report="reports/a")
    assert job_for("replay", "x/u-0001.mcap", shared, {"out": "again"}).options.out == "again/u-0001.mcap"


def test_the_fleet_counts_warnings_as_data_whatever_their_wording(fleet_dir, monkeypatch, capsys):
    """The fleet read a recording's warnings with a regular expression over its stderr, so a change of wording
    changed a fleet's result; now the notes travel as data and are counted by level."""
    import service.wiring.prepare as prepare

    said = prepare.skip_spans

    def reworded(said_, source, lab, spans):            # any wording at all
        said_("skip", "§§ a wholly new sentence, no 'warning:' in it §§")
        return said(said_, source, lab, spans)

    monkeypatch.setattr(prepare, "skip_spans", reworded)
    from service.wiring.commands.fit import FitOptions
    from service.wiring.fleet import job_for, run_one  # what each worker runs, here in-process
    from service.wiring.fleet_summary import summary_json

    results = [run_one(job_for("fit", str(p), FitOptions(), {})) for p in sorted(fleet_dir.glob("grad-1*.csv"))]
    summary = summary_json("fit", results, 1.0, "here")
    assert summary["failed"] == 0 and summary["with_warnings"] == 3
    assert all(r["read_warnings"] == ["§§ a wholly new sentence, no 'warning:' in it §§"] for r in summary["results"])


def test_the_fleet_imports_no_command_line_module():
    import ast

    src = (REPO / "service" / "wiring" / "fleet.py").read_text()
    names = {n.module for n in ast.walk(ast.parse(src)) if isinstance(n, ast.ImportFrom) and n.module} | {
        a.name for n in ast.walk(ast.parse(src)) if isinstance(n, ast.Import) for a in n.names}
    assert not {n for n in names if n.endswith(("cli", "fleet_cli"))}, names
    assert "redirect_stdout" not in src and "cli.main" not in src


def test_fit_of_several_recordings_equals_each_alone_and_isolates_a_malformed_one(fleet_dir, tmp_path, capsys):
    status = cli.main(["fit", str(fleet_dir / "*.csv"), "--jobs", "2", "--json", "--out", str(tmp_path / "cals")],
                      install_signals=False)
    summary = json.loads(capsys.readouterr().out)
    assert status == 1 and summary["recordings"] == 4 and summary["failed"] == 1
    by_name = {Path(r["recording"]).name: r for r in summary["results"]}
    assert not by_name["broken.csv"]["ok"] and "broken.csv" in by_name["broken.csv"]["error"]
    for seed in (11, 12, 13):
        r = by_name[f"grad-{seed}.csv"]
        assert r["ok"] and r["rms_nT"] < 2.0
        assert cli.main(["fit", str(fleet_dir / f"grad-{seed}.csv"), "--json"], install_signals=False) == 0
        alone = json.loads(capsys.readouterr().out)
        assert r["result"]["sensors"] == alone["sensors"]            # the same numbers, bit for bit
        assert (tmp_path / "cals" / f"grad-{seed}.cal.json").exists()
    assert not (tmp_path / "cals" / "broken.cal.json").exists()
    # the table says the same
    status = cli.main(["fit", str(fleet_dir), "--jobs", "2"], install_signals=False)
    table = capsys.readouterr().out
    assert status == 1 and re.search(r"broken\.csv\s+FAILED", table) and "4 recording(s), 1 failed" in table
    assert len(re.findall(r"grad-1\d\.csv\s+ok", table)) == 3


def die_or_answer(job) -> dict:
    """A stand-in job for run_pool: a worker that dies without a word on 'die', an answer otherwise."""
    if job.source == "die":
        os._exit(9)
    return {"recording": job.source, "status": 0, "ok": True, "result": None, "notes": [], "seconds": 0.0}


def test_a_worker_that_dies_fails_only_its_own_recording():
    from service.wiring.fleet import Job

    got = []
    jobs = [Job("fit", name, None) for name in ("a", "b", "die", "c", "d")]
    run_pool(jobs, 2, got.append, fn=die_or_answer)
    by = {r["recording"]: r for r in got}
    assert sorted(by) == ["a", "b", "c", "d", "die"]
    assert not by["die"]["ok"] and "died" in by["die"]["error"]
    assert all(by[k]["ok"] for k in "abcd")


def test_replay_of_several_recordings(tmp_path, capsys):
    shutil.copy(REPO / "recordings" / "grad1-sim-30s.mcap", tmp_path / "a.mcap")
    shutil.copy(REPO / "recordings" / "grad1-sim-30s.mcap", tmp_path / "b.mcap")
    shutil.copy(REPO / "recordings" / "grad3-pump.mcap", tmp_path / "pump.mcap")     # lab data: no stored config
    status = cli.main(["replay", str(tmp_path / "*.mcap"), "--jobs", "2"], install_signals=False)
    out = capsys.readouterr().out
    assert status == 1, out
    # made on another machine: equal within the rounding tolerance, not assumed bit for bit (docs/recording.md)
    assert len(re.findall(r"[ab]\.mcap\s+ok .* compared with the recording: 2000, bit-identical: \d+", out)) == 2, out
    assert re.search(r"pump\.mcap\s+FAILED .*no configuration stored in the recording; give --config", out)
    assert "3 recording(s), 1 failed" in out


@pytest.mark.slow
def test_the_same_runs_go_to_a_dask_cluster(fleet_dir, capsys):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None, silence_logs=40) as cluster:
        files = [str(fleet_dir / f"grad-{s}.csv") for s in (11, 12)] + [str(fleet_dir / "broken.csv")]
        status = cli.main(["fit", *files, "--scheduler", cluster.scheduler_address, "--json"], install_signals=False)
    summary = json.loads(capsys.readouterr().out)
    assert status == 1 and summary["ran_on"].startswith("tcp://127.0.0.1")
    by_name = {Path(r["recording"]).name: r for r in summary["results"]}
    assert not by_name["broken.csv"]["ok"]
    for seed in (11, 12):
        assert cli.main(["fit", str(fleet_dir / f"grad-{seed}.csv"), "--json"], install_signals=False) == 0
        assert by_name[f"grad-{seed}.csv"]["result"]["sensors"] == json.loads(capsys.readouterr().out)["sensors"]


def test_a_recording_named_twice_runs_once(tmp_path, monkeypatch):
    """By its name and through its folder (or by a relative and an absolute path): one recording, one row."""
    for name in ("a.csv", "b.csv"):
        (tmp_path / name).write_bytes(b"x")
    monkeypatch.chdir(tmp_path)
    got = expand_inputs(["a.csv", str(tmp_path), str(tmp_path / "b.csv")], tmp_path / "links")
    assert [Path(g).resolve() for g in got] == [tmp_path / "a.csv", tmp_path / "b.csv"]


def test_a_run_of_rotated_files_named_twice_runs_once(tmp_path):
    """A folder holding one run's files and a pattern matching the same files (or a folder of runs and a pattern
    for one of them): one run each, never two link folders of the same files (the review's case)."""
    one = tmp_path / "one"
    one.mkdir()
    for name in ("u-20261101T000000-0001.mcap", "u-20261101T001000-0002.mcap"):
        (one / name).write_bytes(b"x")
    links = tmp_path / "links"
    assert expand_inputs([str(one), str(one / "u-*.mcap")], links) == [str(one)]
    many = tmp_path / "many"
    many.mkdir()
    for name in ("a-20261101T000000-0001.mcap", "a-20261101T001000-0002.mcap", "b-20261102T000000-0001.mcap"):
        (many / name).write_bytes(b"x")
    got = expand_inputs([str(many), str(many / "a-*.mcap")], tmp_path / "links2")
    assert len(got) == 2 and got[1] == str(many / "b-20261102T000000-0001.mcap")
