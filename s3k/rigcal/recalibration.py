"""Recalibrating cameras from ChArUco frames (``s3k check-calibration --recalibrate``) with the solver of
``s3k calibrate`` (:mod:`s3k.rigcal`): a camera's intrinsics from its own board views, its pose from the views
it shares with trusted cameras, refined by bundle adjustment with the trusted cameras held fixed
(:func:`recalibrate_charuco`), and a dataset's cameras with some of them recalibrated
(:func:`recalibrate_dataset`). Which cameras to distrust is :mod:`s3k.geometry.consistency`'s check.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.base.fileio import resolve_from
from s3k.data.formats.anipose import read_anipose_calibration
from s3k.data.formats.labels2d import frame_id_from_path
from s3k.geometry import Cameras
from s3k.geometry.warp import crop_resize_matrix
from s3k.rigcal.boards import (
    Board,
    BoardDetector,
    Detections,
    check_board_matches,
    detect_images,
    read_board_toml,
)
from s3k.rigcal.rig import calibrate_detections, intrinsics_of

CharucoBoardSpec = Board  # the board of anipose's board.toml (s3k.rigcal.boards.Board)

__all__ = ["CharucoBoardSpec", "DatasetRecalibration", "Recalibration", "detect_charuco", "read_board_toml",
           "recalibrate_charuco", "recalibrate_dataset"]


def _detect(image_paths, board: Board, min_corners: int = 6) -> Detections:
    """The board's corners in calibration images, keyed by the last run of digits in each file name, with what
    detection took and dropped (for :func:`s3k.rigcal.boards.check_board_matches`)."""
    keys = []
    for path in image_paths:
        key = frame_id_from_path(str(path))
        if key is None:
            raise UserError(f"{path}: no frame number in the file name to pair it with the other views",
                            hint="name the images <camera>-<index>.jpg")
        keys.append(key)

    def images():
        for key, path in zip(keys, image_paths):
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise UserError(f"{path}: cannot read image")
            yield key, image

    return detect_images(images(), BoardDetector(board, min_corners=min_corners))


def detect_charuco(image_paths, board: Board, min_corners: int = 6) -> dict[int, tuple]:
    """Detect ChArUco corners in calibration images.

    Args:
        image_paths: image files; the frame key of each is the last run of digits in its name (anipose names
            them ``<camera>-<time>-<index>.jpg``), which pairs the views of one board position.
        board: the board.
        min_corners: detections with fewer corners are dropped.

    Returns:
        ``{key: (ids (n,) int, corners (n, 2) float64 pixels)}``.
    """
    return _detect(image_paths, board, min_corners).frames


@dataclass
class Recalibration:
    """A camera recalibrated from ChArUco frames: full-resolution ``K (3, 3)``, ``dist (5,)``, ``R, t``."""

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    intrinsics_rms_px: float
    pose_median_px: float
    frames: int
    corners: int


def recalibrate_charuco(
    rig, camera: str, detections: dict[str, dict[int, tuple]], board: Board, reference: list[str],
) -> Recalibration:
    """Recalibrate ``camera`` with the whole-rig solver of ``s3k calibrate`` (:mod:`s3k.rigcal`), the
    ``reference`` cameras (trusted, from ``rig``) held fixed: its intrinsics from its own board views
    (anipose's model: one focal length, centred principal point, k1), its pose from the board views it shares
    with them, then one bundle adjustment of it and every board pose.

    Args:
        rig: :class:`s3k.data.rig.Rig` (full-resolution intrinsics).
        camera: the camera to recalibrate.
        detections: ``{camera: detect_charuco(...)}`` for ``camera`` and the reference cameras.
        board: the board.
        reference: trusted cameras.
    """
    names = [*reference, camera]
    cams = rig.cameras.numpy()
    if len(detections.get(camera, {})) < 3:
        raise UserError(f"camera {camera!r}: {len(detections.get(camera, {}))} board detections; need >= 3 "
                        "to calibrate", hint="give --charuco images of the board seen by it")
    sizes = {n: (int(rig.size[rig.index(n)][0]), int(rig.size[rig.index(n)][1])) for n in names}
    dets = [Detections(detections.get(n, {}), sizes[n]) for n in names]
    initial: list = [(intrinsics_of(cams["K"][rig.index(n)], cams["dist"][rig.index(n)]),
                      cams["R"][rig.index(n)], cams["t"][rig.index(n)]) for n in reference] + [None]
    try:
        cal = calibrate_detections(names, dets, board, radial=1, initial=initial,
                                   fixed=list(range(len(reference))))
    except UserError as exc:
        raise UserError(f"camera {camera!r}: no board position seen by it and by a reference camera "
                        f"({', '.join(reference)})", hint="give --charuco images of one board position in "
                        "both") from exc
    a, rep = cal.adjusted, cal.report[-1]
    return Recalibration(a.intrinsics[-1].K(), a.intrinsics[-1].dist(), a.R[-1], a.t[-1], rep.initial_rms_px,
                         rep.median_px, rep.views, rep.corners)


# ------------------------------------------------------------------------------------------------------------
# Recalibrating cameras of a dataset


@dataclass
class DatasetRecalibration:
    """Cameras of a dataset with some of them recalibrated from ChArUco frames.

    Attributes:
        cameras: ``Cameras (B, C)`` float64 in the dataset's pixels (the importer's crop and resize applied).
        rig: the recording's calibration with the recalibrated cameras (full resolution, for writing back).
        fixes: ``{camera: Recalibration}`` of each recalibrated camera.
        reference: the trusted cameras that placed the board.
        frames: ``{camera: number of ChArUco frames}`` used.
    """

    cameras: Cameras
    rig: Any
    fixes: dict[str, Recalibration]
    reference: list[str]
    frames: dict[str, int]


def recalibrate_dataset(
    ds, ids, targets: list[str], flagged: list[str], *, calibration: str | Path | None = None,
    board: str | Path | None = None, charuco: dict[str, str] | None = None,
) -> DatasetRecalibration:
    """Recalibrate ``targets`` of dataset ``ds`` from ChArUco frames; unflagged cameras are the reference.

    Args:
        ds: an open ``s3k.data.Dataset`` imported from a recording.
        ids: frame ids whose calibration is returned.
        targets: cameras to recalibrate.
        flagged: cameras the check named (never used as reference).
        calibration: the recording's anipose ``calibration.toml`` (default: the one the dataset names).
        board: anipose ``board.toml`` (default: beside the calibration).
        charuco: ``{camera: glob}`` of calibration images (default:
            ``<calibration dir>/<camera>/calibration_images/*.jpg``).
    """

    source = ds.source if isinstance(ds.source, dict) else {}
    toml_path = calibration
    if not toml_path and source.get("calibration"):

        toml_path = resolve_from(ds.path, source["calibration"])
    if not toml_path:
        raise UserError("recalibration needs the recording's calibration.toml (the dataset does not name it)",
                        hint="pass --calibration")
    rig = read_anipose_calibration(toml_path)
    for cam in [*targets, *ds.cameras]:
        if cam not in rig.names:
            raise UserError(f"{toml_path}: no camera {cam!r} (it has {', '.join(rig.names)})")
    board_spec = read_board_toml(board or Path(toml_path).parent / "board.toml")
    patterns = charuco or {}
    reference = [c for c in ds.cameras if c not in targets and c not in flagged]
    if len(reference) < 1:
        raise UserError("recalibration needs at least one trusted camera besides those recalibrated",
                        hint="name fewer cameras in --recalibrate")
    detections = {}
    for cam in [*targets, *reference]:
        pattern = patterns.get(cam, str(Path(toml_path).parent / cam / "calibration_images" / "*.jpg"))
        files = sorted(glob.glob(pattern))
        if not files:
            raise UserError(f"no ChArUco images for camera {cam!r} at {pattern}",
                            hint="pass --charuco CAM=GLOB")
        found = _detect(files, board_spec)
        check_board_matches(cam, pattern, found, board_spec)
        detections[cam] = found.frames
    arrays = ds.calibration(ids, dtype=np.float64).numpy()
    crop_boxes = source.get("crop_boxes", {})
    fixes = {}
    for cam in targets:
        fix = recalibrate_charuco(rig, cam, detections, board_spec, reference)
        fixes[cam] = fix
        c = rig.index(cam)
        rig = rig.replace_camera(cam, fix.K, fix.dist, fix.R, fix.t)
        # Into the dataset's pixels: the importer's crop box and output size (K' = M K).
        W, H = (float(v) for v in rig.size[c])
        box = crop_boxes.get(cam, (0.0, 0.0, W, H))
        M = crop_resize_matrix(box, ds.source_image_size)
        d = ds.cameras.index(cam)
        arrays["K"][:, d] = ds.pixel_map @ M @ fix.K
        arrays["dist"][:, d], arrays["R"][:, d], arrays["t"][:, d] = fix.dist, fix.R, fix.t
    cams = Cameras.from_numpy(arrays["K"], arrays["dist"], arrays["R"], arrays["t"], dtype=torch.float64)
    return DatasetRecalibration(cams, rig, fixes, reference, {c: len(detections[c]) for c in targets})
