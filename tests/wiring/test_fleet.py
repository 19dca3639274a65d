"""Fleets: fit, diagnose and replay over several recordings on a process pool or a Dask cluster, one summary,
failures isolated (a malformed file, a worker that dies)."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest

from fluxcal.service.wiring import cli
from fluxcal.service.wiring.fleet import expand_inputs, run_pool

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.wiring.fleet_cli",)

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
    got = expand_inputs([str(tmp_path)]).recordings
    assert got[0].path == str(tmp_path / "a.csv")             # in name order
    assert got[1].path == str(tmp_path / "single.mcap")
    assert [Path(p).name for p in got[2].parts] == [           # two rotated files of one run: its parts
        "u-20261101T000000-0001.mcap", "u-20261101T001000-0002.mcap"]
    assert got[3].path == str(tmp_path / "u-20261102T000000-0001.mcap") and len(got) == 4
    assert [r.path for r in expand_inputs([str(tmp_path / "*.csv"), str(tmp_path / "a.csv")]).recordings] == [
        str(tmp_path / "a.csv")]
    assert expand_inputs([str(tmp_path / "*.nothing")]).unreadable[0][1].startswith("matches no file")


def test_each_recording_gets_the_shared_options_and_its_own_outputs():
    from fluxcal.service.wiring.commands.fit import FitOptions
    from fluxcal.service.wiring.fleet import job_for

    shared = FitOptions(effects=["drift"], site="1,2,3")
    job = job_for("fit", "survey/a.csv", shared, {"out": "cals", "report": "reports"})
    assert job.options == FitOptions(effects=["drift"], site="1,2,3", out="cals/a.cal.json", report="reports/a")
    assert job_for("replay", "x/u-0001.mcap", shared, {"out": "again"}).options.out == "again/u-0001.mcap"
    from fluxcal.service.wiring.commands.replay import ReplayOptions

    assert job_for("replay", "x/u-0001.mcap", ReplayOptions(), {"ros2_out": "bags"}).options.ros2_out == "bags/u-0001"


def test_every_path_in_the_options_goes_to_the_workers_absolute(tmp_path, monkeypatch):
    """--config, --calibration, --out, --report, --write-effect, --ros2-out and an effect's FILE.py are the user's
    paths from where they typed them: a worker in another folder (or on another host) gets them absolute."""
    from fluxcal.service.wiring.commands.diagnose import DiagnoseOptions
    from fluxcal.service.wiring.commands.fit import FitOptions
    from fluxcal.service.wiring.commands.replay import ReplayOptions
    from fluxcal.service.wiring.fleet_cli import absolute_paths

    monkeypatch.chdir(tmp_path)
    fit = absolute_paths(FitOptions(config="site.toml", effects=["drift", "mine/eff.py:Sag", "pkg.mod:Sag"],
                                    site="1,2,3", out="cals", report="../reports"))
    assert fit == FitOptions(config=str(tmp_path / "site.toml"), site="1,2,3", out=str(tmp_path / "cals"),
                             effects=["drift", f"{tmp_path / 'mine' / 'eff.py'}:Sag", "pkg.mod:Sag"],
                             report=str(tmp_path.parent / "reports"))
    diag = absolute_paths(DiagnoseOptions(calibration="c.json", write_effect="found.py", max_samples=10))
    assert (diag.calibration, diag.write_effect, diag.max_samples) == (str(tmp_path / "c.json"),
                                                                       str(tmp_path / "found.py"), 10)
    assert absolute_paths(ReplayOptions(config="/etc/u.toml", ros2_out="bags")) == ReplayOptions(
        config="/etc/u.toml", ros2_out=str(tmp_path / "bags"))


def test_the_fleet_counts_warnings_as_data_whatever_their_wording(fleet_dir, monkeypatch, capsys):
    """The fleet read a recording's warnings with a regular expression over its stderr, so a change of wording
    changed a fleet's result; now the notes travel as data and are counted by level."""
    import fluxcal.service.wiring.prepare as prepare

    said = prepare.skip_spans

    def reworded(said_, source, lab, spans):            # any wording at all
        said_("skip", "§§ a wholly new sentence, no 'warning:' in it §§")
        return said(said_, source, lab, spans)

    monkeypatch.setattr(prepare, "skip_spans", reworded)
    from fluxcal.service.wiring.commands.fit import FitOptions
    from fluxcal.service.wiring.fleet import job_for, run_one  # what each worker runs, here in-process
    from fluxcal.service.wiring.fleet_summary import summary_json

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
    from fluxcal.service.wiring.fleet import Job

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


