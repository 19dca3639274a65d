"""What `diagnose` writes beside its result (fluxcal.service.wiring.commands.diagnose): the term discovery found as an
effect module of the user's own (--write-effect), and the HTML report (--report). Each is said, and counted in the
result's `written`; a report that cannot be written costs the exit status, never the diagnosis."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from fluxcal.drivers.errors import FluxcalError
from fluxcal.drivers.outputs import replacing
from fluxcal.service.wiring.result import Said


def write_discovered(out: Any, path: str, source: str, said: Said) -> None:
    """The terms discovery found, written as an effect module at `path` (atomically: a temporary file renamed), said
    with how to take it back; where it found none, no file, and that is said instead (the exit status stays 0)."""
    from fluxcal.service.numerics.diagnose.write_effect import effect_classes, effect_source

    found = getattr(out.diagnosis, "discovery", None)
    if found is None or not found.claimed:
        why = "discovery did not run" if found is None else (found.reason or "it claims nothing")
        said("write-effect", f"--write-effect {path}: nothing written: no term was discovered beyond the catalogue "
                             f"({why})")
        return
    text = effect_source(found, data_name=Path(source).name)
    target = Path(path)
    kept = _keep_earlier(target, text)
    if kept is not None:
        said("write-effect", f"{target} held another module (your edits?): kept as {kept}", level="say")
    with replacing(target, "w") as f:               # a link at the path replaced, never written through
        f.write(text)
    out.written.append(str(target))
    use = ",".join(f"{target}:{c}" for c in effect_classes([g.group for g in found.groups]))
    said("write-effect", f"the discovered term written to {target} as an effect of your own: rename it and give it "
                         f"back with --effects {use} (fit, diagnose; a running service takes it from [effects] "
                         f"plugins where it acts on each sample alone)", level="say")


def _keep_earlier(target: Path, text: str) -> Path | None:
    """Where a file at `target` that differs from `text` is kept (renamed to the first free target.~N~, as GNU's
    numbered backups), so that writing the module again never loses what a user edited there; None where there was
    none, or the same text."""
    try:
        if not target.is_file() or target.read_text(encoding="utf-8", errors="replace") == text:
            return None
    except OSError:
        return None
    n = 1
    while (kept := target.with_name(f"{target.name}.~{n}~")).exists():
        n += 1
    os.replace(target, kept)
    return kept


def write_diagnosis_report(out: Any, folder: str, said: Said) -> None:
    """The HTML report of the diagnosis `out` holds, in `folder` (checked before any work): its path in
    out.report and out.written; what it lacks (no matplotlib: no plots) said; one that cannot be written (a full
    disk) said, and the exit status 1."""
    from fluxcal.service.io.report import write_report
    from fluxcal.service.io.report.page import NO_MATPLOTLIB, has_matplotlib
    from fluxcal.service.wiring.calib_report import section_from_diagnosis

    result = out.diagnosis
    try:
        out.report = str(write_report(result, folder, title=f"fluxcal diagnose {Path(out.source).name}",
                                      calibration=section_from_diagnosis(result)))
        out.written.append(out.report)
        if not has_matplotlib():
            said("report", f"report without plots: {NO_MATPLOTLIB}", level="note")
    except (OSError, FluxcalError) as e:
        said("report", f"{folder}: the report could not be written: {e}")
        out.status = 1


__all__ = ["write_diagnosis_report", "write_discovered"]
