"""Which files make one recording: a file of a format fluxcal reads is one; the service rotates one run into
-0001.mcap, -0002.mcap, ... files, which together are one; a ROS 2 bag's folder is one; and what paths, folders and
glob patterns name (fleets, and a folder given to fit, diagnose or replay), resolved here into absolute paths, so a
worker anywhere (another process, another folder, another host with the same files) reads what the user named."""

from __future__ import annotations

import glob
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from fluxcal.service.io.recordings.formats import DATAFLASH_HEAD

_RUN_PART = re.compile(r"^(?P<stem>.+)-(?P<n>\d{4})\.mcap$")
#: the files a folder's listing takes as recordings (as the readers tell them apart: formats.detect_format)
SUFFIXES = (".mcap", ".csv", ".ulg", ".bin", ".db3")


#: why a path in a folder is not a recording of it (listed in the summary, never skipped unsaid)
NOT_SEARCHED = "a folder inside a folder given: not searched (give it too, or a pattern such as '{}/**/*.mcap')"
NOT_RECORDING = "not a recording (allowed: .mcap, .csv, .ulg, .bin, .db3, a ROS 2 bag's folder)"
NOT_DATAFLASH = "not a recording: a .bin that is no ArduPilot log (a serial capture? `fluxcal decode` reads those)"


def is_bag(path: Path) -> bool:
    """A rosbag2 bag: a folder holding its metadata.yaml (with .db3 or .mcap storage), read as one recording."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _not_a_recording(f: Path, directory: Path) -> str | None:
    """Why a path found in `directory` is no recording of it (None: it is one)."""
    if is_bag(f):
        return None
    if f.is_dir():
        return NOT_SEARCHED.format(directory)
    if f.suffix.lower() not in SUFFIXES:
        return NOT_RECORDING
    if f.suffix.lower() == ".bin":
        try:
            with open(f, "rb") as fh:
                if fh.read(2) != DATAFLASH_HEAD[:2]:
                    return NOT_DATAFLASH
        except OSError:
            return None                                  # tried: its reader says why it cannot be read
    return None


def runs_in(directory: Path, skipped: list[tuple[str, str]] | None = None) -> list[list[Path]]:
    """The recordings in a directory: each CSV file, flight log and ROS 2 bag, and each run of MCAP files (a -0001
    file and the rotated files after it, in name order; a file outside that naming is a run by itself). What is not
    one (a folder in it, another file) goes into `skipped` as (path, reason)."""
    files = []
    for f in sorted(directory.iterdir()):
        why = _not_a_recording(f, directory)
        if why is None:
            files.append(f)
        elif skipped is not None:
            skipped.append((str(f), why))
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


@dataclass(frozen=True)
class Recording:
    """One recording of several: `name` as the user named it (their relative path, for the summary); `path`
    absolute (a file, a bag's folder, the folder of one run, or a run's first file when `parts`); `parts` the
    absolute paths of one run's rotated files picked out of a folder of several (the worker links them into a
    folder of its own: linked_run)."""

    name: str
    path: str
    parts: tuple[str, ...] = ()


@dataclass
class Inputs:
    """What paths, folders and patterns name: the recordings; what a folder held besides them (skipped: path,
    reason); and each item that names none (unreadable: item, reason: no such path, a pattern matching nothing,
    a folder holding no recording)."""

    recordings: list[Recording] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    unreadable: list[tuple[str, str]] = field(default_factory=list)


def _absolute(p: Path | str) -> str:
    """Where the user's path points from here, as a worker elsewhere must read it (links kept, not resolved)."""
    return os.path.abspath(p)


def expand_inputs(items: Iterable[str]) -> Inputs:
    """Paths, folders and glob patterns -> the recordings, in the order given (duplicates once). A folder holding
    one run of rotated files (or a ROS 2 bag) stays one recording (as for a single command); a folder of several
    becomes each of them, a run of several rotated files as its parts (so do the rotated files of one run a pattern
    matches). Relative paths and patterns are taken from this process's working folder; each Recording's path is
    absolute, its name as the user gave it."""
    got = Inputs()
    taken: set[tuple[str, ...]] = set()              # the files of each run given: a run named twice runs once

    def add(run: list[Path], whole: Path | None = None) -> None:
        key = tuple(sorted(str(f.resolve()) for f in run))
        if key in taken:
            return
        taken.add(key)
        if len(run) == 1 or whole is not None:
            one = run[0] if whole is None else whole
            got.recordings.append(Recording(str(one), _absolute(one)))
        else:
            got.recordings.append(Recording(f"{run[0]} (+{len(run) - 1} rotated)", _absolute(run[0]),
                                            tuple(_absolute(f) for f in run)))

    for item in items:
        pattern = os.path.expanduser(item)
        magic = glob.has_magic(pattern)
        paths = sorted(glob.glob(pattern, recursive=True)) if magic else [pattern]
        if not paths:
            got.unreadable.append((item, "matches no file (allowed: recordings (.mcap, .csv, .ulg, .bin, .db3), "
                                         "folders of them, or glob patterns such as 'survey/*.mcap')"))
        loose: list[Path] = []                        # the files a pattern matched: one run's files are one
        for p in map(Path, paths):
            if not p.exists():
                got.unreadable.append((str(p), "no such file or folder"))
                continue
            if not p.is_dir() or is_bag(p):
                why = _not_a_recording(p, p.parent) if magic else None
                if why is None:                       # a file named is tried (its reader says what is wrong)
                    loose.append(p)
                else:                                 # a pattern's match that is none: as a folder's
                    got.skipped.append((str(p), why))
                continue
            for run in _runs_of_files(loose):
                add(run)
            loose = []
            if runs := runs_in(p, got.skipped):
                for run in runs:                      # one run of rotated files: the folder, read as that run
                    add(run, p if len(runs) == 1 and len(run) > 1 else None)
            else:
                got.unreadable.append((str(p), "holds no recording (.mcap, .csv, .ulg, .bin, .db3, a ROS 2 bag)"))
        for run in _runs_of_files(loose):
            add(run)
    seen: set[str] = set()                          # one recording named twice (by name, through a folder): once
    got.recordings = [r for r in got.recordings
                      if not ((key := str(Path(r.path).resolve())) in seen or seen.add(key))]
    return got


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


def linked_run(parts: Iterable[str], folder: Path) -> Path:
    """One run's rotated files as a folder of links under `folder` (a run read as a folder: labdata reads it so),
    made where the run is read."""
    parts = list(parts)
    d = folder / Path(parts[0]).stem
    d.mkdir(parents=True)
    for f in parts:
        (d / Path(f).name).symlink_to(f)
    return d
