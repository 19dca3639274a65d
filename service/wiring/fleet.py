"""Fleets of recordings: `fit`, `diagnose` and `replay` over several recordings (paths, folders, globs) on
all cores (a process pool) or on a Dask cluster (`--scheduler ADDRESS`), with one summary table (or JSON)
of per-recording results and failures. A failing recording, even one whose worker dies, never stops the
others.

Each recording runs the single-recording command in a worker exactly as `fluxcal CMD RECORDING OPTIONS`
would (fit and diagnose with --json, so the summary reads their contract; files a command writes go
into the directory given by --out / --report, one per recording, named by the recording).
"""

from __future__ import annotations

import contextlib
import glob
import io
import json
import os
import re
import sys
import tempfile
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from pathlib import Path
from collections.abc import Callable, Iterable
from typing import Any

from drivers.errors import ConfigError

_WARNING = re.compile(r"(?m)^fluxcal [a-z-]+: warning: (.*)$")
_RUN_PART = re.compile(r"^(?P<stem>.+)-(?P<n>\d{4})\.mcap$")
SUFFIXES = (".mcap", ".csv")


#: why a path in a folder is not a recording of it (listed in the summary, never skipped unsaid)
NOT_SEARCHED = "a folder inside a folder given: not searched (give it too, or a pattern such as '{}/**/*.mcap')"
NOT_RECORDING = "not a recording (allowed: .mcap, .csv)"


def _runs_in(directory: Path, skipped: list[tuple[str, str]] | None = None) -> list[list[Path]]:
    """The recordings in a directory: each CSV file, and each run of MCAP files (a -0001 file and the rotated
    files after it, in name order; a file outside that naming is a run by itself). What is not one (a folder
    in it, another file) goes into `skipped` as (path, reason)."""
    files = []
    for f in sorted(directory.iterdir()):
        if f.is_file() and f.suffix in SUFFIXES:
            files.append(f)
        elif skipped is not None:
            skipped.append((str(f), NOT_SEARCHED.format(directory) if f.is_dir() else NOT_RECORDING))
    return runs_of(files)


def runs_of(files: list[Path]) -> list[list[Path]]:
    """Files (in name order) grouped into recordings as _runs_in does."""
    runs: list[list[Path]] = []
    for f in files:
        m = _RUN_PART.match(f.name)
        if f.suffix == ".mcap" and m and int(m.group("n")) > 1 and runs and runs[-1][0].suffix == ".mcap" \
                and _RUN_PART.match(runs[-1][0].name):
            runs[-1].append(f)
        else:
            runs.append([f])
    return runs


def expand_inputs(items: Iterable[str], links: Path, skipped: list[tuple[str, str]] | None = None,
                  labels: dict[str, str] | None = None) -> list[str]:
    """Paths, folders and glob patterns -> the recordings, in the order given (duplicates once). A folder holding
    one run stays one recording (as for a single command); a folder of several becomes each of them, a run of
    several rotated files as a folder of links under `links` (so do the rotated files of one run a pattern
    matches; `labels` gets each such folder's name for the summary: its first file and how many follow). What a
    folder holds besides recordings goes into `skipped` as (path, reason). ConfigError names a pattern or path
    that matches nothing."""
    out: list[str] = []
    taken: set[tuple[str, ...]] = set()              # the files of each run given: a run named twice runs once

    def add(run: list[Path], whole: Path | None = None) -> None:
        key = tuple(sorted(str(f.resolve()) for f in run))
        if key in taken:
            return
        taken.add(key)
        if len(run) == 1:
            out.append(str(run[0]))
        elif whole is not None:
            out.append(str(whole))
        else:
            d = links / f"{len(out):04d}-{run[0].stem}"
            d.mkdir(parents=True)
            for f in run:
                (d / f.name).symlink_to(f.resolve())
            out.append(str(d))
            if labels is not None:
                labels[str(d)] = f"{run[0]} (+{len(run) - 1} rotated)"

    for item in items:
        paths = sorted(glob.glob(item, recursive=True)) if glob.has_magic(item) else [item]
        if not paths:
            raise ConfigError(f"{item!r} matches no file (allowed: recordings (.mcap, .csv), folders of them, or glob "
                              f"patterns such as 'survey/*.mcap')")
        loose: list[Path] = []                        # the files a pattern matched: one run's files are one
        for p in map(Path, paths):
            if not p.exists():
                raise ConfigError(f"{p}: no such file or folder")
            if not p.is_dir():
                loose.append(p)
                continue
            for run in _runs_of_files(loose):
                add(run)
            loose = []
            runs = _runs_in(p, skipped)
            if not runs:
                raise ConfigError(f"{p}: holds no recording (.mcap, .csv)")
            for run in runs:
                add(run, p if len(runs) == 1 else None)
        for run in _runs_of_files(loose):
            add(run)
    seen: set[str] = set()                          # one recording named twice (by name, through a folder): once
    return [x for x in out if not ((key := str(Path(x).resolve())) in seen or seen.add(key))]


