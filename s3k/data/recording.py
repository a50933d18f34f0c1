"""A calibrated multi-camera recording -> an s3k dataset (the work of ``s3k import``).

The recording is a calibration (anipose ``calibration.toml``, Qualisys ``.qca.txt``, OpenCV / JARVIS YAML or
XML, DeepFly3D pickle: :mod:`s3k.data.formats.calibration_files`), one video or image sequence per camera
(:mod:`s3k.data.video`) and, optionally, 2D labels per camera: SLEAP analysis files
(:mod:`s3k.data.formats.sleap`), DeepLabCut / Lightning Pose CSVs (:mod:`s3k.data.formats.dlc`), OpenPose or
MMPose JSON (:mod:`s3k.data.formats.pose_json`) or a DeepFly3D pose result
(:mod:`s3k.data.formats.deepfly3d`), each read by its format's dataclass of :mod:`s3k.data.import_labels`,
which this module never asks about. Frames whose labels have a keypoint in ``min_views`` cameras are split at
random into labelled and test frames; every ``stride``-th other frame is unlabelled (without labels every kept
frame is). Images may be cropped and resized on the way; intrinsics and labels follow exactly (``K' = M K``).
The dataset is written to a temporary folder beside ``out`` and renamed at the end, so a failed import leaves
nothing behind.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.base.outputs import check_replaceable, replace_folder
from s3k.data import video
from s3k.data.formats import pixels
from s3k.data.formats.calibration_files import read_calibration
from s3k.data.formats.labels2d import LabelTable, coverage_warnings, unique_edges
from s3k.data.formats.skeleton import anipose_project_config, check_edges, read_skeleton
from s3k.data.import_choices import (
    PADDING_PX,
    Box,
    drop_outside,
    image_areas,
    labelled_count,
    output_size,
    pad_to_one_size,
    split_frames,
)
from s3k.data.import_labels import LabelFormat, LabelsRead
from s3k.data.import_report import calibration_warnings, kept_labels_summary
from s3k.data.rig import Rig, check_camera_name
from s3k.data.splits import TestFrames, held_out_split, session_split
from s3k.data.tables import NAME_RE
from s3k.data.writer import DatasetWriter
from s3k.geometry import Cameras
from s3k.geometry.warp import crop_resize_matrix, resize_crop, transform_points

log = logging.getLogger(__name__)


def _prepare_rig(calibration: str | Path, videos: Mapping[str, str | Path], units: str | None,
                 regions: Mapping[str, Sequence[float]] | None,
                 convention: pixels.Convention | None) -> tuple[Rig, dict[str, tuple[int, int]]]:
    """The calibration's cameras of ``videos`` in s3k's pixels (its file's in ``convention``) at the videos'
    sizes (after ``regions``); the video sizes."""
    cameras = list(videos)
    rig = pixels.rig_to_s3k(read_calibration(calibration, units=units), convention)
    try:
        rig = rig.select(cameras)
    except KeyError as exc:
        raise UserError(f"{calibration}: {exc.args[0]}") from None
    missing = [f"{cam}={p}" for cam, p in videos.items() if not video.exists(p)]
    if missing:
        raise UserError(f"--videos {missing[0]}: no such video file, image folder or image pattern")
    sizes = {cam: video.frame_size(videos[cam]) for cam in cameras}
    rig = rig.with_sizes(sizes)
    if regions:
        unknown = sorted(set(regions) - set(cameras))
        if unknown:
            raise UserError(f"--video-region: cameras {unknown} have no --videos entry "
                            f"({', '.join(cameras)})")
        try:
            rig = rig.with_video_regions({cam: tuple(box) for cam, box in regions.items()})  # type: ignore[misc]
        except ValueError as exc:
            raise UserError(f"--video-region {exc}") from None
    off = [cam for c, cam in enumerate(cameras) if sizes[cam] != tuple(int(v) for v in rig.size[c])]
    if off:
        c = cameras.index(off[0])
        W, H = sizes[off[0]]
        calibrated = {cam: tuple(int(v) for v in rig.size[cameras.index(cam)]) for cam in off}
        padding = all(abs(sizes[cam][i] - calibrated[cam][i]) <= PADDING_PX for cam in off for i in (0, 1))
        regions_hint = " ".join(f"{cam}=0,0,{sizes[cam][0]},{sizes[cam][1]}" for cam in off)
        raise UserError(
            f"{videos[off[0]]}: video is {W}x{H} but {calibration} gives camera {off[0]!r} size "
            f"{rig.size[c][0]}x{rig.size[c][1]}" + (f" ({len(off)} cameras differ)" if len(off) > 1 else ""),
            hint=f"if the videos are the calibrated images with rows or columns cut or added at the bottom "
                 f"and right (an encoder's padding), pass --video-region {regions_hint} (other placements: "
                 "docs/importing.md)" if padding else
                 f"if the video is the calibrated image cropped or padded, declare the region it shows with "
                 f"--video-region {off[0]}=X0,Y0,X1,Y1 (docs/importing.md)",
        )
    return rig, sizes


def _frame_offsets(given: Mapping[str, int] | None, cameras: list[str]) -> list[int]:
    """Each camera's frame offset (``--frame-offsets``), 0 where not given."""
    unknown = sorted(set(given or {}) - set(cameras))
    if unknown:
        raise UserError(f"--frame-offsets {unknown[0]}={(given or {})[unknown[0]]}: no camera {unknown[0]!r} "
                        f"(cameras: {', '.join(cameras)})")
    return [int((given or {}).get(cam, 0)) for cam in cameras]


def _shifted(read: LabelsRead, cameras: list[str], offsets: list[int]) -> LabelsRead:
    """The labels of each camera at the frames of the cameras of offset 0: frame ``i`` becomes ``i + N``."""
    if not any(offsets):
        return read
    tables = {}
    for cam, table in read.tables.items():
        ids = table.frame_ids + offsets[cameras.index(cam)]
        keep = ids >= 0
        tables[cam] = replace(table, frame_ids=ids[keep], uv=table.uv[keep])
    return replace(read, tables=tables)


def _frame_range(videos: Mapping[str, str | Path], offsets: list[int]) -> tuple[int, int]:
    """The frames ``first .. end - 1`` that every camera filmed (camera ``c``: its frames ``f - N_c``)."""
    counts = _frame_counts(videos)
    ends = [counts[cam] + n for cam, n in zip(videos, offsets)]
    first, end = max(0, *offsets), min(ends)
    if len(set(ends)) > 1 or first:
        shifted = f" with --frame-offsets {dict(zip(videos, offsets))}" if any(offsets) else ""
        log.warning("videos have different frame counts %s%s; using frames %d to %d", counts, shifted, first,
                    end - 1)
    if end - first < 1:
        raise UserError(f"--frame-offsets {dict(zip(videos, offsets))}: no frame is filmed by every camera "
                        f"(frame counts {counts})")
    return first, end


def _frame_counts(videos: Mapping[str, str | Path]) -> dict[str, int]:
    """Frames each video decodes to; a warning when the container header says otherwise."""
    counts = {}
    for cam, path in videos.items():
        decoded = video.frame_count(path, exact=True)
        header = video.frame_count(path)
        if header != decoded:
            log.warning("%s: the header says %d frames but %d decode; using %d", path, header, decoded,
                        decoded)
        counts[cam] = decoded
    return counts


@dataclass(frozen=True)
class SplitOptions:
    """How the frames are split.

    Attributes:
        labelled: number of labelled frames, or ``"all"``; None: 10, or all there are after the test frames
            when fewer (the import says so).
        test: number of test frames (their labels are kept for evaluation).
        seed: seed of the random split.
        stride: keep every ``stride``-th video frame as unlabelled.
        min_views: a frame can be labelled/test when a keypoint is labelled in this many cameras.
        test_frames: ``"blocks"`` (test frames in ``blocks`` contiguous runs, no labelled frame within
            ``margin`` frames of them), ``"last"`` (one block, the last frames with labels), ``"random"``,
            or ``"session"`` (every labelled frame a test frame, nothing to train on: a held-out session);
            :mod:`s3k.data.splits`.
        margin: frames between the test blocks and the labelled frames (None: the default, or less where
            the recording is too short, said in a note).
        blocks: the number of contiguous test blocks.
    """

    labelled: int | Literal["all"] | None = None
    test: int = 0
    seed: int = 0
    stride: int = 1
    min_views: int = 2
    test_frames: TestFrames = "blocks"
    margin: int | None = None
    blocks: int = 1


@dataclass(frozen=True)
class ImageOptions:
    """How the images are cut and sized; intrinsics and labels follow exactly (``K' = M K``).

    Attributes:
        size: output image size ``(W, H)``, or the longer side in pixels (aspect kept).
        scale: output image scale factor (instead of ``size``).
        crops: ``{camera: (x0, y0, x1, y1)}`` crop boxes in pixel edge coordinates (default: whole image).
        video_regions: ``{camera: (x0, y0, x1, y1)}``: the region of the calibrated image each video shows
            (:meth:`s3k.data.rig.Rig.with_video_regions`), for videos a few pixels smaller or larger.
    """

    size: int | tuple[int, int] | None = None
    scale: float | None = None
    crops: Mapping[str, Sequence[float]] | None = None
    video_regions: Mapping[str, Sequence[float]] | None = None


def import_recording(calibration: str | Path, videos: Mapping[str, str | Path], out: str | Path,
                     labels: LabelFormat | None = None, *, split: SplitOptions = SplitOptions(),
                     images: ImageOptions = ImageOptions(), keypoints: Sequence[str] | None = None,
                     units: str | None = None, overwrite: bool = False,
                     skeleton: str | Path | None = None, session: str | None = None,
                     subject: str | None = None, frame_offsets: Mapping[str, int] | None = None,
                     label_pixels: pixels.Convention | None = None,
                     calibration_pixels: pixels.Convention | None = None) -> Path:
    """Convert a recording to a dataset folder; returns the folder.

    Args:
        calibration: a calibration file (or folder) of any format :func:`s3k.data.formats.calibration_files.
            read_calibration` reads.
        videos: ``{camera: video or image sequence}``; the order sets the dataset's camera order.
        out: dataset folder to write (all or nothing: written beside it and renamed at the end).
        labels: the 2D labels, one of :data:`s3k.data.import_labels.LABEL_FORMATS` (e.g.
            ``SleapFiles({"cam0": "cam0.analysis.h5", ...})``); None: every frame is unlabelled and
            ``keypoints`` names the keypoints.
        split: how the frames are split (:class:`SplitOptions`).
        images: how the images are cropped and sized (:class:`ImageOptions`).
        keypoints: keypoints to keep, in this order (default: all, in the label files' order).
        units: world length unit of the calibration (default: from the file or its board).
        overwrite: replace an existing dataset folder.
        skeleton: a file to take the skeleton from (:func:`s3k.data.formats.skeleton.read_skeleton`);
            default: the labels' own (SLEAP, a DeepLabCut project), else an anipose project's config.toml.
        session: name the recording's session (frames.csv's ``session`` column; s3k.json's ``sessions``
            records its frame rate and ``subject``); None: a dataset without sessions.
        frame_offsets: ``{camera: N}`` for cameras whose clock is off (default 0): the camera's frame ``i``
            shows the others' frame ``i + N`` (:mod:`s3k.data.sync` estimates it, ``s3k validate`` reports
            it). A dataset frame ``f`` holds each camera's frame ``f - N`` and its labels; frame ids follow
            the cameras of offset 0, and only the frames every camera filmed are kept.
        label_pixels, calibration_pixels: the pixel convention (:mod:`s3k.data.formats.pixels`) of the
            label files and of the calibration where it is not their format's (None: the format's).
    """
    out = Path(out)
    for camera in videos:
        check_camera_name(camera, "--videos")
    check_replaceable(out, overwrite, {"--calibration": calibration, "--videos": list(videos.values())})
    if split.stride < 1:
        raise UserError(f"--stride must be >= 1, got {split.stride}")
    if session is not None and not NAME_RE.match(session):
        raise UserError(f"--session {session!r}: a session name must be usable as a file name (letters, "
                        "digits, _ . + -)")
    cameras = list(videos)
    rig, sizes = _prepare_rig(calibration, videos, units, images.video_regions, calibration_pixels)
    read = labels.read(cameras, sizes, rig) if labels is not None else LabelsRead("none", {}, {})
    if label_pixels is not None and read.tables:
        own = pixels.FORMATS[read.kind][0]
        read = replace(read, tables={cam: replace(t, uv=pixels.relabel(t.uv, own, label_pixels))
                                     for cam, t in read.tables.items()})
    for note in read.notes:
        log.info(note)
    offsets = _frame_offsets(frame_offsets, cameras)
    read = _shifted(read, cameras, offsets)
    names = _keypoint_names(read.tables, keypoints, split.test)
    edges = _skeleton(read.tables, names, skeleton, calibration)
    first, n_frames = _frame_range(videos, offsets)
    geometry = _image_geometry(rig, cameras, images)
    uv = _dense_labels(read, cameras, names, n_frames, geometry.maps)
    uv[:first] = np.nan  # a frame some camera did not film
    dropped = drop_outside(uv, image_areas(geometry.boxes, rig.size, geometry.out_size), cameras, names)
    mask = np.isfinite(uv).all(-1)
    candidates = np.flatnonzero((mask.sum(axis=1) >= split.min_views).any(axis=1))
    splits, n_labelled, split = _choose_splits(candidates, np.arange(first, n_frames), split, dropped,
                                               bool(read.tables))
    named = None if session is None else (session, _session_info(videos, subject))
    _write_dataset(out, overwrite, calibration, videos, read, rig, names, edges, geometry, uv, mask, splits,
                   split, images, named, offsets)
    _report(out, calibration, rig, cameras, names, geometry, uv, mask, candidates, splits, n_labelled, split)
    return out


def _choose_splits(candidates: np.ndarray, frames: np.ndarray, split: SplitOptions, dropped: str,
                   labels: bool) -> tuple[dict[int, str], int | str, SplitOptions]:
    """The split of every kept frame (of ``frames``) by ``split.test_frames``, the number of labelled frames
    asked for, and the options as the report tells them (a held-out session's test count)."""
    if split.test_frames == "session":
        if not len(candidates):
            raise UserError("a held-out test session needs labels: give the session's label files")
        return session_split(candidates), 0, replace(split, labelled=0, test=len(candidates))
    n_labelled = (labelled_count(candidates, split.labelled, split.test, split.min_views, dropped)
                  if labels else 0)
    if split.test_frames == "random":
        chosen = split_frames(candidates, frames, n_labelled, split.test, split.seed, split.stride)
        return chosen, n_labelled, split
    splits = held_out_split(candidates, frames, n_labelled, split.test, split.seed, split.stride,
                            split.margin, split.blocks, fewer_ok=split.labelled is None,
                            last=split.test_frames == "last")
    return splits, n_labelled, split


def _skeleton(tables: Mapping[str, LabelTable], keypoints: list[str], skeleton: str | Path | None,
              calibration: str | Path) -> list[tuple[str, str]]:
    """The dataset's skeleton: the file given (``--skeleton``), else the labels' own (SLEAP's edges, a
    DeepLabCut project's config.yaml), else an anipose project's config.toml above the calibration; its edges
    between the kept ``keypoints``."""
    labels_keypoints: list[str] = []
    for table in tables.values():
        labels_keypoints += [k for k in table.keypoints if k not in labels_keypoints]
    edges: list[tuple[str, str]] = []
    source = ""
    if skeleton is not None:
        edges, source = read_skeleton(skeleton), str(skeleton)
        check_edges(edges, labels_keypoints or keypoints, f"--skeleton {skeleton}")
        if not edges:
            log.warning(f"--skeleton {skeleton}: the file gives no skeleton edges")
    else:
        for table in tables.values():
            if table.skeleton:
                edges, source = unique_edges([*edges, *table.skeleton]), source or table.skeleton_source
        config = anipose_project_config(calibration) if not edges else None
        if config is not None:
            edges, source = read_skeleton(config), str(config)
            edges = [e for e in edges if set(e) <= set(labels_keypoints or keypoints)]
    kept = [e for e in edges if set(e) <= set(keypoints)]
    if edges:
        left = len(edges) - len(kept)
        dropped = f" ({left} to keypoints not kept left out)" if left else ""
        log.info(f"skeleton: {len(kept)} edges from {source}{dropped}")
    return kept


def _recorded(path: str | Path, out: str | Path) -> str:
    """How ``s3k.json`` records a source file: absolute when given absolute, else relative to the dataset
    folder ``out`` (read back with :func:`s3k.base.fileio.resolve_from`), so that a dataset moved together
    with its recording keeps finding it."""
    path = Path(path)
    if path.is_absolute():
        return str(path)
    return Path(os.path.relpath(path.resolve(), Path(out).resolve())).as_posix()


def _keypoint_names(tables: Mapping[str, LabelTable], keypoints: Sequence[str] | None,
                    test: int) -> list[str]:
    """The dataset's keypoints: ``keypoints`` when given (each must be in the labels), else every label
    file's, merged by name in their order."""
    names: list[str] = []
    for table in tables.values():
        names += [k for k in table.keypoints if k not in names]
    if not tables:
        if not keypoints:
            raise UserError("no labels given: name the keypoints with --keypoints a,b,c (every frame is "
                            "imported unlabelled), or give labels in one of the formats of docs/importing.md")
        if test:
            raise UserError(f"--test {test}: test frames need labels, and none are given")
    elif keypoints:
        missing = [k for k in keypoints if k not in names]
        if missing:
            raise UserError(f"--keypoints: {missing} not in the labels ({', '.join(names)})")
    return list(keypoints) if keypoints else names


@dataclass
class _Geometry:
    """Each camera's crop box in its video, the output size, the pixel maps and the output intrinsics."""

    boxes: list[Box]
    out_size: tuple[int, int]
    maps: list[np.ndarray]
    K: np.ndarray
    arrays: dict[str, np.ndarray]


def _image_geometry(rig: Rig, cameras: list[str], images: ImageOptions) -> _Geometry:
    """Crop and resize: one pixel map per camera, applied to K and to the labels."""
    boxes: list[Box] = [(0.0, 0.0, float(W), float(H)) for W, H in rig.size]
    if not images.crops and images.size is None:
        boxes = pad_to_one_size(boxes, cameras)
    for cam, box in (images.crops or {}).items():
        if cam not in cameras or len(box) != 4:
            raise UserError(f"--crop {cam}={box}: need one of the cameras ({', '.join(cameras)}) and "
                            "x0,y0,x1,y1")
        boxes[cameras.index(cam)] = (float(box[0]), float(box[1]), float(box[2]), float(box[3]))
    out_size = output_size(boxes, images.size, images.scale)
    maps = [crop_resize_matrix(box, out_size) for box in boxes]
    arrays = rig.cameras.numpy()
    K_out = np.stack([resize_crop(None, arrays["K"][c], boxes[c], out_size)[1] for c in range(len(cameras))])
    return _Geometry(boxes, out_size, maps, K_out, arrays)


def _dense_labels(read: LabelsRead, cameras: list[str], names: list[str], n_frames: int,
                  maps: list[np.ndarray]) -> np.ndarray:
    """``(F, C, K, 2)`` labels in output pixels (NaN where unlabelled); warns of labels beyond the videos and
    of what each camera's labels leave out."""
    uv = np.full((n_frames, len(cameras), len(names), 2), np.nan)
    for c, cam in enumerate(cameras):
        if cam not in read.tables:
            continue
        table = read.tables[cam]
        beyond = table.frame_ids >= n_frames
        if beyond.any():
            log.warning("%s: %d labelled frames beyond the video's %d frames are ignored", table.source,
                        int(beyond.sum()), n_frames)
        present = [k for k in names if k in table.keypoints]
        cols = [names.index(k) for k in present]
        uv[:, c, cols] = transform_points(table.dense(n_frames, present), maps[c])
    if read.tables:
        unseen = {cam: table.unseen for cam, table in read.tables.items()}
        for line in coverage_warnings(np.isfinite(uv).all(-1), cameras, names, read.files, unseen):
            log.info(line)
    return uv


def _write_dataset(out: Path, overwrite: bool, calibration: str | Path, videos: Mapping[str, str | Path],
                   read: LabelsRead, rig: Rig, names: list[str], edges: list[tuple[str, str]],
                   geometry: _Geometry, uv: np.ndarray,
                   mask: np.ndarray, splits: dict[int, str], split: SplitOptions,
                   images: ImageOptions, session: tuple[str, dict[str, Any]] | None,
                   offsets: list[int]) -> None:
    """Write the dataset beside ``out`` and rename it at the end (all or nothing)."""
    cameras = list(videos)
    source: dict[str, Any] = {
        "importer": read.kind,
        "calibration": _recorded(calibration, out),
        "videos": {cam: _recorded(p, out) for cam, p in videos.items()},
        "labels": {cam: _recorded(p, out) for cam, p in read.files.items()},
        "crop_boxes": {cam: list(b) for cam, b in zip(cameras, geometry.boxes)},
        "source_image_size": {cam: [int(v) for v in rig.size[c]] for c, cam in enumerate(cameras)},
        "split_seed": split.seed,
    }
    if images.video_regions:
        source["video_regions"] = {cam: [float(v) for v in box] for cam, box in images.video_regions.items()}
    if any(offsets):
        source["frame_offsets"] = dict(zip(cameras, offsets))
    what = f"{read.kind} labels" if read.tables else "no labels"
    boxes, out_size, arrays = geometry.boxes, geometry.out_size, geometry.arrays
    with replace_folder(out, overwrite) as tmp:
        writer = DatasetWriter(
            tmp, names, cameras, out_size, rig.units,
            calibration=(geometry.K, arrays["dist"], arrays["R"], arrays["t"]), source=source, skeleton=edges,
            description=f"imported from {what} and {Path(calibration).name}",
            sessions=None if session is None else {session[0]: {**session[1], "source": source}},
        )
        extra = {} if session is None else {"session": session[0]}
        kept = sorted(splits)
        streams = [video.iter_frames(videos[cam], [f - n for f in kept]) for cam, n in zip(cameras, offsets)]
        for f, frames in zip(kept, zip(*streams)):
            pictures = []
            for c, (i, image) in enumerate(frames):
                if i != f - offsets[c]:  # pragma: no cover - iter_frames yields the frames asked for
                    raise RuntimeError(f"{videos[cameras[c]]}: decoded frame {i}, expected {f - offsets[c]}")
                pictures.append(resize_crop(image, None, boxes[c], out_size)[0])
            frame_labels = (np.nan_to_num(uv[f]), mask[f]) if splits[f] != "unlabelled" else None
            writer.add_frame(f, splits[f], np.stack(pictures), labels=frame_labels,
                             extra={**extra, "video_frame": f})
        writer.close()


def _session_info(videos: Mapping[str, str | Path], subject: str | None) -> dict[str, Any]:
    """A session's metadata: its videos' frame rate (the first camera's) and its subject when given."""
    first = next(iter(videos.values()))
    try:
        rate: float | None = video.frame_rate(first)
    except ValueError:
        log.warning("%s declares no frame rate; the session's frame_rate is not recorded", first)
        rate = None
    return {k: v for k, v in (("frame_rate", rate), ("subject", subject)) if v is not None}


def _report(out: Path, calibration: str | Path, rig: Rig, cameras: list[str], names: list[str],
            geometry: _Geometry, uv: np.ndarray, mask: np.ndarray, candidates: np.ndarray,
            splits: dict[int, str], n_labelled: int | str, split: SplitOptions) -> None:
    """What was written, what the labels kept, and the calibration's consistency with the labels."""
    n = {s: sum(1 for v in splits.values() if v == s) for s in ("labelled", "test", "unlabelled")}
    n_labels = int(sum(mask[f].sum() for f, s in splits.items() if s != "unlabelled"))
    W, H = geometry.out_size
    log.info(f"wrote {out}: {len(splits)} frames (labelled {n['labelled']}, test {n['test']}, unlabelled "
             f"{n['unlabelled']}), {len(cameras)} cameras {', '.join(cameras)}, {len(names)} keypoints, "
             f"{W}x{H} px, {n_labels} 2D labels, units {rig.units}")
    for line in kept_labels_summary(mask.sum(axis=(1, 2)), candidates, splits, n_labelled, split.test,
                                    split.min_views):
        if line.startswith("warning: "):
            log.warning(line.removeprefix("warning: "))
        else:
            log.info(line)
    arrays = geometry.arrays
    cams = Cameras.from_numpy(geometry.K, arrays["dist"], arrays["R"], arrays["t"], dtype=torch.float64)
    for line in calibration_warnings(cams, uv[candidates], mask[candidates], cameras, geometry.out_size, out):
        log.warning(line)
    if rig.units == "unknown":
        log.warning("%s does not give its world unit; pass --units (e.g. mm) so that 3D errors have one",
                    calibration)
