"""The examples in the code's docstrings run and give what they show (a stale one misleads the reader: the simulated
unit's list of probe keys had grown by three since its example was written)."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import index
import pytest

ROOT = Path(__file__).resolve().parents[2]
#: the public modules that re-export names, whose examples here are their tests (tests/index.py)
COVERS = ("fluxcal.bus", "fluxcal.effects", "fluxcal.recordings")
MODULES = sorted(index.module_name(p) for pkg in index.PACKAGES for p in (ROOT / pkg).rglob("*.py")
                 if ">>> " in p.read_text(encoding="utf-8"))


def test_the_modules_with_examples_are_found():
    assert len(MODULES) >= 25 and "fluxcal.drivers.sim.config" in MODULES and "fluxcal.service.numerics.diagnose.spectra" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_the_examples_in_a_modules_docstrings_hold(name):
    module = importlib.import_module(name.removesuffix(".__init__"))
    got = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert got.attempted > 0 and got.failed == 0, f"{name}: {got.failed} of {got.attempted} examples failed"
