"""The README's command blocks marked cheap run as written.

A line ``<!-- cheap -->`` immediately before a fenced block of shell commands (```` ```bash ````, ``sh``,
``shell`` or ``console``) marks it: the block runs, as one bash script with ``set -euo pipefail``, in a
temporary working directory where ``s3k`` is this checkout's command (and ``python`` the Python running the
tests), and must exit with status 0. In a ``console`` block the lines that start with ``$ `` are the commands
and the others their output. Mark only blocks that run in well under a minute on a 2-core CPU, without a
network, and that need no file of the repository.

The README read is ``$S3K_README`` when set (to try a draft), else the repository's README.md.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers.paths import REPO as ROOT

MARK = "<!-- cheap -->"
FENCE = re.compile(r"^(?P<fence>`{3,}|~{3,})\s*(?P<lang>[A-Za-z0-9_+-]*)")
SHELLS = ("bash", "sh", "shell", "console")
TIMEOUT_S = 300


@dataclass(frozen=True)
class Block:
    line: int  # 1-based line of the opening fence
    lang: str
    commands: str  # the script that runs

    def __str__(self) -> str:
        return f"line {self.line} (```{self.lang})"


def readme_path() -> Path:
    return Path(os.environ.get("S3K_README") or ROOT / "README.md")


def marked_blocks(text: str) -> tuple[list[Block], list[str]]:
    """The blocks marked cheap in the Markdown ``text``, and the problems of marks that mark no shell block
    (a mark not followed by a fence, or followed by one of another language, or a block never closed)."""
    lines = text.splitlines()
    blocks: list[Block] = []
    problems: list[str] = []
    for i, line in enumerate(lines):
        if line.strip() != MARK:
            continue
        opening = FENCE.match(lines[i + 1].strip()) if i + 1 < len(lines) else None
        if opening is None:
            problems.append(f"line {i + 1}: {MARK} is not immediately followed by a fenced code block")
            continue
        lang = opening["lang"].lower()
        if lang not in SHELLS:
            problems.append(f"line {i + 2}: {MARK} marks a ```{lang} block; only {', '.join(SHELLS)} run")
            continue
        fence = opening["fence"]
        end = next((j for j in range(i + 2, len(lines)) if lines[j].strip().startswith(fence)
                    and not lines[j].strip().strip(fence[0])), None)
        if end is None:
            problems.append(f"line {i + 2}: the block marked {MARK} is never closed")
            continue
        body = lines[i + 2:end]
        if lang == "console":
            body = [b.strip()[2:] for b in body if b.strip().startswith("$ ")]
        commands = [b for b in body if b.strip() and not b.strip().startswith("#")]
        if not commands:
            problems.append(f"line {i + 2}: the block marked {MARK} holds no command")
            continue
        blocks.append(Block(i + 2, lang, "\n".join(commands) + "\n"))
    return blocks, problems


def run_block(block: Block, workdir: Path) -> subprocess.CompletedProcess:
    """Run ``block`` in ``workdir`` with ``s3k`` (and ``python``) resolving to this checkout's code."""
    bin_dir = workdir / ".bin"
    bin_dir.mkdir()
    for name, target in (("s3k", f'"{sys.executable}" -m s3k.cli'), ("python", f'"{sys.executable}"'),
                         ("python3", f'"{sys.executable}"')):
        shim = bin_dir / name
        shim.write_text(f'#!/bin/sh\nexec {target} "$@"\n')
        shim.chmod(0o755)
    env = dict(os.environ)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    script = workdir / ".block.sh"
    script.write_text(block.commands)
    return subprocess.run(["bash", "-euo", "pipefail", str(script)], cwd=workdir, env=env, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=TIMEOUT_S)


BLOCKS, PROBLEMS = marked_blocks(readme_path().read_text())


def test_the_readme_marks_cheap_command_blocks():
    assert PROBLEMS == []
    assert BLOCKS, (f"{readme_path()}: no command block is marked {MARK!r}, so no README command is run; "
                    "put the mark on the line before the cheap ```bash blocks")


@pytest.mark.parametrize("block", BLOCKS, ids=str)
def test_a_cheap_block_runs(block, tmp_path):
    done = run_block(block, tmp_path)
    assert done.returncode == 0, (f"{readme_path()} {block} exited with status {done.returncode}:\n"
                                  f"{block.commands}\n--- output ---\n{done.stdout}")


SAMPLE = """# Title

<!-- cheap -->
```bash
# a comment
s3k --version

s3k validate --help | head -1
```

```bash
s3k demo   # not marked
```

<!-- cheap -->
```console
$ s3k --help
usage: s3k ...
```

<!-- cheap -->
```python
print("not a shell")
```

<!-- cheap -->

```bash
s3k --help
```
"""


def test_marks_are_read_as_the_convention_says():
    blocks, problems = marked_blocks(SAMPLE)
    assert [(b.line, b.lang, b.commands) for b in blocks] == [
        (4, "bash", "s3k --version\ns3k validate --help | head -1\n"), (16, "console", "s3k --help\n")]
    assert len(problems) == 2
    assert "line 22" in problems[0] and "python" in problems[0]
    assert "line 26" in problems[1] and "not immediately followed" in problems[1]


def test_a_block_runs_this_checkout_and_fails_on_a_failing_line(tmp_path):
    blocks, _ = marked_blocks(SAMPLE)
    for name in ("ok", "where", "bad"):
        (tmp_path / name).mkdir()
    done = run_block(blocks[0], tmp_path / "ok")
    assert done.returncode == 0, done.stdout
    assert done.stdout.splitlines()[1].startswith("usage: s3k validate")
    where = run_block(Block(1, "bash", "s3k --version\npython -c 'import s3k; print(s3k.__file__)'\n"),
                      tmp_path / "where")
    assert where.stdout.splitlines()[1] == str(ROOT / "s3k" / "__init__.py"), where.stdout
    failed = run_block(Block(1, "bash", "s3k validate no-such-dataset\necho not reached\n"), tmp_path / "bad")
    assert failed.returncode != 0 and "not reached" not in failed.stdout
