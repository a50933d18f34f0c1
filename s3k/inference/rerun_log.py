"""Logging a rig, its views and 3D keypoints to Rerun: the one logger of ``s3k view`` and ``s3k stream
--rerun`` (:class:`RerunLog`).

Entities (the timeline is ``frame``: video frame index, or dataset frame id):

- ``world/cameras/<camera>``: the camera's pose (``Transform3D``, OpenCV's ``x_cam = R x_world + t``, i.e.
  camera-from-world) and intrinsics (``Pinhole``, RDF: x right, y down, z forward), drawn as a frustum;
  static for a fixed rig, per frame when the cameras move;
- ``world/cameras/<camera>/image``: the view, JPEG-compressed (``EncodedImage``), optionally downscaled (the
  pinhole is scaled with it: ``K' = M K``);
- ``world/cameras/<camera>/reprojections``: the 3D keypoints projected into the view (with the lens
  distortion, which a Rerun pinhole lacks), one colour per keypoint;
- ``world/cameras/<camera>/detections``: the view's own 2D detections, their radius growing with their
  confidence weight (a detector's); ``.../labels``: 2D labels (a dataset's);
- ``world/keypoints`` (``Points3D``, named and coloured, radius by confidence), ``world/skeleton``
  (``LineStrips3D``, the edges whose two ends are triangulated); ``world/truth`` and ``world/truth_skeleton``
  for the ground truth (a dataset's 3D points or triangulated labels);
- ``confidence/<keypoint>``: each keypoint's confidence as a scalar series, named and coloured as the
  keypoint (``SeriesLines``, static).

The recording opens on its own layout (:func:`layout`, sent once the rig is known): the camera views in a
grid, each with its 2D points, beside the 3D view and one plot of every keypoint's confidence. The 3D view
stands on the work: ``world`` is placed under the root (``Transform3D``) so that the table's normal,
estimated from the cameras and the 3D points (:mod:`s3k.geometry.framing`), is the root's +Z
(``ViewCoordinates``, Z up) and the object's centre its origin, and the eye starts where it sees every point.
The keypoints' names are drawn once, on the 3D keypoints; the 2D points and the ground truth carry them for
hovering only.

Rerun puts pixel (0, 0)'s centre at (0.5, 0.5) (rerun-io/rerun#3896), s3k (and OpenCV) at (0, 0): the logged
2D points and principal points are shifted by half a pixel so that they sit on the logged images exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from s3k.base.draw import edge_indices, keypoint_colours
from s3k.base.errors import UserError
from s3k.geometry import framing as framing_geometry
from s3k.geometry import project
from s3k.geometry.framing import Framing
from s3k.geometry.warp import crop_resize_matrix

__all__ = ["RerunLog", "layout", "recording_summary", "rerun_module"]

DEFAULT_JPEG_QUALITY = 75


def rerun_module(option: str = "--rerun") -> Any:
    """The ``rerun`` module, or a one-line UserError saying how to install it."""
    try:
        import rerun as rr
    except ImportError:
        raise UserError(f"{option} needs the Rerun SDK, which is not installed",
                        hint="pip install 's3k[stream]' (or rerun-sdk)") from None
    return rr


def _display_map(size: Sequence[int], scale: float) -> tuple[np.ndarray, tuple[int, int]]:
    """The pixel map from s3k's pixels of an image of ``size (W, H)`` to Rerun's pixels of the logged image
    (downscaled by ``scale``, pixel centres at half-integers), and the logged image's size."""

    W, H = int(size[0]), int(size[1])
    out = (max(1, round(W * scale)), max(1, round(H * scale)))
    M = crop_resize_matrix((0.0, 0.0, float(W), float(H)), out)
    M[:2, 2] += 0.5
    return M, out


