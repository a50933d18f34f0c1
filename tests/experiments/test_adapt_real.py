"""benchmarks/adapt_real.py and s3k.experiments.adapt: the adapting copy of a dataset, and one round of
fine-tunes scored end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.paths import REPO as ROOT
from helpers.synthetic_rig import CAMERAS, KEYPOINTS, _add_frame, make_dataset, rig

from s3k.data import Dataset
from s3k.experiments.adapt import held_out_as_unlabelled


def _labelled_test_frames(path: Path, size: int = 32) -> Path:
    """The dots dataset with labels on its test frames too (the reference the benchmark scores against)."""
    from s3k.data import DatasetWriter

    rng, cal = np.random.default_rng(0), rig(size)
    with DatasetWriter(path, KEYPOINTS, CAMERAS, (size, size), "m", calibration=cal) as w:
        for fid, split in enumerate(["labelled"] * 4 + ["unlabelled"] * 4 + ["test"] * 3):
            _add_frame(w, fid, split, cal, size, rng, label_test=True)
    return path


def test_the_adapting_copy_turns_test_frames_unlabelled_and_keeps_the_rest(tmp_path: Path):
    data = make_dataset(tmp_path / "ds", size=32, labelled=3, unlabelled=4, test=2)
    copy = held_out_as_unlabelled(data, tmp_path / "adapt")
    a, b = Dataset.open(data, cache="none"), Dataset.open(copy, cache="none")
    assert b.frames("test").size == 0
    assert sorted(b.frames("unlabelled").tolist()) == sorted(
        a.frames("unlabelled").tolist() + a.frames("test").tolist())
    assert b.frames("labelled").tolist() == a.frames("labelled").tolist()
    ids = a.frames("test")
    assert np.array_equal(a.images(ids), b.images(ids))
    assert (data / "frames.csv").read_text() != (copy / "frames.csv").read_text()
    assert held_out_as_unlabelled(data, tmp_path / "adapt") == copy  # made once


@pytest.mark.slow  # a training and four fine-tunes in subprocesses: about 50 s on 2 busy cores
def test_one_round_fine_tunes_both_arms_and_scores_them(tmp_path: Path):
    data = _labelled_test_frames(tmp_path / "work" / "crop")
    run = tmp_path / "work" / "runs" / "s3k-seed0"
    train = [sys.executable, "-m", "s3k.cli", "train", str(data), "--out", str(run), "--steps", "3",
             "--channels", "8,16", "--res-blocks", "1", "--batch-labelled", "2", "--batch-unlabelled", "2",
             "--warmup-steps", "0", "--ramp-steps", "1", "--threads", "1", "--no-progress"]
    subprocess.run(train, check=True, cwd=ROOT, capture_output=True)
    out = tmp_path / "adapt.json"
    proc = subprocess.run([sys.executable, "benchmarks/adapt_real.py", "--work", str(tmp_path / "work"),
                           "--seeds", "0", "1", "--steps", "2", "--out", str(out)], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    assert list(result["seeds"]) == ["0"]  # seed 1 has no run: skipped
    assert "seed 1" in proc.stdout and "skipped" in proc.stdout
    for arm in ("adapted", "control"):
        assert (tmp_path / "work" / "runs" / f"s3k-seed0-{arm}2" / "model.pt").is_file()
    block = result["seeds"]["0"]["test_block"]
    assert block["adapted_minus_run"]["points"] > 0
    assert np.isfinite(block["adapted_minus_control"]["mean_diff_mm"])
