"""Fleets on a Dask cluster started as a cluster's are (issue 42): a scheduler and two workers in processes of their
own, bound to 127.0.0.1 on free ports, their working folder another than the user's. fit, diagnose and replay of
relative paths, a folder and a pattern run every recording there, and the table is the one --jobs gives; a worker
with another fluxcal is said in the summary and given nothing; a scheduler with another is refused, naming both."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers import write_rotated
from test_fleet import simulate

from fluxcal.service.wiring import cli
from fluxcal.service.wiring.fleet import fluxcal_version

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.wiring.fleet_cli", "fluxcal.service.wiring.fleet_summary")

REPO = Path(__file__).resolve().parents[2]
LIVE = REPO / "recordings" / "grad1-sim-30s.mcap"
#: a worker's (or scheduler's) preload that makes its process say another fluxcal is installed there
OTHER_VERSION = '''import importlib.metadata as m
_real = m.version
m.version = lambda name: "0.0.1" if name == "fluxcal" else _real(name)
'''


@dataclass
class Cluster:
    address: str
    folder: Path                     # the workers' working folder
    procs: list[subprocess.Popen]


def _start(folder: Path, name: str, *args: str) -> subprocess.Popen:
    log = open(folder / f"{name}.log", "w")
    return subprocess.Popen([sys.executable, "-m", *args], cwd=folder, stdout=log, stderr=subprocess.STDOUT)


def _scheduler(folder: Path, *extra: str) -> tuple[str, subprocess.Popen]:
    info = folder / "scheduler.json"
    proc = _start(folder, "scheduler", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                  "--no-dashboard", "--scheduler-file", str(info), *extra)
    deadline = time.monotonic() + 60
    while not info.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert info.exists(), (folder / "scheduler.log").read_text()
    return json.loads(info.read_text())["address"], proc


def _worker(folder: Path, address: str, name: str, *extra: str) -> subprocess.Popen:
    return _start(folder, name, "distributed.cli.dask_worker", address, "--host", "127.0.0.1", "--no-dashboard",
                  "--no-nanny", "--nthreads", "1", "--local-directory", str(folder / name), *extra)


def _wait_for_workers(address: str, n: int) -> None:
    from distributed import Client

    with Client(address, timeout=30) as client:
        client.wait_for_workers(n, timeout=60)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in reversed(procs):                    # workers first, then the scheduler
        p.terminate()
        try:
            p.wait(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cluster")
    address, scheduler = _scheduler(folder)
    procs = [scheduler, _worker(folder, address, "w1"), _worker(folder, address, "w2")]
    try:
        _wait_for_workers(address, 2)
        yield Cluster(address, folder, procs)
    finally:
        _stop(procs)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The user's folder: a recording named by a relative path, a folder of several (one of them a run of rotated
    files), and a folder a pattern picks from."""
    d = tmp_path_factory.mktemp("site")
    for sub in ("survey", "pat", "runs", "rotated"):
        (d / sub).mkdir()
    shutil.move(simulate(d, 21), d / "one.csv")
    for seed, where in ((22, "survey"), (23, "survey"), (24, "pat")):
        shutil.move(simulate(d, seed), d / where / f"grad-{seed}.csv")
    write_rotated(LIVE, d / "runs")                      # a folder of a run of rotated files and another recording
    shutil.copy(LIVE, d / "runs" / "b.mcap")
    write_rotated(LIVE, d / "rotated")                   # a folder of one run: that run
    shutil.copy(LIVE, d / "a.mcap")
    shutil.copy(LIVE, d / "pat" / "p.mcap")
    return d


def _table(argv: list[str], capsys) -> tuple[int, list[str]]:
    """A fleet's table without what differs from run to run: each row's seconds, the footer's time and place."""
    status = cli.main(argv, install_signals=False)
    lines = capsys.readouterr().out.splitlines()
    head = lines[0]
    at = head.index(" s  ") - 5                          # the seconds column: 7 characters, right-aligned
    n = lines.index("") if "" in lines else len(lines) - 1           # the header and the rows
    rows = [ln[:at] + ln[at + 7:] for ln in lines[:n]]
    return status, rows + lines[n:-1] + [lines[-1].split(";")[0]]