def _runs_of_files(files: list[Path]) -> list[list[Path]]:
    """Files a pattern matched (in name order): the rotated files of one run in one folder together, as in a
    folder (runs_of); every other file alone."""
    runs: list[list[Path]] = []
    group: list[Path] = []
    for f in [*files, None]:
        if group and (f is None or f.parent != group[-1].parent):
            runs += runs_of(group)
            group = []
        if f is not None:
            group.append(f)
    return runs


def _name(path: str) -> str:
    p = Path(path)
    return re.sub(r"^\d{4}-", "", p.name) if p.is_dir() else p.stem


def worker_argv(command: str, path: str, options: list[str], outputs: dict[str, str]) -> list[str]:
    """The single-recording command line of one recording: its path, the shared options, JSON output for fit and
    diagnose, and its own file under each output folder (--out DIR/<name>.cal.json, --report DIR/<name>/)."""
    argv = [command, path, *options]
    if command in ("fit", "diagnose"):
        argv.append("--json")
    name = _name(path)
    for flag, folder in outputs.items():
        target = Path(folder) / (f"{name}.cal.json" if (command, flag) == ("fit", "--out") else
                                 f"{name}.mcap" if flag == "--out" else name)
        argv += [flag, str(target)]
    return argv


def run_one(argv: list[str]) -> dict[str, Any]:
    """Run one single-recording command in this process (a worker); never raises: the outcome, its exit status,
    what it printed, its JSON result (fit, diagnose) and how long it took."""
    from service.wiring import cli

    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    status = 1
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            status = cli.main(argv, install_signals=False)
    except SystemExit as e:                            # argparse's usage errors
        status = e.code if isinstance(e.code, int) else 2
    except BaseException as e:                         # noqa: BLE001 - a recording's failure is its result
        err.write(f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=3)}")
        status = 1
    text = out.getvalue()
    # what reading lost (a cut tail, damaged records) and other warnings, as the command said them on stderr
    warned = [m.group(1) for m in _WARNING.finditer(err.getvalue())]
    result = None
    if "--json" in argv:
        try:
            result = json.loads(text.strip().splitlines()[-1]) if text.strip() else None
        except (ValueError, IndexError):
            result = None
    import resource

    return {"recording": argv[1], "status": int(status), "ok": status == 0, "result": result, "warnings": warned,
            "stdout": text[-4000:], "stderr": err.getvalue()[-4000:], "seconds": round(time.perf_counter() - t0, 3),
            # the worker's peak so far (it may have run other recordings before): an upper bound for this one
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def _failed(argv: list[str], why: str) -> dict[str, Any]:
    return {"recording": argv[1], "status": 1, "ok": False, "result": None, "stdout": "", "stderr": why,
            "seconds": None}


def _context():
    """Workers forked from a clean server process that has imported the numerics once (no state of this process,
    no threads, and no second import per worker); "spawn" where there is no fork."""
    try:
        ctx = get_context("forkserver")
    except ValueError:
        return get_context("spawn")
    ctx.set_forkserver_preload(["service.wiring.cli", "service.wiring.fleet", "numpy", "scipy.linalg",
                                "service.numerics.diagnose", "service.wiring.fitting"])
    return ctx


def run_pool(jobs: list[list[str]], workers: int, done: Callable[[dict], None],
             fn: Callable[[list[str]], dict] = run_one) -> None:
    """Every job on a pool of `workers` processes (`_context`: no state from this one). A worker that dies (killed,
    out of memory) breaks the pool: the jobs it left unfinished are then run one by one, each in a process of its
    own, so only the recording that kills its worker fails."""
    left: list[list[str]] = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=_context()) as pool:
        running = {pool.submit(fn, argv): argv for argv in jobs}
        while running:
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                argv = running.pop(f)
                try:
                    done(f.result())
                except BrokenProcessPool:
                    left.append(argv)
    for argv in left:
        with ProcessPoolExecutor(max_workers=1, mp_context=_context()) as alone:
            try:
                done(alone.submit(fn, argv).result())
            except BrokenProcessPool:
                done(_failed(argv, "its worker process died (killed, or out of memory)"))


