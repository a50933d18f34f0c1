"""Calibration check from 2D labels (the ``s3k check-calibration`` command).

Labels seen by >= 2 cameras are triangulated (unit weights, the solver of docs/method.md#triangulation) and
reprojected:

- **residual**: triangulate from every labelled view, reproject into each labelled view; median and RMS of
  the pixel distance per camera. A bad camera pulls every point it sees, which spreads its error over the rig.
- **leave-one-camera-out (LOO)**: for camera c, triangulate from the *other* labelled views (>= 2), reproject
  into c. A camera whose pose or intrinsics disagree with the rig shows a LOO residual far above the others'.

Inconsistent cameras are named greedily: take the camera with the largest LOO median; it is inconsistent if
its LOO median exceeds both a floor ``min_px`` and ``factor`` times the baseline of the remaining cameras (the
median of their LOO medians computed without it). With three cameras a bad one inflates the others' LOO
too, so the test compares camera pairs instead: the two-view residual (epipolar consistency) of the pair
without camera c against that of the two pairs with it. Drop the named camera and repeat while at least three
cameras remain.

Residuals are in pixels of the dataset's images; proofread tracker output is typically a few pixels off.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.geometry import Cameras, project, triangulate_pixels

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def _as_cameras(cams) -> Cameras:
    if isinstance(cams, Cameras):
        return cams.to(torch.float64)
    raise TypeError(f"cams must be s3k.geometry.Cameras, got {type(cams).__name__}")


def _check_inputs(cams: Cameras, uv: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    uv = np.asarray(uv, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    if uv.ndim != 4 or uv.shape[-1] != 2:
        raise ValueError(f"uv must have shape (B, C, K, 2), got {uv.shape}")
    if mask.shape != uv.shape[:-1]:
        raise ValueError(f"mask must have shape {uv.shape[:-1]} (B, C, K), got {mask.shape}")
    C = uv.shape[1]
    if cams.shape[-1] != C:
        raise ValueError(f"cams have {cams.shape[-1]} views, uv has {C} cameras")
    mask = mask & np.isfinite(uv).all(-1)
    return np.where(mask[..., None], uv, 0.0), mask, C


def _triangulate_reproject(cams: Cameras, uv: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, ...]:
    """Triangulate with ``weights (B, C, K)`` (0/1), project into every camera.

    Returns:
        ``proj (B, C, K, 2)`` (NaN where the point is invalid or behind the camera), ``X (B, K, 3)``.
    """
    uv_t = torch.as_tensor(uv, dtype=torch.float64)
    w_t = torch.as_tensor(weights, dtype=torch.float64)
    X, valid = triangulate_pixels(cams, uv_t, w_t)
    # Require >= 2 views explicitly: a point from one ray is not a measurement.
    valid = valid & (w_t.sum(dim=1) >= 2)
    proj, depth = project(cams, X[:, None])
    ok = valid[:, None] & (depth > 1e-9)
    proj = torch.where(ok[..., None], proj, torch.full_like(proj, float("nan")))
    X = torch.where(valid[..., None], X, torch.full_like(X, float("nan")))
    return proj.numpy(), X.numpy()


def reprojection_residuals(cams: Cameras, uv, mask, views=None) -> np.ndarray:
    """Pixel residuals of labels against the reprojection of the point triangulated from ``views``.

    Args:
        cams: cameras ``(C,)`` or ``(B, C)``.
        uv: ``(B, C, K, 2)`` labelled pixels.
        mask: ``(B, C, K)`` True where labelled.
        views: ``(C,)`` bool, the cameras that triangulate (all by default). Residuals are reported for all
            labelled cameras, including those not used.

    Returns:
        ``(B, C, K)`` distances in pixels, NaN where not labelled or the point is not triangulable.
    """
    cams = _as_cameras(cams)
    uv, mask, C = _check_inputs(cams, uv, mask)
    views = np.ones(C, bool) if views is None else np.asarray(views, bool)
    proj, _ = _triangulate_reproject(cams, uv, mask & views[None, :, None])
    res = np.linalg.norm(proj - uv, axis=-1)
    return np.where(mask, res, np.nan)


def leave_one_out_residuals(cams: Cameras, uv, mask, views=None) -> np.ndarray:
    """For each camera c in ``views``: triangulate from the other labelled ``views`` (>= 2), reproject into c.

    Returns:
        ``(B, C, K)`` distances in pixels, NaN where not computed (camera not in ``views``, unlabelled, or
        fewer than two other views).
    """
    cams = _as_cameras(cams)
    uv, mask, C = _check_inputs(cams, uv, mask)
    views = np.ones(C, bool) if views is None else np.asarray(views, bool)
    out = np.full(mask.shape, np.nan)
    for c in np.flatnonzero(views):
        others = views.copy()
        others[c] = False
        proj, _ = _triangulate_reproject(cams, uv, mask & others[None, :, None])
        out[:, c] = np.where(mask[:, c], np.linalg.norm(proj[:, c] - uv[:, c], axis=-1), np.nan)
    return out


def _stats(values: np.ndarray) -> tuple[int, float, float]:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0, float("nan"), float("nan")
    return int(v.size), float(np.median(v)), float(np.sqrt(np.mean(v**2)))


@dataclass
class CameraResidual:
    """Residual statistics of one camera, in pixels."""

    name: str
    n: int
    median_px: float
    rms_px: float
    loo_n: int
    loo_median_px: float
    loo_rms_px: float


@dataclass
class CalibrationCheck:
    """Result of :func:`check_calibration`.

    Attributes:
        cameras: residuals of every camera, all cameras triangulating.
        inconsistent: names of the cameras found inconsistent, in the order found.
        decisions: one line per test made, with the numbers compared.
        consistent: residuals with the inconsistent cameras left out of triangulation (for a left-out camera,
            the residual of its labels against points triangulated from the consistent cameras).
        factor, min_px: the thresholds used.
        notes: other findings (e.g. two cameras with identical parameters, which usually means a copy error).
        undecided: the test stopped before judging every camera (too few points, or a pair that cannot
            triangulate).
    """

    cameras: list[CameraResidual]
    inconsistent: list[str]
    decisions: list[str] = field(default_factory=list)
    consistent: list[CameraResidual] = field(default_factory=list)
    factor: float = 3.0
    min_px: float = 0.0
    notes: list[str] = field(default_factory=list)
    undecided: bool = False

    def format(self) -> str:
        """A plain-text report."""

        def table(rows: list[CameraResidual]) -> list[str]:
            out = [f"  {'camera':<12} {'points':>7} {'median px':>10} {'rms px':>9}   "
                   f"{'LOO points':>10} {'LOO median':>10} {'LOO rms':>9}"]
            for r in rows:
                out.append(
                    f"  {r.name:<12} {r.n:>7d} {r.median_px:>10.2f} {r.rms_px:>9.2f}   "
                    f"{r.loo_n:>10d} {r.loo_median_px:>10.2f} {r.loo_rms_px:>9.2f}"
                )
            return out

        lines = ["reprojection residual per camera (all cameras triangulate; LOO = leave that camera out):"]
        lines += table(self.cameras)
        lines += [f"note: {n}" for n in self.notes]
        lines.append(f"consistency test (factor {self.factor:g}, floor {self.min_px:.2f} px):")
        lines += [f"  {d}" for d in self.decisions]
        if self.inconsistent:
            lines.append(f"INCONSISTENT: {', '.join(self.inconsistent)}")
            lines.append("residual with the consistent cameras only triangulating:")
            lines += table(self.consistent)
        else:
            lines.append("no camera could be judged inconsistent, but the test was incomplete (see above)"
                         if self.undecided else "all cameras consistent")
        return "\n".join(lines)


def _residual_rows(names, res, loo) -> list[CameraResidual]:
    rows = []
    for c, name in enumerate(names):
        rows.append(CameraResidual(name, *_stats(res[:, c]), *_stats(loo[:, c])))
    return rows


def check_calibration(
    cams: Cameras,
    uv,
    mask,
    names: list[str],
    factor: float = 3.0,
    min_px: float | None = None,
    min_points: int = 10,
    image_size: tuple[int, int] | None = None,
) -> CalibrationCheck:
    """Per-camera residuals, leave-one-camera-out residuals, and the cameras inconsistent with the rest.

    Args:
        cams: cameras ``(C,)`` or ``(B, C)``.
        uv: ``(B, C, K, 2)`` labels in pixels.
        mask: ``(B, C, K)`` True where labelled.
        names: the ``C`` camera names.
        factor: a camera is inconsistent when its LOO median exceeds ``factor`` times the others' baseline...
        min_px: ...and ``min_px`` pixels, so that label noise on a good rig is not flagged. By default 0.5% of
            the image diagonal (8 px at 1280x1024): errors below that are within what hand or tracker labels
            of animals show between good views.
        image_size: ``(W, H)`` for the default ``min_px``; by default twice the principal point.
        min_points: cameras with fewer LOO residuals than this are not judged.

    Returns:
        A :class:`CalibrationCheck`; ``.format()`` gives the report.
    """
    cams = _as_cameras(cams)
    C = len(names)
    if np.asarray(uv).ndim == 4 and np.asarray(uv).shape[1] != C:
        raise ValueError(f"names has {C} cameras, uv has {np.asarray(uv).shape[1]}")
    res = reprojection_residuals(cams, uv, mask)
    lead = len(cams.shape)
    fields = [v.reshape(-1, C, *v.shape[lead:]) for v in cams.numpy().values()]
    notes = []
    for a in range(C):
        for b in range(a + 1, C):
            if all(np.array_equal(v[:, a], v[:, b]) for v in fields):
                notes.append(f"{names[a]} and {names[b]} have identical calibration parameters")
    loo = leave_one_out_residuals(cams, uv, mask)
    if min_px is None:
        if image_size is None:
            pp = cams.K[..., :2, 2].reshape(-1, 2).mean(dim=0).numpy()
            image_size = (2 * pp[0] + 1, 2 * pp[1] + 1)
        min_px = 0.005 * float(np.hypot(*image_size))
    check = CalibrationCheck(_residual_rows(names, res, loo), [], factor=factor, min_px=min_px, notes=notes)

    active = np.ones(C, bool)
    while active.sum() >= 3:
        loo_a = leave_one_out_residuals(cams, uv, mask, active)
        medians = {int(c): _stats(loo_a[:, c]) for c in np.flatnonzero(active)}
        judged = {c: m for c, (n, m, _) in medians.items() if n >= min_points}
        if not judged:
            check.decisions.append("too few points seen by >= 3 cameras to judge")
            check.undecided = True
            break
        if active.sum() >= 4:
            worst = max(judged, key=lambda c: judged[c])
            rest = active.copy()
            rest[worst] = False
            loo_rest = leave_one_out_residuals(cams, uv, mask, rest)
            base = float(np.nanmedian([_stats(loo_rest[:, c])[1] for c in np.flatnonzero(rest)]))
            value = judged[worst]
            what = f"LOO median {value:.2f} px vs the others' LOO without it {base:.2f} px"
        else:
            # Three cameras: a bad one inflates both LOO of the others, so compare camera pairs instead. The
            # two-view residual of a pair measures its epipolar consistency; a bad camera is in both bad ones.
            idx = [int(i) for i in np.flatnonzero(active)]
            pair: dict[frozenset[int], float] = {}
            for i, a in enumerate(idx):
                for b in idx[i + 1:]:
                    views = np.zeros(C, bool)
                    views[[a, b]] = True
                    r = reprojection_residuals(cams, uv, mask, views)[:, [a, b]]
                    pair[frozenset((a, b))] = _stats(r)[1]
            without = {c: pair[frozenset(set(idx) - {c})] for c in idx}
            if any(not np.isfinite(v) for v in pair.values()):
                broken = [" and ".join(names[c] for c in sorted(k)) for k, v in pair.items()
                          if not np.isfinite(v)]
                check.decisions.append(
                    f"cannot judge {', '.join(names[c] for c in idx)}: {'; '.join(broken)} triangulate no "
                    "point together (same centre, or no shared labels)"
                )
                check.undecided = True
                break
            worst = min(without, key=lambda c: without[c])
            base = without[worst]
            value = float(np.median([v for k, v in pair.items() if worst in k]))
            rest = active.copy()
            rest[worst] = False
            what = f"two-view residual of its pairs {value:.2f} px vs of the other pair {base:.2f} px"
        bad = value > max(min_px, factor * base)
        check.decisions.append(f"{names[worst]}: {what} -> " + ("INCONSISTENT" if bad else "consistent"))
        if not bad:
            break
        check.inconsistent.append(names[worst])
        active = rest
    if check.inconsistent:
        res_c = reprojection_residuals(cams, uv, mask, active)
        loo_c = leave_one_out_residuals(cams, uv, mask, active)
        # A left-out camera's "LOO" is its residual against the consistent cameras' points.
        for c in np.flatnonzero(~active):
            loo_c[:, c] = res_c[:, c]
        check.consistent = _residual_rows(names, res_c, loo_c)
    return check


# ------------------------------------------------------------------------------------------------------------
# Recalibrating one camera from ChArUco frames seen by it and by trusted cameras


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

    from s3k.data.labels2d import frame_id_from_path

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

    from s3k.data.anipose import read_anipose_calibration
    from s3k.data.transforms import crop_resize_matrix
    from s3k.errors import UserError

    source = ds.source if isinstance(ds.source, dict) else {}
    toml_path = calibration or source.get("calibration")
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
