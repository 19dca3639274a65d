"""Which files make one recording: a CSV file is one; the service rotates one run into -0001.mcap, -0002.mcap, ...
files, which together are one; and what paths, folders and glob patterns name (fleets, and a folder given to
fit, diagnose or replay)."""

from __future__ import annotations

import glob
import re
from collections.abc import Iterable
from pathlib import Path

from drivers.errors import ConfigError

_RUN_PART = re.compile(r"^(?P<stem>.+)-(?P<n>\d{4})\.mcap$")
SUFFIXES = (".mcap", ".csv")


#: why a path in a folder is not a recording of it (listed in the summary, never skipped unsaid)
NOT_SEARCHED = "a folder inside a folder given: not searched (give it too, or a pattern such as '{}/**/*.mcap')"
NOT_RECORDING = "not a recording (allowed: .mcap, .csv)"


def runs_in(directory: Path, skipped: list[tuple[str, str]] | None = None) -> list[list[Path]]:
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
            runs = runs_in(p, skipped)
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
