"""Fleets of recordings: `fit`, `diagnose` and `replay` over several recordings (paths, folders, globs) on
all cores (a process pool) or on a Dask cluster (`--scheduler ADDRESS`), with one summary table (or JSON)
of per-recording results and failures. A failing recording, even one whose worker dies, never stops the
others.

Each recording is one Job: the command's own `execute(source, options, said)` (fluxcal.service.wiring.commands.<name>)
run in a worker, which ships back the Result's JSON and its notes as data (fluxcal.service.wiring.result); nothing
here parses what a command prints. Files a command writes go into the folder given by --out / --report, one
per recording, named by the recording.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import json
import os
import re
import socket
import sys
import tempfile
import time
import traceback
import uuid
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from fluxcal.drivers.errors import CalibrationRefused, ConfigError, DataError, FluxcalError
from fluxcal.service.io.recordings.runs import expand_inputs, linked_run

from .result import Said, refusal


@dataclasses.dataclass(frozen=True)
class Job:
    """One recording's work: the command, the recording and the command's options (its outputs its own); every
    path in them absolute, so a worker reads what the user named wherever it runs. `parts`: one run's rotated
    files, linked into a folder where the job runs (runs.linked_run)."""

    command: str                  # "fit", "diagnose" or "replay"
    source: str
    options: Any                  # the command's options dataclass (commands.fit.FitOptions, ...)
    parts: tuple[str, ...] = ()


def _name(path: str) -> str:
    p = Path(path)
    return re.sub(r"^\d{4}-", "", p.name) if p.is_dir() else p.stem


def job_for(command: str, path: str, options: Any, outputs: dict[str, str], parts: tuple[str, ...] = ()) -> Job:
    """One recording's job: the shared options with its own file under each output folder (out: DIR/<name>.cal.json
    for fit, DIR/<name>.mcap for replay; report: DIR/<name>/)."""
    name = _name(path)
    own = {}
    for key, folder in outputs.items():
        own[key] = str(Path(folder) / (f"{name}.cal.json" if (command, key) == ("fit", "out") else
                                       f"{name}.mcap" if key == "out" else name))
    return Job(command, path, dataclasses.replace(options, **own), parts)


@functools.lru_cache(maxsize=1)
def fluxcal_version() -> str:
    """The fluxcal installed in this process's environment (a worker's results are this version's)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fluxcal")
    except PackageNotFoundError:
        return "not installed"


#: what stopped a recording, by the error it raised (the summary's JSON "failure"; "missing": no such path)
FAILURES = ((CalibrationRefused, "refused"), (DataError, "data"), (ConfigError, "usage"), (FluxcalError, "failed"))


def _not_here(job: Job, host: str) -> str | None:
    """The path of the job that this host cannot see, said with the host (None: every one is here)."""
    missing = next((p for p in job.parts or (job.source,) if not os.path.exists(p)), None)
    return None if missing is None else (f"{missing}: no such file on host {host} (the workers need the same files "
                                         f"at the same paths)")


def _execute(job: Job, said: Said) -> Any:
    module = importlib.import_module(f"fluxcal.service.wiring.commands.{job.command}")
    kwargs = {"progress": False} if job.command == "diagnose" else {}
    if not job.parts:
        return module.execute(job.source, job.options, said, **kwargs)
    with tempfile.TemporaryDirectory(prefix="fluxcal-run-") as links:
        return module.execute(str(linked_run(job.parts, Path(links))), job.options, said, **kwargs)


def run_one(job: Job) -> dict[str, Any]:
    """Run one recording's command in this process (a worker); never raises: its outcome as data (the Result's JSON,
    its notes, exit status, time and memory, the host and fluxcal version that ran it), or why it failed."""
    import resource

    said = Said(job.command)                       # kept, not printed: they travel with the outcome
    t0 = time.perf_counter()
    host = socket.gethostname()
    out: dict[str, Any] = {"recording": job.source, "result": None, "error": None, "host": host,
                           "fluxcal": fluxcal_version()}
    try:
        if (missing := _not_here(job, host)) is not None:
            out.update(status=2, error=missing, failure="missing")
        else:
            result = _execute(job, said)
            out.update(status=result.status, result=result.as_dict())
    except FluxcalError as e:
        kind = next(k for cls, k in FAILURES if isinstance(e, cls))
        out.update(status=1 if kind == "failed" else 2, error=str(e), failure=kind,
                   **({"refused": refusal(e, job.source)["refused"]}
                      if isinstance(e, (ConfigError, DataError, CalibrationRefused)) else {}))
    except BaseException as e:                     # noqa: BLE001 - a recording's failure is its result
        out.update(status=1, error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=3),
                   failure="failed")
    out["ok"] = out["status"] == 0
    out["notes"] = [n.as_dict() for n in said.notes]
    out["seconds"] = round(time.perf_counter() - t0, 3)
    # the worker's peak so far (it may have run other recordings before): an upper bound for this one
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return out


