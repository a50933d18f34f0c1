"""A recording added to a dataset as a new session (``s3k import --into DATASET --session NAME``).

The session is first imported as a dataset of its own beside ``DATASET`` (:func:`s3k.data.recording.
import_recording`), then merged: its frame ids continue after the dataset's, its frames name their session,
its labels and 3D points follow their frames, its images take the dataset's names, its rig becomes the
session's (``calibration/<session>.json`` when the rigs differ) and its metadata goes to ``s3k.json``'s
``sessions``. The merged dataset is written beside ``DATASET``, checked by opening it, and renamed over it
(:func:`s3k.base.outputs.replace_folder`): a refused or failed merge leaves ``DATASET`` as it was.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import shutil
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.errors import UserError
from s3k.base.outputs import replace_folder
from s3k.data.dataset import Dataset
from s3k.data.formats.pixels import Convention
from s3k.data.import_labels import LabelFormat
from s3k.data.recording import ImageOptions, SplitOptions, import_recording
from s3k.data.sessions import (
    DEFAULT_SESSION,
    SESSION_CALIBRATION_DIR,
    SESSION_COLUMN,
    session_calibration_file,
)
from s3k.data.tables import (
    CACHE_DIR,
    CALIBRATION_COLUMNS,
    DEFAULT_IMAGE_PATTERN,
    FRAMES_FILE,
    LABELS_FILE,
    METADATA_FILE,
    NAME_RE,
    PER_FRAME_CALIBRATION_FILE,
    POINTS3D_FILE,
    STATIC_CALIBRATION_FILE,
)
from s3k.data.writer import Calibration, calibration_rows, json_text, rig_json
from s3k.geometry import Cameras

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

log = logging.getLogger(__name__)

REPLACED = {METADATA_FILE, FRAMES_FILE, LABELS_FILE, POINTS3D_FILE, STATIC_CALIBRATION_FILE,
            PER_FRAME_CALIBRATION_FILE, SESSION_CALIBRATION_DIR, CACHE_DIR}
"""The files of the dataset that the merge writes anew (every other file is carried over as it is)."""


def check_new_session(dataset: Dataset, session: str, option: str = "--session") -> None:
    """Refuse a session name that cannot name a file or that the dataset already holds."""
    if not NAME_RE.match(session):
        raise UserError(f"{option} {session!r}: a session name must be usable as a file name (letters, "
                        "digits, _ . + -)")
    if session in dataset.sessions:
        raise UserError(f"{option} {session}: {dataset.path} already holds session {session!r} (its "
                        f"sessions: {', '.join(dataset.sessions)})", hint=f"choose another {option}")


def check_compatible(dataset: Dataset, part: Dataset, session: str) -> None:
    """Refuse a session whose cameras, keypoints, image size or units differ from the dataset's."""
    where = f"session {session}"
    if set(part.cameras) != set(dataset.cameras):
        raise UserError(f"{where}: cameras {part.cameras} differ from {dataset.path}'s {dataset.cameras}",
                        hint="give --videos for exactly the dataset's cameras")
    if set(part.keypoints) != set(dataset.keypoints):
        raise UserError(f"{where}: keypoints {part.keypoints} differ from {dataset.path}'s "
                        f"{dataset.keypoints}", hint=f"pass --keypoints {','.join(dataset.keypoints)}")
    if part.source_image_size != dataset.source_image_size:
        W, H = dataset.source_image_size
        raise UserError(f"{where}: images are {part.source_image_size[0]}x{part.source_image_size[1]}, "
                        f"{dataset.path}'s {W}x{H}", hint=f"pass --size {W},{H}")
    if part.units != dataset.units:
        raise UserError(f"{where}: units {part.units!r} differ from {dataset.path}'s {dataset.units!r}",
                        hint=f"pass --units {dataset.units} if the calibration is in {dataset.units}")
    for ds in (dataset, part):
        images = ds.metadata.get("images", {})
        if images.get("type", "png") != "png" or not _pattern(ds).endswith(".png"):
            raise UserError(f"{ds.path}: its images are {images}; a session is added only to and from a "
                            "dataset of PNG images", hint="import the recordings with a manifest")


