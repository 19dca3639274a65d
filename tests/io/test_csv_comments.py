"""`#` comment lines anywhere in a lab CSV are skipped and kept as comments (an operator's note between two
turns gave "line 3001: 1 values, expected 12"); a bad row after them still names its own line."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.recordings.labdata import load_csv
from fluxcal.service.wiring.cli import main

HEADER = "t,s1_x,s1_y,s1_z,ref_total"


def rows(n: int) -> list[str]:
    rng = np.random.default_rng(1)
    v = rng.normal(size=(n, 3))
    v *= 50_000.0 / np.linalg.norm(v, axis=1, keepdims=True)
    return [f"{i * 0.01:.2f},{x + 200:.3f},{y - 300:.3f},{z + 100:.3f},50000.0" for i, (x, y, z) in enumerate(v)]


def test_comments_after_the_header_are_skipped_and_kept(tmp_path):
    data = rows(3000)
    plain = tmp_path / "plain.csv"
    plain.write_text("\n".join(["# lab export", HEADER, *data]) + "\n")
    noted = tmp_path / "noted.csv"
    noted.write_text("\n".join(["# lab export", HEADER, *data[:1500], "# turned the unit over here",
                                "  #indented note", *data[1500:], "# end of run"]) + "\n")
    a, b = load_csv(plain), load_csv(noted)
    assert b.block.n_samples == a.block.n_samples == 3000
    assert np.array_equal(a.block.field_nT, b.block.field_nT) and np.array_equal(a.block.t_s, b.block.t_s)
    assert b.comments == ["lab export", "turned the unit over here", "indented note", "end of run"]


def test_a_bad_row_after_a_comment_names_its_own_line(tmp_path):
    p = tmp_path / "bad.csv"
    data = rows(10)
    data[6] = "0.06,1,oops,3,50000"
    p.write_text("\n".join([HEADER, *data[:3], "# note", *data[3:]]) + "\n")     # the bad row is line 9
    with pytest.raises(DataError, match=r"bad.csv: line 9, column 's1_y'"):
        load_csv(p)


def test_fit_reads_a_csv_with_a_comment_line_in_its_body(tmp_path, capsys):
    p = tmp_path / "lab.csv"
    data = rows(3000)
    p.write_text("\n".join([HEADER, *data[:2999], "# operator: a note", data[2999]]) + "\n")
    assert main(["fit", str(p), "--json"]) == 0
    assert "expected" not in capsys.readouterr().err


def test_a_bad_value_after_a_nan_is_named_on_its_own_line(tmp_path):
    """NaN is allowed in a probe's axes (a saturated sample); the slow search for the bad cell stopped at the
    first NaN and named that line (the review's case)."""
    p = tmp_path / "bad.csv"
    p.write_text("t,s1_x,s1_y,s1_z\n0,1,2,3\n1,nan,2,3\n2,1,2,3\n3,1,abc,3\n")
    with pytest.raises(DataError, match=r"line 5, column 's1_y': 'abc' is not a number"):
        load_csv(p)