def layout(cameras: Sequence[str], framing: Framing, confidence: bool = True) -> Any:
    """The recording's ``rerun.blueprint.Blueprint``: a grid of one 2D view per camera (its image and 2D
    points) beside the 3D view of ``world``, its eye on ``framing``'s, and (``confidence``) under it one
    time series of every keypoint's confidence."""
    import rerun.blueprint as rrb

    cams = rrb.Grid(*[rrb.Spatial2DView(origin=f"/world/cameras/{c}", name=c) for c in cameras])
    eye = rrb.EyeControls3D(position=framing.eye, look_target=[0.0, 0.0, 0.0], eye_up=[0.0, 0.0, 1.0])
    view3d = rrb.Spatial3DView(origin="/", contents="/world/**", name="3D", eye_controls=eye)
    right = (rrb.Vertical(view3d, rrb.TimeSeriesView(origin="/confidence", name="confidence"),
                          row_shares=[3, 1]) if confidence else view3d)
    return rrb.Blueprint(rrb.Horizontal(cams, right, column_shares=[1, 1]))


def _apply(M: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return np.asarray(uv, dtype=np.float64) @ M[:2, :2].T + M[:2, 2]


class RerunLog:
    """One Rerun recording of a rig's views and keypoints (module docstring).

    Args:
        app: the recording's application id (``"s3k view"``, ``"s3k stream"``).
        target: ``"spawn"`` (a viewer), or a ``.rrd`` file to write.
        keypoints, cameras: the ``K`` and ``C`` names.
        skeleton: edges as keypoint name pairs.
        image_scale: the logged images' size relative to the views (in (0, 1]).
        jpeg_quality: JPEG quality of the logged images (1-100).
        units: the world unit (the keypoints' radius is set in it).
        confidence: whether the keypoints' confidence is logged (the layout's time series).
    """

    def __init__(self, app: str, target: str | Path, keypoints: Sequence[str], cameras: Sequence[str],
                 skeleton: Sequence[Sequence[str]] = (), image_scale: float = 1.0,
                 jpeg_quality: int = DEFAULT_JPEG_QUALITY, units: str = "m", confidence: bool = True) -> None:
        if not 0 < image_scale <= 1:
            raise UserError(f"--image-scale {image_scale:g}: give a scale in (0, 1]")
        if not 1 <= jpeg_quality <= 100:
            raise UserError(f"--jpeg-quality {jpeg_quality}: give a quality from 1 to 100")
        rr = self.rr = rerun_module("--rerun" if app == "s3k stream" else "s3k view")
        self.rec = rr.RecordingStream(app)
        self._file: Path | None = None
        if str(target) == "spawn":
            try:
                self.rec.spawn()
            except Exception as exc:  # noqa: BLE001 - the viewer could not be started, whatever the cause
                raise UserError(f"the Rerun viewer could not be started ({exc})",
                                hint="write a file with --save FILE.rrd (s3k view) or --rerun FILE.rrd "
                                     "(s3k stream) and open it with: rerun FILE.rrd") from None
        else:
            # written beside the target and renamed over it once complete: a failed run leaves the old file
            self._file = Path(target)
            self._file.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(self._partial))
        self.keypoints, self.cameras = list(keypoints), list(cameras)
        self.edges = edge_indices(skeleton, self.keypoints)
        self.colours = np.array(keypoint_colours(len(self.keypoints)), dtype=np.uint8)
        self.image_scale, self.jpeg_quality = float(image_scale), int(jpeg_quality)
        self.radius = {"mm": 2.0, "cm": 0.2, "m": 0.002}.get(units, 0.002)
        self._maps: dict[str, np.ndarray] = {}
        self.confidence = bool(confidence)
        self.framing: Framing | None = None

    @property
    def _partial(self) -> Path:
        assert self._file is not None
        return self._file.with_name(self._file.name + ".partial")

    def close(self, keep: bool = True) -> None:
        """Flush and close the recording; a ``.rrd`` file is complete after it, in its place (``keep``), or
        removed with the target left as it was (``keep=False``, after a failure)."""
        self.rec.flush()
        self.rec.disconnect()
        if self._file is not None and self._partial.exists():
            if keep:
                self._partial.replace(self._file)
            else:
                self._partial.unlink()

    def __enter__(self) -> RerunLog:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(keep=exc_type is None)

    # -- the layout and the cameras ------------------------------------------------------------------------

    def frame(self, cams: Any, points: np.ndarray | None = None) -> Framing:
        """Stand the 3D view on the work, once (the module docstring): the table's normal and the object's
        centre from the cameras ``cams`` (a :class:`s3k.geometry.Cameras` or its ``numpy()`` arrays) and the
        object's ``points (..., 3)`` (NaN where unknown; without them, from the cameras alone); then send the
        layout. Later calls return the first framing."""
        if self.framing is not None:
            return self.framing
        rr = self.rr
        arrays = cams.numpy() if hasattr(cams, "numpy") else cams
        framing = self.framing = framing_geometry.frame(arrays["R"], arrays["t"], points)
        self.rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log("world", rr.Transform3D(translation=framing.translation, mat3x3=framing.rotation,
                                             relation=rr.TransformRelation.ParentFromChild), static=True)
        if self.confidence:
            for k, kp in enumerate(self.keypoints):
                self.rec.log(f"confidence/{kp}", rr.SeriesLines(colors=self.colours[k], names=kp),
                             static=True)
        self.rec.send_blueprint(layout(self.cameras, framing, self.confidence))
        return framing

    def cameras_at(self, cams: Any, sizes: Sequence[Sequence[int]], static: bool = True) -> None:
        """Log each camera's pose and intrinsics: ``cams`` a :class:`s3k.geometry.Cameras` ``(C,)`` (or its
        ``numpy()`` arrays), ``sizes`` the views' ``(W, H)``; ``static`` for a fixed rig, else at the current
        frame."""
        rr = self.rr
        arrays = cams.numpy() if hasattr(cams, "numpy") else cams
        self.frame(arrays)
        for c, cam in enumerate(self.cameras):
            M, out = _display_map(sizes[c], self.image_scale)
            self._maps[cam] = M
            path = f"world/cameras/{cam}"
            self.rec.log(path, rr.Transform3D(translation=arrays["t"][c], mat3x3=arrays["R"][c],
                                              relation=rr.TransformRelation.ChildFromParent), static=static)
            self.rec.log(path, rr.Pinhole(image_from_camera=M @ arrays["K"][c], resolution=list(out),
                                          camera_xyz=rr.ViewCoordinates.RDF,
                                          image_plane_distance=self.radius * 40), static=static)

    def set_frame(self, frame: int) -> None:
        self.rec.set_time("frame", sequence=int(frame))

    def images(self, views: Sequence[np.ndarray]) -> None:
        """Log the current frame's views (``uint8 (H, W, 3)`` RGB each), downscaled and JPEG-compressed."""

        for cam, view in zip(self.cameras, views):
            image = np.ascontiguousarray(view)
            if self.image_scale < 1:
                H, W = image.shape[:2]
                size = (max(1, round(W * self.image_scale)), max(1, round(H * self.image_scale)))
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            ok, data = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                                    [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if not ok:  # pragma: no cover - OpenCV encodes any uint8 RGB image
                raise RuntimeError(f"camera {cam}: the image could not be JPEG-encoded")
            self.rec.log(f"world/cameras/{cam}/image",
                         self.rr.EncodedImage(contents=data.tobytes(), media_type="image/jpeg"))

    # -- keypoints ------------------------------------------------------------------------------------------

    def points2d(self, name: str, uv: np.ndarray, shown: np.ndarray,
                 weights: np.ndarray | None = None) -> None:
        """Log ``uv (C, K, 2)`` (s3k pixels of the views) where ``shown (C, K)`` under each camera as
        ``world/cameras/<camera>/<name>``; ``weights (C, K)`` in [0, 1] set the radius."""
        rr = self.rr
        for c, cam in enumerate(self.cameras):
            finite = np.isfinite(uv[c]).all(-1) & (np.abs(np.nan_to_num(uv[c])) < 1e5).all(-1)
            keep = np.asarray(shown[c], dtype=bool) & finite
            where = np.flatnonzero(keep)
            radii = 1.5 + 3.0 * np.clip(weights[c][where], 0, 1) if weights is not None else 2.5
            self.rec.log(f"world/cameras/{cam}/{name}", rr.Points2D(
                _apply(self._maps[cam], uv[c][where]), colors=self.colours[where], radii=radii,
                labels=[self.keypoints[k] for k in where], show_labels=False))

    def points3d(self, X: np.ndarray, valid: np.ndarray, confidence: np.ndarray | None = None,
                 name: str = "keypoints", skeleton: str = "skeleton", show_names: bool = True) -> None:
        """Log the keypoints ``X (K, 3)`` where ``valid (K,)`` as ``world/<name>`` and the skeleton's edges
        between them as ``world/<skeleton>``; ``confidence (K,)`` in [0, 1] sets the points' radius and is
        logged as ``confidence/<keypoint>``; ``show_names``: the names drawn beside the points (else shown on
        hovering only)."""
        rr = self.rr
        valid = np.asarray(valid, dtype=bool) & np.isfinite(X).all(-1)
        where = np.flatnonzero(valid)
        radii = (self.radius * (0.5 + np.clip(confidence[where], 0, 1)) if confidence is not None
                 else self.radius)
        self.rec.log(f"world/{name}", rr.Points3D(X[where], colors=self.colours[where], radii=radii,
                                                  labels=[self.keypoints[k] for k in where],
                                                  show_labels=show_names))
        edges = [e for e in self.edges if valid[e[0]] and valid[e[1]]]
        self.rec.log(f"world/{skeleton}", rr.LineStrips3D([X[list(e)] for e in edges],
                                                          radii=self.radius / 3))
        if confidence is not None:
            for k, kp in enumerate(self.keypoints):
                if np.isfinite(confidence[k]):
                    self.rec.log(f"confidence/{kp}", rr.Scalars(float(confidence[k])))

    def detection(self, frame: int, views: Sequence[np.ndarray] | None, det: Any, b: int = 0) -> None:
        """Log frame ``b`` of a detector's :class:`s3k.detector.Detection` (on the CPU) at ``frame``: the
        views (when given), each view's detections (radius by confidence weight), the 3D keypoints with their
        confidence (the mean weight over the views), the skeleton and the reprojections."""
        self.set_frame(frame)
        if views is not None:
            self.images(views)
        valid = det.valid[b].numpy()
        self.points2d("detections", det.uv[b].numpy(), det.used[b].numpy(), det.weights[b].numpy())
        self.points2d("reprojections", det.reproj[b].numpy(), np.broadcast_to(valid, det.used[b].shape))
        self.points3d(det.X[b].numpy(), valid, det.score[b].numpy())

    def reprojections(self, cams: Any, X: np.ndarray, valid: np.ndarray) -> None:
        """Project ``X (K, 3)`` into the cameras ``(C,)`` (with lens distortion) and log where ``valid`` and
        in front of the camera."""


        X64 = torch.as_tensor(np.nan_to_num(np.asarray(X, dtype=np.float64)))
        uv, depth = project(cams.to(dtype=torch.float64), X64)
        shown = np.asarray(valid, dtype=bool)[None] & (depth.numpy() > 0)
        self.points2d("reprojections", uv.numpy(), shown)


def recording_summary(path: str | Path) -> dict[str, Any]:
    """What a ``.rrd`` file holds, read back with Rerun's own reader (``rerun.chunk.RrdReader``):
    ``entities`` ``{entity path: components logged}``, ``frames`` (the distinct values of the ``frame``
    timeline), ``bytes`` and ``bytes_per_frame``."""
    from rerun.chunk import RrdReader

    entities: dict[str, set[str]] = {}
    frames: set[int] = set()
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if ":" in n]
        entities.setdefault(chunk.entity_path, set()).update(names)
        if "frame" in batch.schema.names:
            frames.update(int(v) for v in batch.column("frame").to_pylist() if v is not None)
    size = Path(path).stat().st_size
    return {"entities": {k: sorted(v) for k, v in sorted(entities.items())}, "frames": sorted(frames),
            "bytes": size, "bytes_per_frame": size / max(1, len(frames))}