def _pattern(ds: Dataset) -> str:
    return str(ds.metadata.get("images", {}).get("pattern", DEFAULT_IMAGE_PATTERN))


def _rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """Header and rows of a dataset CSV (comment lines left out); empty when the file is absent."""
    if not path.exists():
        return [], []
    lines = [line for line in path.read_text(encoding="utf-8-sig").splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    reader = csv.DictReader(io.StringIO("\n".join(lines)))
    return list(reader.fieldnames or []), list(reader)


def _write_rows(path: Path, header: list[str], rows: list[dict[str, str]]) -> None:
    text = io.StringIO()
    writer = csv.DictWriter(text, header, lineterminator="\n", restval="")
    writer.writeheader()
    writer.writerows(rows)
    path.write_text(text.getvalue())


def _renumbered(path: Path, new_id: dict[int, int]) -> Iterator[dict[str, str]]:
    """The rows of the frames ``new_id`` keeps, under their new ids."""
    for row in _rows(path)[1]:
        if int(row["frame"]) in new_id:
            yield {**row, "frame": str(new_id[int(row["frame"])])}


def _merge_table(out: Path, name: str, old: Path, part: Path, new_id: dict[int, int], first: list[str],
                 defaults: dict[str, str]) -> None:
    header, rows = _rows(old / name)
    new_header, _ = _rows(part / name)
    if not rows and not new_header:
        return
    columns = list(dict.fromkeys([*first, *header, *new_header, *defaults]))
    rows = [{**defaults, **row} for row in rows] + [{**defaults, **row} for row in _renumbered(part / name,
                                                                                                new_id)]
    _write_rows(out / name, columns, rows)


def _link(src: Path, dst: Path, link: bool = True) -> None:
    """``dst`` becomes ``src``'s content: a hard link where the file system allows and ``link`` (files of a
    folder that is removed once the merged one is in place), else a copy."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        if not link:
            raise OSError
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _carry_over(src: Path, out: Path) -> None:
    """Every file of the dataset ``src`` that the merge does not write anew, into ``out``."""
    for entry in src.iterdir():
        if entry.name in REPLACED:
            continue
        if entry.is_dir() and not entry.is_symlink():
            for path in entry.rglob("*"):
                if not path.is_dir():
                    _link(path, out / path.relative_to(src))
        else:
            _link(entry, out / entry.name)


def _calibration(out: Path, dataset: Dataset, part: Dataset, kept: np.ndarray, session: str,
                 sessions: list[str]) -> str:
    """Write the merged calibration; returns its mode: static when the session's rig is the dataset's,
    one rig per session when each session has one, else per frame."""
    order = [part.cameras.index(c) for c in dataset.cameras]
    mode = dataset.metadata.get("calibration", "static")
    per_frame = (mode == "per_frame" or not part.static_calibration)
    if not per_frame:
        new_rig = _arrays(part.rig(np.float64), order)
        rigs = {s: _arrays(dataset.rig(np.float64, session=s if mode == "per_session" else None))
                for s in dataset.sessions}
        if mode == "static" and all(np.array_equal(a, b) for a, b in zip(rigs[dataset.sessions[0]], new_rig)):
            shutil.copy2(dataset.path / STATIC_CALIBRATION_FILE, out / STATIC_CALIBRATION_FILE)
            return "static"
        rigs[session] = new_rig
        (out / SESSION_CALIBRATION_DIR).mkdir()
        for name in sessions:
            (out / session_calibration_file(name)).write_text(rig_json(dataset.cameras, rigs[name]))
        return "per_session"
    with open(out / PER_FRAME_CALIBRATION_FILE, "w") as f:
        f.write(",".join(CALIBRATION_COLUMNS) + "\n")
        for ds, ids, offset, cams in ((dataset, dataset.frames(), 0, list(range(len(dataset.cameras)))),
                                      (part, kept, _offset(dataset), order)):
            arrays = ds.calibration(ids, np.float64).numpy()
            for i, frame in enumerate(ids):
                f.write(calibration_rows(int(frame) + offset, dataset.cameras,
                                         tuple(arrays[k][i][cams] for k in ("K", "dist", "R", "t"))))
    return "per_frame"


def _arrays(cams: Cameras, order: list[int] | None = None) -> Calibration:
    """``(K, dist, R, t)`` float64 arrays of a rig ``Cameras (C,)``, cameras in ``order``."""
    a = cams.numpy()
    keep = slice(None) if order is None else order
    return a["K"][keep], a["dist"][keep], a["R"][keep], a["t"][keep]


def _offset(dataset: Dataset) -> int:
    """What the new session's frame ids are shifted by: they continue after the dataset's."""
    return int(dataset.frame_ids.max()) + 1


def merge_session(into: str | Path, part: str | Path, session: str, info: dict[str, Any], *,
                  hold_out: bool = False, link: bool = False) -> Path:
    """Add the dataset ``part`` (one recording) to the dataset ``into`` as session ``session`` with metadata
    ``info`` (``frame_rate``, ``subject``, ``source``, ...); all or nothing. Returns ``into``.

    ``hold_out``: the session is held out whole (``--test-sessions``): its labelled and test frames become
    test frames and its unlabelled frames are left out. ``link``: hard-link ``part``'s images rather than
    copy them (``part`` is a temporary folder that goes away)."""
    into = Path(into)
    dataset = Dataset.open(into, cache="none")
    new = Dataset.open(part, cache="none")
    check_new_session(dataset, session)
    check_compatible(dataset, new, session)
    kept = new.frames(("labelled", "test")) if hold_out else new.frames()
    new_id = {int(f): int(f) + _offset(dataset) for f in kept}
    sessions = [*dataset.sessions, session]
    meta = dict(dataset.metadata)
    meta["sessions"] = {name: dataset.session_info(name) for name in dataset.sessions} | {session: info}
    with replace_folder(into, overwrite=True, option="--into") as out:
        out.mkdir()
        _carry_over(into, out)
        for frame in kept:
            for cam in new.cameras:
                _link(new.path / _pattern(new).format(camera=cam, frame=int(frame)),
                      out / _pattern(dataset).format(camera=cam, frame=new_id[int(frame)]), link)
        default = {SESSION_COLUMN: DEFAULT_SESSION}
        _merge_table(out, FRAMES_FILE, into, new.path, new_id, ["frame", "split"], default)
        _fill_frames(out / FRAMES_FILE, session, new_id, hold_out)
        _merge_table(out, LABELS_FILE, into, new.path, new_id, ["frame", "camera", "keypoint", "u", "v"],
                     {"visible": "1"})
        _merge_table(out, POINTS3D_FILE, into, new.path, new_id, ["frame", "keypoint", "x", "y", "z"], {})
        meta["calibration"] = _calibration(out, dataset, new, kept, session, sessions)
        (out / METADATA_FILE).write_text(json_text(meta))
        Dataset.open(out, cache="none")  # the merged dataset reads back, or nothing is replaced
    return into


def import_session(into: str | Path, session: str, calibration: str | Path, videos: Mapping[str, str | Path],
                   labels: LabelFormat | None = None, *, split: SplitOptions | None = None,
                   images: ImageOptions | None = None, keypoints: Sequence[str] | None = None,
                   units: str | None = None, skeleton: str | Path | None = None,
                   subject: str | None = None, frame_offsets: Mapping[str, int] | None = None,
                   label_pixels: Convention | None = None,
                   calibration_pixels: Convention | None = None) -> Path:
    """Import a recording (the arguments of :func:`s3k.data.recording.import_recording`) and add it to the
    dataset ``into`` as session ``session``; returns ``into``. Its images are resized to the dataset's size
    unless ``images`` gives one; without labels its keypoints are the dataset's. All or nothing."""
    into = Path(into)
    dataset = Dataset.open(into, cache="none")
    check_new_session(dataset, session)
    if set(videos) != set(dataset.cameras):
        raise UserError(f"--videos: cameras {list(videos)} differ from {into}'s {dataset.cameras}",
                        hint="give one video for each of the dataset's cameras")
    if keypoints is not None and set(keypoints) != set(dataset.keypoints):
        raise UserError(f"--keypoints {','.join(keypoints)}: keypoints differ from {into}'s "
                        f"{dataset.keypoints}", hint=f"pass --keypoints {','.join(dataset.keypoints)}")
    split, images = split or SplitOptions(), images or ImageOptions()
    if images.size is None and images.scale is None:
        _check_aspect(images.crops or {}, dataset.source_image_size, into)
        images = replace(images, size=dataset.source_image_size)
    if labels is None and keypoints is None:
        keypoints = dataset.keypoints
    part = into.parent / f".{into.name}.importing-{os.getpid()}"  # beside it: its relative paths hold
    shutil.rmtree(part, ignore_errors=True)
    try:
        import_recording(calibration, videos, part, labels, split=split, images=images, keypoints=keypoints,
                         units=units, skeleton=skeleton, session=session, subject=subject,
                         frame_offsets=frame_offsets, label_pixels=label_pixels,
                         calibration_pixels=calibration_pixels)
        new = Dataset.open(part, cache="none")
        merge_session(into, part, session, new.session_info(session), link=True)
    finally:
        shutil.rmtree(part, ignore_errors=True)
    ids = Dataset.open(into, cache="none").frames(session=session)
    log.info(f"added session {session} to {into}: {len(ids)} frames (ids {ids.min()}..{ids.max()})")
    return into


def _check_aspect(crops: Mapping[str, Sequence[float]], size: tuple[int, int], into: Path) -> None:
    """Refuse crop boxes that the dataset's image size would stretch (another aspect ratio, beyond 1%)."""
    W, H = size
    for cam, (x0, y0, x1, y1) in crops.items():
        w, h = x1 - x0, y1 - y0
        if abs((w / h) / (W / H) - 1) > 0.01:
            side = max(w, h)
            raise UserError(f"--crop {cam}={x0:g},{y0:g},{x1:g},{y1:g}: a {w:g}x{h:g} box would be stretched "
                            f"to {into}'s {W}x{H} images",
                            hint=f"give boxes of {W}:{H} (e.g. {side:g}x{round(side * H / W):g}), or --size "
                                 f"{W},{H} to stretch them")


def _fill_frames(path: Path, session: str, new_id: dict[int, int], hold_out: bool) -> None:
    """The merged frames.csv's session of the new frames (test frames all when it is held out), and a
    ``video_frame`` for every frame (a frame without one is its own video frame)."""
    header, rows = _rows(path)
    added = set(new_id.values())
    for row in rows:
        if int(row["frame"]) in added:
            row[SESSION_COLUMN] = session
            row["split"] = "test" if hold_out else row["split"]
        if "video_frame" in header and not row.get("video_frame"):
            row["video_frame"] = row["frame"]
    _write_rows(path, header, rows)


def manifest_sessions(path: str | Path) -> list[dict[str, Any]]:
    """The sessions of an import manifest (JSON or TOML, ``docs/importing.md#sessions``): a list of
    ``{"session": NAME, ...import options}``; a malformed manifest is refused naming the field."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except OSError as exc:
        raise UserError(f"--manifest {path}: cannot read: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise UserError(f"--manifest {path}: not valid {path.suffix.lstrip('.').upper() or 'JSON'}: "
                        f"{str(exc).splitlines()[0]}") from None
    sessions = data.get("sessions") if isinstance(data, dict) else None
    if not isinstance(sessions, list) or not sessions or not all(isinstance(s, dict) for s in sessions):
        raise UserError(f"--manifest {path}: field 'sessions' must be a non-empty list of tables, each with "
                        "'session', and 'calibration' and 'videos' or 'dataset'")
    names = []
    for i, entry in enumerate(sessions):
        for key in ("session", "calibration", "videos") if "dataset" not in entry else ("session",):
            if key not in entry:
                raise UserError(f"--manifest {path}: sessions[{i}] has no field {key!r}")
        if "videos" in entry and not isinstance(entry["videos"], dict):
            raise UserError(f"--manifest {path}: sessions[{i}].videos must map each camera to a video")
        names.append(str(entry["session"]))
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise UserError(f"--manifest {path}: session {repeated[0]!r} is listed twice")
    return sessions

