"""Which test files test which module: read from the tests' own imports (a name imported from a package counts for the
module that defines it) and from the commands they run (`main(["fit", ...])` tests fluxcal.service.wiring.commands.fit).
`python tests/index.py` prints the table tests/README.md holds; tests/e2e/test_tests_mirror.py checks that it is
up to date and that every module has a test."""

from __future__ import annotations

import ast
import re
import sys
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WINGS = ("numerics", "io", "drivers", "wiring", "e2e")
#: modules with no test of their own, and why
UNTESTED = {
    "fluxcal.drivers.sim.__main__": "`python -m fluxcal.drivers.sim`, the simulated unit as a process: started by the tests that "
                            "run it (tests/drivers/test_sim_ports.py) through fluxcal.drivers.sim.ports",
}


#: the repository's folders and the import packages they are (pyproject.toml's package-dir)
PACKAGES = {"fluxcal": "fluxcal", "service": "fluxcal.service", "drivers": "fluxcal.drivers"}


def module_name(path: Path, root: Path = ROOT) -> str:
    """The dotted name a source file under `root` is imported by: service/io/bus/desk.py ->
    fluxcal.service.io.bus.desk (a package's __init__.py keeps its last part: ...bus.__init__)."""
    top, *rest = path.relative_to(root).with_suffix("").parts
    return ".".join([PACKAGES.get(top, top), *rest])


def source_modules() -> dict[str, Path]:
    out = {}
    for top in PACKAGES:
        for p in sorted((ROOT / top).rglob("*.py")):
            if p.name == "__init__.py" or "__pycache__" in p.parts:
                continue
            out[module_name(p)] = p
    return out


@lru_cache(maxsize=None)
def _defines(module_file: Path) -> frozenset[str]:
    """Top-level names a module defines (functions, classes, assignments)."""
    names = set()
    for n in ast.parse(module_file.read_text(encoding="utf-8")).body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(n.name)
        elif isinstance(n, (ast.Assign, ast.AnnAssign)):
            for t in (n.targets if isinstance(n, ast.Assign) else [n.target]):
                if isinstance(t, ast.Name):
                    names.add(t.id)
    return frozenset(names)


def _resolve(package: str, name: str, modules: dict[str, Path]) -> str | None:
    """The module under `package` that defines `name` (a package re-exports its modules' names)."""
    if f"{package}.{name}" in modules:
        return f"{package}.{name}"
    for mod, path in modules.items():
        if mod.startswith(package + ".") and name in _defines(path):
            return mod
    return None


def covered_by(test_file: Path, modules: dict[str, Path]) -> set[str]:
    """The source modules one test file tests."""
    text = test_file.read_text(encoding="utf-8")
    found: set[str] = set()
    for n in ast.walk(ast.parse(text)):
        if isinstance(n, ast.ImportFrom) and n.module:
            if n.module in modules:
                found.add(n.module)
            else:
                for a in n.names:
                    mod = _resolve(n.module, a.name, modules) if n.module.split(".")[0] == "fluxcal" \
                        else None
                    if mod:
                        found.add(mod)
        elif isinstance(n, ast.Import):
            found |= {a.name for a in n.names if a.name in modules}
    for decl in re.findall(r"^COVERS = \(([^)]*)\)", text, flags=re.M):    # what a file declares it tests
        found |= {m for m in re.findall(r'"([a-z_.]+)"', decl) if m in modules}
    for cmd in re.findall(r"""(?:main|cli\.main|run)\(\s*\[\s*["']([a-z-]+)["']""", text):
        mod = f"fluxcal.service.wiring.commands.{cmd.replace('-', '_')}"
        if mod in modules:
            found.add(mod)
    return found


def test_files() -> list[Path]:
    return sorted((ROOT / "tests").glob("*/test_*.py"))


def index() -> dict[str, list[str]]:
    """module -> the test files (paths from the repository's root) that test it."""
    modules = source_modules()
    out: dict[str, list[str]] = {m: [] for m in modules}
    for t in test_files():
        for m in sorted(covered_by(t, modules)):
            out[m].append(t.relative_to(ROOT).as_posix())
    return out


def table() -> str:
    lines = ["| module | tested by |", "| --- | --- |"]
    for mod, tests in index().items():
        why = UNTESTED.get(mod)
        shown = ", ".join(f"`{t.removeprefix('tests/')}`" for t in tests[:6]) + (f" and {len(tests) - 6} more"
                                                                                if len(tests) > 6 else "")
        lines.append(f"| `{mod}` | {shown or '(' + why + ')' if why and not tests else shown} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(table())
