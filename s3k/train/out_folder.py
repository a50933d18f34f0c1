"""Starting a run in its folder: the checks made before anything is written, and the run's history.

Before a single file is written, :func:`check_out` refuses an ``--out`` that is a file, is not writable, or
already holds a run (unless ``--resume`` or ``--overwrite``), and :func:`check_resume` compares the call with
the run being resumed: every field of the configuration outside the few a resume may change
(``s3k.config.resumable_fields``: more steps, threads, progress, validation cadence, ...) must match, and so
must the dataset's identity (:func:`s3k.detector.geometry_record.dataset_identity`: keypoints, cameras and
a fingerprint of its tables).
A refusal names the field with its value there and now, and leaves ``config.json`` untouched. Allowed
changes are recorded in ``config.json``'s ``"history"``: one entry per start of the run with the time, the
command line and the fields that changed.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from s3k.base.errors import UserError
from s3k.base.outputs import check_output_folder, check_run_folder
from s3k.config import TrainConfig, config_from_dict, option_argv, resumable_fields
from s3k.detector import DetectorMeta, load_torch_file
from s3k.run_folder import RunFolder


def is_run_folder(out: Path) -> bool:
    """True when ``out`` holds what ``s3k train`` writes (a configuration, checkpoint or model)."""
    return RunFolder(out).is_one_pass_run()


def check_out(out: Path, resume: bool, overwrite: bool, data: Path | None = None) -> None:
    """Refuse an ``--out`` that cannot take this run (a file, read-only, holding a run without --resume, the
    dataset ``data`` or inside a dataset)."""
    if resume and overwrite:
        raise UserError("--resume and --overwrite exclude each other", hint="pass one of them")
    # a two-pass run trains its passes inside itself: only datasets and the input are refused here
    check_output_folder(out, inputs={"DATASET": data}, runs=False)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file, not a run folder", hint="choose another --out")
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not _can_create_in(existing):
        raise UserError(f"--out {out}: {existing} is not writable", hint="choose another --out")
    check_run_folder(out, resume, overwrite)  # a folder of other files is never trained into nor cleared


def _can_create_in(folder: Path) -> bool:
    """True when a file can be created in ``folder``, found by creating (and removing) an empty one:
    ``os.access`` says yes to root for a folder without write permission and to anyone for a pseudo file
    system that refuses new files (/proc), where the run would only fail on its first write."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".s3k-write-probe-", dir=folder)
    except OSError:
        return False
    os.close(fd)
    os.unlink(probe)
    return True


def clear_run(out: Path) -> None:
    """Delete the files of the run in ``out`` (``--overwrite``); other files in the folder are kept."""
    if not is_run_folder(out):
        return  # not a run: nothing of ours to delete
    for name in RunFolder.ONE_PASS_FILES:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def _shown(value: Any) -> str:
    return ",".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)


def _option(name: str, value: Any) -> str:
    """The command-line option that sets field ``name`` to ``value`` (``--layout-tol 0.2``,
    ``--no-layout-fit``)."""
    return " ".join(option_argv(name, value))


def check_resume(out: Path, cfg: TrainConfig, identity: dict[str, Any], data: Path) -> dict[str, list[Any]]:
    """Compare this call with the run in ``out``; return the allowed changes ``{field: [old, new]}``.

    Raises:
        UserError: naming the first field or dataset property that differs where it must not.
    """
    doc = RunFolder(out).read_record()
    changed = _compare_config(doc, str(RunFolder(out).config_file), cfg)
    saved = doc.get("dataset_identity")
    if saved is None:  # written before identities were recorded: the names are all that can be compared
        meta = DetectorMeta.from_dict(doc["meta"])
        saved = {"keypoints": meta.keypoints, "cameras": meta.cameras}
    for key in ("keypoints", "cameras", "fingerprint"):
        if key in saved and saved[key] != identity[key]:
            what = key
            if key == "fingerprint":
                what = "tables (frames, splits, labels, calibration) differ: fingerprint"
            raise UserError(f"--resume: dataset {data} is not the one the run in {out} was trained on "
                            f"({doc.get('dataset')}): {what} {_shown(identity[key])} now, "
                            f"{_shown(saved[key])} there", hint="resume with the run's dataset, or choose "
                                                                 "another --out")
    return changed


def check_config(out: Path, cfg: TrainConfig) -> dict[str, list[Any]]:
    """:func:`check_resume`'s comparison of the configuration alone (for a pass whose dataset is derived from
    what was checked already, as a two-pass run's crops are from its coarse pass and the crop rule)."""
    return _compare_config(RunFolder(out).read_record(), str(RunFolder(out).config_file), cfg)


def _compare_config(doc: dict[str, Any], where: str, cfg: TrainConfig) -> dict[str, list[Any]]:
    old = config_from_dict(TrainConfig, doc["config"], where=where).to_dict()
    free = resumable_fields()
    changed: dict[str, list[Any]] = {}
    for name, value in cfg.to_dict().items():
        if old[name] == value:
            continue
        if name not in free:
            raise UserError(f"--resume: {name} is {_shown(value)} now but {_shown(old[name])} in {where}",
                            hint=f"pass {_option(name, old[name])} to continue the run, or choose another "
                                 "--out")
        changed[name] = [old[name], value]
    return changed


def finished_step(out: Path, steps: int) -> int | None:
    """The step of the run's final model (``model.pt``) when it is at or past ``steps``: a run with nothing
    left to train, which ``--resume`` leaves as it is; None otherwise (no model yet, or more steps asked)."""
    model = RunFolder(out).model
    if not model.is_file():
        return None
    step = int(load_torch_file(model, "model", ("step",))["step"])
    return step if step >= steps else None


def write_start(out: Path, cfg: TrainConfig, meta: DetectorMeta, data: Path, identity: dict[str, Any],
                resumed: bool, changed: dict[str, list[Any]], command: str | None) -> None:
    """Write ``config.json`` for this start of the run, appending to its history."""
    history: list[dict[str, Any]] = []
    if resumed and RunFolder(out).config_file.is_file():
        history = list(RunFolder(out).read_record().get("history", []))
    entry: dict[str, Any] = {"time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                             "event": "resumed" if resumed else "created", "command": command}
    if changed:
        entry["changed"] = changed
    RunFolder(out).write_record(cfg.to_dict(), meta.to_dict(), str(data), dataset_identity=identity,
                                history=[*history, entry])
