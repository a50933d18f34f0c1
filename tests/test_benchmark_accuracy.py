"""benchmarks/accuracy.py --labels-only-from: the renders and labels-only runs of an earlier working folder
are linked, not made again, and an unfinished run is refused."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks are scripts beside s3k

from benchmarks.accuracy import reuse_labels_only  # noqa: E402


def test_labels_only_runs_are_linked_from_an_earlier_working_folder(tmp_path):
    args = SimpleNamespace(scene="box", render=384, passes=2)
    old, new = tmp_path / "old", tmp_path / "new"
    for s in (0, 1):
        (old / f"box384-seed{s}").mkdir(parents=True)
        (old / f"labels_only-seed{s}").mkdir()
        (old / f"labels_only-seed{s}" / "two_pass.json").write_text("{}")
        (old / f"labels_only-seed{s}-cpu.json").write_text('{"cpu_minutes": 1.0}')
        (old / f"s3k-seed{s}").mkdir()
    new.mkdir()
    reuse_labels_only(old, new, [0, 1], args)
    linked = sorted(p.name for p in new.iterdir())
    assert linked == ["box384-seed0", "box384-seed1", "labels_only-seed0", "labels_only-seed0-cpu.json",
                      "labels_only-seed1", "labels_only-seed1-cpu.json"]  # no S3K run, no missing record
    assert (new / "labels_only-seed1").resolve() == (old / "labels_only-seed1").resolve()
    (old / "labels_only-seed2").mkdir()
    with pytest.raises(SystemExit, match="labels_only-seed2"):
        reuse_labels_only(old, new, [2], args)