def _failed(job: Job, why: str) -> dict[str, Any]:
    return {"recording": job.source, "status": 1, "ok": False, "result": None, "error": why, "notes": [],
            "seconds": None, "failure": "failed"}


def _context():
    """Workers forked from a clean server process that has imported the numerics once (no state of this process,
    no threads, and no second import per worker); "spawn" where there is no fork."""
    try:
        ctx = get_context("forkserver")
    except ValueError:
        return get_context("spawn")
    ctx.set_forkserver_preload(["fluxcal.service.wiring.fleet", "numpy", "scipy.linalg", "fluxcal.service.numerics.diagnose",
                                "fluxcal.service.wiring.fitting", "fluxcal.service.wiring.commands.fit",
                                "fluxcal.service.wiring.commands.diagnose", "fluxcal.service.wiring.commands.replay"])
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


@dataclasses.dataclass(frozen=True)
class Worker:
    """A worker of a Dask cluster as the fleet found it: its address, host and installed fluxcal."""

    address: str
    host: str
    fluxcal: str                  # its version, "not installed", or why it could not say

    def as_dict(self, here: str) -> dict[str, Any]:
        return {"address": self.address, "host": self.host, "fluxcal": self.fluxcal, "same": self.fluxcal == here}


def _asked(answer: Any) -> str:
    """A worker's answer to a question sent with Client.run: the text, or what stopped it."""
    from importlib.metadata import PackageNotFoundError

    if isinstance(answer, PackageNotFoundError):
        return "not installed"
    text = answer if isinstance(answer, str) else f"unknown ({type(answer).__name__}: {answer})"
    return text if text.isprintable() and len(text) <= 80 else repr(text[:80])      # said as it came, escaped


def cluster_workers(client: Any, address: str) -> list[Worker]:
    """The cluster's workers, each with the fluxcal installed where it runs (asked with the standard library's own
    functions, which every worker can run, with or without fluxcal). ConfigError when it has none, or when its
    scheduler has another fluxcal (it unpickles the jobs, fluxcal's classes among them)."""
    from importlib.metadata import version

    try:
        on_scheduler = _asked(client.run_on_scheduler(version, "fluxcal"))
    except Exception as e:                                 # noqa: BLE001 - said, whatever it is
        on_scheduler = _asked(e)
    if on_scheduler != fluxcal_version():                  # it unpickles every job: fluxcal's classes
        raise ConfigError(f"--scheduler: the scheduler at {address!r} has fluxcal {on_scheduler}, this one "
                          f"{fluxcal_version()}: it reads the jobs too, so install fluxcal {fluxcal_version()} there")
    try:
        client.wait_for_workers(1, timeout=30)
    except TimeoutError:
        raise ConfigError(f"--scheduler: the cluster at {address!r} has no worker (start one where the files are: "
                          f"dask worker {address})") from None
    versions = client.run(version, "fluxcal", on_error="return")
    hosts = client.run(socket.gethostname, on_error="return")
    return [Worker(a, _asked(hosts.get(a, "?")), _asked(v)) for a, v in sorted(versions.items())]


def _restrict(workers: list[Worker], address: str) -> dict[str, Any]:
    """Where the jobs may run: on the workers with this fluxcal (any other kept out while one of them is there).
    ConfigError when none has it."""
    here = fluxcal_version()
    same = [w.address for w in workers if w.fluxcal == here]
    if not same:
        raise ConfigError(f"--scheduler: no worker of the cluster at {address!r} has fluxcal {here}, this one's ("
                          + "; ".join(f"{w.address} on {w.host}: {w.fluxcal}" for w in workers)
                          + f"): install fluxcal {here} where the workers run")
    # strict: a loose restriction lets an idle worker of any version steal a job (distributed's stealing)
    return {} if len(same) == len(workers) else {"workers": same}