def test_a_recording_named_twice_runs_once(tmp_path, monkeypatch):
    """By its name and through its folder (or by a relative and an absolute path): one recording, one row."""
    for name in ("a.csv", "b.csv"):
        (tmp_path / name).write_bytes(b"x")
    monkeypatch.chdir(tmp_path)
    got = expand_inputs(["a.csv", str(tmp_path), str(tmp_path / "b.csv")]).recordings
    assert [(r.name, r.path) for r in got] == [("a.csv", str(tmp_path / "a.csv")), (str(tmp_path / "b.csv"),
                                                                                   str(tmp_path / "b.csv"))]


def test_a_run_of_rotated_files_named_twice_runs_once(tmp_path):
    """A folder holding one run's files and a pattern matching the same files (or a folder of runs and a pattern
    for one of them): one run each, never two recordings of the same files (the review's case)."""
    one = tmp_path / "one"
    one.mkdir()
    for name in ("u-20261101T000000-0001.mcap", "u-20261101T001000-0002.mcap"):
        (one / name).write_bytes(b"x")
    assert [r.path for r in expand_inputs([str(one), str(one / "u-*.mcap")]).recordings] == [str(one)]
    many = tmp_path / "many"
    many.mkdir()
    for name in ("a-20261101T000000-0001.mcap", "a-20261101T001000-0002.mcap", "b-20261102T000000-0001.mcap"):
        (many / name).write_bytes(b"x")
    got = expand_inputs([str(many), str(many / "a-*.mcap")]).recordings
    assert len(got) == 2 and got[1].path == str(many / "b-20261102T000000-0001.mcap")


def test_a_batch_goes_on_past_files_it_cannot_read_and_names_each(fleet_dir, tmp_path, capsys):
    """Ten files, three of them unreadable (a ULog that is none, a cut MCAP, a CSV of text), and an item that names
    nothing: the seven are fitted (each as alone), the three and the item are one line each with the reason, in
    the table and in --json, and the exit status says some failed (it was 2, and nothing fitted)."""
    batch, more = tmp_path / "batch", tmp_path / "more"
    batch.mkdir()
    more.mkdir()
    good = sorted(fleet_dir.glob("grad-1*.csv"))
    for k in range(7):
        shutil.copy(good[k % 3], (batch if k < 5 else more) / f"g{k}.csv")
    (batch / "flight.ulg").write_bytes(b"junk\n")
    (batch / "cut.mcap").write_bytes((REPO / "recordings" / "grad1-sim-30s.mcap").read_bytes()[:3000])
    (more / "text.csv").write_text("this is not data\n")
    status = cli.main(["fit", str(batch), str(more / "*.csv"), str(tmp_path / "gone"), "--jobs", "2", "--json"],
                      install_signals=False)
    s = json.loads(capsys.readouterr().out)
    assert status == 1 and s["recordings"] == 11 and s["failed"] == 4
    by = {Path(r["recording"]).name: r for r in s["results"]}
    assert sorted(n for n, r in by.items() if r["ok"]) == [f"g{k}.csv" for k in range(7)]
    assert {n: by[n]["failure"] for n in ("flight.ulg", "cut.mcap", "text.csv", "gone")} == {
        "flight.ulg": "data", "cut.mcap": "data", "text.csv": "data", "gone": "input"}
    assert all(str(p) in by[p.name]["error"] for p in (batch / "flight.ulg", batch / "cut.mcap", more / "text.csv"))
    assert "no such file or folder" in by["gone"]["error"] and by["gone"]["recording"] == str(tmp_path / "gone")
    assert cli.main(["fit", str(batch / "g0.csv"), "--json"], install_signals=False) == 0
    assert by["g0.csv"]["result"]["sensors"] == json.loads(capsys.readouterr().out)["sensors"]
    status = cli.main(["fit", str(batch), str(more / "*.csv"), str(tmp_path / "gone"), "--jobs", "2"],
                      install_signals=False)
    table = capsys.readouterr().out
    for name in ("flight.ulg", "cut.mcap", "text.csv", "gone"):
        (row,) = [ln for ln in table.splitlines() if re.match(rf"\S*{re.escape(name)}\s", ln)]
        assert " FAILED " in row and row.split("FAILED")[1].split(maxsplit=1)[1].strip()    # with its reason
    assert "11 recording(s), 4 failed" in table


