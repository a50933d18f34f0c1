"""Where a command may write: the one check every output goes through before any work, and replacing a
dataset folder all or nothing.

:func:`check_output` (a file) and :func:`check_output_folder` (a folder a command fills, such as a run)
refuse, naming the path and what it belongs to:

- anything inside a dataset folder (a folder holding ``s3k.json``): every later step reads a dataset's
  files, and none of s3k's outputs belongs there;
- a file a run holds (``config.json``, ``checkpoint.pt``, ``model.pt``, ``train.log``, ``tensorboard/``,
  ``progress.json``; a two-pass run's passes, crops, estimates and records); other files may sit beside
  them (``--out RUN/tracks.csv``);
- an input of this call (``--out`` naming the calibration, the CSV being converted, a video);
- an existing file, unless ``--overwrite`` is given.

A path is compared after resolving links, so a link into a dataset is refused as the dataset's file is.

A dataset folder (``s3k import``, ``s3k simulate``) is written beside ``--out`` and renamed over it when
complete (:func:`replace_folder`); ``--overwrite`` replaces only a folder s3k made
(:func:`check_replaceable`), and the next call cleans up after one that was killed (:func:`recover_folder`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path

from s3k.errors import UserError
from s3k.run_folder import RunFolder

__all__ = ["DATASET_MARKER", "RUN_NAMES", "UNFINISHED_MARKER", "check_output", "check_output_folder",
           "check_replaceable", "is_dataset", "is_run", "made_by_s3k", "recover_folder", "replace_folder"]

DATASET_MARKER = "s3k.json"
"""The file that makes a folder a dataset (``s3k.data.tables.METADATA_FILE``)."""

RUN_NAMES = frozenset(RunFolder.ONE_PASS_FILES + RunFolder.TWO_PASS_FILES)
"""Names a run folder's own files and folders take (``tests/test_outputs.py`` checks them against the
modules that write them)."""


def is_dataset(folder: Path) -> bool:
    """True when ``folder`` holds a dataset (its ``s3k.json``)."""
    return (folder / DATASET_MARKER).is_file()


def is_run(folder: Path) -> bool:
    """True when ``folder`` holds a run of ``s3k train`` (its model or checkpoint, a run's ``config.json``)
    or of ``s3k train --two-pass`` (``two_pass.json``, or a coarse pass)."""
    run = RunFolder(folder)
    if any(p.is_file() for p in (run.model, run.checkpoint, run.two_pass_file)):
        return True
    if run.coarse.path.is_dir() and is_run(run.coarse.path):
        return True
    config = run.config_file
    if not config.is_file():
        return False
    try:
        doc = json.loads(config.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and "config" in doc and "meta" in doc


def _inside(target: Path, option: str, shown: Path, runs: bool) -> None:
    """Refuse ``target`` inside a dataset (``target`` itself included) or, with ``runs``, a run's own file."""
    for folder in (target, *target.parents):
        if is_dataset(folder):
            what = "is the dataset" if folder == target else f"is inside the dataset {folder}"
            raise UserError(f"{option} {shown} {what} (a file of the dataset is never replaced)",
                            hint=f"give {option} a path outside it")
        if runs and folder != target and is_run(folder):
            first = target.relative_to(folder).parts[0]
            if first in RUN_NAMES:
                raise UserError(f"{option} {shown} is a file of the run {folder} ({first}); a run's files "
                                "are not replaced", hint=f"give {option} another name")


def _check_inputs(target: Path, inputs: Mapping[str, object], option: str, shown: Path) -> None:
    for name, given in inputs.items():
        if given is None:
            continue
        for one in given if isinstance(given, (list, tuple, set)) else [given]:
            if Path(str(one)).resolve() == target:
                raise UserError(f"{option} {shown} is this command's input ({name} {one}); it would be "
                                "replaced by the output", hint=f"give {option} another path")


def check_output(path: str | Path, overwrite: bool, inputs: Mapping[str, object] | None = None,
                 option: str = "--out") -> Path:
    """Refuse an output file that is an input of this call, inside a dataset, a run's own file, a folder,
    or (without ``overwrite``) an existing file; returns ``path`` as a ``Path``.

    Args:
        path: the file to write.
        overwrite: whether an existing file may be replaced (``--overwrite``).
        inputs: ``{option: path or paths}`` the call reads, e.g. ``{"--calibration": "calib.toml"}``.
        option: the option that names ``path``, for the message.

    Raises:
        UserError: naming the path, what it is, and the option that fixes it.
    """
    path = Path(path)
    target = path.resolve()
    _inside(target, option, path, runs=True)
    _check_inputs(target, inputs or {}, option, path)
    if path.is_dir():
        raise UserError(f"{option} {path} is a folder", hint="give a file name")
    if path.exists() and not overwrite:
        raise UserError(f"{option} {path} exists", hint="pass --overwrite to replace it")
    return path


def check_output_folder(path: str | Path, inputs: Mapping[str, object] | None = None,
                        option: str = "--out", runs: bool = True) -> Path:
    """Refuse an output folder that is an input of this call, a dataset or inside one, or (with ``runs``)
    inside a run's own files; whether an existing folder may be filled or replaced is the command's to say.
    A two-pass run trains its passes inside itself: it checks them with ``runs=False``."""
    path = Path(path)
    target = path.resolve()
    _inside(target, option, path, runs=runs)
    _check_inputs(target, inputs or {}, option, path)
    return path


# ------------------------------------------------------------------------------------------------------------
# Folders s3k fills as a whole (a dataset from s3k import or s3k simulate): written beside the target and
# renamed over it, replaced only when s3k made what is there.

UNFINISHED_MARKER = ".s3k-unfinished"
"""A dataset folder being written holds this file until its ``s3k.json`` is written (``DatasetWriter``)."""

_HIDDEN = re.compile(r"\.(?P<name>.+)\.(?P<kind>writing|importing|replaced)-(?P<pid>\d+)")


def made_by_s3k(folder: Path) -> bool:
    """True when ``folder`` is a dataset or a dataset s3k was writing (its marker files)."""
    return is_dataset(folder) or (folder / UNFINISHED_MARKER).is_file()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def recover_folder(out: Path) -> list[str]:
    """Finish what a killed writer of ``out`` left beside it; returns what was done, in words.

    A folder being written (``.OUT.writing-PID``) whose process is gone is removed; a dataset moved aside to
    be replaced (``.OUT.replaced-PID``) is put back when ``OUT`` is missing (the process died between its two
    renames), else removed (the new dataset is in place).
    """
    done: list[str] = []
    if not out.parent.is_dir():
        return done
    for entry in sorted(out.parent.iterdir(), key=lambda p: p.name):
        m = _HIDDEN.fullmatch(entry.name)
        if not m or m["name"] != out.name or not entry.is_dir() or _alive(int(m["pid"])):
            continue
        if m["kind"] == "replaced" and not out.exists() and not out.is_symlink():
            os.replace(entry, out)
            done.append(f"restored {out} from {entry.name}, left by an interrupted replacement")
        else:
            shutil.rmtree(entry, ignore_errors=True)
            done.append(f"removed {entry.name}, left by an interrupted run")
    return done


def check_replaceable(out: str | Path, overwrite: bool, inputs: Mapping[str, object] | None = None,
                      option: str = "--out") -> Path:
    """Refuse before any work an ``out`` folder that a dataset may not be written to: a file, inside a
    dataset, a non-empty folder without ``overwrite``, or one s3k did not make (it holds no ``s3k.json``):
    ``--overwrite`` replaces a dataset, never someone's other files. Leftovers of a killed writer of
    ``out`` are cleaned up first (:func:`recover_folder`)."""
    out = Path(out)
    for line in recover_folder(out):
        print(f"note: {line}", file=sys.stderr)
    target = out.resolve()
    for folder in target.parents:
        if is_dataset(folder):
            raise UserError(f"{option} {out} is inside the dataset {folder}", hint=f"give {option} a path "
                                                                                   "outside it")
    if out.exists() and not out.is_dir():
        raise UserError(f"{option} {out} is a file, not a dataset folder", hint=f"give {option} a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise UserError(f"{option} {out}: folder exists and is not empty",
                            hint="pass --overwrite to replace it")
        if not made_by_s3k(out):
            raise UserError(f"{option} {out} is not a dataset (no {DATASET_MARKER}): --overwrite replaces "
                            "only a folder s3k made", hint=f"give {option} another folder, or empty it first")
        for name, given in (inputs or {}).items():
            for one in given if isinstance(given, (list, tuple, set)) else [given]:
                if one is not None and Path(str(one)).resolve().is_relative_to(target):
                    raise UserError(f"{option} {out} holds this command's input ({name} {one}); replacing "
                                    "it would delete it", hint=f"give {option} another folder")
    return out


@contextlib.contextmanager
def replace_folder(out: str | Path, overwrite: bool, option: str = "--out") -> Iterator[Path]:
    """Yield a hidden folder beside ``out`` to write into; on success it takes ``out``'s place (the folder
    there before, checked by :func:`check_replaceable`, is removed), on error it is removed and ``out`` is
    left as it was. A process killed at any moment leaves ``out`` as it was or complete; what it left beside
    it is cleaned up (or ``out`` restored) by the next :func:`check_replaceable` of ``out``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.writing-{os.getpid()}"
    old = out.parent / f".{out.name}.replaced-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        yield tmp
        check_replaceable(out, overwrite, option=option)  # again: something may have appeared meanwhile
        if out.exists():
            os.replace(out, old)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists():
            if out.exists():
                shutil.rmtree(old, ignore_errors=True)
            else:  # the second rename failed: put the old dataset back
                os.replace(old, out)
