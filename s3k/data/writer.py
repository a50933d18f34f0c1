"""Writing a dataset folder (``docs/dataset-format.md``) frame by frame: :class:`DatasetWriter`.

Images are written as each frame is added; the tables and, last, ``s3k.json`` are written by
:meth:`DatasetWriter.close`, so a folder without ``s3k.json`` is an unfinished one (it holds the marker
``.s3k-unfinished`` until then, so that it is known as s3k's to replace).
"""

from __future__ import annotations

import csv
import json
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from s3k.base.errors import UserError
from s3k.base.outputs import UNFINISHED_MARKER, foreign_dataset_file, made_by_s3k
from s3k.data.cameras import camera_defects, camera_tuple
from s3k.data.problems import Problems
from s3k.data.sessions import SESSION_CALIBRATION_DIR, SESSION_COLUMN, session_calibration_file
from s3k.data.tables import (
    CALIBRATION_COLUMNS,
    DEFAULT_IMAGE_PATTERN,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAMES_COLUMNS,
    FRAMES_FILE,
    LABELS_COLUMNS,
    LABELS_FILE,
    METADATA_FILE,
    NAME_RE,
    PER_FRAME_CALIBRATION_FILE,
    POINTS3D_COLUMNS,
    POINTS3D_FILE,
    SPLITS,
    STATIC_CALIBRATION_FILE,
    check_names,
)

Calibration = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # K (C, 3, 3), dist (C, 5), R, t (C, 3)


