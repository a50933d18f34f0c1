"""Recalibrating cameras from ChArUco frames (``s3k check-calibration --recalibrate``): a camera's intrinsics
from its own board views and its pose from board corners placed in the world by trusted cameras
(:func:`recalibrate_charuco`), and a dataset's cameras with some of them recalibrated
(:func:`recalibrate_dataset`). Which cameras to distrust is :mod:`s3k.calibration`'s check.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.geometry import Cameras

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@dataclass
class CharucoBoardSpec:
    """A ChArUco board as anipose's ``board.toml`` describes it (lengths in the rig's unit)."""

    squares_x: int
    squares_y: int
    square_length: float
    marker_length: float
    marker_bits: int = 4
    dict_size: int = 50

    def cv2_board(self):
        import cv2

        name = f"DICT_{self.marker_bits}X{self.marker_bits}_{self.dict_size}"
        if not hasattr(cv2.aruco, name):
            raise ValueError(f"no ArUco dictionary {name} in OpenCV (marker_bits, dict_size)")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, dictionary
        )


def read_board_toml(path) -> CharucoBoardSpec:
    """Read anipose's ``board.toml`` (``board_x``, ``board_y``, ``square_length``, ``marker_length``,
    ``marker_bits``, ``dict_size``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: board file not found")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from exc
    for key in ("board_x", "board_y", "square_length", "marker_length"):
        if key not in data:
            raise ValueError(f"{path}: no field {key!r} (a ChArUco board needs board_x, board_y, "
                             "square_length, marker_length)")
    return CharucoBoardSpec(
        int(data["board_x"]), int(data["board_y"]),
        float(data["square_length"]), float(data["marker_length"]),
        int(data.get("marker_bits", 4)), int(data.get("dict_size", 50)),
    )


def detect_charuco(image_paths, board: CharucoBoardSpec, min_corners: int = 6) -> dict[int, tuple]:
    """Detect ChArUco corners in calibration images.

    Args:
        image_paths: image files; the frame key of each is the last run of digits in its name (anipose names
            them ``<camera>-<time>-<index>.jpg``), which pairs the views of one board position.
        board: the board.
        min_corners: detections with fewer corners are dropped.

    Returns:
        ``{key: (ids (n,) int, corners (n, 2) float64 pixels)}``.
    """
    import cv2

    from s3k.data.formats.labels2d import frame_id_from_path

    detector = cv2.aruco.CharucoDetector(board.cv2_board())
    found = {}
    for path in image_paths:
        key = frame_id_from_path(str(path))
        if key is None:
            raise ValueError(f"{path}: no frame number in the file name to pair it with the other views")
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"{path}: cannot read image")
        corners, ids, _, _ = detector.detectBoard(image)
        if ids is not None and len(ids) >= min_corners:
            found[key] = (ids.reshape(-1).astype(int), corners.reshape(-1, 2).astype(np.float64))
    return found


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
    rig, camera: str, detections: dict[str, dict[int, tuple]], board: CharucoBoardSpec, reference: list[str],
) -> Recalibration:
    """Intrinsics of ``camera`` from its own board views, pose from board corners placed in the world by the
    ``reference`` cameras (trusted, from ``rig``) at the same instants.

    Args:
        rig: :class:`s3k.data.rig.Rig` (full-resolution intrinsics).
        camera: the camera to recalibrate.
        detections: ``{camera: detect_charuco(...)}`` for ``camera`` and the reference cameras.
        board: the board.
        reference: trusted cameras.
    """
    import cv2

    c = rig.index(camera)
    W, H = (int(v) for v in rig.size[c])
    cams = rig.cameras.numpy()
    corners3d = board.cv2_board().getChessboardCorners().astype(np.float64)  # (N, 3) board frame
    own = detections.get(camera, {})
    if len(own) < 3:
        raise ValueError(f"camera {camera!r}: {len(own)} board detections; need >= 3 to calibrate")
    obj = [corners3d[ids].astype(np.float32) for ids, _ in own.values()]
    img = [pts.astype(np.float32) for _, pts in own.values()]
    # The anipose model: one focal length, centred principal point, radial k1 (what calibration.toml holds).
    K0 = np.array([[max(W, H), 0.0, (W - 1) / 2], [0.0, max(W, H), (H - 1) / 2], [0.0, 0.0, 1.0]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_PRINCIPAL_POINT
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (W, H), K0, np.zeros(5), flags=flags)
    dist = dist.reshape(-1)[:5]
    # Board corners in world coordinates, from each reference camera's view of the board (averaged).
    world_pts, image_pts = [], []
    for key, (ids, pts) in own.items():
        placed = []
        for ref in reference:
            r = rig.index(ref)
            if key not in detections.get(ref, {}):
                continue
            rids, rpts = detections[ref][key]
            ok, rvec, tvec = cv2.solvePnP(corners3d[rids], rpts, cams["K"][r], cams["dist"][r])
            if not ok:
                continue
            X_cam = corners3d @ cv2.Rodrigues(rvec)[0].T + tvec.reshape(3)
            placed.append((X_cam - cams["t"][r]) @ cams["R"][r])  # world = R^T (x_cam - t)
        if placed:
            world_pts.append(np.mean(placed, axis=0)[ids])
            image_pts.append(pts)
    if not world_pts:
        raise ValueError(f"camera {camera!r}: no board position seen by it and by a reference camera "
                         f"({', '.join(reference)})")
    Xw, uv = np.concatenate(world_pts), np.concatenate(image_pts)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(Xw, uv, K, dist, reprojectionError=8.0)
    if not ok or inliers is None:
        raise ValueError(f"camera {camera!r}: pose estimation from {len(Xw)} board corners failed")
    inl = inliers.reshape(-1)
    _, rvec, tvec = cv2.solvePnP(Xw[inl], uv[inl], K, dist, rvec, tvec, useExtrinsicGuess=True)
    proj, _ = cv2.projectPoints(Xw, rvec, tvec, K, dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - uv, axis=1)
    return Recalibration(K, dist, cv2.Rodrigues(rvec)[0], tvec.reshape(3), float(rms), float(np.median(err)),
                         len(world_pts), len(Xw))


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
    import glob

    from s3k.data.formats.anipose import read_anipose_calibration
    from s3k.errors import UserError
    from s3k.geometry.warp import crop_resize_matrix

    source = ds.source if isinstance(ds.source, dict) else {}
    toml_path = calibration
    if not toml_path and source.get("calibration"):
        from s3k.fileio import resolve_from

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
        detections[cam] = detect_charuco(files, board_spec)
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
