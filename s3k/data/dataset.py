"""The s3k dataset: a folder a person can read (``docs/dataset-format.md``) and its validating loader.

A dataset folder holds ``s3k.json`` (names, image size, units, sessions, ...), ``frames.csv`` (frame, split,
optional session, video_frame, instance, ... columns), the calibration (``calibration.json`` static,
``calibration.csv`` per frame, or ``calibration/<session>.json`` per session), ``labels.csv`` (partial 2D
labels), optionally ``points3d.csv`` (ground truth, used only by evaluation) and the images (PNG files or
videos). :meth:`Dataset.open` parses and validates everything except the image pixels, and raises a
:class:`~s3k.data.problems.DatasetError` naming the first problem (its ``problems`` list them all).
:func:`s3k.data.checks.check_dataset` runs the same checks plus decoding every image, collecting problems
instead of raising.
Images are decoded once into a uint8 cache (:mod:`s3k.data.cache`) so that random batches are memory copies.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.data.cache import ImageCache, cache_folders, fingerprint
from s3k.data.cameras import cameras_of, read_per_frame_calibration, read_static_calibration
from s3k.data.images import ImageReadError
from s3k.data.problems import DatasetError, DatasetWarning, Problem, Problems
from s3k.data.sessions import (
    frame_sessions,
    frame_times,
    per_session_counts,
    read_session_calibration,
    read_session_metadata,
    session_names,
)
from s3k.data.sources import IMAGE_SOURCES
from s3k.data.tables import (
    FRAMES_FILE,
    SPLITS,
    Frames,
    Labels,
    Meta,
    read_frames,
    read_labels,
    read_metadata,
    read_points3d,
)
from s3k.data.usable import usable_labels
from s3k.geometry import Cameras
from s3k.geometry.warp import crop_resize_matrix, resize_crop, transform_points


@dataclass
class _Contents:
    root: Path
    meta: Meta
    frames: Frames
    calibration: Cameras  # float64, (C,) static or (N, C) per frame, stored-image pixels
    calibration_ok: bool  # False: the calibration failed its checks and ``calibration`` is a NaN placeholder
    labels: Labels
    points3d: np.ndarray | None
    source: Any
    sessions: np.ndarray  # (N,) each frame's session
    session_meta: dict[str, dict[str, Any]]  # per session, in the order of their first frames
    rigs: dict[str, Cameras]  # per session when calibration is per_session
    fingerprint_items: list[str] = field(default_factory=list)
    held: ImageCache | None = None  # frames at their stored size kept in memory (Dataset.hold_frames)


def parse_folder(root: Path, P: Problems) -> _Contents | None:
    meta = read_metadata(root, P, IMAGE_SOURCES)
    if meta is None:
        return None
    frames = read_frames(root, P)
    if frames is None:
        return None
    sessions = frame_sessions(frames, P)
    session_meta = read_session_metadata(meta, session_names(sessions), P)
    rigs: dict[str, Cameras] = {}
    if meta.calibration == "static":
        calib = read_static_calibration(root, meta, P)
    elif meta.calibration == "per_session":
        calib, rigs = read_session_calibration(root, meta, sessions, P)
    else:
        calib = read_per_frame_calibration(root, meta, frames, P)
    labels = read_labels(root, meta, frames, P)
    points = read_points3d(root, meta, frames, P)
    spec = meta.images
    source = IMAGE_SOURCES[spec.get("type", "png")](root, spec, meta.cameras, frames.ids, frames.columns)
    items = source.check(frames.ids, P)
    ok = calib is not None
    if calib is None:
        # Reported already; a NaN placeholder lets check_dataset go on to the images and the summary.
        lead = (len(meta.cameras),) if meta.calibration == "static" else (len(frames.ids), len(meta.cameras))
        calib = cameras_of(*(np.full((*lead, *s), np.nan) for s in ((3, 3), (5,), (3, 3), (3,))))
    return _Contents(root, meta, frames, calib, ok, labels, points, source, sessions, session_meta, rigs,
                     items)


def _torch_dtype(dtype: Any) -> torch.dtype:
    if isinstance(dtype, torch.dtype):
        return dtype
    return torch.float64 if np.dtype(dtype) == np.float64 else torch.float32


class Dataset:
    """A validated dataset folder. Create with :meth:`Dataset.open`.

    Attributes:
        path: the folder.
        keypoints: keypoint names (``K`` of them).
        cameras: camera names (``C``).
        image_size: ``(W, H)`` of the images this object returns (after any resize/crop on open).
        source_image_size: ``(W, H)`` of the stored images.
        units: world units of calibration and 3D points (``"m"`` unless the rig says otherwise).
        static_calibration: True when one calibration serves every frame.
        frame_ids: ``(N,)`` int64 frame ids in file order.
        skeleton: pairs of keypoint names (may be empty); ``metadata``: the raw s3k.json.
        sessions: the recordings the dataset holds (frames.csv's ``session`` column, in the order of their
            first frames; ``["default"]`` without it); ``session_info(name)`` their metadata.
    """

    def __init__(
        self,
        contents: _Contents,
        image_size=None,
        crop_box=None,
        cache: str = "disk",
        workers: int | None = None,
    ):
        self._c = contents
        meta = contents.meta
        self.path = contents.root
        self.metadata = meta.raw
        self.keypoints = list(meta.keypoints)
        self.cameras = list(meta.cameras)
        self.units = meta.units
        self.skeleton = list(meta.skeleton)
        self.description = meta.raw.get("description")
        self.source = meta.raw.get("source")
        self.static_calibration = meta.calibration == "static"
        self.source_image_size = meta.image_size
        self.frame_ids = contents.frames.ids.copy()
        self.frame_columns = dict(contents.frames.columns)
        self.sessions = list(contents.session_meta)
        W, H = meta.image_size
        self._resample = crop_box is not None or (image_size is not None and tuple(image_size) != (W, H))
        box = (0, 0, W, H) if crop_box is None else tuple(crop_box)
        if image_size is None:
            image_size = (int(box[2] - box[0]), int(box[3] - box[1]))
        self.crop_box = box
        self.image_size = (int(image_size[0]), int(image_size[1]))
        # M maps stored-image pixels to returned-image pixels; K' = M K (transforms.resize_crop).
        self.pixel_map = crop_resize_matrix(box, self.image_size)
        self._workers = workers or min(8, os.cpu_count() or 1)
        w, h = self.image_size
        self._cache = ImageCache(
            cache, (len(self), len(self.cameras), h, w, 3), f"images-{self.fingerprint()}-{w}x{h}",
            cache_folders(self.path),
        )
        self._sorted = np.argsort(self.frame_ids, kind="stable")

        labels = contents.labels
        uv = transform_points(labels.uv, self.pixel_map)
        inside_new = (
            (uv[..., 0] >= -0.5) & (uv[..., 0] <= w - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= h - 0.5)
        )
        self._label_mask = labels.present & labels.visible & labels.inside & inside_new
        self._label_uv = np.where(self._label_mask[..., None], uv, 0.0)

    # -- construction ------------------------------------------------------------------------------------

    @classmethod
    def open(
        cls,
        path: str | Path,
        image_size: Sequence[int] | None = None,
        crop_box: Sequence[float] | None = None,
        cache: str = "disk",
        workers: int | None = None,
    ) -> Dataset:
        """Open and validate a dataset folder (all tables; image files must exist, pixels are checked on
        decode or by ``s3k validate``).

        Args:
            path: dataset folder.
            image_size: ``(W, H)`` to resize images to on load; intrinsics and labels follow exactly.
            crop_box: ``(x0, y0, x1, y1)`` region of the stored images (pixel edge coordinates) to keep.
            cache: ``"disk"`` (uint8 memmap under ``DATASET/.cache/``, shared by processes and runs; falls
                back to memory if the folder is read-only), ``"memory"``, or ``"none"`` (decode every call).
            workers: image decoding threads.

        Raises:
            DatasetError: naming the first problem (file, field, line/frame/camera); ``problems`` has all.
        """
        P = Problems()
        contents = parse_folder(Path(path), P)
        if P.errors or contents is None:
            raise DatasetError(path, P.errors)
        outside = P.warnings
        if outside:
            shown = "; ".join(str(p) for p in outside[:5])
            more = f" (and {len(outside) - 5} more)" if len(outside) > 5 else ""
            warnings.warn(f"dataset {path}: {shown}{more}", DatasetWarning, stacklevel=2)
        return cls(contents, image_size=image_size, crop_box=crop_box, cache=cache, workers=workers)

    def resized(self, image_size: Sequence[int]) -> Dataset:
        """The same dataset served at ``image_size`` (W, H) (intrinsics and labels follow exactly), without
        reading and checking the folder again; ``self`` when the size already matches."""
        if tuple(image_size) == self.image_size:
            return self
        return self._view(image_size, self._cache.mode)

    def with_cache(self, cache: str) -> Dataset:
        """The same view of the dataset with another image cache (``cache`` as for :meth:`open`), sharing
        its tables and held frames (:meth:`hold_frames`), without reading the folder again."""
        return self._view(self.image_size, cache)

    def _view(self, image_size: Sequence[int], cache: str) -> Dataset:
        full = self.crop_box == (0, 0, *self.source_image_size)
        return Dataset(self._c, image_size=image_size, crop_box=None if full else self.crop_box,
                       cache=cache, workers=self._workers)

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __repr__(self) -> str:
        counts = ", ".join(f"{s} {len(self.frames(s))}" for s in SPLITS)
        return (
            f"Dataset({str(self.path)!r}, {len(self)} frames ({counts}), cameras {self.cameras}, "
            f"keypoints {self.keypoints}, image_size {self.image_size})"
        )

    # -- tables ------------------------------------------------------------------------------------------

    def frames(self, split: str | Sequence[str] | None = None, session: str | None = None) -> np.ndarray:
        """Frame ids ``(N,)`` of a split (``"labelled" | "unlabelled" | "test"``), of several splits one after
        the other (each frame is in one split), or all in file order when None; of one ``session`` only
        when given."""
        ids, splits = self.frame_ids, self._c.frames.splits
        if session is not None:
            if session not in self.sessions:
                raise KeyError(f"unknown session {session!r}; {self.path} has sessions {self.sessions}")
            ids, splits = ids[self._c.sessions == session], splits[self._c.sessions == session]
        if split is None:
            return ids.copy()
        names = [split] if isinstance(split, str) else list(split)
        for name in names:
            if name not in SPLITS:
                raise ValueError(f"unknown split {name!r}; use one of {list(SPLITS)}")
        return np.concatenate([ids[:0], *(ids[splits == n] for n in names)])

    def session_of(self, frame_ids) -> np.ndarray:
        """Session name of each frame id."""
        return self._c.sessions[self._rows(frame_ids)]

    def session_info(self, session: str) -> dict[str, Any]:
        """A session's metadata from s3k.json (``frame_rate``, ``subject``, ``source``, ...; may be empty)."""
        return dict(self._c.session_meta[session])

    def frame_times(self, frame_ids) -> np.ndarray:
        """Each frame's place in its session's recording (``video_frame``, else the frame id), int64."""
        return frame_times(self._c.frames)[self._rows(frame_ids)]

    def split_of(self, frame_ids) -> np.ndarray:
        """Split name of each frame id."""
        return self._c.frames.splits[self._rows(frame_ids)]

    def column(self, name: str, frame_ids=None) -> np.ndarray:
        """An extra frames.csv column (e.g. ``instance``, ``segment``) as text, for ``frame_ids`` or all."""
        if name not in self.frame_columns:
            raise KeyError(f"{FRAMES_FILE} has no column {name!r}; columns: {sorted(self.frame_columns)}")
        values = self.frame_columns[name]
        return values if frame_ids is None else values[self._rows(frame_ids)]

    def _rows(self, frame_ids) -> np.ndarray:
        ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        pos = np.searchsorted(self.frame_ids, ids, sorter=self._sorted)
        pos = np.clip(pos, 0, len(self.frame_ids) - 1)
        rows = self._sorted[pos]
        bad = self.frame_ids[rows] != ids
        if bad.any():
            raise KeyError(f"frame ids {ids[bad][:10].tolist()} are not in {self.path / FRAMES_FILE}")
        return rows

    def calibration(self, frame_ids, dtype: Any = np.float32) -> Cameras:
        """``Cameras`` with leading dims ``(B, C)`` for ``frame_ids``, intrinsics of the returned images
        (after resize/crop). ``dtype``: numpy or torch float32/float64 (``.numpy()`` gives float64 arrays)."""
        rows = torch.from_numpy(self._rows(frame_ids))
        cal = self._c.calibration
        if self.static_calibration:
            assert cal.dist is not None
            B, C = len(rows), len(self.cameras)
            cams = Cameras(*(x.expand(B, C, *x.shape[1:]) for x in (cal.K, cal.dist, cal.R, cal.t)))
        else:
            cams = cal[rows]
        return self._mapped(cams, dtype)

    def rig(self, dtype: Any = np.float32, session: str | None = None) -> Cameras:
        """``Cameras (C,)`` of a static rig, or of ``session``'s rig when calibration is per session; raises
        ``ValueError`` when calibration is per frame (or per session and no session is named)."""
        if session is not None and self._c.rigs:
            return self._mapped(self._c.rigs[session], dtype)
        if not self.static_calibration:
            raise ValueError(f"{self.path}: calibration is {self._c.meta.calibration.replace('_', ' ')}; use "
                             "calibration(frame_ids)" + (" or rig(session=...)" if self._c.rigs else ""))
        return self._mapped(self._c.calibration, dtype)

    def _mapped(self, cams: Cameras, dtype: Any) -> Cameras:
        """``cams`` (float64, stored-image pixels) with the intrinsics of the returned images, ``K' = M K``,
        as contiguous tensors of ``dtype``."""
        assert cams.dist is not None
        K = torch.from_numpy(self.pixel_map) @ cams.K
        to = _torch_dtype(dtype)
        return Cameras(*(x.to(dtype=to).contiguous() for x in (K, cams.dist, cams.R, cams.t)))

    def labels(self, frame_ids, dtype: Any = np.float32) -> tuple[np.ndarray, np.ndarray]:
        """2D labels of ``frame_ids``: ``uv (B, C, K, 2)`` of ``dtype`` (pixels of the returned images, 0
        where masked; ``np.float64`` keeps labels.csv's values exactly) and ``mask (B, C, K) bool`` (labelled,
        visible, inside the image)."""
        rows = self._rows(frame_ids)
        return self._label_uv[rows].astype(dtype), self._label_mask[rows].copy()

    def points3d(self, frame_ids) -> tuple[np.ndarray, np.ndarray] | None:
        """Ground-truth 3D ``(X (B, K, 3) float32, mask (B, K) bool)`` in dataset units, or None when the
        dataset has none. For evaluation only."""
        X = self._c.points3d
        if X is None:
            return None
        rows = self._rows(frame_ids)
        sel = X[rows]
        mask = np.isfinite(sel).all(-1)
        return np.where(mask[..., None], sel, 0.0).astype(np.float32), mask

    @property
    def has_points3d(self) -> bool:
        return self._c.points3d is not None

    # -- images ------------------------------------------------------------------------------------------

    def fingerprint(self) -> str:
        """16 hex digits that change when the returned pixels may change (image files, size, crop, frames)."""
        parts = [list(self.crop_box), list(self.image_size), self.cameras, self.frame_ids.tolist()]
        return fingerprint(parts, self._c.fingerprint_items)

    def _size_problem(self, frame: int, c: int, size: tuple[int, int]) -> Problem | None:
        W, H = self.source_image_size
        if tuple(size) == (W, H):
            return None
        return Problem("error", self._c.source.describe(frame, c), "size", f"image is {size[0]}x{size[1]}, "
                       f"s3k.json image_size is {W}x{H}", frame=int(frame), camera=self.cameras[c])

    def _decode_into(
        self, rows: np.ndarray, out: np.ndarray, out_rows: np.ndarray | None = None, resample: bool = True
    ) -> None:
        """Decode frames ``rows`` (all cameras) into ``out[out_rows]`` (default ``out[:len(rows)]``) of shape
        ``(*, C, H, W, 3)``, checking sizes; a file that cannot be read or has the wrong size raises a
        :class:`DatasetError` naming it. Frames held in memory (:meth:`hold_frames`) are taken from there;
        while frames are held, those this view decodes to resample are kept there too."""
        held = self._c.held
        where = np.arange(len(rows)) if out_rows is None else np.asarray(out_rows)
        resampling = resample and self._resample
        todo = np.arange(len(rows))
        if held is not None:
            have = held.filled[rows] == 1
            for i in np.flatnonzero(have):
                for c in range(len(self.cameras)):
                    image = held.array[rows[i], c]
                    out[where[i], c] = resize_crop(image, None, self.crop_box, self.image_size)[0] \
                        if resampling else image
            todo = np.flatnonzero(~have)
        if not len(todo):
            return
        keep = held if resampling else None  # the stored image would otherwise be thrown away
        ids = self.frame_ids[rows[todo]]
        try:
            for j, c, image in self._c.source.read_rows(ids, self._workers):
                problem = self._size_problem(ids[j], c, (image.shape[1], image.shape[0]))
                if problem is not None:
                    raise DatasetError(self.path, [problem])
                if keep is not None:
                    keep.array[rows[todo[j]], c] = image
                if resampling:
                    image, _ = resize_crop(image, None, self.crop_box, self.image_size)
                out[where[todo[j]], c] = image
        except ImageReadError as exc:
            raise DatasetError(self.path, [exc.problem()]) from None
        if keep is not None:
            keep.filled[rows[todo]] = 1  # every camera of these frames is in

    def hold_frames(self) -> None:
        """From now on, keep in memory, at their stored size, the frames that any view of this dataset
        (:meth:`resized`, :meth:`with_cache`) decodes to resample, and serve them from there instead of
        decoding the files again: a two-pass training decodes each frame once for its coarse pass's images
        and its crops. Memory is taken as frames come in, up to :attr:`stored_mib`; :meth:`release_frames`
        frees it."""
        if self._c.held is None:
            W, H = self.source_image_size
            held = ImageCache("memory", (len(self), len(self.cameras), H, W, 3), "held", [])
            held.open()
            self._c.held = held

    def release_frames(self) -> None:
        """Stop keeping frames in memory (:meth:`hold_frames`) and free them."""
        self._c.held = None

    @property
    def stored_mib(self) -> float:
        """MiB of every frame's images at their stored size, decoded (uint8 RGB)."""
        W, H = self.source_image_size
        return len(self) * len(self.cameras) * W * H * 3 / 2**20

    def preload(self, split: str | None = None, chunk: int = 256) -> None:
        """Decode every image of ``split`` (all when None) into the cache now, in parallel."""
        if not self._cache.open():
            return
        missing = self._cache.missing(self._rows(self.frames(split)))
        if not getattr(self._c.source, "random_access", True):
            chunk = max(1, len(missing))  # a video is decoded front to back: one pass for everything
        for start in range(0, len(missing), chunk):
            self._cache.fill(missing[start : start + chunk], self._decode_into)

    def images(self, frame_ids) -> np.ndarray:
        """Images of ``frame_ids`` as ``uint8 (B, C, H, W, 3)`` RGB (``(W, H) = image_size``).

        The first request of a frame decodes it into the cache; later requests copy from memory.

        Raises:
            DatasetError: an image file that cannot be read or decoded, or has the wrong size (named).
        """
        rows = self._rows(frame_ids)
        if not self._cache.open():
            W, H = self.image_size
            out = np.empty((len(rows), len(self.cameras), H, W, 3), dtype=np.uint8)
            self._decode_into(rows, out)
            return out
        self._fill(rows)
        return self._cache.read(rows)

    def cached_images(self, frame_ids) -> tuple[np.ndarray, np.ndarray] | None:
        """The image cache itself, with ``frame_ids`` decoded into it: ``(uint8 (N, C, H, W, 3), rows (B,))``
        where ``array[rows]`` are the images of ``frame_ids`` (:meth:`images`); None with ``cache="none"``.

        The array is the cache's own memory (a memmap with ``cache="disk"``), not a copy, so that a reader
        keeping every image at hand (``frames.FrameStore``) holds no second copy of them; it must not write
        to it.

        Raises:
            DatasetError: as :meth:`images`.
        """
        rows = self._rows(frame_ids)
        if not self._cache.open():
            return None
        self._fill(rows)
        return self._cache.array, rows

    def _fill(self, rows: np.ndarray) -> None:
        """Decode the ``rows`` not cached yet into the (open) cache."""
        missing = self._cache.missing(rows)
        if len(missing) and not getattr(self._c.source, "random_access", True):
            self.preload()  # decoding a video up to a frame costs as much as decoding them all
        elif len(missing):
            self._cache.fill(missing, self._decode_into)

    # -- reports -----------------------------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        """Counts for reports: frames per split, usable labels per split and per keypoint per camera in the
        labelled split, labelled frames with a keypoint seen by >= 2 cameras (triangulable) and with a usable
        label (:func:`s3k.data.usable.usable_labels`), 3D points."""
        splits = {s: int((self._c.frames.splits == s).sum()) for s in SPLITS}
        in_split = {s: self._c.frames.splits == s for s in SPLITS}
        train = self._label_mask[in_split["labelled"]]
        per = {
            k: {c: int(train[:, ci, ki].sum()) for ci, c in enumerate(self.cameras)}
            for ki, k in enumerate(self.keypoints)
        }
        X = self._c.points3d
        return {
            "frames": len(self),
            "splits": splits,
            "labels": per,
            "labels_per_split": {s: int(self._label_mask[m].sum()) for s, m in in_split.items()},
            "triangulable_labelled_frames": int((train.sum(1) >= 2).any(-1).sum()),
            "usable_labelled_frames": (int(usable_labels(self).any(axis=1).sum())
                                       if self._c.calibration_ok else 0),
            "points3d": None if X is None else int(np.isfinite(X).all(-1).sum()),
            "calibration": self._c.meta.calibration,
            "sessions": per_session_counts(self._c.sessions, self._c.frames.splits, self.sessions),
            "image_size": self.source_image_size,
            "units": self.units,
        }