def json_text(data: Any) -> str:
    """Indented JSON with each list of scalars on one line, so matrices read row by row."""
    text = json.dumps(data, indent=2)
    return re.sub(r"\[\s+([^\[\]{}]+?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def _fmt(x: float) -> str:
    """Shortest text that reads back to the same float64."""
    return repr(float(x))


def rig_json(cameras: Sequence[str], calibration: Calibration) -> str:
    """The text of ``calibration.json`` (or a session's rig file) for ``(K, dist, R, t)`` of ``cameras``."""
    K, dist, R, t = calibration
    cams = {cam: {"K": K[c].tolist(), "dist": dist[c].tolist(), "R": R[c].tolist(), "t": t[c].tolist()}
            for c, cam in enumerate(cameras)}
    return json_text({"cameras": cams})


def calibration_rows(frame: int, cameras: Sequence[str], calibration: Calibration) -> str:
    """``calibration.csv`` lines of one frame's ``(K, dist, R, t)``."""
    K, dist, R, t = calibration
    return "".join(f"{frame},{cam}," + ",".join(_fmt(x) for x in [*K[c].ravel(), *dist[c], *R[c].ravel(),
                                                                  *t[c]]) + "\n"
                   for c, cam in enumerate(cameras))


class DatasetWriter:
    """Write a dataset folder frame by frame; tables and s3k.json are written by :meth:`close`.

    Args:
        path: folder to create (must be absent or empty unless ``overwrite``).
        keypoints: keypoint names (``K``).
        cameras: camera names (``C``), used as folder names.
        image_size: ``(W, H)`` of every image.
        units: world units of calibration and 3D points.
        calibration: a static rig (``Cameras (C,)`` or ``(K, dist, R, t)`` arrays); then ``add_frame`` needs
            none. Without it every frame brings its own, written as a static rig when all are identical
            (unless ``per_frame_calibration=True``).
        per_frame_calibration: force per-frame (True) or static (False; frames must agree) calibration.
        skeleton, description, source: optional metadata (``source`` may be a string or a JSON object).
        sessions: ``{session: metadata}`` (``frame_rate``, ``subject``, ...) for s3k.json's ``sessions``; a
            frame names its session with ``extra={"session": name}``. Frames whose calibration differs
            between sessions but not within one are written as one rig per session (``calibration/``).
        videos: ``{camera: video file}`` to copy into ``videos/``; frames then carry no images and are
            ``video_frame`` (``extra``, default the frame id) of each video.
        png_compression: 0-9, OpenCV's PNG compression level.
        overwrite: replace an existing non-empty folder.
        tables_only: write the tables and no image: frames carry none, and the caller puts the images folder
            in place (e.g. a link to another dataset's images under the same names).

    Example:
        >>> with DatasetWriter("ds", ["a"], ["cam0", "cam1"], (64, 48)) as w:  # doctest: +SKIP
        ...     w.add_frame(0, "labelled", images, cams, labels)
    """

    def __init__(
        self,
        path: str | Path,
        keypoints: Sequence[str],
        cameras: Sequence[str],
        image_size: Sequence[int],
        units: str = "m",
        *,
        calibration: Any = None,
        per_frame_calibration: bool | None = None,
        skeleton: Sequence[Sequence[str]] | None = None,
        description: str | None = None,
        source: Any = None,
        sessions: dict[str, dict[str, Any]] | None = None,
        videos: dict[str, str | Path] | None = None,
        png_compression: int = 3,
        overwrite: bool = False,
        tables_only: bool = False,
    ):
        self.path = Path(path)
        self.keypoints, self.cameras = list(keypoints), list(cameras)
        P = Problems()
        meta = {"keypoints": self.keypoints, "cameras": self.cameras}
        check_names(meta, "keypoints", P, folder_safe=False)
        check_names(meta, "cameras", P, folder_safe=True)
        if P.errors:
            raise ValueError("; ".join(f"{p.field}: {p.message}" for p in P.errors))
        if len(image_size) != 2 or any(int(s) != s or s <= 0 for s in image_size):
            raise ValueError(f"image_size must be (W, H) positive integers, got {image_size!r}")
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.units = units
        for a, b in skeleton or []:
            for n in (a, b):
                if n not in self.keypoints:
                    raise ValueError(f"skeleton: unknown keypoint {n!r}; keypoints are {self.keypoints}")
        self.skeleton = [list(e) for e in skeleton or []]
        self.description, self.source = description, source
        self.sessions = None if sessions is None else {str(k): dict(v) for k, v in sessions.items()}
        self.png_params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)]
        self.tables_only = tables_only
        self.static = None if calibration is None else self._check_calibration(calibration, "calibration")
        if self.static is not None and per_frame_calibration:
            raise ValueError("per_frame_calibration=True contradicts a static calibration argument")
        self.per_frame_calibration = per_frame_calibration
        if self.path.exists() and any(self.path.iterdir()):
            if not overwrite:
                raise FileExistsError(f"{self.path}: folder exists and is not empty (pass overwrite=True)")
            if not made_by_s3k(self.path):  # never someone's other files
                raise UserError(f"{self.path} is not a dataset (no s3k.json): --overwrite replaces only a "
                                "folder s3k made", hint="give another folder, or empty it first")
            foreign = foreign_dataset_file(self.path)
            if foreign is not None:  # a file put in the dataset by hand is not deleted with it
                raise UserError(f"{self.path} holds {foreign.relative_to(self.path)}, which is not a file of "
                                "the dataset; --overwrite would delete it",
                                hint="move it out, or give another folder")
            shutil.rmtree(self.path)
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / UNFINISHED_MARKER).write_text("a dataset being written; s3k.json comes last\n")
        self.videos = None
        if videos is not None:
            missing = sorted(set(self.cameras) - set(videos))
            if missing:
                raise ValueError(f"videos: no video for cameras {missing}")
            (self.path / "videos").mkdir()
            self.videos = {}
            for cam in self.cameras:
                src = Path(videos[cam])
                rel = f"videos/{cam}{src.suffix}"
                shutil.copyfile(src, self.path / rel)
                self.videos[cam] = rel
        else:
            for cam in self.cameras:
                (self.path / "images" / cam).mkdir(parents=True, exist_ok=True)
        self._frames: list[tuple[int, str, dict]] = []
        self._seen: set[int] = set()
        self._calibrations: list[Calibration] = []
        self._labels: list[str] = []
        self._points: list[str] = []
        self._closed = False

    def _check_calibration(self, calibration: Any, arg: str) -> Calibration:
        cal = camera_tuple(calibration)
        C = len(self.cameras)
        for name, value, shape in zip(("K", "dist", "R", "t"), cal, ((C, 3, 3), (C, 5), (C, 3, 3), (C, 3))):
            if value.shape != shape:
                raise ValueError(f"{arg}.{name} must have shape {shape}, got {value.shape}")
        for c, found in enumerate(camera_defects(*cal)):
            for fld, message in found:
                raise ValueError(f"{arg}.{fld} of camera {self.cameras[c]!r}: {message}")
        return cal

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()

    def add_frame(
        self,
        frame_id: int,
        split: str,
        images: Any = None,
        calibration: Any = None,
        labels: Any = None,
        points3d: Any = None,
        visible: Any = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        """Add one frame.

        Args:
            frame_id: non-negative integer, unique.
            split: ``"labelled" | "unlabelled" | "test"``.
            images: ``uint8 (C, H, W, 3)`` RGB (or a sequence / ``{camera: image}``); None for video datasets.
            calibration: this frame's ``Cameras (C,)`` or ``(K, dist, R, t)``; None with a static rig.
            labels: ``uv (C, K, 2)`` pixels, NaN where not labelled; or ``(uv, mask (C, K))``; or None.
            points3d: ground truth ``(K, 3)`` (NaN rows are skipped), or None.
            visible: ``(C, K)`` bool; False writes a labelled-but-occluded row (``visible = 0``, masked).
            extra: more frames.csv columns for this frame, e.g. ``{"instance": 3, "segment": 0}``.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        if isinstance(frame_id, bool) or int(frame_id) != frame_id or frame_id < 0:
            raise ValueError(f"frame_id must be a non-negative integer, got {frame_id!r}")
        frame_id = int(frame_id)
        if frame_id in self._seen:
            raise ValueError(f"frame_id {frame_id} added twice")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {list(SPLITS)}, got {split!r}")
        Kp = len(self.keypoints)
        extra = dict(extra or {})
        for key in extra:
            if key in FRAMES_COLUMNS or not NAME_RE.match(str(key)) or "," in str(key):
                raise ValueError(f"extra column name {key!r} is reserved or not a plain name")

        if calibration is None:
            if self.static is None:
                raise ValueError("calibration is required (the writer has no static calibration)")
            cal = self.static
        else:
            cal = self._check_calibration(calibration, "calibration")
            if self.static is not None and not all(np.array_equal(a, b) for a, b in zip(cal, self.static)):
                raise ValueError("calibration differs from the writer's static calibration")

        imgs = self._check_images(images)
        label_rows = [] if labels is None else self._label_rows(frame_id, labels, visible)
        point_rows = []
        if points3d is not None:
            X = np.asarray(points3d, dtype=np.float64)
            if X.shape != (Kp, 3):
                raise ValueError(f"points3d must have shape {(Kp, 3)}, got {X.shape}")
            for k in range(Kp):
                if np.isfinite(X[k]).all():
                    point_rows.append(f"{frame_id},{self.keypoints[k]},{','.join(_fmt(x) for x in X[k])}")

        for c, im in enumerate(imgs):
            rel = DEFAULT_IMAGE_PATTERN.format(camera=self.cameras[c], frame=frame_id)
            ok, data = cv2.imencode(".png", cv2.cvtColor(im, cv2.COLOR_RGB2BGR), self.png_params)
            if not ok:  # pragma: no cover
                raise ValueError(f"{rel}: PNG encoding failed")
            data.tofile(str(self.path / rel))
        self._seen.add(frame_id)
        self._frames.append((frame_id, split, extra))
        self._calibrations.append(cal)
        self._labels.extend(label_rows)
        self._points.extend(point_rows)

    def _check_images(self, images: Any) -> list[np.ndarray]:
        """A frame's images as ``C`` arrays ``uint8 (H, W, 3)`` to write (none for tables only or videos)."""
        C = len(self.cameras)
        W, H = self.image_size
        if self.tables_only:
            if images is not None:
                raise ValueError("this writer writes tables only; pass images=None")
        elif self.videos is None:
            if images is None:
                raise ValueError("images are required (C, H, W, 3) uint8")
            if isinstance(images, dict):
                images = [images[c] for c in self.cameras]
            imgs = [np.asarray(im) for im in images]
            if len(imgs) != C:
                raise ValueError(f"images: expected {C} cameras, got {len(imgs)}")
            for c, im in enumerate(imgs):
                if im.shape != (H, W, 3) or im.dtype != np.uint8:
                    raise ValueError(
                        f"images[{c}] ({self.cameras[c]}) must be uint8 {(H, W, 3)}, got "
                        f"{im.dtype} {im.shape}"
                    )
            return imgs
        elif images is not None:
            raise ValueError("this writer stores videos; pass images=None and extra={'video_frame': i}")
        return []

    def _label_rows(self, frame_id: int, labels: Any, visible: Any) -> list[str]:
        """labels.csv rows of a frame's labels (``uv`` or ``(uv, mask)``), checked."""
        C, Kp = len(self.cameras), len(self.keypoints)
        if isinstance(labels, tuple):
            uv, lmask = (np.asarray(x) for x in labels)
        else:
            uv = np.asarray(labels, dtype=np.float64)
            lmask = np.isfinite(uv).all(-1)
        uv = np.asarray(uv, dtype=np.float64)
        if uv.shape != (C, Kp, 2) or lmask.shape != (C, Kp):
            raise ValueError(f"labels must be uv {(C, Kp, 2)} (and mask {(C, Kp)}), got {uv.shape}")
        vis = np.ones((C, Kp), bool) if visible is None else np.asarray(visible, bool)
        if vis.shape != (C, Kp):
            raise ValueError(f"visible must have shape {(C, Kp)}, got {vis.shape}")
        label_rows = []
        for c, k in zip(*np.nonzero(lmask.astype(bool))):
            u, v = uv[c, k]
            if vis[c, k] and not (np.isfinite(u) and np.isfinite(v)):
                raise ValueError(f"labels[{c}, {k}] is marked labelled but not finite: {uv[c, k]}")
            cells = ["" if not np.isfinite(x) else _fmt(x) for x in (u, v)]
            label_rows.append(
                f"{frame_id},{self.cameras[c]},{self.keypoints[k]},{cells[0]},{cells[1]},{int(vis[c, k])}"
            )
        return label_rows

    def _session_rigs(self) -> dict[str, Calibration] | None:
        """One rig per session when every frame names its session and its session's frames share one
        calibration; else None (the calibration is written per frame)."""
        rigs: dict[str, Calibration] = {}
        for (_, _, extra), cal in zip(self._frames, self._calibrations):
            session = extra.get(SESSION_COLUMN)
            if session is None or not NAME_RE.match(str(session)):
                return None
            first = rigs.setdefault(str(session), cal)
            if not all(np.array_equal(a, b) for a, b in zip(first, cal)):
                return None
        return rigs

    def close(self) -> Path:
        """Write frames.csv, calibration, labels.csv, points3d.csv and (last) s3k.json; returns the folder."""
        if self._closed:
            return self.path
        if not self._frames:
            raise ValueError(f"{self.path}: no frames added")
        static = self.static
        if static is None:
            first = self._calibrations[0]
            same = all(all(np.array_equal(a, b) for a, b in zip(first, cal)) for cal in self._calibrations)
            if self.per_frame_calibration is False and not same:
                raise ValueError("per_frame_calibration=False but frames have different calibrations")
            if same and not self.per_frame_calibration:
                static = first
        columns: list[str] = []
        for _, _, extra in self._frames:
            columns.extend(k for k in extra if k not in columns)
        with open(self.path / FRAMES_FILE, "w", newline="") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow([*FRAMES_COLUMNS, *columns])
            for frame, split, extra in self._frames:
                writer.writerow([frame, split, *(extra.get(k, "") for k in columns)])
        rigs = None if static is not None or self.per_frame_calibration else self._session_rigs()
        if static is not None:
            (self.path / STATIC_CALIBRATION_FILE).write_text(rig_json(self.cameras, static))
        elif rigs is not None:
            (self.path / SESSION_CALIBRATION_DIR).mkdir(exist_ok=True)
            for session, rig in rigs.items():
                (self.path / session_calibration_file(session)).write_text(rig_json(self.cameras, rig))
        else:
            with open(self.path / PER_FRAME_CALIBRATION_FILE, "w") as f:
                f.write(",".join(CALIBRATION_COLUMNS) + "\n")
                for (frame, _, _), cal in zip(self._frames, self._calibrations):
                    f.write(calibration_rows(frame, self.cameras, cal))
        if self._labels:
            (self.path / LABELS_FILE).write_text(
                ",".join(LABELS_COLUMNS) + "\n" + "\n".join(self._labels) + "\n"
            )
        if self._points:
            (self.path / POINTS3D_FILE).write_text(
                ",".join(POINTS3D_COLUMNS) + "\n" + "\n".join(self._points) + "\n"
            )
        meta: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "keypoints": self.keypoints,
            "cameras": self.cameras,
            "image_size": list(self.image_size),
            "units": self.units,
            "calibration": "static" if static is not None else "per_frame" if rigs is None else "per_session",
            "images": (
                {"type": "png", "pattern": DEFAULT_IMAGE_PATTERN}
                if self.videos is None
                else {"type": "video", "videos": self.videos}
            ),
        }
        if self.skeleton:
            meta["skeleton"] = self.skeleton
        if self.description is not None:
            meta["description"] = self.description
        if self.source is not None:
            meta["source"] = self.source
        if self.sessions:
            meta["sessions"] = self.sessions
        (self.path / METADATA_FILE).write_text(json_text(meta))
        (self.path / UNFINISHED_MARKER).unlink(missing_ok=True)
        self._closed = True
        return self.path
