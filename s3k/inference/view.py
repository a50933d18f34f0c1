"""``s3k view``: a dataset, a run's detections on a dataset, or tracks, in Rerun
(:class:`s3k.inference.rerun_log.RerunLog` logs them; the entities are listed there).

- **tracks**: the 3D CSV of ``s3k track`` / ``s3k predict`` (its ``_score`` column is each keypoint's
  confidence), with the rig's calibration (``--calibration``, else the one the CSV's ``.s3k.json`` names) and
  the videos (``--videos``; without them, cameras and points only); the points are reprojected into every
  view.
- **a dataset**: its cameras and images, the 2D labels, and the 3D keypoints: its ground truth where it has
  one, else its labels triangulated (every labelled view, unit weights).
- **a run's evaluation**: the run's :class:`s3k.detector.Detector` on a dataset split (``--data``, default
  the dataset it was trained on), as ``s3k evaluate`` runs it: each view's detections with their confidence,
  the 3D keypoints, their reprojections, and the ground truth (``world/truth``) beside them.

The skeleton is the dataset's, the run's, or ``--skeleton FILE``'s (any file
:func:`s3k.data.formats.skeleton.read_skeleton` reads).
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.base.choices import Device
from s3k.base.errors import UserError
from s3k.base.fileio import open_text
from s3k.base.metrics import keypoint_order
from s3k.data import Dataset, video
from s3k.data.formats.calibration_files import read_calibration
from s3k.data.formats.skeleton import check_edges, read_skeleton
from s3k.data.frames import FrameStore
from s3k.data.tracks_csv import read_source
from s3k.detector import Detector, DetectorMeta, detect_store, split_frames
from s3k.geometry import triangulate_labels
from s3k.inference.rerun_log import RerunLog
from s3k.run_folder import RunFolder

log = logging.getLogger(__name__)

__all__ = ["ViewOptions", "read_tracks", "target_kind", "view_dataset", "view_run", "view_tracks"]


@dataclass
class ViewOptions:
    """What to log and where: ``target`` ``"spawn"`` or a ``.rrd`` file; frames ``start <= f < stop``, every
    ``step``-th, at most ``max_frames``; the images' ``image_scale`` and ``jpeg_quality`` (no images with
    ``images=False``); ``skeleton`` a file to take the skeleton from."""

    target: str = "spawn"
    start: int = 0
    stop: int | None = None
    step: int = 1
    max_frames: int | None = 300
    image_scale: float = 0.5
    jpeg_quality: int = 75
    images: bool = True
    skeleton: str | None = None

    def pick(self, frames: Sequence[int] | np.ndarray) -> list[int]:
        """The frames of ``frames`` (in order) to log."""
        chosen = [int(f) for f in frames if f >= self.start and (self.stop is None or f < self.stop)]
        chosen = chosen[::self.step]
        return chosen[:self.max_frames] if self.max_frames is not None else chosen

    def recorder(self, keypoints: Sequence[str], cameras: Sequence[str], skeleton: Sequence[Sequence[str]],
                 units: str, confidence: bool = True) -> RerunLog:
        if self.skeleton is not None:

            skeleton = check_edges(read_skeleton(self.skeleton), keypoints, f"--skeleton {self.skeleton}")
        return RerunLog("s3k view", self.target, keypoints, cameras, skeleton, self.image_scale,
                        self.jpeg_quality, units, confidence)


def target_kind(path: str | Path) -> str:
    """``"tracks"`` (a CSV file), ``"dataset"`` (a folder with ``s3k.json``) or ``"run"`` (a run folder)."""
    path = Path(path)
    if path.is_file():
        if path.suffix.lower() == ".csv":
            return "tracks"
        raise UserError(f"{path}: not a 3D CSV, a dataset or a run folder",
                        hint="give the CSV of 's3k track' or 's3k predict', a dataset folder or a run folder")
    if (path / "s3k.json").is_file():
        return "dataset"
    if RunFolder(path).config_file.is_file():
        return "run"
    if not path.exists():
        raise UserError(f"{path}: no such file or folder")
    raise UserError(f"{path}: a folder that is neither a dataset (no s3k.json) nor a run (no config.json)")


def run_skeleton(run: str | Path) -> list[tuple[str, str]]:
    """The skeleton a run recorded (:meth:`s3k.detector.DetectorMeta.recorded_skeleton`; ``[]`` if none)."""

    run = Path(run)
    try:
        doc = RunFolder(run).first_pass().read_record()
        return DetectorMeta.from_dict(doc["meta"]).recorded_skeleton()
    except (OSError, UserError, KeyError, TypeError, ValueError):
        return []


# ------------------------------------------------------------------------------------------------------------
# Tracks


def read_tracks(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """``(keypoints, fnums (T,), X (T, K, 3), score (T, K))`` of a 3D CSV (:mod:`s3k.data.tracks_csv`); NaN
    where not triangulated (a score column that is missing reads as NaN)."""
    with open_text(path) as f:
        reader = csv.reader(f)
        header = next(reader, [])
        keypoints = [c[:-2] for c in header if c.endswith("_x")]
        if not keypoints or "fnum" not in header:
            raise UserError(f"{path}: not a 3D keypoints CSV (expected columns <keypoint>_x, _y, _z, ..., "
                            "fnum)")
        cols = [[header.index(f"{k}_{a}") if f"{k}_{a}" in header else -1 for a in ("x", "y", "z", "score")]
                for k in keypoints]
        fcol = header.index("fnum")
        fnums, values = [], []
        for row in reader:
            if not row:
                continue
            try:
                fnums.append(int(float(row[fcol])))
                values.append([[float(row[i] or "nan") if i >= 0 else np.nan for i in c] for c in cols])
            except (IndexError, ValueError, OverflowError):
                raise UserError(f"{path}, line {reader.line_num}: a short row or a value that is not a "
                                "number (a truncated file?)") from None
    arr = np.array(values, dtype=np.float64).reshape(len(fnums), len(keypoints), 4)
    return keypoints, np.array(fnums, dtype=np.int64), arr[..., :3], arr[..., 3]


def view_tracks(csv_path: str | Path, opts: ViewOptions, calibration: str | Path | None = None,
                videos: dict[str, str] | None = None, units: str | None = None) -> int:
    """Log the tracks of ``csv_path`` with the rig's cameras (and the ``videos``' frames); returns the
    number of frames logged."""

    csv_path = Path(csv_path)
    source = read_source(csv_path) or {}
    calibration = calibration or source.get("calibration")
    if not calibration:
        if source.get("dataset"):
            raise UserError(f"{csv_path}: points of the dataset {source['dataset']} ('s3k predict'), not of "
                            "videos", hint=f"show them with s3k view {source.get('run', 'RUN')} --data "
                            f"{source['dataset']}, or give the rig's calibration with --calibration")
        raise UserError(f"{csv_path}: no calibration named beside it (no {csv_path.name}.s3k.json)",
                        hint="give the rig's calibration with --calibration")
    keypoints, fnums, X, score = read_tracks(csv_path)
    rig = read_calibration(calibration, units=units or source.get("units"))
    videos = dict(videos or {})
    unknown = [c for c in videos if c not in rig.names]
    if unknown:
        raise UserError(f"--videos: camera {unknown[0]!r} is not in {calibration} (its cameras are "
                        f"{', '.join(rig.names)})")
    sizes = {c: video.frame_size(p) for c, p in videos.items()}
    rig = rig.with_sizes(sizes)
    names = list(videos) or list(rig.names)
    rig = rig.select(names)
    for c, name in enumerate(names):
        if min(int(v) for v in rig.size[c]) <= 0:
            raise UserError(f"{calibration}: camera {name} has no image size (the file does not give one)",
                            hint=f"give its video with --videos {name}=FILE")
        if name in sizes and tuple(sizes[name]) != tuple(int(v) for v in rig.size[c]):
            W, H = sizes[name]
            log.warning(f"--videos {name}: frames of {W}x{H} px but {calibration} gives "
                        f"{rig.size[c][0]}x{rig.size[c][1]}; the reprojections assume the calibrated image")
    skeleton = run_skeleton(source["run"]) if source.get("run") else []
    rows = {int(f): i for i, f in enumerate(fnums)}
    frames = opts.pick(sorted(rows))
    if not frames:
        raise UserError(f"{csv_path}: no frames to show between --start {opts.start} and --stop {opts.stop}")
    for name, path in videos.items() if opts.images else ():
        count = video.frame_count(path)
        if frames[-1] >= count:
            raise UserError(f"{csv_path}: frame {frames[-1]} is beyond the {count} frames of --videos "
                            f"{name}={path}", hint=f"give the videos the tracks came from, or --stop {count}")
    with opts.recorder(keypoints, names, skeleton, rig.units, bool(np.isfinite(score).any())) as rec:
        rec.frame(rig.cameras, X[[rows[f] for f in frames]])
        rec.cameras_at(rig.cameras, [tuple(int(v) for v in s) for s in rig.size])
        streams = [video.iter_frames(videos[c], frames) for c in names] if videos and opts.images else None
        for f in frames:
            rec.set_frame(f)
            if streams is not None:
                rec.images([next(s)[1] for s in streams])
            i = rows[f]
            valid = np.isfinite(X[i]).all(-1)
            rec.points3d(X[i], valid, score[i] if np.isfinite(score[i]).any() else None)
            rec.reprojections(rig.cameras, X[i], valid)
    return len(frames)


# ------------------------------------------------------------------------------------------------------------
# A dataset, and a run's detections on one


def _truth(ds: Any, ids: np.ndarray, cams: Any, uv: np.ndarray, mask: np.ndarray):
    """``(X (B, K, 3), valid (B, K))``: the dataset's 3D ground truth where it has one, else its labels
    triangulated."""
    points = ds.points3d(ids)
    if points is not None:
        return np.asarray(points[0], dtype=np.float64), np.asarray(points[1], dtype=bool)


    X, valid = triangulate_labels(cams, torch.as_tensor(uv), torch.as_tensor(mask))
    return X.numpy(), valid.numpy()


def _framed(rec: RerunLog, ds: Any, ids: np.ndarray) -> None:
    """Frame the recording's 3D view on the dataset's 3D points of the frames ``ids`` (its ground truth, or
    its labels triangulated) and its first frame's cameras."""
    cams = ds.calibration(ids, np.float64)
    uv, mask = ds.labels(ids, np.float64)
    X, valid = _truth(ds, ids, cams, uv, mask)
    rec.frame(cams[0], np.where(valid[..., None], X, np.nan))


