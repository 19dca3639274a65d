"""Text that came from outside (a command's payload, a file, a network peer) made safe to print: every control
character shown as an escape, never interpreted by a terminal or a log reader.

A refused payload whose probe name held a line break and a line shaped like the service's own ("command apply:
applied (calibration 99)"), or ESC sequences (clear the screen, colours), reached the service's console and log as
they were. `printable` is applied where lines are printed (the service's console, the batch commands' stderr,
`fluxcal command` and `watch`, the dashboard's stderr); the dashboard's page escapes the same characters itself.
"""

from __future__ import annotations

import re

#: C0 and C1 controls, DEL, and the Unicode marks that reorder or hide what follows (bidi overrides, isolates,
#: zero-width joiners, line and paragraph separators)
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200b-\u200f\u2028-\u202e\u2060-\u2069\ufeff]")


def _shown(m: re.Match) -> str:
    c = m.group()
    return {"\n": "\\n", "\r": "\\r", "\t": "\\t"}.get(c) or (f"\\x{ord(c):02x}" if ord(c) < 0x100 else f"\\u{ord(c):04x}")


def printable(text: object) -> str:
    """`text` with every control character shown as an escape (\\n, \\x1b, \\u202e); printable text unchanged, and
    applying it twice changes nothing more.

    >>> printable("s1\\ncommand apply: applied (calibration 99)\\x1b[2J")
    's1\\\\ncommand apply: applied (calibration 99)\\\\x1b[2J'
    """
    return _CONTROL.sub(_shown, str(text))


def printable_json(obj: object) -> object:
    """A parsed JSON value with `printable` applied to every string in it, keys too (for a view that prints what
    a peer sent among its own terminal codes)."""
    if isinstance(obj, str):
        return printable(obj)
    if isinstance(obj, dict):
        return {printable(k): printable_json(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [printable_json(v) for v in obj]
    return obj
