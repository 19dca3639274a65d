"""What a batch command gives back: a Result with its figures and its notes as data, never text another part
of fluxcal parses. The command line formats a Result as text or JSON; a fleet ships Results from its workers.

    Note     one thing a command says besides its figures: a warning (something was lost, left out or is
             doubtful), a note (what was done), or a loud warning (the figures may mean nothing)
    Said     the notes of one run, in order; each handed at once to a `say` callback (the command line prints
             it on stderr as it comes; a fleet's worker keeps it with the result)
    Result   command, source, notes, exit status, files written; `as_dict()` (JSON) and `text()` (a person)
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from fluxcal.drivers.text import printable

#: how loud a note is: said as "note: ...", "warning: ..." or "WARNING: ..."; "say" (what was done) and
#: "error" (what failed: the exit status says so too) are said as they are, without a word before them
LEVELS = ("note", "say", "warning", "loud", "error")
_WORDS = {"note": "note: ", "say": "", "warning": "warning: ", "loud": "WARNING: ", "error": ""}


@dataclass(frozen=True)
class Note:
    """One thing said, as data. `kind` names what it is about (a fleet counts warnings by it, whatever the
    wording): "read" (what reading lost), "skip", "part-of-run", "config", "field-scale", "left-out", ...; `text`
    is the sentence for a person."""

    kind: str
    text: str
    level: str = "warning"

    @property
    def is_warning(self) -> bool:
        """Whether it says something was lost, left out, doubtful or failed (not only what was done)."""
        return self.level in ("warning", "loud", "error")

    def line(self, command: str) -> str:
        """As the command line says it on stderr."""
        return f"fluxcal {command}: {_WORDS[self.level]}{self.text}"

    def as_dict(self) -> dict[str, str]:
        return {"kind": self.kind, "level": self.level, "text": self.text}


def stderr_say(command: str) -> Callable[[Note], None]:
    """The command line's `say`: each note on stderr as it comes."""
    def say(note: Note) -> None:
        print(printable(note.line(command)), file=sys.stderr, flush=True)      # a file's words never act
    return say


class Said:
    """The notes of one command's run, in the order said; each also handed to `say` at once (None: kept only)."""

    def __init__(self, command: str, say: Callable[[Note], None] | None = None) -> None:
        self.command = command
        self.say = say
        self.notes: list[Note] = []

    def __call__(self, kind: str, text: str, level: str = "warning") -> Note:
        if level not in LEVELS:
            raise ValueError(f"level {level!r} (allowed: {', '.join(LEVELS)})")
        note = Note(kind, text, level)
        self.notes.append(note)
        if self.say is not None:
            self.say(note)
        return note

    @property
    def warnings(self) -> list[Note]:
        return [n for n in self.notes if n.is_warning]

    def lost_in_reading(self, besides: Sequence[str] = ()) -> list[str]:
        """The warnings said so far (what reading lost or left out: a logger's holds, a gap, a cut message), for a
        result's JSON, but those a command carries in its own words (CARRIED) and those in `besides`."""
        return [n.text for n in self.warnings if n.kind not in CARRIED and n.text not in besides]


#: the kinds of what was said that a command's result carries in its own words already (the data's scale, the
#: configuration, a part of a run)
CARRIED = ("field-scale", "config", "part-of-run")


@dataclass
class Result:
    """One batch command's outcome on one input. Subclasses add the figures and override `as_dict` (the
    command's JSON contract, docs/contracts.md) and `text` (what a person reads)."""

    command: str
    source: str
    notes: list[Note] = field(default_factory=list)
    status: int = 0                                   # the exit status the command line returns
    written: list[str] = field(default_factory=list)  # files and folders written

    @property
    def ok(self) -> bool:
        return self.status == 0

    @property
    def warnings(self) -> list[Note]:
        return [n for n in self.notes if n.is_warning]

    def as_dict(self) -> dict[str, Any]:
        return {"command": self.command, "source": self.source, "status": self.status,
                "notes": [n.as_dict() for n in self.notes], "written": list(self.written)}

    def text(self) -> str:
        return ""

    # in Python (fluxcal.service.wiring.api): the same figures as the command line's
    def to_dict(self) -> dict[str, Any]:
        """The command's JSON (docs/contracts.md), as a dict."""
        return self.as_dict()

    def to_dataframe(self) -> Any:
        """The result's table as a pandas DataFrame (pandas needed): its parameters with standard errors."""
        import pandas as pd

        return pd.DataFrame(self.rows())

    def rows(self) -> list[dict[str, Any]]:
        """The result's table as rows (to_dataframe): none here; a command's result says its own."""
        return []

    def _repr_html_(self) -> str:
        """A notebook's display: the table, the text as the command line prints it, and the notes."""
        from fluxcal.service.io.report.notebook import result_html

        return result_html(self)


def refusal(error: BaseException, file: Any = None) -> dict[str, Any]:
    """The JSON of a refusal (docs/contracts.md section 3): {"refused": {"reason", "advice", "file"}}. reason: why
    (the error's own reason where it gives one apart, else its message); advice: what would help, or None where the
    reason says it itself; file: the input refused (None: not one file), unless the error names its own (`error.file`:
    a configuration or calibration given beside the data, prepare.refusing)."""
    reason = getattr(error, "reason", None) or str(error)
    file = getattr(error, "file", None) or file
    advice = getattr(error, "advice", None) or None
    if isinstance(file, (list, tuple)):
        file = file[0] if len(file) == 1 else None
    return {"refused": {"reason": str(reason), "advice": advice, "file": None if file is None else str(file)}}


def print_result(result: Result, as_json: bool) -> None:
    """A result on stdout: its JSON on one line, or its text for a person."""
    import json

    if as_json:
        print(json.dumps(result.as_dict()))
    else:
        text = result.text()
        if text:
            print(text)
    sys.stdout.flush()
