"""The house in three wings: numerics import no I/O and no wiring, I/O imports no wiring, and modules
stay small enough to hold in mind (docs/architecture.md names any that must be longer, and why)."""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import index
import pytest

ROOT = Path(__file__).resolve().parents[2]
SERVICE = ROOT / "service"
MAX_MODULE_LINES = 500
MAX_CLASS_LINES = 200

#: what each wing may not import (module name prefixes); drivers' sources talk to hardware and files
FORBIDDEN = {
    "numerics": ("fluxcal.service.io", "fluxcal.service.wiring", "zenoh", "mcap", "serial", "can",
                 "fluxcal.drivers.source", "fluxcal.drivers.serial_source", "fluxcal.drivers.can_source", "fluxcal.drivers.mcap_source",
                 "fluxcal.drivers.sim", "fluxcal.drivers.config", "matplotlib", "socket", "threading", "subprocess"),
    "io": ("fluxcal.service.wiring",),
}


def _module_name(path: Path) -> str:
    return index.module_name(path, ROOT).removesuffix(".__init__")


def _imports(path: Path) -> list[tuple[int, str]]:
    """Every module a file imports, relative imports resolved, and importlib calls with a literal name."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = _module_name(path) if path.name == "__init__.py" else _module_name(path).rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.append((node.lineno, name))
            # `from fluxcal.service.io import calfile` names a module in the import list
            found += [(node.lineno, f"{name}.{alias.name}") for alias in node.names]
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            found.append((node.lineno, node.args[0].value))
    return found


def _violations(wing: str) -> list[str]:
    bad = []
    for path in sorted((SERVICE / wing).rglob("*.py")):
        for line, name in _imports(path):
            for prefix in FORBIDDEN[wing]:
                if name == prefix or name.startswith(prefix + "."):
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return bad


@pytest.mark.parametrize("wing", sorted(FORBIDDEN))
def test_wing_imports_stay_inside_the_rule(wing):
    assert _violations(wing) == []


def test_the_rule_catches_a_forbidden_import(tmp_path, monkeypatch):
    """The checker itself: a numerics module importing the bus, relatively or absolutely, is caught."""
    fake = tmp_path / "service" / "numerics" / "calib"
    fake.mkdir(parents=True)
    (fake / "bad.py").write_text("from ...io.bus import BusClient\nimport importlib\n"
                                 "importlib.import_module('fluxcal.service.wiring.daemon')\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "SERVICE", tmp_path / "service")
    assert _violations("numerics") == [
        "service/numerics/calib/bad.py:1 imports fluxcal.service.io.bus",
        "service/numerics/calib/bad.py:1 imports fluxcal.service.io.bus.BusClient",
        "service/numerics/calib/bad.py:3 imports fluxcal.service.wiring.daemon",
    ]


def test_no_code_imports_the_folders_as_top_level_packages():
    """Installed, service/ and drivers/ are fluxcal.service and fluxcal.drivers (issue 39): a module, test, benchmark,
    tool or example that imports `service` or `drivers` would work in a checkout run from its root and fail installed."""
    bad = []
    for top in ("fluxcal", "service", "drivers", "tests", "bench", "tools", "docs"):
        for path in sorted((ROOT / top).rglob("*.py")):
            bad += [f"{path.relative_to(ROOT)}:{line} imports {name}" for line, name in _imports(path)
                    if name.split(".")[0] in ("service", "drivers")]
    assert bad == []


def _documented_exceptions() -> set[str]:
    """Paths (and path:Class) that docs/architecture.md's section on longer modules names with a reason."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text.split("## Longer than the limits", 1)
    if len(section) < 2:
        return set()
    body = section[1].split("\n## ", 1)[0]
    return set(re.findall(r"^- `([^`]+)`: \S", body, flags=re.M))


def _too_long() -> list[str]:
    long = []
    for top in ("service", "drivers", "bench"):
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            text = path.read_text()
            if text.count("\n") > MAX_MODULE_LINES:
                long.append(rel)
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES:
                    long.append(f"{rel}:{node.name}")
    return long


def test_modules_and_classes_fit_in_a_head_or_say_why():
    assert sorted(set(_too_long()) - _documented_exceptions()) == []


def test_documented_exceptions_are_still_needed():
    """A module brought under the limit leaves the list, so the list stays true."""
    assert sorted(_documented_exceptions() - set(_too_long())) == []
