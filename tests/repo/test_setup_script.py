"""``scripts/setup.sh`` (run by ``scripts/test.sh`` and ``scripts/demo.sh``) installs on a fresh checkout and
skips what is installed: a second call runs no pip install until pyproject.toml changes."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
from pathlib import Path

import pytest
from helpers.paths import REPO as ROOT

FAKE_PYTHON = """#!/usr/bin/env bash
echo "python $*" >> "$CALLS"
exit 0
"""


def _executable(path: Path, text: str) -> None:
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)


@pytest.fixture()
def checkout(tmp_path):
    """A copy of the scripts and pyproject.toml whose .venv holds a Python that records its calls (and says
    every import works), and a PATH whose apt-get and sudo record theirs."""
    repo = tmp_path / "repo"
    (repo / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "setup.sh", repo / "scripts" / "setup.sh")
    shutil.copy(ROOT / "pyproject.toml", repo / "pyproject.toml")
    bin_dir = repo / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    _executable(bin_dir / "python", FAKE_PYTHON)
    (bin_dir / "activate").write_text(f'export PATH="{bin_dir}:$PATH"\n')
    tools = tmp_path / "tools"
    tools.mkdir()
    for tool in ("apt-get", "sudo"):
        _executable(tools / tool, f'#!/usr/bin/env bash\necho "{tool} $*" >> "$CALLS"\n')
    calls = tmp_path / "calls.txt"
    env = {**os.environ, "CALLS": str(calls), "PATH": f"{tools}:{os.environ['PATH']}"}
    return repo, calls, env


def _setup(repo: Path, calls: Path, env: dict, *args: str) -> list[str]:
    calls.write_text("")
    subprocess.run(["bash", str(repo / "scripts" / "setup.sh"), *args], env=env, check=True, timeout=60)
    return [line for line in calls.read_text().splitlines() if line.startswith("python -m pip")]


def test_setup_installs_once_then_skips_until_pyproject_changes(checkout):
    repo, calls, env = checkout
    first = _setup(repo, calls, env)
    assert any("install -q -e .[dev,formats,robot,label,stream,cluster]" in c for c in first), first
    assert _setup(repo, calls, env) == []  # installed: nothing to do
    assert _setup(repo, calls, env, "--demo") == []  # the full install serves the demo
    with (repo / "pyproject.toml").open("a") as f:
        f.write("\n# changed\n")
    again = _setup(repo, calls, env)
    assert any("install -q -e .[dev,formats,robot,label,stream,cluster]" in c for c in again), again


def test_setup_for_the_demo_then_everything(checkout):
    repo, calls, env = checkout
    demo = _setup(repo, calls, env, "--demo")
    assert any(c.endswith("install -q -e .") for c in demo), demo
    assert _setup(repo, calls, env, "--demo") == []
    full = _setup(repo, calls, env)  # the demo's install lacks the extras
    assert any("[dev,formats,robot,label,stream,cluster]" in c for c in full), full