@pytest.mark.slow
@pytest.mark.parametrize("command, items", [
    ("fit", ["one.csv", "survey", "pat/*.csv", "runs"]),
    ("diagnose", ["one.csv", "survey", "pat/*.csv"]),
    ("replay", ["a.mcap", "rotated", "pat/*.mcap"]),
])
def test_relative_paths_folders_and_patterns_reach_workers_in_another_folder(cluster, site, command, items,
                                                                               monkeypatch, capsys):
    """Every recording done on workers whose working folder is another (they failed 'no such file' with the
    relative paths), and the table the one --jobs gives."""
    monkeypatch.chdir(site)
    out = [] if command == "diagnose" else ["--out"]                      # a relative folder, written there
    status, there = _table([command, *items, "--scheduler", cluster.address, *out, *(["there"] if out else [])],
                           capsys)
    status_here, here = _table([command, *items, "--jobs", "2", *out, *(["here"] if out else [])], capsys)
    assert status == status_here == 0, there
    assert there == here
    n = {"fit": 6, "diagnose": 4, "replay": 3}[command]
    assert there[-1].startswith(f"{n} recording(s), 0 failed")
    assert len([r for r in there[1:] if re.match(r"\S.*\s+ok", r)]) == n
    assert not any(r.startswith("/") for r in there[1:n + 1])              # as the user named them
    if out:
        written = sorted(f.name for f in (site / "there").iterdir())
        assert len(written) == n and written == sorted(f.name for f in (site / "here").iterdir())
        shutil.rmtree(site / "there")
        shutil.rmtree(site / "here")
    if command == "fit":                                                  # a run's parts, linked where it ran
        assert any(re.match(r"runs/grad1-\S+-0001\.mcap \(\+\d+ rotated\)\s+ok", r) for r in there)


@pytest.mark.slow
def test_a_worker_with_another_fluxcal_is_said_and_given_nothing(cluster, site, monkeypatch, capsys):
    monkeypatch.chdir(site)
    preload = cluster.folder / "other_version.py"
    preload.write_text(OTHER_VERSION)
    odd = _worker(cluster.folder, cluster.address, "odd", "--preload", str(preload))
    try:
        _wait_for_workers(cluster.address, 3)
        status = cli.main(["fit", "one.csv", "survey", "pat/*.csv", "--scheduler", cluster.address, "--json"],
                          install_signals=False)
        s = json.loads(capsys.readouterr().out)
        status_table = cli.main(["fit", "survey", "--scheduler", cluster.address], install_signals=False)
        table = capsys.readouterr().out
    finally:
        _stop([odd])
    assert status == status_table == 0 and s["recordings"] == 4 and s["failed"] == 0
    assert all(r["fluxcal"] == fluxcal_version() for r in s["results"])          # none ran on the odd one
    (other,) = [w for w in s["workers"] if not w["same"]]
    assert other["fluxcal"] == "0.0.1" and len(s["workers"]) == 3
    assert (f"workers with another fluxcal than this one ({fluxcal_version()}): sent no recording; install fluxcal "
            f"{fluxcal_version()} there\n  {other['address']} on {other['host']}: fluxcal 0.0.1") in table
    assert "Traceback" not in table


@pytest.mark.slow
def test_a_scheduler_with_another_fluxcal_is_refused_naming_both(tmp_path, capsys):
    (tmp_path / "other_version.py").write_text(OTHER_VERSION)
    address, proc = _scheduler(tmp_path, "--preload", str(tmp_path / "other_version.py"))
    try:
        status = cli.main(["fit", str(REPO / "recordings" / "grad1-sim-30s.mcap"), "--scheduler", address],
                          install_signals=False)
    finally:
        _stop([proc])
    err = capsys.readouterr().err
    assert status == 2
    assert err.strip() == (f"fluxcal fit: --scheduler: the scheduler at {address!r} has fluxcal 0.0.1, this one "
                           f"{fluxcal_version()}: it reads the jobs too, so install fluxcal {fluxcal_version()} there")