def test_a_worker_that_cannot_see_a_recording_names_its_host_and_the_summary_says_what_workers_need(tmp_path):
    """The fleet sends paths absolute; a worker on a host without the file says which host and which path, and the
    summary says what the workers need (the same files at the same paths)."""
    import socket

    from fluxcal.service.wiring.commands.fit import FitOptions
    from fluxcal.service.wiring.fleet import job_for, run_one
    from fluxcal.service.wiring.fleet_summary import summary_json, summary_table

    gone = str(tmp_path / "on-the-client-only.csv")
    r = {**run_one(job_for("fit", gone, FitOptions(), {})), "recording": "on-the-client-only.csv"}
    assert not r["ok"] and r["failure"] == "missing" and r["host"] == socket.gethostname()
    assert r["error"] == f"{gone}: no such file on host {socket.gethostname()} (the workers need the same files at " \
                         f"the same paths)"
    workers = [{"address": "tcp://10.0.0.9:4000", "host": "node9", "fluxcal": "0.1.0", "same": True}]
    table = summary_table("fit", [r], 1.0, "tcp://10.0.0.9:8786", [], "0.1.0", workers)
    assert f"1 recording(s) not found where the workers run ({socket.gethostname()}): a worker reads the path " \
           f"named here, made absolute, so the workers need the same files at the same paths" in table
    assert summary_json("fit", [r], 1.0, "x", [], "0.1.0", workers)["results"][0]["failure"] == "missing"


def test_jobs_kept_to_workers_that_all_left_fail_instead_of_waiting_for_ever(monkeypatch):
    """Jobs kept to the workers with this fluxcal (another worker is there) would wait for ever once those have
    all left the cluster: each fails, saying why; a job whose worker was lost fails alone."""
    import distributed

    from fluxcal.service.wiring.fleet import Job, _collect, fluxcal_version

    class Lost:
        def result(self):
            raise OSError("worker lost")

    class Cluster:
        workers = {"tcp://10.0.0.9:4000": {}}

        def scheduler_info(self):
            return {"workers": self.workers}

    lost, waiting = Lost(), object()
    answers = iter([({lost}, {waiting}), TimeoutError, TimeoutError])

    def wait(pending, timeout, return_when):               # the first answer, then nothing comes in `timeout`
        assert return_when == "FIRST_COMPLETED" and timeout > 0
        got = next(answers)                                # (a third wait would be waiting for ever)
        if got is TimeoutError:
            raise TimeoutError
        return got

    monkeypatch.setattr(distributed, "wait", wait)
    jobs = {lost: Job("fit", "a.csv", None), waiting: Job("fit", "b.csv", None)}
    got: list[dict] = []
    cluster = Cluster()

    def done(r):
        got.append(r)
        if len(got) == 1:                                  # the kept-to worker leaves after the first answer
            cluster.workers = {"tcp://10.0.0.7:4000": {}}

    _collect(cluster, jobs, ["tcp://10.0.0.9:4000"], done)
    assert [(r["recording"], r["ok"]) for r in got] == [("a.csv", False), ("b.csv", False)]
    assert got[0]["error"] == "on the cluster: OSError: worker lost"
    assert got[1]["error"] == f"on the cluster: every worker with fluxcal {fluxcal_version()} left before it ran"
