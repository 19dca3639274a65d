"""Progress of long work (issue 16): a tqdm bar on a terminal for decode, replay, diagnose and simulate,
only once the work has run for a second; on a log or a pipe a plain line every ten seconds, and nothing
for short work."""

from __future__ import annotations

import io
import sys
from pathlib import Path

from fluxcal.service.wiring import progress as progress_mod
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.progress import Progress

ROOT = Path(__file__).resolve().parents[2]


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_terminal_gets_a_bar_with_what_is_being_done(monkeypatch):
    monkeypatch.setattr(progress_mod, "REDRAW_S", 0.0)
    tty = Tty()
    bar = Progress(1.0, "diagnose", stream=tty, fraction=True, delay_s=0.0)
    bar(0.5, "trying eddy")
    bar.close()
    out = tty.getvalue()
    assert "diagnose:  50%|" in out and "trying eddy" in out


def test_short_work_shows_nothing_on_a_terminal():
    tty = Tty()
    with Progress(1000, "replay", stream=tty) as bar:        # the default one-second delay
        bar.to(500)
        bar.to(1000)
    assert "replay" not in tty.getvalue()


def test_a_log_gets_a_plain_line_for_long_work_and_nothing_for_short(monkeypatch):
    plain = io.StringIO()
    with Progress(200, "simulate", stream=plain) as bar:
        bar.to(100)
    assert plain.getvalue() == ""
    monkeypatch.setattr(progress_mod, "LINE_S", 0.0)
    with Progress(200, "simulate", stream=plain) as bar:
        bar.to(100)
        bar.to(200)                     # the end is said by the command itself, not by a 100 % line
    lines = plain.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fluxcal simulate: 50 % of 200 samples after")


def test_simulate_decode_replay_and_diagnose_draw_bars(tmp_path, monkeypatch):
    # stderr as a terminal (set here, not in a fixture: pytest's capture takes stderr back for the call),
    # and a bar for work of any length
    terminal = Tty()
    monkeypatch.setattr(sys, "stderr", terminal)
    monkeypatch.setattr(progress_mod, "DELAY_S", 0.0)
    monkeypatch.setattr(progress_mod, "REDRAW_S", 0.0)
    cap, out = tmp_path / "cap.bin", tmp_path / "decoded.csv"
    assert main(["simulate", "--out", str(cap)]) == 0
    assert "simulate: " in terminal.getvalue() and "simulate: 100%|" in terminal.getvalue() and "12.0k/12.0k" in terminal.getvalue()
    assert main(["decode", str(cap), "--probes", "2", "--out", str(out)]) == 0
    assert "decode: 100%|" in terminal.getvalue()
    monkeypatch.chdir(ROOT)
    assert main(["replay", "recordings/grad1-sim-30s.mcap"]) == 0
    assert "replay: 100%|" in terminal.getvalue()
    assert main(["diagnose", str(out)]) == 0
    assert "diagnose: 100%|" in terminal.getvalue()
