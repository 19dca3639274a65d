"""No function of service/, drivers/ or bench/ is over 80 lines (issue 29), counted from its def line to its last
line as `ast` gives them (end_lineno - lineno + 1; methods and nested functions each on their own)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("service", "drivers", "bench")
MAX_LINES = 80

#: functions still over MAX_LINES, as "path:name"; each entry goes once its function is split
LONGER: set[str] = set()


def function_lengths() -> dict[str, int]:
    """Lines of every function and method of FOLDERS, by "path:name" (the longest where a name repeats)."""
    lengths: dict[str, int] = {}
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            if ".venv" in path.parts or "__pycache__" in path.parts:
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    key = f"{path.relative_to(ROOT).as_posix()}:{node.name}"
                    lengths[key] = max(lengths.get(key, 0), node.end_lineno - node.lineno + 1)
    return lengths


def test_no_function_is_over_80_lines():
    lengths = function_lengths()
    assert len(lengths) > 1000                  # the walk found the code (1,737 when this test was written)
    long = {k: n for k, n in lengths.items() if n > MAX_LINES and k not in LONGER}
    assert not long, (f"over {MAX_LINES} lines (split into helpers that each do one thing): "
                      + ", ".join(f"{k} ({n})" for k, n in sorted(long.items(), key=lambda kv: -kv[1])))


def test_every_exception_is_still_a_long_function():
    """An entry of LONGER whose function has been split (or renamed) goes, so that it cannot grow back unseen."""
    lengths = function_lengths()
    stale = sorted(k for k in LONGER if lengths.get(k, 0) <= MAX_LINES)
    assert not stale, f"no longer over {MAX_LINES} lines or gone: remove from LONGER in {__file__}: {stale}"
