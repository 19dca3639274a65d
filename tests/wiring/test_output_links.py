"""Outputs never follow a planted link (issue 38, build 5): over every command that writes, a symbolic link at the
output's path pointing at a file of someone else's is replaced by the output, its target untouched; an output
folder that is a link is refused before any work (exit 2, naming where it points). One helper (fluxcal.drivers.outputs)
for all.

Before: `replay --out LINK` wrote through a planted link and overwrote its target, and `--report LINKDIR` wrote into
the linked folder; simulate's, decode's and repair's temporary files had names anyone could plant a link at.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fluxcal.drivers.outputs import open_output, replacing
from fluxcal.service.wiring.cli import main

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "recordings" / "grad1-sim-30s.mcap"
PRECIOUS = "someone else's file: must not change\n"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("inputs")
    csv, capture = tmp / "grad.csv", tmp / "grad.bin"
    assert main(["simulate", "--out", str(csv)]) == 0
    assert main(["simulate", "--out", str(capture)]) == 0
    return SimpleNamespace(csv=csv, capture=capture)


def plant(path: Path, tmp_path: Path) -> Path:
    """A link at `path` to a victim file outside the output's folder; the victim."""
    victim = tmp_path / "elsewhere" / f"victim-{path.name}"
    victim.parent.mkdir(exist_ok=True)
    victim.write_text(PRECIOUS)
    path.symlink_to(victim)
    return victim


#: command (given the inputs and the output path) -> the output files it writes (a link is planted at each)
FILE_COMMANDS = {
    "fit --out": (lambda i, o: ["fit", str(i.csv), "--out", str(o / "cal.json")], ["cal.json"]),
    "replay --out": (lambda i, o: ["replay", str(SAMPLE), "--out", str(o / "again.mcap")], ["again.mcap"]),
    "simulate --out csv": (lambda i, o: ["simulate", "--out", str(o / "s.csv")], ["s.csv", "s.truth.json"]),
    "simulate --out mcap": (lambda i, o: ["simulate", "--out", str(o / "s.mcap")], ["s.mcap", "s.truth.json"]),
    "simulate --out bin": (lambda i, o: ["simulate", "--out", str(o / "s.bin")], ["s.bin", "s.truth.json"]),
    "simulate --out log": (lambda i, o: ["simulate", "--out", str(o / "s.log")], ["s.log", "s.truth.json"]),
    "decode --out csv": (lambda i, o: ["decode", str(i.capture), "--probes", "2", "--out", str(o / "d.csv")],
                         ["d.csv"]),
    "decode --out mcap": (lambda i, o: ["decode", str(i.capture), "--probes", "2", "--out", str(o / "d.mcap")],
                          ["d.mcap"]),
    "repair": (lambda i, o: ["repair", str(SAMPLE), str(o / "fixed.mcap")], ["fixed.mcap"]),
}


@pytest.mark.parametrize("case", list(FILE_COMMANDS))
def test_a_link_at_an_output_file_is_replaced_never_written_through(tmp_path, inputs, case, capsys):
    make, names = FILE_COMMANDS[case]
    out = tmp_path / "out"
    out.mkdir()
    victims = [plant(out / name, tmp_path) for name in names]
    assert main(make(inputs, out)) == 0, capsys.readouterr().err
    for name, victim in zip(names, victims):
        assert victim.read_text() == PRECIOUS, (case, name)
        assert (out / name).is_file() and not (out / name).is_symlink() and (out / name).stat().st_size > 0


FOLDER_COMMANDS = {
    "fit --report": lambda i, d: ["fit", str(i.csv), "--report", str(d)],
    "diagnose --report": lambda i, d: ["diagnose", str(i.csv), "--report", str(d)],
    "replay --ros2-out": lambda i, d: ["replay", str(SAMPLE), "--ros2-out", str(d)],
    "repair (a folder of files)": lambda i, d: ["repair", str(SAMPLE.parent), str(d)],
    "fit of several --out": lambda i, d: ["fit", str(i.csv), str(SAMPLE), "--out", str(d)],
}


@pytest.mark.parametrize("case", list(FOLDER_COMMANDS))
def test_an_output_folder_that_is_a_link_is_refused_before_any_work(tmp_path, inputs, case, capsys):
    victim = tmp_path / "elsewhere"
    victim.mkdir()
    link = tmp_path / "report"
    link.symlink_to(victim, target_is_directory=True)
    assert main(FOLDER_COMMANDS[case](inputs, link)) == 2
    out, err = capsys.readouterr()
    assert f"{link}: is a symbolic link (to {victim})" in err and "never written through a link" in err, err
    assert list(victim.iterdir()) == []


def test_diagnose_write_effect_replaces_a_link(tmp_path):
    from fluxcal.service.numerics.diagnose.library import Feature, Group
    from fluxcal.service.wiring.commands.diagnose import DiagnoseResult
    from fluxcal.service.wiring.commands.written import write_discovered
    from fluxcal.service.wiring.result import Said

    f = Feature("heater_A", "heater_A", "A", "value", {"source": "column", "column": "heater_A", "centre": 0.0},
                np.linspace(0.0, 1.0, 50))
    found = SimpleNamespace(claimed=True, groups=[SimpleNamespace(group=Group("offset", 0, "s1", f),
                                                                  reading="s1's offset follows heater_A")])
    target = tmp_path / "found.py"
    victim = plant(target, tmp_path)
    write_discovered(DiagnoseResult("diagnose", "rec.mcap", diagnosis=SimpleNamespace(discovery=found)),
                     str(target), "rec.mcap", Said("diagnose"))
    assert victim.read_text() == PRECIOUS and target.is_file() and not target.is_symlink()
    assert "class Discovered(" in target.read_text()


def test_the_helpers_never_follow_a_link(tmp_path):
    victim = tmp_path / "victim"
    victim.write_text(PRECIOUS)
    for mode in ("wb", "xb"):
        link = tmp_path / f"link-{mode}"
        link.symlink_to(victim)
        if mode == "xb":
            with pytest.raises(FileExistsError):
                open_output(link, mode)
            assert link.is_symlink()
        else:
            with open_output(link, mode) as f:
                f.write(b"new")
            assert link.read_bytes() == b"new" and not link.is_symlink()
    link = tmp_path / "replaced"
    link.symlink_to(victim)
    with pytest.raises(RuntimeError):
        with replacing(link) as f:                     # a failed write leaves the path as it was, and no temporary
            f.write(b"half")
            raise RuntimeError
    assert link.is_symlink() and sorted(p.name for p in tmp_path.iterdir()) == ["link-wb", "link-xb", "replaced",
                                                                                 "victim"]
    with replacing(link, "w") as f:
        f.write("whole")
    assert link.read_text() == "whole" and victim.read_text() == PRECIOUS
    assert oct(link.stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
