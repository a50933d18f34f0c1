"""Frames queued for labelling: ``s3k add-frames`` adds the frames a tracked video was most in doubt about to
a dataset and lists them, worst first, in ``label-queue.csv``, for the labelling app to offer first.

``label-queue.csv`` (in the dataset folder) has one row per queued frame::

    frame,rank,doubt,video_frame,source

``frame`` a frame id of frames.csv, ``rank`` 1 for the frame to label first, ``doubt`` the tracker's score
(``s3k track``'s ``<stem>.doubt.csv``), ``video_frame`` the frame of the videos, ``source`` the tracks it came
from. A frame of the queue that has been labelled (its split is no longer ``unlabelled``) is done; a later
``s3k add-frames`` puts its frames first and keeps the earlier ones still to label after them.

A frame the videos show and the dataset does not hold is added as an ``unlabelled`` frame (``video_frame`` its
video frame when frames.csv has that column, else its id is the video frame): for a dataset of images, its
views are cut from the videos as the dataset's own were (the import's crop box and size,
:func:`s3k.detector.geometry_record.dataset_geometry`) and written where the dataset's image pattern
says; a dataset whose images are the videos only gets the row. Frames already labelled or held out for
testing are never queued. All of it happens under the dataset's label lock (``.labels.lock``), as the app's
edits do.

The labelling app lists the queue's frames still unlabelled first in its *Frames to label*, by rank and with
their doubt, before a run's own ranking of the other frames (:func:`queue_ranking`).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import atomic_path, file_lock, open_text
from s3k.data import Dataset, video
from s3k.detector.geometry_record import dataset_geometry
from s3k.geometry.warp import resize_crop
from s3k.label.store import LOCK_FILE

__all__ = ["QUEUE_COLUMNS", "QUEUE_FILE", "Queued", "queue_frames", "queue_ranking", "read_queue"]

QUEUE_FILE = "label-queue.csv"
QUEUE_COLUMNS = ["frame", "rank", "doubt", "video_frame", "source"]


@dataclass
class Queued:
    """What :func:`queue_frames` did: the dataset ``frames`` queued (worst first) and their ``video_frames``,
    those of them ``added`` to the dataset, and the frames passed over, by reason."""

    frames: list[int] = field(default_factory=list)
    video_frames: list[int] = field(default_factory=list)
    added: list[int] = field(default_factory=list)
    skipped: dict[str, int] = field(default_factory=dict)
    path: Path | None = None


def read_queue(data: str | Path) -> list[dict[str, str]]:
    """The rows of the dataset's ``label-queue.csv``, by rank (empty without one)."""
    path = Path(data) / QUEUE_FILE
    if not path.is_file():
        return []
    with open_text(path) as fh:
        rows = list(csv.DictReader(fh))
    for line, row in enumerate(rows, 2):
        for column in ("frame", "rank"):
            try:
                int(row.get(column) or "")
            except ValueError:
                raise UserError(f"{path}: line {line}: {column} {row.get(column)!r} is not a whole number",
                                hint=f"fix or delete {QUEUE_FILE}; s3k add-frames writes it anew") from None
    return sorted(rows, key=lambda r: int(r["rank"]))


def _number(text: str | None, kind: type) -> Any:
    """``text`` as ``kind`` (int or float), None when empty or not such a number (JSON-ready)."""
    try:
        value = kind(text)
    except (TypeError, ValueError):
        return None
    return value if np.isfinite(value) else None


def queue_ranking(data: str | Path, ids: np.ndarray, splits: np.ndarray, split: str = "unlabelled",
                  shown: np.ndarray | None = None) -> tuple[list[dict[str, Any]], np.ndarray]:
    """The labelling app's *Frames to label* as far as the queue decides it: the queue's frames still
    ``unlabelled`` by ``ids``/``splits`` (the label store's current splits, so a frame labelled since drops
    out), in rank order, as JSON-ready rows ``{"frame", "queue" (its rank), "score" and "doubt" (the
    tracker's), "video_frame", "source"}``; and the other frames of ``split`` (``"all"``: every frame), for a
    run to rank after them. Only the ``unlabelled`` split and ``"all"`` have queued frames; frames the queue
    names that are not in ``ids``, or not in ``shown`` when given (the frames the app opened with: one
    ``s3k add-frames`` added since shows once the app is started again), are passed over.

    Raises:
        UserError: ``label-queue.csv`` has a frame or rank that is not a whole number.
    """
    ids = np.asarray(ids, dtype=np.int64)
    splits = np.asarray(splits).astype(str)
    if shown is not None:
        keep = np.isin(ids, np.asarray(shown, dtype=np.int64))
        ids, splits = ids[keep], splits[keep]
    split_of = dict(zip(ids.tolist(), splits.tolist()))
    queued: list[dict[str, Any]] = []
    if split in ("unlabelled", "all"):
        seen: set[int] = set()
        for row in read_queue(data):
            frame = int(row["frame"])
            if split_of.get(frame) != "unlabelled" or frame in seen:
                continue
            seen.add(frame)
            doubt = _number(row.get("doubt"), float)
            queued.append({"frame": frame, "queue": int(row["rank"]), "score": doubt, "doubt": doubt,
                           "video_frame": _number(row.get("video_frame"), int),
                           "source": row.get("source") or ""})
    rest = ids if split == "all" else ids[splits == split]
    done = np.array([q["frame"] for q in queued], dtype=np.int64)
    return queued, rest[~np.isin(rest, done)]


