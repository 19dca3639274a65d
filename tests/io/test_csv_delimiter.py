"""A lab CSV exported where the decimal point is a comma (European Excel, LabVIEW: `t;s1_x;...`, `0,01;200,5`) is
refused with what fluxcal reads and how to convert it (it said "no 't' column"), never read by a guess; the
conversion it gives, run as given, gives the same samples as the file written with ',' and '.'."""

from __future__ import annotations

import json
import re
import subprocess

import numpy as np
import pytest

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.recordings.labdata import load_csv
from fluxcal.service.wiring.cli import main

HEADER = ["t", "s1_x", "s1_y", "s1_z"]


def _table(n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(3)
    v = rng.normal(size=(n, 3))
    v *= 50_000.0 / np.linalg.norm(v, axis=1, keepdims=True)
    return np.column_stack([np.arange(n) * 0.01, v + [200.5, -300.25, 100.125]])


def _write(path, sep: str, decimal: str) -> None:
    lines = [sep.join(HEADER)] + [sep.join(f"{x:.3f}".replace(".", decimal) for x in row) for row in _table()]
    path.write_text("# exported by a spreadsheet\n" + "\n".join(lines) + "\n")


@pytest.mark.parametrize("sep, decimal, said", [(";", ",", "';'"), (";", ".", "';'"), ("\t", ",", "tabs"),
                                                ("\t", ".", "tabs")])
def test_another_separator_is_said_with_a_conversion_that_works(tmp_path, capsys, sep, decimal, said):
    plain, other = tmp_path / "plain.csv", tmp_path / "export.csv"
    _write(plain, ",", ".")
    _write(other, sep, decimal)
    with pytest.raises(DataError) as e:
        load_csv(other)
    msg = str(e.value)
    assert msg.startswith(f"{other}: line 2: no 't' column (time in seconds) in the header: the file is separated by "
                          f"{said}, and fluxcal reads values separated by ',' with '.' as the decimal point")
    assert main(["fit", str(other), "--json"]) == 2
    assert json.loads(capsys.readouterr().out)["refused"]["reason"] == msg
    # the advice's own command, the one for the file's decimal mark, run as it is written
    commands = re.findall(r"`(sed [^`]*)`", msg)
    assert len(commands) == 2
    subprocess.run(commands[1 if decimal == "," else 0], shell=True, check=True, cwd=tmp_path)
    converted = load_csv(tmp_path / "export-comma.csv")
    assert np.array_equal(converted.block.field_nT, load_csv(plain).block.field_nT)
    assert np.array_equal(converted.block.t_s, load_csv(plain).block.t_s)


def test_a_header_without_t_for_another_reason_says_only_that(tmp_path):
    p = tmp_path / "no_t.csv"
    p.write_text("time;s1_x;s1_y;s1_z\n0;1;2;3\n")
    with pytest.raises(DataError, match=r"no 't' column \(time in seconds\) in the header$"):
        load_csv(p)
