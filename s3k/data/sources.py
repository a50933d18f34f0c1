"""Image sources: where a dataset's pixels come from. PNG files per camera per frame, or one video per camera;
other sources plug in with :func:`register_image_source`.

A source reports missing files (``check``), yields decoded images (``read_rows``) and names the file behind an
image (``describe``). A file that cannot be read raises :class:`ImageReadError`, which names the file.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from s3k.data.images import ImageReadError, decode_image
from s3k.data.problems import Problems
from s3k.data.tables import DEFAULT_IMAGE_PATTERN, METADATA_FILE
from s3k.data.video import iter_frames


class PngImages:
    """One image file per camera per frame at ``pattern`` (default ``images/{camera}/{frame:06d}.png``)."""

    random_access = True

    def __init__(self, root: Path, spec: dict, cameras: list[str], frame_ids: np.ndarray, columns: dict):
        self.root = root
        self.pattern = spec.get("pattern", DEFAULT_IMAGE_PATTERN)
        self.cameras = cameras

    def relpath(self, frame: int, camera: str) -> str:
        return self.pattern.format(camera=camera, frame=int(frame))

    def check(self, frame_ids: np.ndarray, P: Problems) -> list[str]:
        """Report missing files; returns fingerprint items (path, size, mtime)."""
        items = []
        root = str(self.root)
        for frame in frame_ids:
            for cam in self.cameras:
                rel = self.relpath(frame, cam)
                try:
                    st = os.stat(os.path.join(root, rel))
                except OSError:
                    P.error(rel, "image", "image file missing", frame=int(frame), camera=cam)
                    continue
                items.append(f"{rel}:{st.st_size}:{st.st_mtime_ns}")
        return items

    def read_rows(self, frame_ids: Sequence[int], workers: int) -> Iterator[tuple[int, int, np.ndarray]]:
        """Yield ``(index into frame_ids, camera index, image (H, W, 3) uint8)`` for every requested image."""
        jobs = [(i, c) for i in range(len(frame_ids)) for c in range(len(self.cameras))]

        def load(job):
            i, c = job
            frame, camera = int(frame_ids[i]), self.cameras[c]
            rel = self.relpath(frame, camera)
            try:
                return i, c, decode_image(self.root / rel, rel)
            except ImageReadError as exc:
                raise ImageReadError(rel, exc.reason, frame=frame, camera=camera) from None

        if workers <= 1 or len(jobs) <= 1:
            yield from map(load, jobs)
            return
        with ThreadPoolExecutor(max_workers=workers) as pool:  # cv2 decodes without holding the GIL
            yield from pool.map(load, jobs)

    def describe(self, frame: int, c: int) -> str:
        return self.relpath(frame, self.cameras[c])


class VideoImages:
    """One video per camera (``spec["videos"][camera]``, relative paths), or one per camera of each session
    (``spec["sessions"][session][camera]``, the session from frames.csv's ``session`` column); frame ``f`` is
    video frame ``video_frame`` from frames.csv (the frame id itself when that column is absent)."""

    random_access = False

    def __init__(self, root: Path, spec: dict, cameras: list[str], frame_ids: np.ndarray, columns: dict):
        self.root = root
        self.per_session = "sessions" in spec
        self.videos = spec.get("sessions", {}) if self.per_session else {None: spec.get("videos", {})}
        self.cameras = cameras
        index = columns.get("video_frame")
        session = columns.get("session")
        self.video_frame = {
            int(f): (int(index[i]) if index is not None and str(index[i]).lstrip("-").isdigit() else int(f))
            for i, f in enumerate(frame_ids)
        }
        self.session = {int(f): (None if not self.per_session else "default" if session is None
                                 else str(session[i])) for i, f in enumerate(frame_ids)}

    def _field(self, session: str | None) -> str:
        return "images.videos" if session is None else f"images.sessions.{session}"

    def check(self, frame_ids: np.ndarray, P: Problems) -> list[str]:
        items: list[str] = []
        if not isinstance(self.videos, dict) or not all(isinstance(v, dict) for v in self.videos.values()):
            where = "images.sessions" if self.per_session else "images.videos"
            P.error(METADATA_FILE, where, "must map each camera name to a video file"
                    + (" per session" if self.per_session else ""))
            return items
        for session in sorted({self.session[int(f)] for f in frame_ids}, key=str):
            if session not in self.videos:
                P.error(METADATA_FILE, self._field(session), "no videos given for this session's frames")
        for session, videos in self.videos.items():
            for cam in self.cameras:
                rel = videos.get(cam)
                if not isinstance(rel, str):
                    P.error(METADATA_FILE, f"{self._field(session)}.{cam}", "no video file given for this "
                            "camera", camera=cam)
                    continue
                try:
                    st = os.stat(self.root / rel)
                except OSError:
                    P.error(rel, "video", "video file missing", camera=cam)
                    continue
                items.append(f"{rel}:{st.st_size}:{st.st_mtime_ns}")
            for cam in sorted(set(videos) - set(self.cameras)):
                P.error(METADATA_FILE, f"{self._field(session)}.{cam}", f"unknown camera {cam!r}", camera=cam)
        return items

    def read_rows(self, frame_ids: Sequence[int], workers: int) -> Iterator[tuple[int, int, np.ndarray]]:
        wanted = [self.video_frame[int(f)] for f in frame_ids]
        sessions = [self.session[int(f)] for f in frame_ids]
        for session in dict.fromkeys(sessions):
            rows = [i for i, s in enumerate(sessions) if s == session]
            for c, cam in enumerate(self.cameras):
                rel = self.videos[session][cam]
                images = dict(_iter_video(self.root / rel, rel, cam, sorted({wanted[i] for i in rows})))
                for i in rows:
                    if wanted[i] not in images:
                        raise ImageReadError(rel, f"video frame {wanted[i]} not found",
                                             frame=int(frame_ids[i]), camera=cam)
                    yield i, c, images[wanted[i]]

    def describe(self, frame: int, c: int) -> str:
        videos = self.videos.get(self.session.get(int(frame)), {})
        return f"{videos.get(self.cameras[c])} frame {self.video_frame.get(int(frame))}"


def _iter_video(path: Path, rel: str, camera: str, indices: list[int]) -> Iterator[tuple[int, np.ndarray]]:
    """Decode frames ``indices`` of a video (RGB uint8) in one front-to-back pass (``s3k.data.video``)."""
    try:
        yield from iter_frames(path, indices)
    except (ValueError, IndexError, OSError) as exc:  # unreadable, or a frame index beyond the video's end
        reason = str(exc).removeprefix(f"{path}: ")
        raise ImageReadError(rel, reason, camera=camera) from exc


IMAGE_SOURCES: dict[str, Callable[..., Any]] = {"png": PngImages, "video": VideoImages}


def register_image_source(type_name: str, factory: Callable[..., Any]) -> None:
    """Make ``{"images": {"type": type_name, ...}}`` in s3k.json read through ``factory``.

    ``factory(root, spec, cameras, frame_ids, columns)`` returns an object with ``check(frame_ids, problems)``
    (reports missing files, returns fingerprint strings), ``read_rows(frame_ids, workers)`` (yields
    ``(i, camera_index, uint8 (H, W, 3) RGB)``; raises :class:`ImageReadError` naming the file it cannot
    read) and ``describe(frame, camera_index)`` (text naming the file); a class attribute
    ``random_access = False`` makes the loader decode all frames in one pass on first use.
    """
    IMAGE_SOURCES[type_name] = factory