def _pick(ranked: Sequence[tuple[int, float]], worst: int, held: dict[int, tuple[int, str]], spacing: int,
          out: Queued) -> list[tuple[int, float]]:
    """The first ``worst`` video frames of ``ranked`` that are not labelled or test frames, at least
    ``spacing`` frames apart."""
    picked: list[tuple[int, float]] = []
    for vf, score in ranked:
        if len(picked) >= worst:
            break
        split = held.get(vf, (None, "unlabelled"))[1]
        if split != "unlabelled":
            out.skipped[f"already {split}"] = out.skipped.get(f"already {split}", 0) + 1
            continue
        if spacing and any(abs(vf - p) < spacing for p, _ in picked):
            out.skipped["within --spacing of a worse frame"] = out.skipped.get(
                "within --spacing of a worse frame", 0) + 1
            continue
        picked.append((vf, score))
    return picked


def _write_images(ds, root: Path, new: dict[int, int], videos: dict[str, Path]) -> None:
    """Cut the new frames' views from the videos as the dataset's own images were (``new``: ``{video frame:
    frame id}``) and write them where the dataset's pattern says."""


    missing = [c for c in ds.cameras if c not in videos]
    if missing:
        raise UserError(f"--videos: no video for camera(s) {', '.join(missing)} of {root}",
                        hint="give every camera's video as CAM=FILE (s3k track records them beside its CSV)")
    geometry = dataset_geometry(ds)
    pattern = (ds.metadata.get("images") or {}).get("pattern", "images/{camera}/{frame:06d}.png")
    size = tuple(int(v) for v in ds.image_size)
    for cam in ds.cameras:
        entry = geometry["cameras"][cam]
        got, want = tuple(video.frame_size(videos[cam])), tuple(entry["frame_size"])
        if got != want:
            raise UserError(f"--videos {cam}={videos[cam]}: frames of {got} px, but {root}'s images of {cam} "
                            f"were cut from frames of {want} px",
                            hint="give the videos the dataset was imported from")
        for vf, image in video.iter_frames(videos[cam], sorted(new)):
            out, _ = resize_crop(image, crop_box=tuple(entry["box"]), out_size=size)
            target = root / pattern.format(camera=cam, frame=new[vf])
            target.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(target), np.ascontiguousarray(out[:, :, ::-1])):
                raise OSError(f"{target}: could not write the image")


def _append_frames(root: Path, rows: list[dict[str, str]]) -> None:
    """Append ``rows`` to frames.csv (other columns empty), keeping every line as it was."""
    path = root / "frames.csv"
    text = path.read_text(encoding="utf-8")
    header = next(csv.reader([next(ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#"))]))
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    for row in rows:
        writer.writerow([row.get(h.strip(), "") for h in header])
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text.rstrip("\n") + "\n" + buf.getvalue())


def _write_queue(root: Path, queued: list[tuple[int, int, float]], source: str) -> Path:
    """Write the queue: ``queued`` ``(frame, video frame, doubt)`` first, then the earlier queue's frames
    still unlabelled."""

    ds = Dataset.open(root, cache="none")
    unlabelled = set(ds.frames("unlabelled").tolist())
    mine = {f for f, _, _ in queued}
    rows: list[dict[str, object]] = [{"frame": f, "doubt": f"{d:.6g}", "video_frame": vf, "source": source}
                                     for f, vf, d in queued]
    rows += [dict(r) for r in read_queue(root)
             if int(r["frame"]) in unlabelled and int(r["frame"]) not in mine]
    path = root / QUEUE_FILE
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, QUEUE_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for rank, row in enumerate(rows, 1):
            writer.writerow({**row, "rank": rank})
    return path


def queue_frames(data: str | Path, ranked: Sequence[tuple[int, float]], worst: int,
                 videos: dict[str, Path] | None = None, source: str = "", spacing: int = 0) -> Queued:
    """Queue the ``worst`` first frames of ``ranked`` (``(video frame, doubt)``, worst first) for labelling in
    the dataset ``data``, adding those it does not hold (module docstring).

    Raises:
        UserError: a per-frame calibration (a new frame has none), videos missing or of another size, no frame
            left to queue.
    """

    root = Path(data)
    out = Queued()
    with file_lock(root / LOCK_FILE):
        ds = Dataset.open(root, cache="none")
        ids = ds.frames()
        by_video = ds.column("video_frame").astype(int) if "video_frame" in ds.frame_columns else ids
        held = {int(v): (int(f), str(s)) for v, f, s in zip(by_video, ids, ds.split_of(ids))}
        picked = _pick(ranked, worst, held, spacing, out)
        if not picked:
            raise UserError(f"{root}: none of the {len(ranked)} ranked frames can be queued ({out.skipped})",
                            hint="the dataset holds them all as labelled or test frames")
        new_ids: dict[int, int] = {}
        start = int(ids.max()) + 1 if len(ids) else 0
        for vf, _ in picked:
            if vf not in held:
                new_ids[vf] = start + len(new_ids) if "video_frame" in ds.frame_columns else vf
        if new_ids:
            if not ds.static_calibration:
                raise UserError(f"{root}: a per-frame calibration has no rows for new frames",
                                hint="queue only frames the dataset holds")
            if (ds.metadata.get("images") or {}).get("type", "png") == "png":
                _write_images(ds, root, new_ids, videos or {})
            _append_frames(root, [{"frame": str(i), "split": "unlabelled", "video_frame": str(vf)}
                                  for vf, i in new_ids.items()])
        queued = [(held[vf][0] if vf in held else new_ids[vf], vf, score) for vf, score in picked]
        out.frames, out.video_frames = [q[0] for q in queued], [q[1] for q in queued]
        out.added = [new_ids[vf] for vf in sorted(new_ids)]
        out.path = _write_queue(root, queued, source)
    return out
