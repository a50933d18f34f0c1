"""The documentation's relative links point at files that exist in the repository (a results file renamed
or never committed shows up here, not as a dead link on a reader's screen)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)\s]*)?\)")


def _relative_links(text: str) -> list[str]:
    return [t for t in LINK.findall(text) if "://" not in t and not t.startswith("mailto:")]


def test_the_link_pattern_finds_relative_targets_only():
    text = "[a](docs/x.md#part) [b](https://example.org/y) [c](results/z.json) [d](#anchor)"
    assert _relative_links(text) == ["docs/x.md", "results/z.json"]


def test_every_relative_link_in_the_docs_exists():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    assert len(pages) > 5
    dead = [f"{page.relative_to(ROOT)}: {target}" for page in pages
            for target in _relative_links(page.read_text(encoding="utf-8"))
            if not (page.parent / target).exists()]
    assert dead == []
