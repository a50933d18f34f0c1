"""Every default the README and docs state for a command's option is the default that command has.

A sentence such as ``--filter-gate`` standard deviations (default 4), ```--spacing N`, default 2`` or
``--coarse-size`` px, 96 by default names an option and its default. The option's default is read from the
commands' own parsers: the argparse default where it is a value, else the default that the option's ``--help``
text states (the configuration options, whose argparse default is ``SUPPRESS``, show their field's default
there). A stated default must equal the default of at least one command that has the option; options no
command has (a benchmark script's) are not checked here.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
from helpers.paths import REPO as ROOT

from s3k.cli import COMMANDS, command_parser

DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SKIP = {"accuracy-log.md"}  # the dated log quotes the defaults of its day

OPTION = r"`(?P<opt>--[a-z0-9][a-z0-9-]*)(?:[ =][^`]*)?`"
VALUE = r"(?P<val>-?\d+(?:\.\d+)?(?:e-?\d+)?|`[^`\s]+`)"
STATED = [
    re.compile(OPTION + r"[^`\n]{0,60}?\(default:? " + VALUE + r"[,;) ]"),
    re.compile(OPTION + r"[^`\n(|.;]{0,40}?,? default:? " + VALUE + r"[,;). ]"),
    re.compile(OPTION + r"[^`\n|]{0,40}?,? " + VALUE + r" by default"),
]
HELP_DEFAULT = re.compile(r"\(default:? ([^,;)\s]+)|(\S+) by default")


def _same(a: str, b: str) -> bool:
    a, b = a.strip("`'\"."), b.strip("`'\".")
    try:
        return float(a) == float(b)
    except ValueError:
        return a == b


def command_defaults() -> dict[str, dict[str, list[str]]]:
    """``{option: {command: [default as text, ...]}}`` for every ``--option`` of every command."""
    out: dict[str, dict[str, list[str]]] = {}
    for name in COMMANDS:
        for action in command_parser(name)._actions:
            values: list[str] = []
            if action.default not in (None, argparse.SUPPRESS) and not isinstance(action.default, bool):
                d = action.default
                values.append(",".join(map(str, d)) if isinstance(d, (tuple, list)) else str(d))
            for m in HELP_DEFAULT.finditer(action.help or ""):
                values.append(m.group(1) or m.group(2))
            for opt in action.option_strings:
                if opt.startswith("--"):
                    out.setdefault(opt, {}).setdefault(name, []).extend(values)
    return out


def stated_defaults(text: str) -> list[tuple[int, str, str]]:
    """``(line, option, value)`` for each default the Markdown ``text`` states."""
    found = set()
    for pattern in STATED:
        for m in pattern.finditer(text):
            found.add((text.count("\n", 0, m.start()) + 1, m["opt"], m["val"]))
    return sorted(found)


def test_the_patterns_read_the_ways_docs_state_defaults():
    text = ("`--filter-gate` standard deviations (default 4). `--spacing N`, default 2, then "
            "`--coarse-size` px, 96 by default; `--norm` (default `batch`); `--worst` apart, default 3.")
    assert [(o, v) for _, o, v in stated_defaults(text)] == [
        ("--coarse-size", "96"), ("--filter-gate", "4"), ("--norm", "`batch`"), ("--spacing", "2"),
        ("--worst", "3")]


@pytest.mark.parametrize("doc", [d for d in DOCS if d.name not in SKIP], ids=lambda d: d.name)
def test_stated_defaults_match_help(doc: Path):
    defaults = command_defaults()
    wrong = []
    for line, opt, value in stated_defaults(doc.read_text(encoding="utf-8")):
        per_command = defaults.get(opt)
        if not per_command:
            continue
        if not any(_same(value, d) for ds in per_command.values() for d in ds):
            wrong.append(f"{doc.name}:{line}: {opt} stated default {value}, --help: {per_command}")
    assert not wrong, "\n".join(wrong)
