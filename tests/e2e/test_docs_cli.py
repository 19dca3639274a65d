"""docs/cli.md is the command-line reference: every command `fluxcal --help` lists and every option each
command's `--help` shows are in it (read from the installed `fluxcal`, as a user runs it)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FLUXCAL = Path(sys.executable).parent / "fluxcal"


def help_text(*argv: str) -> str:
    cmd = [str(FLUXCAL)] if FLUXCAL.exists() else [sys.executable, "-m", "fluxcal.service.wiring.cli"]
    out = subprocess.run([*cmd, *argv, "--help"], capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 0, out.stderr
    return out.stdout


def commands() -> list[str]:
    text = help_text()
    block = text.split("positional arguments:", 1)[1].split("options:", 1)[0]
    return re.findall(r"^ {4}([a-z][\w-]*)\b", block, flags=re.M)


def test_every_command_and_option_is_in_the_reference():
    doc = (ROOT / "docs" / "cli.md").read_text()
    names = commands()
    assert {"fit", "diagnose", "run", "replay", "watch"} <= set(names), names
    missing = []
    for name in names:
        if not re.search(rf"^#+ .*\b{re.escape(name)}\b", doc, flags=re.M):
            missing.append(f"{name}: no section")
        usage = help_text(name).split("\n\n", 1)[0]                       # the usage lines
        for option in sorted(set(re.findall(r"\[?(--[a-z][\w-]*)", usage)) - {"--help"}):
            if f"`{option}" not in doc:
                missing.append(f"{name} {option}")
    assert missing == []
