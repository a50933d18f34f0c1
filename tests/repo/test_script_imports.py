"""The Python that the shell scripts run inline (heredocs) imports names that exist: a module moved or a
helper renamed shows up here, not as a script that fails on a user's machine (scripts/loose-ends.sh is not
part of the test run)."""

from __future__ import annotations

import importlib
import re

from helpers.paths import REPO

FROM_IMPORT = re.compile(r"^from ((?:s3k|helpers)(?:\.\w+)*) import ([\w, ]+)$", re.M)


def _imports() -> list[tuple[str, str, list[str]]]:
    found = []
    for script in sorted(REPO.joinpath("scripts").rglob("*.sh")):
        for module, names in FROM_IMPORT.findall(script.read_text(encoding="utf-8")):
            found.append((script.relative_to(REPO).as_posix(), module,
                          [n.strip() for n in names.split(",") if n.strip()]))
    return found


def test_the_scripts_inline_imports_are_found():
    assert any(module.startswith("helpers") for _, module, _ in _imports())  # the pattern reads them


def test_every_name_a_script_imports_exists():
    missing = []
    for script, module, names in _imports():
        try:
            mod = importlib.import_module(module)
        except ImportError as e:
            missing.append(f"{script}: {module} ({e})")
            continue
        missing += [f"{script}: {module}.{n}" for n in names if not hasattr(mod, n)]
    assert missing == []


def test_no_script_imports_a_test_module():
    """Test modules live in folders and may be renamed: a script's set-up comes from tests/helpers."""
    pattern = re.compile(r"^\s*(?:from|import) (test_\w+)", re.M)
    bad = [f"{p.relative_to(REPO).as_posix()}: {m}" for p in sorted(REPO.joinpath("scripts").rglob("*.sh"))
           for m in pattern.findall(p.read_text(encoding="utf-8"))]
    assert bad == []
