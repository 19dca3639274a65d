"""Fleets of recordings: `fit`, `diagnose` and `replay` over several recordings (paths, folders, globs) on
all cores (a process pool) or on a Dask cluster (`--scheduler ADDRESS`), with one summary table (or JSON)
of per-recording results and failures. A failing recording, even one whose worker dies, never stops the
others.

Each recording is one Job: the command's own `execute(source, options, said)` (service.wiring.commands.<name>)
run in a worker, which ships back the Result's JSON and its notes as data (service.wiring.result); nothing
here parses what a command prints. Files a command writes go into the folder given by --out / --report, one
per recording, named by the recording.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import re
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from drivers.errors import CalibrationRefused, ConfigError, DataError, FluxcalError
from service.io.recordings.runs import expand_inputs

from .result import Said, refusal


@dataclasses.dataclass(frozen=True)
class Job:
    """One recording's work: the command, the recording and the command's options (its outputs its own)."""

    command: str                  # "fit", "diagnose" or "replay"
    source: str
    options: Any                  # the command's options dataclass (commands.fit.FitOptions, ...)


def _name(path: str) -> str:
    p = Path(path)
    return re.sub(r"^\d{4}-", "", p.name) if p.is_dir() else p.stem


def job_for(command: str, path: str, options: Any, outputs: dict[str, str]) -> Job:
    """One recording's job: the shared options with its own file under each output folder (out: DIR/<name>.cal.json
    for fit, DIR/<name>.mcap for replay; report: DIR/<name>/)."""
    name = _name(path)
    own = {}
    for key, folder in outputs.items():
        own[key] = str(Path(folder) / (f"{name}.cal.json" if (command, key) == ("fit", "out") else
                                       f"{name}.mcap" if key == "out" else name))
    return Job(command, path, dataclasses.replace(options, **own))


def run_one(job: Job) -> dict[str, Any]:
    """Run one recording's command in this process (a worker); never raises: its outcome as data (the Result's JSON,
    its notes, exit status, time and memory), or why it failed."""
    import resource

    said = Said(job.command)                       # kept, not printed: they travel with the outcome
    t0 = time.perf_counter()
    out: dict[str, Any] = {"recording": job.source, "result": None, "error": None}
    try:
        module = importlib.import_module(f"service.wiring.commands.{job.command}")
        kwargs = {"progress": False} if job.command == "diagnose" else {}
        result = module.execute(job.source, job.options, said, **kwargs)
        out.update(status=result.status, result=result.as_dict())
    except (ConfigError, DataError, CalibrationRefused) as e:
        out.update(status=2, error=str(e), refused=refusal(e, job.source)["refused"])
    except FluxcalError as e:
        out.update(status=1, error=str(e))
    except BaseException as e:                     # noqa: BLE001 - a recording's failure is its result
        out.update(status=1, error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=3))
    out["ok"] = out["status"] == 0
    out["notes"] = [n.as_dict() for n in said.notes]
    out["seconds"] = round(time.perf_counter() - t0, 3)
    # the worker's peak so far (it may have run other recordings before): an upper bound for this one
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return out


def _failed(job: Job, why: str) -> dict[str, Any]:
    return {"recording": job.source, "status": 1, "ok": False, "result": None, "error": why, "notes": [],
            "seconds": None}


def _context():
    """Workers forked from a clean server process that has imported the numerics once (no state of this process,
    no threads, and no second import per worker); "spawn" where there is no fork."""
    try:
        ctx = get_context("forkserver")
    except ValueError:
        return get_context("spawn")
    ctx.set_forkserver_preload(["service.wiring.fleet", "numpy", "scipy.linalg", "service.numerics.diagnose",
                                "service.wiring.fitting", "service.wiring.commands.fit",
                                "service.wiring.commands.diagnose", "service.wiring.commands.replay"])
    return ctx


def run_pool(jobs: list[Job], workers: int, done: Callable[[dict], None],
             fn: Callable[[Job], dict] = run_one) -> None:
    """Every job on a pool of `workers` processes (`_context`: no state from this one). A worker that dies (killed,
    out of memory) breaks the pool: the jobs it left unfinished are then run one by one, each in a process of its
    own, so only the recording that kills its worker fails."""
    left: list[list[str]] = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=_context()) as pool:
        running = {pool.submit(fn, job): job for job in jobs}
        while running:
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                job = running.pop(f)
                try:
                    done(f.result())
                except BrokenProcessPool:
                    left.append(job)
    for job in left:
        with ProcessPoolExecutor(max_workers=1, mp_context=_context()) as alone:
            try:
                done(alone.submit(fn, job).result())
            except BrokenProcessPool:
                done(_failed(job, "its worker process died (killed, or out of memory)"))


def run_dask(jobs: list[Job], address: str, done: Callable[[dict], None]) -> None:
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
        futures = {client.submit(run_one, job, pure=False, key=f"fluxcal-{k}-{_name(job.source)}"): job
                   for k, job in enumerate(jobs)}
        for f in as_completed(futures):
            try:
                done(f.result())
            except Exception as e:                         # noqa: BLE001 - a lost worker fails only this one
                done(_failed(futures[f], f"on the cluster: {type(e).__name__}: {e}"))
    finally:
        client.close()


def run_fleet(command: str, inputs: list[str], options: Any, outputs: dict[str, str], *, workers: int | None,
              scheduler: str | None, as_json: bool, progress: Callable[[int, int], None] | None = None) -> int:
    """Expand `inputs`, run `command` with `options` on each recording (outputs: {"out" | "report": folder}), print
    the summary; exit status 0 when every one succeeded (replay: and equalled the live run), 1 otherwise."""
    from .fleet_summary import summary_json, summary_table

    for folder in outputs.values():
        Path(folder).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="fluxcal-fleet-") as links:
        skipped: list[tuple[str, str]] = []
        labels: dict[str, str] = {}
        recordings = expand_inputs(inputs, Path(links), skipped, labels)
        jobs = [job_for(command, r, options, outputs) for r in recordings]
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
