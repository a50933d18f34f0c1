"""A dataset's 2D labels out to other tools (``s3k export-labels``) and 3D tracks to NWB
(``s3k export-tracks``).

Formats: ``dlc`` (one DeepLabCut CSV per camera, ``labeled-data/<camera>/CollectedData_<scorer>.csv``, with
the labelled images beside it, and the project's ``config.yaml`` with the bodyparts and the skeleton),
``lightning-pose`` (Lightning Pose's multi-view layout:
``CollectedData_<camera>.csv`` per view, the same frames on the same rows of every view, images under
``labeled-data/<camera>/``), ``sleap`` (one ``.slp`` project, a video per camera, a recording session with
the calibration) and ``nwb`` (ndx-pose training frames, cameras as calibrated devices).

Frame numbers are the dataset's ``video_frame`` column when it has one (a dataset made by ``s3k import``),
else the frame ids. The DLC and Lightning Pose exports carry the dataset's images, so labels are in their
pixels. SLEAP and NWB refer to videos: for a dataset imported from videos they are the original videos, and
labels are mapped back through the import's crop and resize into the videos' pixels; otherwise they are the
dataset's videos, its PNG sequences (frame ids 0..N-1), or names ``<camera>.mp4`` to be pointed at the
videos in SLEAP.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from s3k.base.errors import UserError
from s3k.base.fileio import open_text, resolve_from
from s3k.base.outputs import check_output, check_output_folder
from s3k.data.dataset import Dataset
from s3k.data.formats.anipose import read_anipose_calibration
from s3k.data.formats.dlc import write_dlc_csv
from s3k.data.formats.labels2d import LabelTable
from s3k.data.formats.nwb import write_nwb_labels, write_nwb_tracks
from s3k.data.formats.skeleton import write_dlc_config
from s3k.data.formats.slp import write_slp
from s3k.data.tables import DEFAULT_IMAGE_PATTERN
from s3k.data.tracks_csv import read_csv, read_source, source_path
from s3k.geometry.warp import crop_resize_matrix, transform_points

log = logging.getLogger(__name__)

FORMATS = ("dlc", "lightning-pose", "sleap", "nwb")
SUFFIX = {"sleap": ".slp", "nwb": ".nwb"}


def dataset_tables(ds: Dataset, splits: Sequence[str] | None = None
                   ) -> tuple[np.ndarray, dict[str, LabelTable]]:
    """The dataset's labels as one :class:`LabelTable` per camera over the frames with a label.

    Returns:
        ``frame_ids (F,)`` of the dataset, and ``{camera: LabelTable}`` whose ``frame_ids`` are the frames'
        video frame numbers (the ``video_frame`` column, else the frame ids), ``uv`` NaN where unlabelled.
    """
    ids = ds.frames(list(splits) if splits else None)
    ids = np.sort(ids)
    uv, mask = ds.labels(ids, dtype=np.float64)
    keep = mask.reshape(len(ids), -1).any(axis=1)
    ids, uv, mask = ids[keep], uv[keep], mask[keep]
    if not len(ids):
        raise UserError(f"{ds.path}: no 2D labels in splits {', '.join(splits or ['any'])}",
                        hint="choose other splits with --split")
    video_frames = ids
    if "video_frame" in ds.frame_columns:
        video_frames = np.array([int(v) for v in ds.column("video_frame", ids)], dtype=np.int64)
    uv = np.where(mask[..., None], uv, np.nan)
    return ids, {
        cam: LabelTable(list(ds.keypoints), video_frames, uv[:, c], f"{ds.path} ({cam})")
        for c, cam in enumerate(ds.cameras)
    }


def _image_path(ds: Dataset, cam: str, frame: int) -> Path:
    pattern = ds.metadata.get("images", {}).get("pattern", DEFAULT_IMAGE_PATTERN)
    return (Path(ds.path) / pattern.format(camera=cam, frame=int(frame))).resolve()


def source_maps(ds: Dataset) -> dict[str, np.ndarray] | None:
    """``{camera: M}``, the pixel map of ``s3k import``'s crop and resize from the source video to the
    dataset's images, for a dataset imported from videos; else None."""
    source = ds.source if isinstance(ds.source, dict) else {}
    videos, boxes = source.get("videos"), source.get("crop_boxes")
    if not isinstance(videos, dict) or not isinstance(boxes, dict) or not set(ds.cameras) <= set(boxes):
        return None
    return {cam: crop_resize_matrix(tuple(boxes[cam]), ds.source_image_size) for cam in ds.cameras}


def video_references(ds: Any, tables: dict[str, LabelTable]) -> dict[str, Any]:
    """``{camera: video file, or a list of image files}`` that the labels' frame numbers index. For a
    dataset imported from videos the labels are mapped into the videos' pixels (``tables`` changes)."""
    images = ds.metadata.get("images", {})
    if images.get("type") == "video":
        return {cam: str((Path(ds.path) / images["videos"][cam]).resolve()) for cam in ds.cameras}
    maps = source_maps(ds)
    if maps is not None:
        for cam in ds.cameras:
            tables[cam].uv = transform_points(tables[cam].uv, np.linalg.inv(maps[cam]))

        return {cam: str(resolve_from(ds.path, ds.source["videos"][cam])) for cam in ds.cameras}
    if np.array_equal(np.sort(ds.frame_ids), np.arange(len(ds.frame_ids))):
        return {cam: [str(_image_path(ds, cam, f)) for f in range(len(ds.frame_ids))] for cam in ds.cameras}
    return {cam: f"{cam}.mp4" for cam in ds.cameras}