def view_dataset(data: str | Path, opts: ViewOptions, split: str = "all") -> int:
    """Log a dataset's frames of ``split``: cameras, images, 2D labels and 3D keypoints; returns the number of
    frames logged."""

    ds = Dataset.open(data, cache="none")
    ids = np.array(opts.pick(split_frames(ds, split)), dtype=np.int64)
    if not len(ids):
        raise UserError(f"{data}: no frames of split {split!r} between --start {opts.start} and --stop "
                        f"{opts.stop}", hint="choose another --split, --start or --stop")
    sizes = [tuple(ds.image_size)] * len(ds.cameras)
    with opts.recorder(ds.keypoints, ds.cameras, ds.skeleton, ds.units, confidence=False) as rec:
        _framed(rec, ds, ids)
        if ds.static_calibration:
            rec.cameras_at(ds.rig(np.float64), sizes)
        for start in range(0, len(ids), 16):
            batch = ids[start:start + 16]
            cams = ds.calibration(batch, np.float64)
            uv, mask = ds.labels(batch, np.float64)
            X, valid = _truth(ds, batch, cams, uv, mask)
            images = ds.images(batch) if opts.images else None
            for b, f in enumerate(batch):
                rec.set_frame(int(f))
                if not ds.static_calibration:
                    rec.cameras_at(cams[b], sizes, static=False)
                if images is not None:
                    rec.images(list(images[b]))
                rec.points2d("labels", uv[b], mask[b])
                rec.points3d(X[b], valid[b])
                rec.reprojections(cams[b], X[b], valid[b])
    return len(ids)


