"""Figures in a markdown page checked against the committed JSON they come from, to the digits shown.

A check is a list of ``(template, specs)``: a piece of the page with ``{}`` where a figure stands, and for
each ``{}`` a rounding rule and a getter of the JSON value. ``mismatches`` gives one line per piece not found
exactly once in the page (a reworded sentence) and per figure that does not read as its JSON value rounded by
its rule (a figure edited by hand, or a JSON file measured again).

Rounding rules: millimetres, pixels and percentages to three significant digits, at most two decimals
(``sig``); CPU-minutes to one decimal (``d1``); frames per second and counts to whole numbers (``d0``);
ratios to two decimals (``d2``); small differences to three decimals (``d3``); signed differences with their
sign (``signed``).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable

from helpers.paths import REPO as ROOT

NUMBER = r"([-+]?\d+(?:\.\d+)?)"

Getter = Callable[[Callable[[str], dict]], float]
Figures = list[tuple[str, list[tuple[str, Getter]]]]


def sig(v: float) -> str:
    """Three significant digits, at most two decimals: 37.2457 -> 37.2, 0.2761 -> 0.28, 118.3 -> 118."""
    decimals = 2 if v == 0 else max(0, min(2, 2 - math.floor(math.log10(abs(v)))))
    return f"{v:.{decimals}f}"


RULES: dict[str, Callable[[float], str]] = {
    "sig": sig,
    "d0": lambda v: f"{v:.0f}",
    "d1": lambda v: f"{v:.1f}",
    "d2": lambda v: f"{v:.2f}",
    "d3": lambda v: f"{v:.3f}",
    "signed": lambda v: f"{v:+.2f}",
}


def value_at(data, path: str) -> float:
    for part in path.split("/"):
        data = data[int(part)] if isinstance(data, list) else data[part]
    return float(data)


def at(file: str, path: str, scale: float = 1.0) -> Getter:
    """The value at ``path`` (keys joined by ``/``, list indices as numbers) of ``file``."""
    return lambda load: scale * value_at(load(file), path)


def derived(file: str, fn: Callable[[dict], float]) -> Getter:
    """A value computed from ``file`` (a mean over seeds the file lists, a range over counts)."""
    return lambda load: fn(load(file))


def seeds_mean(model: str, key: str) -> Callable[[dict], float]:
    """The mean over its seeds of ``model``'s ``key`` in a real-recording comparison (``{"seeds": {seed:
    {model: {key: value}}}}``), for :func:`derived`."""
    return lambda d: sum(s[model][key] for s in d["seeds"].values()) / len(d["seeds"])


def pct(file: str, path: str) -> tuple[str, Getter]:
    return "sig", at(file, path, 100.0)


def mm(file: str, path: str) -> tuple[str, Getter]:
    return "sig", at(file, path)


def pattern(template: str) -> re.Pattern:
    """The template as a regex: each ``{}`` a number, any run of whitespace any run of whitespace (the README
    wraps its prose)."""
    pieces = ["".join(r"\s+" if t.isspace() else re.escape(t) for t in re.split(r"(\s+)", piece) if t)
              for piece in template.split("{}")]
    return re.compile(NUMBER.join(pieces))


def loader() -> Callable[[str], dict]:
    cache: dict[str, dict] = {}

    def load(file: str) -> dict:
        if file not in cache:
            cache[file] = json.loads((ROOT / file).read_text(encoding="utf-8"))
        return cache[file]
    return load


def mismatches(text: str, load: Callable[[str], dict], figures: Figures) -> list[str]:
    """One line per figure of ``text`` that differs from its JSON value, or per template not found exactly
    once."""
    out = []
    for template, specs in figures:
        assert template.count("{}") == len(specs), template
        found = list(pattern(template).finditer(text))
        if len(found) != 1:
            out.append(f"{len(found)} matches of {template[:70]!r}")
            continue
        for shown, (rule, get) in zip(found[0].groups(), specs):
            want = RULES[rule](get(load))
            if shown != want:
                out.append(f"{shown} in {template[:70]!r} should read {want}")
    return out


def page_mismatches(pages: dict[str, Figures], load: Callable[[str], dict]) -> dict[str, list[str]]:
    """:func:`mismatches` of each page (a path from the repository's root) with its figures, by page."""
    return {page: mismatches((ROOT / page).read_text(encoding="utf-8"), load, figures)
            for page, figures in pages.items()}