def _rig(ds: Any) -> dict[str, Any] | None:
    """``{camera: (K, dist, R, t, (W, H))}`` of a static rig in the pixels of :func:`video_references`,
    else None."""
    if not ds.static_calibration:
        return None
    cams = ds.rig(np.float64).numpy()
    maps = source_maps(ds) if ds.metadata.get("images", {}).get("type") != "video" else None
    rig = {}
    for c, cam in enumerate(ds.cameras):
        K, size = cams["K"][c], tuple(ds.image_size)
        if maps is not None:
            K = np.linalg.inv(maps[cam]) @ K  # back to the source video's pixels (the import made K' = M K)
            size = tuple(ds.source.get("source_image_size", {}).get(cam, size))
        rig[cam] = (K, cams["dist"][c], cams["R"][c], cams["t"][c], size)
    return rig


def _write_images(ds: Dataset, ids: np.ndarray, c: int, paths: list[Path]) -> None:
    """Camera ``c``'s images of frames ``ids`` to ``paths`` (PNG)."""
    for start in range(0, len(ids), 64):
        images = ds.images(ids[start:start + 64])
        for b, target in enumerate(paths[start:start + 64]):
            target.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(target), cv2.cvtColor(images[b, c], cv2.COLOR_RGB2BGR)):
                raise OSError(f"{target}: cannot write the image")


def export_labels(
    dataset: str | Path,
    fmt: str,
    out: str | Path,
    *,
    splits: Sequence[str] | None = None,
    scorer: str = "s3k",
    images: bool = True,
    overwrite: bool = False,
) -> list[Path]:
    """Write a dataset's 2D labels in another tool's format; returns the files written.

    Args:
        dataset: the dataset folder.
        fmt: one of :data:`FORMATS`.
        out: a folder for ``dlc`` / ``lightning-pose``; a ``.slp`` / ``.nwb`` file otherwise.
        splits: the splits whose labels to write (default every split).
        scorer: the annotator name (DLC / Lightning Pose header).
        images: write the labelled frames' images beside the CSVs (``dlc`` / ``lightning-pose``).
        overwrite: replace existing output files.
    """
    if fmt not in FORMATS:
        raise UserError(f"--format {fmt!r}: choose one of {', '.join(FORMATS)}")
    out = Path(out)
    ds = Dataset.open(dataset, cache="none")
    check_output_folder(out, inputs={"DATASET": dataset})  # never inside a dataset or over a run's files
    ids, tables = dataset_tables(ds, splits)
    if fmt in SUFFIX:
        if out.is_dir():
            raise UserError(f"--out {out} is a folder; give a {SUFFIX[fmt]} file name")
        if out.exists() and not overwrite:
            raise UserError(f"--out {out} exists", hint="pass --overwrite to replace it")
        refs = video_references(ds, tables)
        rig = _rig(ds)
        if fmt == "sleap":
            return [write_slp(out, tables, refs, skeleton=ds.skeleton, rig=rig)]

        return [write_nwb_labels(out, tables, refs, skeleton=ds.skeleton, rig=rig,
                                 description=f"2D keypoint labels of the s3k dataset {Path(ds.path).name}")]


    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder for --format {fmt}")
    config = out / "config.yaml"
    if fmt == "dlc" and config.exists() and not overwrite:
        raise UserError(f"{config} exists", hint="pass --overwrite to replace it")
    written = []
    for cam, table in tables.items():
        # DLC: the frames labelled in this camera; Lightning Pose: the same frames on the same rows of every
        # view
        keep = np.isfinite(table.uv).all(-1).any(-1) if fmt == "dlc" else np.ones(len(ids), bool)
        if not keep.any():
            log.warning(f"camera {cam} has no labels; no CSV written for it")
            continue
        names = [f"labeled-data/{cam}/img{int(f):06d}.png" for f in table.frame_ids[keep]]
        if fmt == "dlc":
            path = out / "labeled-data" / cam / f"CollectedData_{scorer}.csv"
        else:
            path = out / f"CollectedData_{cam}.csv"
        if path.exists() and not overwrite:
            raise UserError(f"{path} exists", hint="pass --overwrite to replace it")
        table = LabelTable(table.keypoints, table.frame_ids[keep], table.uv[keep], table.source)
        written.append(write_dlc_csv(path, table, names, scorer=scorer))
        if images:
            _write_images(ds, ids[keep], c=ds.cameras.index(cam), paths=[out / n for n in names])
    if fmt == "dlc" and written:

        # the project's config.yaml: its bodyparts and skeleton, which DeepLabCut and s3k import read
        written.append(write_dlc_config(config, ds.keypoints, ds.skeleton, scorer,
                                        [str(p.parent.name) for p in written], Path(ds.path).name))
    return written


