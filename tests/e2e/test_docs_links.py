"""The README and the manual hold together: every relative link and image in README.md, docs/ and
recordings/README.md points at a file of the repository (and at a heading of it where it names one), every
`docs/*.md` they mention exists, and the README opens with the two commands, the second the one .ci/run runs."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), ROOT / "recordings" / "README.md"]
INLINE = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")     # [text](target), ![alt](target)
DEFINITION = re.compile(r"^\[[^\]]+\]:\s+(\S+)", re.M)                   # [key]: target


def prose(text: str) -> str:
    """The text without fenced or indented code blocks and without inline code."""
    out, fenced, prev_blank = [], False, True
    for line in text.split("\n"):
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced or (line.startswith("    ") and prev_blank and not line.lstrip().startswith(("-", "*", "|"))):
            continue                                    # an indented code block starts after a blank line
        prev_blank = not line.strip()
        out.append(re.sub(r"`[^`]*`", "", line))
    return "\n".join(out)


def slugs(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation dropped, spaces to hyphens, -1, -2 ..."""
    seen: dict[str, int] = {}
    out = set()
    for line in prose(page.read_text()).split("\n"):
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = re.sub(r"[^\w\- ]", "", m.group(1).replace("`", "").lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def links(page: Path) -> list[str]:
    text = prose(page.read_text())
    return INLINE.findall(text) + DEFINITION.findall(text)


def test_every_relative_link_points_at_a_file_and_heading_that_exist():
    broken = []
    for page in PAGES:
        for target in links(page):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):                  # http:, https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(ROOT)}: {target}"
            if not dest.exists():
                broken.append(f"{where}: no such file")
            elif anchor and dest.suffix == ".md" and anchor not in slugs(dest):
                broken.append(f"{where}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert broken == []


def test_the_link_check_sees_links_and_headings():
    """The checker itself, on the pages it checks: it finds their links, resolves an anchor, refuses a wrong one."""
    assert sum(len(links(p)) for p in PAGES) > 100
    assert "the-catalogue" in slugs(ROOT / "docs" / "effects.md")
    assert "twofluxgate-paper-000" in slugs(ROOT / "docs" / "references.md")
    assert "no-such-heading" not in slugs(ROOT / "docs" / "effects.md")
    assert links(ROOT / "docs" / "references.md")[-1] == "#twostep-paper-004"


def test_every_docs_page_mentioned_exists():
    missing = []
    for page in PAGES:
        for name in re.findall(r"(?<![\w/.-])docs/([\w./-]+\.md)\b", page.read_text()):
            if not (ROOT / "docs" / name).exists():
                missing.append(f"{page.relative_to(ROOT)}: docs/{name}")
    assert missing == []


def test_the_readme_opens_with_the_two_commands_and_ci_runs_the_second_verbatim():
    readme = (ROOT / "README.md").read_text()
    commands = re.findall(r"^ {4}(\S.*)$", readme, flags=re.M)
    run, tests = commands[0], commands[1]
    assert run == ("python3 -m venv .venv && .venv/bin/pip install -e . && "
                   ".venv/bin/fluxcal run --config configs/sim-gradiometer.toml --dashboard")
    assert tests == "python3 -m venv .venv && .venv/bin/pip install -e '.[test]' && .venv/bin/python -m pytest -q"
    assert tests in (ROOT / ".ci" / "run").read_text().split("\n")
    assert readme.index(run) < readme.index("##")                         # before any section
    assert len(readme.split("\n")) <= 160                                   # a front door, the manual in docs/
