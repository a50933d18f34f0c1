"""``s3k.train(...)`` trains however often it is read and whatever of the package was imported before: the
name is both the package ``s3k.train`` and its :func:`~s3k.train.entry.train`."""

from __future__ import annotations

import subprocess
import sys

from helpers.paths import REPO

PROGRAM = """
import s3k
from s3k.base.errors import UserError
first = s3k.train
second = s3k.train  # the package bound by the first read's import
import s3k.train.presets
third = s3k.train
for f in (first, second, third):
    try:
        f({data!r}, {run!r}, s3k.TrainConfig())
    except UserError as e:
        print("refused:", e)
print(type(s3k.train.presets.preset("box-fast")).__name__)
"""


def test_s3k_train_stays_the_training_after_its_modules_are_imported(tmp_path):
    code = PROGRAM.format(data=str(tmp_path / "missing"), run=str(tmp_path / "run"))
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    lines = out.stdout.splitlines()
    assert len(lines) == 4, out.stdout + out.stderr
    assert all(line.startswith("refused:") and "missing" in line for line in lines[:3]), lines
    assert lines[3] == "TrainConfig"
