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
import logging
import os
import re
import shutil
from collections.abc import Callable, Collection, Iterator, Mapping
from pathlib import Path

from s3k.base.errors import UserError
from s3k.base.messages import NOTE
from s3k.base.run_files import RunFiles

log = logging.getLogger(__name__)

__all__ = ["DATASET_MARKER", "DATASET_NAMES", "OUTPUT_MARKER", "RUN_NAMES", "RUN_NEIGHBOURS",
           "UNFINISHED_MARKER", "check_companion", "check_folder", "check_output", "check_output_folder",
           "check_replaceable", "check_run_folder", "claim_folder", "foreign_dataset_file", "is_dataset",
           "is_run", "made_by_s3k", "owns_run", "recover_folder", "replace_folder", "staging_folder"]

DATASET_MARKER = "s3k.json"
"""The file that makes a folder a dataset (``s3k.data.tables.METADATA_FILE``)."""

RUN_NAMES = frozenset(RunFiles.ONE_PASS_FILES + RunFiles.TWO_PASS_FILES)
"""Names a run folder's own files and folders take (``tests/base/test_outputs.py`` checks them against the
modules that write them)."""

RUN_NEIGHBOURS = frozenset({"run.lock", "result.json", RunFiles.CPU, RunFiles.OPTIONS})
"""Files s3k keeps in a run folder before the run is started: an experiment's lock and result
(``s3k.experiments``), a two-pass run's options and CPU record."""


def is_dataset(folder: Path) -> bool:
    """True when ``folder`` holds a dataset (its ``s3k.json``)."""
    return (folder / DATASET_MARKER).is_file()


def is_run(folder: Path) -> bool:
    """True when ``folder`` holds a run of ``s3k train`` (its model or checkpoint, a run's ``config.json``)
    or of ``s3k train --two-pass`` (``two_pass.json``, or a coarse pass)."""
    run = RunFiles(folder)
    if any(p.is_file() for p in (run.model, run.checkpoint, run.two_pass_file)):
        return True
    if run.coarse.path.is_dir() and is_run(run.coarse.path):
        return True
    return run.holds_record()


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
# Folders a command writes files into (a run, a report, an overlay folder, a demo, a published experiment):
# a new or empty folder, or one s3k made for the same purpose; never a folder of someone else's files.

OUTPUT_MARKER = ".s3k-output.json"
"""The file that marks a folder s3k made for a command's output (``{"kind": "report"}``,
:func:`claim_folder`); a run is known by its own files (:func:`owns_run`), a dataset by ``s3k.json``, a
published experiment by its ``summary.json``."""


def marked_kind(folder: Path) -> str | None:
    """The kind of output :func:`claim_folder` marked ``folder`` with, or None."""
    try:
        doc = json.loads((folder / OUTPUT_MARKER).read_text())
    except (OSError, ValueError):
        return None
    return doc.get("kind") if isinstance(doc, dict) else None


