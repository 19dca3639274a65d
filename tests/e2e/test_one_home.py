"""One home per input (issue 41): a source kind, its protocols, clock, simulator transports and counters are declared
once, in drivers/kinds/, and nothing else in the package lists the kinds or the transports, compares a kind with a
name, or defaults one by name; the example configurations name no list of them either; docs/sources.md shows what
the declarations say. Before, the list of kinds was written out in seven places (fluxcal.drivers.source.SOURCES,
config._SOURCE_CONFIGS, config.SOURCE_KINDS, two "allowed: ..." messages, rate_stated's tuple, the daemon's port
keys, RateCheck's kind == "can") and the transports twice."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from fluxcal.drivers.registry import kinds, markdown, transports

ROOT = Path(__file__).resolve().parents[2]
DECLARATIONS = ROOT / "drivers" / "kinds"


def _names() -> tuple[set[str], set[str]]:
    return {k.name for k in kinds()}, {t.name for _, t in transports()}


def _strings(nodes) -> list[str]:
    return [n.value for n in nodes if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def named_kinds(source: str, where: str) -> list[str]:
    """Where a piece of code names the kinds or transports: a tuple, list, set or dict's keys holding two of them, a
    string quoting two, a comparison of a kind or transport with one, or one given as the default of a kind."""
    kinds_, ways = _names()

    def many(values: list[str]) -> bool:
        return len(set(values) & kinds_) >= 2 or len(set(values) & ways) >= 2

    found = []
    for node in ast.walk(ast.parse(source)):
        line = f"{where}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and many(_strings(node.elts)):
            found.append(f"{line} lists {_strings(node.elts)}")
        elif isinstance(node, ast.Dict) and many(_strings([k for k in node.keys if k is not None])):
            found.append(f"{line} maps {_strings([k for k in node.keys if k is not None])}")
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and many(
                re.findall(r"""['"]([a-z][a-z-]*)['"]""", node.value)):
            found.append(f"{line} says {node.value[:60]!r}")
        elif isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            for side in sides:
                named = _strings(side.elts) if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else _strings([side])
                others = " ".join(ast.unparse(s) for s in sides if s is not side)
                if set(named) & (kinds_ | ways) and re.search(r"kind|transport", others):
                    found.append(f"{line} compares {ast.unparse(node)}")
        elif isinstance(node, ast.Call):
            args = _strings(node.args)
            if {"kind", "transport"} & set(args) and set(args) & (kinds_ | ways):
                found.append(f"{line} defaults {ast.unparse(node)}")
    return found


def test_no_code_names_a_kind_outside_its_declaration():
    found = []
    for top in ("drivers", "service"):
        for path in sorted((ROOT / top).rglob("*.py")):
            if DECLARATIONS not in path.parents:
                found += named_kinds(path.read_text(encoding="utf-8"), str(path.relative_to(ROOT)))
    assert found == []


def test_the_check_finds_the_lists_there_were():
    """The lines the house held before, each found."""
    before = {
        'SOURCES = {"serial": "fluxcal.drivers.serial_source:open_source", "can": "fluxcal.drivers.can_source:open_source"}': "maps",
        'SOURCE_KINDS = ("serial", "can", "sim", "replay")': "lists",
        "raise ConfigError(f\"source.kind: {kind!r} is not allowed (allowed: 'sim', 'serial', 'can', 'replay')\")":
            "says",
        'ok = src.get("kind") not in ("serial", "replay")': "compares",
        'keys = {"serial": "source.port", "can": "source.interface, source.channel"}.get(kind, "source")': "maps",
        'checked = getattr(cfg.source, "kind", "") == "can"': "compares",
        'TRANSPORTS = ("direct", "pty", "can-virtual", "slcan")': "lists",
        'if transport == "pty":\n    pass': "compares",
        'kind = str(getattr(cfg.source, "kind", "sim"))': "defaults",
    }
    for code, what in before.items():
        found = named_kinds(code, "old")
        assert any(f" {what} " in f for f in found), (code, found)
    # python-can's interface of that name is no transport of ours: not a kind's name in its place
    assert named_kinds('interface = "slcan"\nif self.interface == "slcan":\n    pass', "can_source") == []


def test_the_example_configurations_list_no_kinds():
    kinds_, ways = _names()
    for path in sorted((ROOT / "configs").glob("*.toml")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            quoted = set(re.findall(r'"([a-z][a-z-]*)"', line))
            assert len(quoted & kinds_) < 2 and len(quoted & ways) < 2, f"{path.name}:{n}: {line}"


def test_docs_sources_is_what_the_declarations_say():
    text = (ROOT / "docs" / "sources.md").read_text()
    mark = "<!-- kinds: python -m fluxcal.drivers.registry -->\n"
    start = text.index(mark) + len(mark)
    end = text.index("<!-- end of kinds -->")
    assert text[start:end] == markdown(), "run `python -m fluxcal.drivers.registry` and paste it into docs/sources.md"


def test_the_architecture_says_where_each_new_thing_goes():
    text = (ROOT / "docs" / "architecture.md").read_text()
    where = text[text.index("## Where a new thing goes"):text.index("## Longer than the limits")]
    for thing in ("A physical effect", "A source kind", "A protocol", "A simulator transport", "A sink", "A command"):
        assert where.count(f"- **{thing}") == 1, thing
    assert "drivers/kinds/" in where and "register_kind" in where and "register_protocol" in where