def view_run(run: str | Path, opts: ViewOptions, data: str | Path | None = None, split: str = "test",
             device: Device = "auto", batch_size: int = 8) -> int:
    """Log a run's detections on a dataset split (as ``s3k evaluate`` detects them) beside the ground truth;
    returns the number of frames logged."""

    data = data or RunFolder(run).dataset()
    if not data:
        raise UserError(f"{run}: the run does not record its dataset", hint="give one with --data")
    detector = Detector.load(run, device)
    ds = Dataset.open(data, cache="none")
    order = keypoint_order(detector.keypoints, ds.keypoints)  # refuse a mismatch before detecting anything
    ids = np.array(opts.pick(split_frames(ds, split)), dtype=np.int64)
    if not len(ids):
        raise UserError(f"{data}: no frames of split {split!r} between --start {opts.start} and --stop "
                        f"{opts.stop}", hint="choose another --split, --start or --stop")
    skeleton = detector.meta.recorded_skeleton() or ds.skeleton
    sizes = [tuple(ds.image_size)] * len(ds.cameras)
    store = FrameStore(ds, ids, preload_mb=0, labels=True, points=True)
    with opts.recorder(detector.keypoints, ds.cameras, skeleton, ds.units) as rec:
        _framed(rec, ds, ids)
        if ds.static_calibration:
            rec.cameras_at(ds.rig(np.float64), sizes)
        for batch, det in detect_store(detector, store, batch_size):
            uv, mask = ds.labels(batch.frame_ids, np.float64)
            cams = ds.calibration(batch.frame_ids, np.float64)
            X, valid = _truth(ds, batch.frame_ids, cams, uv, mask)
            for b, f in enumerate(batch.frame_ids):
                if not ds.static_calibration:
                    rec.set_frame(int(f))
                    rec.cameras_at(cams[b], sizes, static=False)
                views = list(batch.images[b].numpy()) if opts.images else None
                rec.detection(int(f), views, det, b)
                rec.points2d("labels", uv[b][:, order], mask[b][:, order])
                rec.points3d(X[b][order], valid[b][order], name="truth", skeleton="truth_skeleton",
                             show_names=False)
    return len(ids)
