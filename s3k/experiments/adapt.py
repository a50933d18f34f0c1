"""Adapting a trained detector to frames it never saw: a dataset's held-out frames made unlabelled frames
for a fine-tune (``benchmarks/adapt_real.py``)."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path


def held_out_as_unlabelled(data: Path, out: Path) -> Path:
    """A copy of the dataset ``data`` whose ``test`` frames are ``unlabelled`` (images linked, not copied)."""
    if (out / "s3k.json").is_file():
        return out
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for item in data.iterdir():
        if item.name in ("frames.csv", ".cache"):
            continue
        if item.is_dir():
            (tmp / item.name).symlink_to(item.resolve())
        else:
            shutil.copy2(item, tmp / item.name)
    with open(data / "frames.csv", newline="") as src, open(tmp / "frames.csv", "w", newline="") as dst:
        lines = [line for line in src if not line.startswith("#")]
        rows = list(csv.DictReader(lines))
        writer = csv.DictWriter(dst, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({**row, "split": "unlabelled" if row["split"] == "test" else row["split"]})
    tmp.rename(out)
    return out