def claim_folder(folder: str | Path, kind: str) -> Path:
    """Create ``folder`` (checked by :func:`check_folder`) and mark it as s3k's ``kind`` of output, so that
    a later call may write into it again."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if marked_kind(folder) != kind:
        (folder / OUTPUT_MARKER).write_text(json.dumps({"kind": kind, "by": "s3k"}) + "\n")
    return folder


def _first_entry(folder: Path, skip: Collection[str] = frozenset(), writes: Collection[str] = frozenset()
                 ) -> Path | None:
    """The entry of ``folder`` to name: the first the command would write over (``writes``), else the first
    one, leaving out ``skip`` (and s3k's marker)."""
    entries = [p for p in sorted(folder.iterdir(), key=lambda p: p.name)
               if p.name not in skip and p.name != OUTPUT_MARKER]
    return next((p for p in entries if p.name in writes), entries[0] if entries else None)


def check_folder(path: str | Path, kind: str, inputs: Mapping[str, object] | None = None,
                 option: str = "--out", owns: Callable[[Path], bool] | None = None,
                 writes: Collection[str] = (), ours: Collection[str] = ()) -> Path:
    """The rule for a folder a command writes its files into: refuse it when it is a file, a dataset or inside
    one, a run's own file, an input of this call, or a folder that holds files and was not made by s3k for a
    ``kind`` of output (marked by :func:`claim_folder`, or recognised by ``owns``); the message names one of
    the files that are not s3k's (one the command would replace, ``writes``, if any; never one of the names
    s3k's own output of this kind takes, ``ours``, while another is there). A new or empty folder is fine."""
    path = Path(path)
    check_output_folder(path, inputs, option)
    if path.exists() and not path.is_dir():
        raise UserError(f"{option} {path} is a file", hint=f"give {option} a folder")
    if not path.is_dir():
        return path
    first = _first_entry(path)
    if first is None or marked_kind(path) == kind or (owns is not None and owns(path)):
        return path
    first = _first_entry(path, ours, writes) or first
    raise UserError(f"{option} {path} holds files s3k did not write ({first.name}); s3k writes a {kind} only "
                    f"into a new or empty folder, or one it made for a {kind}",
                    hint=f"give {option} a new folder")


def owns_run(folder: Path) -> bool:
    """True when ``folder`` holds a run s3k wrote: a run's ``config.json``, or a two-pass run's description,
    options or coarse pass (a model or checkpoint file alone may be anyone's)."""
    run = RunFiles(folder)
    if run.two_pass_file.is_file() or run.options_file.is_file():
        return True
    if run.coarse.path.is_dir() and owns_run(run.coarse.path):
        return True
    return run.holds_record()


def check_run_folder(out: str | Path, resume: bool, overwrite: bool, whole: bool = False,
                     option: str = "--out") -> None:
    """Refuse a run folder ``out`` that holds files but no run (with or without ``--overwrite``: it would
    replace someone's ``config.json`` or ``train.log``), a run without ``--resume`` or ``--overwrite``, and,
    when ``whole`` (``--overwrite`` deletes the folder, as a two-pass run does), a run beside files that are
    not the run's own."""
    out = Path(out)
    first = _first_entry(out, RUN_NEIGHBOURS, writes=RUN_NAMES) if out.is_dir() else None
    if first is None:
        return
    if not owns_run(out):
        raise UserError(f"{option} {out} holds no run but files s3k did not write ({first.name})",
                        hint=f"give {option} a new or empty folder (--overwrite replaces only a run)")
    if not resume and not overwrite:
        raise UserError(f"{option} {out} already holds a run", hint="pass --resume to continue it or "
                        f"--overwrite to replace it, or choose another {option}")
    other = _first_entry(out, RUN_NAMES | RUN_NEIGHBOURS)
    if overwrite and whole and other is not None:
        raise UserError(f"{option} {out} holds {other.name} beside the run, which s3k did not write there; "
                        "--overwrite would delete it",
                        hint=f"move it out of {out}, or choose another {option}")


def check_companion(path: str | Path, overwrite: bool, named: str, owns: Callable[[Path], bool],
                    option: str = "--out") -> Path:
    """Check a file a command writes beside the one its command line named (``named``): as
    :func:`check_output`, and an existing one is replaced (with ``--overwrite``) only when ``owns`` says it is
    s3k's own output of the same kind; the message names the file."""
    path = Path(path)
    try:
        check_output(path, overwrite, option=option)
    except UserError as exc:
        if not path.exists() or path.is_dir() or overwrite:
            raise
        raise UserError(f"{option} {named} also writes {path}, which exists",
                        hint="pass --overwrite to replace it, or choose another name") from exc
    if path.exists() and not owns(path):
        raise UserError(f"{option} {named} also writes {path}, which exists and is not s3k's (--overwrite "
                        "replaces only s3k's own files beside the one named)",
                        hint=f"move {path} away, or give {option} another name")
    return path


# ------------------------------------------------------------------------------------------------------------
# Folders s3k fills as a whole (a dataset from s3k import or s3k simulate): written beside the target and
# renamed over it, replaced only when s3k made what is there.

UNFINISHED_MARKER = ".s3k-unfinished"
"""A dataset folder being written holds this file until its ``s3k.json`` is written (``DatasetWriter``)."""

_HIDDEN = re.compile(r"\.(?P<name>.+)\.(?P<kind>writing|importing|replaced)-(?P<pid>\d+)")


DATASET_NAMES = frozenset({
    # s3k.data.tables: the metadata, tables and cache of a dataset
    "s3k.json", "frames.csv", "calibration.json", "calibration.csv", "labels.csv", "points3d.csv", ".cache",
    # s3k.data.sessions: the folder of each session's rig
    "calibration",
    # s3k.label.store: the label history and its lock; s3k.data.writer: the mark of an unfinished dataset
    "labels-history.jsonl", ".labels.lock", UNFINISHED_MARKER,
})
"""Names a dataset folder's own files take besides its images (``tests/base/test_outputs.py`` checks them
against the modules that write them)."""

_ATOMIC_TMP = re.compile(r"\..+\.\d+\.tmp")  # s3k.base.fileio.atomic_path's temporary files


def _dataset_images(folder: Path) -> tuple[set[str], str]:
    """The top-level names a dataset's images take (its image folder, or its videos) and their suffix."""
    try:
        images = json.loads((folder / DATASET_MARKER).read_text()).get("images") or {}
    except (OSError, ValueError, AttributeError):
        images = {}
    if isinstance(images, dict) and images.get("type") == "video":
        per = images.get("sessions")
        groups = list(per.values()) if isinstance(per, dict) else [images.get("videos")]
        paths = [Path(str(v)) for g in groups for v in (g.values() if isinstance(g, dict) else [])]
        return {p.parts[0] for p in paths if p.parts and not p.is_absolute()}, ""
    pattern = Path(str(images.get("pattern", "images/{camera}/{frame:06d}.png"))
                   if isinstance(images, dict) else "images/{camera}/{frame:06d}.png")
    top = pattern.parts[0] if len(pattern.parts) > 1 else ""
    return ({top} if "{" not in top else {"*"}), pattern.suffix


def foreign_dataset_file(folder: Path) -> Path | None:
    """A file in the dataset ``folder`` that s3k did not write there (not one of its tables, images or
    label history), or None: replacing the dataset would delete it."""
    tops, suffix = _dataset_images(folder)
    for entry in sorted(folder.iterdir(), key=lambda p: p.name):
        if entry.name in DATASET_NAMES or _ATOMIC_TMP.fullmatch(entry.name):
            continue
        if entry.is_dir() and not entry.is_symlink() and (entry.name in tops or "*" in tops) and suffix:
            other = next((p for p in sorted(entry.rglob("*")) if not p.is_dir() and p.suffix != suffix), None)
            if other is None:
                continue
            return other
        if entry.name in tops and not suffix:
            continue
        return entry
    return None


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
    shown = Path(out)
    out = _real(shown)
    for line in recover_folder(out):
        log.log(NOTE, f"note: {line}")
    target = out.resolve()
    for folder in target.parents:
        if is_dataset(folder):
            raise UserError(f"{option} {shown} is inside the dataset {folder}", hint=f"give {option} a path "
                                                                                   "outside it")
    if out.exists() and not out.is_dir():
        raise UserError(f"{option} {shown} is a file, not a dataset folder", hint=f"give {option} a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise UserError(f"{option} {shown}: folder exists and is not empty",
                            hint="pass --overwrite to replace it")
        if not made_by_s3k(out):
            raise UserError(f"{option} {shown} is not a dataset (no {DATASET_MARKER}): --overwrite replaces "
                            "only a folder s3k made", hint=f"give {option} another folder, or empty it first")
        foreign = foreign_dataset_file(out)
        if foreign is not None:
            raise UserError(f"{option} {shown} holds {foreign.relative_to(out)}, which is not a file of the "
                            "dataset; --overwrite would delete it",
                            hint=f"move it out of {shown}, or give {option} another folder")
        for name, given in (inputs or {}).items():
            for one in given if isinstance(given, (list, tuple, set)) else [given]:
                if one is not None and Path(str(one)).resolve().is_relative_to(target):
                    raise UserError(f"{option} {shown} holds this command's input ({name} {one}); replacing "
                                    "it would delete it", hint=f"give {option} another folder")
    return shown


def _real(out: Path) -> Path:
    """``out`` with the links in it resolved: a dataset reached through a link is replaced where it is, and
    the link kept."""
    return Path(os.path.realpath(out)) if out.is_symlink() else out


@contextlib.contextmanager
def replace_folder(out: str | Path, overwrite: bool, option: str = "--out") -> Iterator[Path]:
    """Yield a hidden folder beside ``out`` to write into; on success it takes ``out``'s place (the folder
    there before, checked by :func:`check_replaceable`, is removed), on error it is removed and ``out`` is
    left as it was. A process killed at any moment leaves ``out`` as it was or complete; what it left beside
    it is cleaned up (or ``out`` restored) by the next :func:`check_replaceable` of ``out``."""
    out = _real(Path(out))
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


@contextlib.contextmanager
def staging_folder(out: Path) -> Iterator[Path]:
    """A hidden folder beside ``out`` for files that are written, then checked, before they take their
    places (``path.replace(...)``); whatever is left in it is removed on leaving, so a file that fails its
    check never reaches ``out``'s folder."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.writing-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