def export_tracks(
    csv_path: str | Path,
    fmt: str,
    out: str | Path,
    *,
    fps: float | None = None,
    calibration: str | Path | None = None,
    units: str | None = None,
    overwrite: bool = False,
) -> tuple[Path, str]:
    """Write the 3D CSV of ``s3k track`` / ``s3k predict`` as NWB; returns the file and the unit used.

    Args:
        csv_path: the anipose-style 3D CSV.
        fmt: ``"nwb"``.
        out: the ``.nwb`` file.
        fps: frame rate of the videos (timestamps are ``fnum / fps``); default the one ``s3k track`` wrote
            beside the CSV (:func:`s3k.data.tracks_csv.read_source`).
        calibration: the anipose ``calibration.toml`` of the rig, stored with the tracks and giving the unit.
        units: world unit (default: the calibration's, else the one ``s3k track`` / ``s3k predict`` wrote
            beside the CSV, :func:`s3k.data.tracks_csv.read_source`).
        overwrite: replace an existing file.

    Raises:
        UserError: the unit or the frame rate is not known (none given, no calibration, nothing beside the
            CSV): never guessed.
    """

    if fmt != "nwb":
        raise UserError(f"--format {fmt!r}: 3D tracks export to nwb")
    check_output(out, overwrite, inputs={"CSV": csv_path, "--calibration": calibration})
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise FileNotFoundError(2, "3D CSV not found", str(csv_path))
    with open_text(csv_path) as f:
        header = next(csv.reader(f), [])
    keypoints = [c[:-2] for c in header if c.endswith("_x")]
    if not keypoints or "fnum" not in header:
        raise UserError(f"{csv_path}: not a 3D keypoints CSV (expected columns <keypoint>_x, _y, _z, ..., "
                        "fnum)")
    points = read_csv(csv_path, keypoints)
    fnums = np.array(sorted(points), dtype=np.int64)
    X = np.stack([points[f] for f in fnums]) if len(fnums) else np.zeros((0, len(keypoints), 3))
    score = _column(csv_path, header, [f"{k}_score" for k in keypoints], fnums)
    rig = None
    if calibration is not None:
        r = read_anipose_calibration(calibration, units=units)
        arrays = r.cameras.numpy()
        rig = {cam: (arrays["K"][c], arrays["dist"][c], arrays["R"][c], arrays["t"][c], tuple(r.size[c]))
               for c, cam in enumerate(r.names)}
        units = units or (r.units if r.units != "unknown" else None)
    source = read_source(csv_path)
    if units is None and source is not None and source["units"] != "unknown":
        units = source["units"]
    if units is None:
        raise UserError(f"{csv_path}: the unit of its points is not known (no --calibration, and no "
                        f"{source_path(csv_path).name} with it as 's3k track' and 's3k predict' write)",
                        hint="pass --units (e.g. mm), or --calibration with the rig's calibration")
    if source is not None and source["units"] not in (units, "unknown"):
        log.warning(f"{csv_path}'s points are in {source['units']} ({source_path(csv_path).name}) but are "
                    f"written as {units}")
    if fps is None:
        fps = _source_rate(source)
    if fps is None:
        raise UserError(f"{csv_path}: the frame rate of its frames is not known (no "
                        f"{source_path(csv_path).name} with it, as 's3k track' writes from videos)",
                        hint="pass --fps (e.g. --fps 30)")
    path = write_nwb_tracks(out, keypoints, fnums, X, score, fps=fps, units=units, rig=rig,
                            description=f"3D keypoints from {csv_path.name} (s3k)")
    return path, units


def _source_rate(source: dict[str, str] | None) -> float | None:
    """The frame rate recorded beside a 3D CSV (``fps`` of its ``.s3k.json``), None when absent or not a
    positive finite number."""
    try:
        fps = float((source or {}).get("fps", "nan"))
    except ValueError:
        return None
    return fps if math.isfinite(fps) and fps > 0 else None


def _column(path: Path, header: list[str], names: list[str], fnums: np.ndarray) -> np.ndarray:
    """``(T, len(names))`` float values of columns ``names`` in the rows of ``fnums`` (NaN where empty)."""
    cols = [header.index(n) if n in header else None for n in names]
    fcol = header.index("fnum")
    rows: dict[int, list[float]] = {}
    with open_text(path) as f:
        reader = csv.reader(f)
        next(reader)
        for row in reader:
            if not row:
                continue
            try:
                rows[int(float(row[fcol]))] = [
                    float(row[c]) if c is not None and row[c] not in ("", "nan") else np.nan for c in cols]
            except (IndexError, ValueError, OverflowError):
                raise UserError(f"{path}, line {reader.line_num}: a short row or a value that is not a "
                                "number (a truncated file?)") from None
    return np.array([rows[int(f)] for f in fnums], dtype=np.float64).reshape(len(fnums), len(names))
