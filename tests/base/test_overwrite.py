"""``--overwrite`` of s3k import and s3k simulate replaces a dataset, never a folder s3k did not make; the
replacement is all or nothing, and what a killed import or simulation left is cleaned up (or the dataset
put back) by the next call."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers.recordings import run_import

from s3k import cli
from s3k.base.outputs import UNFINISHED_MARKER, check_replaceable


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _thesis(folder: Path) -> dict[str, str]:
    (folder / "chapters").mkdir(parents=True)
    (folder / "thesis.txt").write_text("four years of work\n")
    (folder / "chapters" / "one.txt").write_text("chapter one\n")
    return _tree(folder)


def _tree(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): p.read_text() for p in sorted(folder.rglob("*")) if p.is_file()}


def _hidden(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def test_import_overwrite_refuses_a_folder_s3k_did_not_make(import_recording, tmp_path, capsys):
    out = tmp_path / "mine"
    before = _thesis(out)
    assert run_import(import_recording, out, "--overwrite") == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a dataset" in err and str(out) in err
    assert _tree(out) == before and _hidden(tmp_path) == []


def test_simulate_overwrite_refuses_a_folder_s3k_did_not_make(tmp_path, capsys):
    out = tmp_path / "mine"
    before = _thesis(out)
    assert cli.main(["simulate", "box", "--out", str(out), "--overwrite", "--size", "32", "--labelled", "1",
                     "--unlabelled", "0", "--test", "0", "--workers", "1", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a dataset" in err
    assert _tree(out) == before and _hidden(tmp_path) == []


def test_import_overwrite_replaces_a_dataset_whole(import_recording, tmp_path):
    out = tmp_path / "ds"
    assert run_import(import_recording, out, "--labelled", "2") == 0
    assert run_import(import_recording, out, "--labelled", "3", "--overwrite") == 0
    assert (out / "s3k.json").is_file() and not (out / UNFINISHED_MARKER).exists()
    assert _hidden(tmp_path) == []


def test_an_import_killed_between_its_renames_is_restored(import_recording, tmp_path, capsys):
    out = tmp_path / "ds"
    assert run_import(import_recording, out) == 0
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    # What a kill between "dataset -> aside" and "new -> dataset" leaves: no --out, both datasets hidden.
    pid = _dead_pid()
    os.replace(out, tmp_path / f".ds.replaced-{pid}")
    (tmp_path / f".ds.writing-{pid}" / "images").mkdir(parents=True)
    # the old dataset is back, and --overwrite is needed to replace it
    assert run_import(import_recording, out) == 1
    err = capsys.readouterr().err
    assert "restored" in err and "pass --overwrite" in err
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert _hidden(tmp_path) == []


def test_folders_left_by_killed_imports_are_removed(import_recording, tmp_path):
    out = tmp_path / "ds"
    pid = _dead_pid()
    for name in (f".ds.importing-{pid}", f".ds.writing-{pid}"):  # an earlier version's name and this one's
        (tmp_path / name / "images" / "north").mkdir(parents=True)
    (tmp_path / f".ds.writing-{os.getpid()}x").mkdir()  # not one of ours: kept
    assert run_import(import_recording, out) == 0
    assert _hidden(tmp_path) == [f".ds.writing-{os.getpid()}x"]


def test_a_live_writer_is_left_alone(tmp_path):
    busy = tmp_path / f".ds.writing-{os.getpid()}"
    busy.mkdir()
    check_replaceable(tmp_path / "ds", overwrite=False)
    assert busy.is_dir()


def test_a_killed_simulation_leaves_its_out_alone_and_the_rerun_works(tmp_path):
    out = tmp_path / "ds"
    argv = [sys.executable, "-m", "s3k.cli", "simulate", "box", "--out", str(out), "--size", "32",
            "--labelled", "2", "--unlabelled", "400", "--test", "0", "--workers", "1", "--no-progress"]
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    images = tmp_path / f".ds.writing-{proc.pid}" / "images" / "cam0"
    try:
        while proc.poll() is None and not (images.is_dir() and len(list(images.iterdir())) >= 2):
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert images.is_dir() and not out.exists()  # killed while writing beside --out
    assert cli.main(["simulate", "box", "--out", str(out), "--size", "32", "--labelled", "2", "--unlabelled",
                     "0", "--test", "0", "--workers", "1", "--no-progress"]) == 0
    assert (out / "s3k.json").is_file() and _hidden(tmp_path) == []


def test_the_dataset_writer_refuses_to_delete_a_foreign_folder(tmp_path):
    from s3k.base.errors import UserError
    from s3k.data import DatasetWriter

    before = _thesis(tmp_path / "mine")
    with pytest.raises(UserError, match="not a dataset"):
        DatasetWriter(tmp_path / "mine", ["a"], ["cam0", "cam1"], (16, 16), overwrite=True)
    assert _tree(tmp_path / "mine") == before