def run_dask(jobs: list[list[str]], address: str, done: Callable[[dict], None]) -> None:
    """Every job on a Dask distributed cluster at `address` (the workers need fluxcal installed)."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ConfigError("--scheduler: needs Dask distributed (pip install 'fluxcal[cluster]')") from None
    try:
        client = Client(address, timeout=10)
    except (OSError, TimeoutError) as e:
        raise ConfigError(f"--scheduler: cannot reach a Dask scheduler at {address!r}: {e}") from None
    try:
        futures = {client.submit(run_one, argv, pure=False, key=f"fluxcal-{k}-{_name(argv[1])}"): argv
                   for k, argv in enumerate(jobs)}
        for f in as_completed(futures):
            try:
                done(f.result())
            except Exception as e:                         # noqa: BLE001 - a lost worker fails only this one
                done(_failed(futures[f], f"on the cluster: {type(e).__name__}: {e}"))
    finally:
        client.close()


def run_fleet(command: str, inputs: list[str], options: list[str], outputs: dict[str, str], *, workers: int | None,
              scheduler: str | None, as_json: bool, progress: Callable[[int, int], None] | None = None) -> int:
    """Expand `inputs`, run `command` on each recording, print the summary; exit status 0 when every one succeeded
    (replay: and was identical), 1 otherwise."""
    from .fleet_summary import summary_json, summary_table

    for folder in outputs.values():
        Path(folder).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="fluxcal-fleet-") as links:
        skipped: list[tuple[str, str]] = []
        labels: dict[str, str] = {}
        recordings = expand_inputs(inputs, Path(links), skipped, labels)
        jobs = [worker_argv(command, r, options, outputs) for r in recordings]
        results: dict[str, dict[str, Any]] = {}

        def done(r: dict[str, Any]) -> None:
            results[r["recording"]] = r
            if progress is not None:
                progress(len(results), len(jobs))

        t0 = time.perf_counter()
        n = workers or os.cpu_count() or 1
        if scheduler:
            run_dask(jobs, scheduler, done)
        else:
            run_pool(jobs, min(n, len(jobs)), done)
        wall = time.perf_counter() - t0
        ordered = [{**results[r], "recording": labels.get(r, r)} for r in recordings]
    where = scheduler or f"{min(n, len(jobs))} local processes"
    if as_json:
        json.dump(summary_json(command, ordered, wall, where, skipped), sys.stdout)
        sys.stdout.write("\n")
    else:
        print(summary_table(command, ordered, wall, where, skipped))
    return 0 if all(r["ok"] for r in ordered) else 1
