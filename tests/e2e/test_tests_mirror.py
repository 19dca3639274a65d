"""tests/ mirrors the source's wings and every module is findable from its test and back (issue 29): each test file
in a wing's folder, each module of service/ and drivers/ tested by at least one file, tests/README.md's table up to
date (every module has its row; which files test it the table says as of its last writing)."""

from __future__ import annotations

import re
from pathlib import Path

import index

ROOT = Path(__file__).resolve().parents[2]


def test_every_test_file_lives_in_a_wing():
    loose = sorted(p.name for p in (ROOT / "tests").glob("test_*.py"))
    assert loose == []
    folders = {p.parent.name for p in index.test_files()}
    assert folders == set(index.WINGS)


def test_every_module_has_a_test_and_the_table_says_which():
    found = index.index()
    untested = sorted(m for m, tests in found.items() if not tests and m not in index.UNTESTED)
    assert untested == [], "modules no test file imports, runs or declares in COVERS"
    assert all(not found[m] for m in index.UNTESTED), "tested now: take it out of UNTESTED"
    listed = set(re.findall(r"^\| `([a-z0-9_.]+)` \|", (ROOT / "tests" / "README.md").read_text(), flags=re.M))
    assert listed == set(found), "tests/README.md: run python tests/index.py and put its table there"
