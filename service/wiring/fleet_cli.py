"""How `fit`, `diagnose` and `replay` tell one recording from several, and hand several to fluxcal.service.wiring.fleet."""

from __future__ import annotations

import argparse
import dataclasses
import glob
import os
import sys
from pathlib import Path
from typing import Any

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.io.recordings.runs import is_bag
from fluxcal.service.io.recordings.runs import runs_in as _runs_in

from .fleet import run_fleet


def _is_fleet(inputs: list[str]) -> bool:
    if len(inputs) > 1 or glob.has_magic(inputs[0]):
        return True
    p = Path(inputs[0])
    return p.is_dir() and not is_bag(p) and len(_runs_in(p)) > 1        # a folder of several recordings


def _one(path: str, command: str) -> str:
    """The one recording a path names: a folder holding one file is that file; a folder of one run's rotated
    files stays the folder (read as that run). What else the folder holds is said on stderr, not passed over."""
    p = Path(path)
    if not p.is_dir() or is_bag(p):
        return path
    skipped: list[tuple[str, str]] = []
    runs = _runs_in(p, skipped)
    for where, why in skipped:
        print(f"fluxcal {command}: skipped {where}: {why}", file=sys.stderr)
    return str(runs[0][0]) if len(runs) == 1 and len(runs[0]) == 1 else path


def _here(path: str) -> str:
    return os.path.abspath(os.path.expanduser(path))


def absolute_paths(options: Any) -> Any:
    """A command's options with every file and folder they name absolute, as the user meant them from here (the
    fields its options dataclass marks with commands.options.PATH; effect files in --effects FILE.py:Class)."""
    from .user_effects import effect_spec_here

    changes: dict[str, Any] = {}
    for f in dataclasses.fields(options):
        value = getattr(options, f.name)
        if value and f.metadata.get("names") == "path":
            changes[f.name] = _here(value)
        elif value and f.metadata.get("names") == "effects":
            changes[f.name] = [effect_spec_here(e) for e in value]
    return dataclasses.replace(options, **changes)


def dispatch(args: argparse.Namespace) -> int | None:
    """None after putting the one recording back in `args` (the command runs as always); else the exit status
    of the fleet run."""
    key = "recording" if args.command == "replay" else "data"
    inputs = list(getattr(args, key))
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs: {args.jobs} is not allowed (allowed: 1 or more)")
    if not _is_fleet(inputs) and not args.scheduler:
        # one recording: run here, as without --jobs (the processes are capped at the recordings: one)
        setattr(args, key, _one(inputs[0], args.command))
        return None
    given = {k: getattr(args, k) for k in ("out", "report", "ros2_out") if getattr(args, k, None)}
    for k, folder in given.items():
        flag = f"--{k.replace('_', '-')}"
        if Path(folder).suffix in (".json", ".mcap") or (Path(folder).exists() and not Path(folder).is_dir()):
            raise ConfigError(f"{flag}: {folder!r} is not allowed with several recordings (allowed: a folder, "
                              f"which gets one file per recording)")
        from .commands.notes import check_output_folder

        check_output_folder(folder, flag)                # before any work
    # made absolute here, where the user typed them, as every path the workers get (they may run elsewhere)
    outputs = {k: _here(folder) for k, folder in given.items()}
    import importlib

    from .progress import Progress

    module = importlib.import_module(f"fluxcal.service.wiring.commands.{args.command}")
    options = absolute_paths(dataclasses.replace(module.options(args), **{key: None for key in outputs}))
    bar = Progress(1.0, f"{args.command} of several recordings", fraction=True)
    try:
        return run_fleet(args.command, inputs, options, outputs, workers=args.jobs, scheduler=args.scheduler,
                         as_json=getattr(args, "json", False),
                         progress=lambda n, total: bar(n / max(total, 1), f"{n}/{total} recordings"))
    finally:
        bar.close()
