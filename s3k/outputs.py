"""Where a command may write: the one check every output goes through before any work.

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
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from s3k.errors import UserError

__all__ = ["DATASET_MARKER", "RUN_NAMES", "check_output", "check_output_folder", "is_dataset", "is_run"]

DATASET_MARKER = "s3k.json"
"""The file that makes a folder a dataset (``s3k.data.tables.METADATA_FILE``)."""

RUN_NAMES = frozenset({
    # s3k.run.RUN_FILES: what s3k train writes into a run folder
    "config.json", "checkpoint.pt", "model.pt", "train.log", "tensorboard", "progress.json",
    # s3k.two_pass: a two-pass run's description, passes, crops, estimates and CPU record
    "two_pass.json", "coarse", "fine", "crops", "estimates.csv", "cpu.json",
})
"""Names a run folder's own files and folders take (``tests/test_outputs.py`` checks them against the
modules that write them)."""


def is_dataset(folder: Path) -> bool:
    """True when ``folder`` holds a dataset (its ``s3k.json``)."""
    return (folder / DATASET_MARKER).is_file()


def is_run(folder: Path) -> bool:
    """True when ``folder`` holds a run of ``s3k train`` (its model or checkpoint, a run's ``config.json``)
    or of ``s3k train --two-pass`` (``two_pass.json``, or a coarse pass)."""
    if any((folder / name).is_file() for name in ("model.pt", "checkpoint.pt", "two_pass.json")):
        return True
    if (folder / "coarse").is_dir() and is_run(folder / "coarse"):
        return True
    config = folder / "config.json"
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

