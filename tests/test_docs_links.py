"""Every relative link and image in README.md, docs/ and notebooks/README.md points at a file
of the repository (a moved or renamed page breaks this test, not the reader)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", ROOT / "notebooks" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _targets(text: str) -> list[str]:
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # code blocks are not links
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+:", t) and not t.startswith("#")]


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_relative_links_resolve(page: Path):
    missing = [t for t in _targets(page.read_text(encoding="utf-8")) if not (page.parent / t.split("#")[0]).exists()]
    assert not missing, f"{page.relative_to(ROOT)}: broken links {missing}"


def test_link_checker_sees_links_and_ignores_code_and_urls():
    text = "see [a](docs/a.md) and ![p](img/p.png)\n```\n[x](nope.md)\n```\n[w](https://x.org) [s](#sec)"
    assert _targets(text) == ["docs/a.md", "img/p.png"]


def test_readme_picture_is_a_png():
    png = ROOT / "docs" / "img" / "fl_thermal_tail.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