def _collect(client: Any, futures: dict[Any, Job], kept_to: list[str] | None, done: Callable[[dict], None]) -> None:
    """Each job's outcome as it comes; a job whose worker was lost fails alone, and so do the jobs kept to workers
    (`kept_to`) that have all left the cluster (they would wait for them forever)."""
    from distributed import wait as wait_futures

    pending = set(futures)
    while pending:
        try:
            finished, pending = wait_futures(pending, timeout=5, return_when="FIRST_COMPLETED")
        except TimeoutError:
            if kept_to and not set(kept_to) & set(client.scheduler_info()["workers"]):
                for f in pending:
                    done(_failed(futures[f], f"on the cluster: every worker with fluxcal {fluxcal_version()} left "
                                             f"before it ran"))
                return
            continue
        for f in finished:
            try:
                done(f.result())
            except Exception as e:                         # noqa: BLE001 - a lost worker fails only this one
                done(_failed(futures[f], f"on the cluster: {type(e).__name__}: {e}"))


def run_dask(jobs: list[Job], address: str, done: Callable[[dict], None]) -> list[Worker]:
    """Every job on a Dask distributed cluster at `address`, on its workers with this fluxcal; the workers as found
    (the summary says those with another version, which get none)."""
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--scheduler: needs Dask distributed (pip install 'fluxcal[cluster]')") from None
    try:
        client = Client(address, timeout=10)
    except (OSError, TimeoutError) as e:
        raise ConfigError(f"--scheduler: cannot reach a Dask scheduler at {address!r}: {e}") from None
    try:
        workers = cluster_workers(client, address)
        where = _restrict(workers, address)
        batch = uuid.uuid4().hex[:8]
        futures = {client.submit(run_one, job, pure=False, key=f"fluxcal-{batch}-{k}-{_name(job.source)}",
                                 **where): job for k, job in enumerate(jobs)}
        _collect(client, futures, where.get("workers"), done)
    finally:
        client.close()
    return workers


def _input_failures(unreadable: list[tuple[str, str]]) -> list[dict[str, Any]]:
    """The rows of the items that name no recording here (no such path, a pattern matching nothing, a folder
    holding none): each with its reason, as a recording that failed."""
    return [{"recording": item, "status": 2, "ok": False, "result": None, "error": f"{item}: {why}",
             "failure": "input", "notes": [], "seconds": None} for item, why in unreadable]


def run_fleet(command: str, inputs: list[str], options: Any, outputs: dict[str, str], *, workers: int | None,
              scheduler: str | None, as_json: bool, progress: Callable[[int, int], None] | None = None) -> int:
    """Expand `inputs`, run `command` with `options` on each recording (outputs: {"out" | "report" | "ros2_out":
    folder}), print the summary; exit status 0 when every one succeeded (replay: and equalled the live run), 1
    otherwise (an item that names no recording is one that failed; none named at all: ConfigError)."""
    from .fleet_summary import summary_json, summary_table

    found = expand_inputs(inputs)
    if not found.recordings:
        raise ConfigError("; ".join(f"{item}: {why}" for item, why in found.unreadable) or "no recording given")
    for folder in outputs.values():
        Path(folder).mkdir(parents=True, exist_ok=True)
    jobs = [job_for(command, r.path, options, outputs, r.parts) for r in found.recordings]
    results: dict[str, dict[str, Any]] = {}

    def done(r: dict[str, Any]) -> None:
        results[r["recording"]] = r
        if progress is not None:
            progress(len(results), len(jobs))

    t0 = time.perf_counter()
    n = min(workers or os.cpu_count() or 1, len(jobs))
    cluster = run_dask(jobs, scheduler, done) if scheduler else run_pool(jobs, n, done)
    wall = time.perf_counter() - t0
    ordered = [{**results[r.path], "recording": r.name, "path": r.path} for r in found.recordings]
    ordered += _input_failures(found.unreadable)
    about = {"where": scheduler or f"{n} local processes", "skipped": found.skipped, "fluxcal": fluxcal_version(),
             "workers": [w.as_dict(fluxcal_version()) for w in cluster or []]}
    if as_json:
        json.dump(summary_json(command, ordered, wall, **about), sys.stdout)
        sys.stdout.write("\n")
    else:
        print(summary_table(command, ordered, wall, **about))
    return 0 if all(r["ok"] for r in ordered) else 1
