"""The README front page and the documentation pages link only to files that exist, the README
stays a front page, and the site's home page shows the README's tested quickstart."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PAGES = [README, *sorted(DOCS.rglob("*.md"))]

# [text](target) and ![alt](target), the target up to the first space or closing bracket
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^```.*?^```", flags=re.S | re.M)
CODE = re.compile(r"`[^`\n]*`")


def relative_links(path: Path) -> list[str]:
    text = CODE.sub("", FENCE.sub("", path.read_text()))
    return [
        t
        for t in LINK.findall(text)
        if not re.match(r"[a-z][a-z0-9+.-]*:", t, flags=re.I) and not t.startswith("#")
    ]


def test_link_pattern():
    page = "[a](x.md) ![b](../figures/y.png) [c](z.md#part) [d](https://e.org) `[f](g.md)`"
    assert LINK.findall(CODE.sub("", page)) == [
        "x.md",
        "../figures/y.png",
        "z.md#part",
        "https://e.org",
    ]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_to_files(page):
    missing = []
    for target in relative_links(page):
        file = target.split("#", 1)[0]
        if not (page.parent / file).resolve().exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_markdown_renders_in_mkdocs_as_on_github(page):
    """MkDocs' Markdown nests list items by 4 spaces (GitHub: 2) and continues a paragraph
    into a list or table that has no blank line before it (GitHub starts the list)."""
    marker = re.compile(r"^( *)([-*+]|\d+\.) ")
    bad, fence, prev = [], False, ""
    for number, line in enumerate(page.read_text().split("\n"), 1):
        if line.startswith("```"):
            fence = not fence
        elif not fence:
            m = marker.match(line)
            if m and len(m[1]) % 4:
                bad.append((number, "nested list item not indented by a multiple of 4 spaces"))
            if line.startswith("|") and prev.strip() and not prev.startswith("|"):
                bad.append((number, "table without a blank line before it"))
            if m and not m[1] and prev.strip() and not marker.match(prev) and prev[:1] != " ":
                bad.append((number, "list without a blank line before it"))
        prev = line
    assert not bad, f"{page.relative_to(ROOT)}: {bad}"


def test_readme_is_a_front_page():
    n = len(README.read_text().splitlines())
    assert n <= 320, f"README.md has {n} lines; move the details into docs/"


def test_readme_links_every_guide_and_results_page():
    linked = {(README.parent / t.split("#", 1)[0]).resolve() for t in relative_links(README)}
    pages = sorted((DOCS / "guide").glob("*.md")) + sorted((DOCS / "results").glob("*.md"))
    assert pages
    assert not [p.name for p in pages if p.resolve() not in linked]


def test_home_page_shows_the_tested_quickstart():
    def blocks(p: Path) -> list[str]:
        return re.findall(r"```python\n(.*?)```", p.read_text(), flags=re.S)

    assert blocks(DOCS / "index.md") == blocks(README)
