"""The documentation's relative links point at files that exist in the repository (a results file renamed
or never committed shows up here, not as a dead link on a reader's screen)."""

from __future__ import annotations

import re
from pathlib import Path

from helpers.paths import REPO as ROOT

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


HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$")
ANCHOR_LINK = re.compile(r"\]\(([^)\s#]*)#([^)\s]+)\)")
HTML_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"")


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation other than '-' and '_' dropped, spaces to '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text only
    return re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    """The anchors of a page: its headings' (a repeated one numbered as GitHub does) and its HTML ids."""
    seen: dict[str, int] = {}
    out = set(HTML_ANCHOR.findall(page.read_text(encoding="utf-8")))
    fenced = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        m = None if fenced else HEADING.match(line)
        if m:
            slug = _slug(m.group(1))
            out.add(f"{slug}-{seen[slug]}" if slug in seen else slug)
            seen[slug] = seen.get(slug, 0) + 1
    return out


def test_the_slug_follows_githubs_rule():
    assert _slug("Where commands write (`s3k.base.outputs`)") == "where-commands-write-s3kbaseoutputs"
    assert _slug("8. S3K against labels only over seeds") == "8-s3k-against-labels-only-over-seeds"
    assert _slug("Calibrating a rig: `s3k calibrate`") == "calibrating-a-rig-s3k-calibrate"


def test_every_anchor_in_the_docs_names_a_heading_of_its_page():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    dead = []
    for page in pages:
        for target, anchor in ANCHOR_LINK.findall(page.read_text(encoding="utf-8")):
            if "://" in target or (target and not target.endswith(".md")):
                continue
            linked = page if not target else page.parent / target
            if linked.exists() and anchor not in _anchors(linked):
                dead.append(f"{page.relative_to(ROOT)}: {target}#{anchor}")
    assert dead == []
