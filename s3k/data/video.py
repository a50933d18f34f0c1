"""Video I/O with PyAV: frame count, random access to frame ``i``, iteration (also of several videos in
lockstep), extraction to PNG, and encoding.

Frame ``i`` is the ``i``-th frame in presentation order, counted from 0, which is how SLEAP, DeepLabCut and
anipose number frames. Random access seeks to the key frame before the frame's timestamp and decodes forward;
it assumes a constant frame rate (what camera rigs record) and checks the frame it lands on.

Images are ``uint8 (H, W, 3)`` RGB arrays. Wherever a video file is accepted, an image sequence (a folder of
images, a glob or a printf pattern; :mod:`s3k.data.imageseq`) is accepted too: frame ``i`` is its ``i``-th
image, and its frame rate is :data:`SEQUENCE_FPS`.
"""

from __future__ import annotations

import itertools
import queue
import threading
from collections.abc import Iterable, Iterator, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from s3k.base.errors import UserError
from s3k.data import imageseq
from s3k.data.images import decode_image

SEQUENCE_FPS = 30.0  # an image sequence records no frame rate; this one is used for overlay videos


_DECODE_THREADS = 0


def decode_threads(count: int) -> None:
    """Decode each video of this process with ``count`` threads (0, the default: as many as FFmpeg picks
    for the machine's cores); a task of one CPU among many (``s3k track --manifest``) decodes with one. The
    frames are the same whatever the count."""
    global _DECODE_THREADS
    _DECODE_THREADS = int(count)


def _threads(stream) -> None:
    stream.thread_type = "AUTO"
    if _DECODE_THREADS:
        stream.codec_context.thread_count = _DECODE_THREADS


def _read_image(path: Path) -> np.ndarray:
    return decode_image(path)


def _av():
    try:
        import av
    except ImportError as exc:  # pragma: no cover - av is a declared dependency
        raise ImportError("reading videos needs PyAV: pip install av") from exc
    return av


def exists(path: str | Path) -> bool:
    """True when ``path`` is a file or an image sequence with at least one image."""
    if not imageseq.is_sequence(path):
        return Path(path).is_file()
    try:
        return bool(imageseq.sequence_files(path))
    except UserError:
        return False


def _open(path: str | Path):
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: video file not found")
    av = _av()
    try:
        container = av.open(str(path))
    except Exception as exc:  # PyAV raises several error types for unreadable files
        raise UserError(f"{path}: cannot open as a video ({exc})") from exc
    if not container.streams.video:
        container.close()
        raise UserError(f"{path}: no video stream")
    return container, container.streams.video[0]


def frame_count(path: str | Path, exact: bool = False) -> int:
    """Number of frames of the first video stream.

    Args:
        path: video file.
        exact: decode the whole stream and count, instead of trusting the container header (which some
            containers leave empty or approximate).

    Returns:
        The number of frames.
    """
    if imageseq.is_sequence(path):
        return len(imageseq.sequence_files(path))
    container, stream = _open(path)
    with container:
        if stream.frames and not exact:
            return int(stream.frames)
        return sum(1 for _ in container.decode(stream))


def frame_size(path: str | Path) -> tuple[int, int]:
    """Image size ``(W, H)`` of the first video stream."""
    if imageseq.is_sequence(path):
        H, W = _read_image(imageseq.sequence_files(path)[0]).shape[:2]
        return W, H
    container, stream = _open(path)
    with container:
        return int(stream.codec_context.width), int(stream.codec_context.height)


def frame_rate(path: str | Path) -> float:
    """Average frame rate (frames per second) of the first video stream."""
    if imageseq.is_sequence(path):
        return SEQUENCE_FPS
    container, stream = _open(path)
    with container:
        rate = stream.average_rate or stream.guessed_rate
        if not rate:
            raise ValueError(f"{path}: the video stream declares no frame rate")
        return float(rate)


def iter_frames(path: str | Path, frame_ids: Iterable[int] | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Decode a video front to back, yielding ``(i, image (H, W, 3) uint8 RGB)``.

    Args:
        path: video file.
        frame_ids: if given, only these frames are yielded (in increasing order) and decoding stops after the
            last one. Ids beyond the end of the video raise an ``IndexError``.
    """
    wanted = None if frame_ids is None else sorted({int(i) for i in frame_ids})
    if wanted is not None and wanted and wanted[0] < 0:
        raise IndexError(f"{path}: negative frame index {wanted[0]}")
    if imageseq.is_sequence(path):
        files = imageseq.sequence_files(path)
        if wanted and wanted[-1] >= len(files):
            raise IndexError(f"{path}: frame {wanted[-1]} requested but the sequence has {len(files)} images")
        for i in range(len(files)) if wanted is None else wanted:
            yield i, _read_image(files[i])
        return
    container, stream = _open(path)
    with container:
        _threads(stream)
        if wanted is not None and not wanted:
            return
        last = None if wanted is None else wanted[-1]
        targets = None if wanted is None else set(wanted)
        n = 0
        for i, frame in enumerate(container.decode(stream)):
            n = i + 1
            if targets is None or i in targets:
                yield i, frame.to_ndarray(format="rgb24")
            if last is not None and i >= last:
                return
        if last is not None and last >= n:
            raise IndexError(f"{path}: frame {last} requested but the video has {n} frames")


def read_frame(path: str | Path, index: int) -> np.ndarray:
    """Frame ``index`` as ``(H, W, 3) uint8`` RGB, by seeking (constant frame rate assumed).

    Falls back to decoding from the start when the stream has no usable timestamps.
    """
    index = int(index)
    if index < 0:
        raise IndexError(f"{path}: negative frame index {index}")
    if imageseq.is_sequence(path):
        for _, image in iter_frames(path, [index]):
            return image
    container, stream = _open(path)
    with container:
        rate = stream.average_rate or stream.guessed_rate
        tb = stream.time_base
        if rate and tb:
            start = stream.start_time or 0
            seconds_per_frame = 1 / Fraction(rate)
            target_pts = start + int(round(index * seconds_per_frame / tb))
            container.seek(target_pts, stream=stream, backward=True, any_frame=False)
            for frame in container.decode(stream):
                if frame.pts is None:
                    break
                i = int(round((frame.pts - start) * tb / seconds_per_frame))
                if i == index:
                    return frame.to_ndarray(format="rgb24")
                if i > index:
                    break
    # Sequential fallback: exact by construction, slower.
    for _, image in iter_frames(path, [index]):
        return image
    raise IndexError(f"{path}: frame {index} not found")  # pragma: no cover - iter_frames raises first


def extract_frames(
    path: str | Path,
    out_dir: str | Path,
    frame_ids: Iterable[int] | None = None,
    pattern: str = "{:06d}.png",
) -> list[Path]:
    """Write frames of a video to PNG files named by frame index.

    Args:
        path: video file.
        out_dir: folder to write into (created if missing).
        frame_ids: frames to extract (all when None).
        pattern: file name format taking the frame index.

    Returns:
        The written paths, in frame order.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for i, image in iter_frames(path, frame_ids):
        target = out_dir / pattern.format(i)
        if not cv2.imwrite(str(target), image[:, :, ::-1]):
            raise OSError(f"{target}: could not write PNG")
        written.append(target)
    return written


def synchronized_frames(paths: Sequence[str | Path], start: int = 0, stop: int | None = None,
                        offsets: Sequence[int] | None = None) -> Iterator[tuple[int, list[np.ndarray]]]:
    """Decode several videos in lockstep: yields ``(i, [image (H, W, 3) uint8 RGB per video])``.

    Frame ``i`` of every video is one instant (a synchronized rig); with ``offsets`` (one per video, frames)
    instant ``i`` is frame ``i - offsets[c]`` of video ``c`` (its clock runs ``offsets[c]`` frames behind),
    and the instants begin at the first that every video filmed (``max(0, *offsets)``). Frames before
    ``start`` are decoded but not converted. Stops at ``stop`` (exclusive) or when the shortest video ends.
    """
    offsets = list(offsets) if offsets is not None else [0] * len(paths)
    first = max(0, *offsets)
    containers = []
    try:
        decoders: list[Iterator[Any]] = []
        for path in paths:
            if imageseq.is_sequence(path):
                decoders.append(iter(imageseq.sequence_files(path)))
                continue
            container, stream = _open(path)
            containers.append(container)
            _threads(stream)
            decoders.append(container.decode(stream))
        for c, n in enumerate(offsets):  # each video's first frame at instant ``first``
            decoders[c] = itertools.islice(decoders[c], first - n, None)
        for i, frames in enumerate(zip(*decoders), start=first):
            if stop is not None and i >= stop:
                return
            if i >= start:
                yield i, [_read_image(f) if isinstance(f, Path) else f.to_ndarray(format="rgb24")
                          for f in frames]
    finally:
        for container in containers:
            container.close()


def synchronized_batches(paths: Sequence[str | Path], batch: int, start: int = 0, stop: int | None = None,
                         offsets: Sequence[int] | None = None
                         ) -> Iterator[tuple[list[int], list[list[np.ndarray]]]]:
    """:func:`synchronized_frames` in batches: yields ``(indices, frames)``, ``frames`` a list of up to
    ``batch`` lists of one image per video (the last batch may be shorter)."""
    fnums: list[int] = []
    frames: list[list[np.ndarray]] = []
    for i, views in synchronized_frames(paths, start, stop, offsets):
        fnums.append(i)
        frames.append(views)
        if len(fnums) == batch:
            yield fnums, frames
            fnums, frames = [], []
    if fnums:
        yield fnums, frames


class VideoWriter:
    """Incremental encoder of ``(H, W, 3) uint8`` RGB frames of one size (use as a context manager).

    Args:
        path: output file; the container follows the extension (``.mp4``, ``.avi``, ``.mkv``...).
        fps: frame rate (30 when not positive).
        codec: an FFmpeg encoder name (``libx264``, ``mpeg4``, ``ffv1``...). ``ffv1`` (in ``.mkv``/``.avi``)
            stores RGB exactly, which tests that compare pixels need.
        lossless: ask libx264 for ``qp=0`` in 4:4:4 (nearly exact: only the RGB/YUV conversion rounds).

    Frames of odd width or height are padded by one edge pixel for the 4:2:0 formats, which need even sizes.
    """

    def __init__(self, path: str | Path, fps: float = 30.0, codec: str = "libx264",
                 lossless: bool = False) -> None:
        self.path = Path(path)
        self.codec = codec
        self.lossless = lossless
        self._rate = Fraction(fps).limit_denominator(1001) if fps > 0 else Fraction(30)
        self._container = _av().open(str(self.path), mode="w")
        self._stream: Any = None  # created with the first frame, whose size it takes
        self._size: tuple[int, int] | None = None
        self.frames = 0

    def _pix_fmt(self) -> str:
        if self.codec == "ffv1":
            return "bgr0"
        return "yuv444p" if self.lossless and self.codec == "libx264" else "yuv420p"

    def write(self, image: np.ndarray) -> None:
        """Encode one frame (the same size as the first)."""
        av = _av()
        image = np.ascontiguousarray(image, dtype=np.uint8)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"{self.path}: frame {self.frames} has shape {image.shape}, expected (H, W, 3)")
        H, W = image.shape[:2]
        if self._size is None:
            self._size = (W, H)
            options = {"qp": "0"} if self.lossless and self.codec == "libx264" else {}
            self._stream = self._container.add_stream(self.codec, rate=self._rate, options=options)
            pix_fmt = self._pix_fmt()
            even = pix_fmt == "yuv420p"
            self._stream.width, self._stream.height = (W + W % 2, H + H % 2) if even else (W, H)
            self._stream.pix_fmt = pix_fmt
        elif (W, H) != self._size:
            raise ValueError(f"{self.path}: frame {self.frames} is {W}x{H}, the first was "
                             f"{self._size[0]}x{self._size[1]}")
        pad = (self._stream.height - H, self._stream.width - W)
        if any(pad):
            image = np.pad(image, ((0, pad[0]), (0, pad[1]), (0, 0)), mode="edge")
        frame = av.VideoFrame.from_ndarray(image, format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder and close the file."""
        if self._stream is not None:
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._stream = None
        self._container.close()

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_video(
    path: str | Path,
    frames: Iterable[np.ndarray],
    fps: float = 30.0,
    codec: str = "libx264",
    lossless: bool = False,
) -> int:
    """Encode ``(H, W, 3) uint8`` RGB frames to a video file (:class:`VideoWriter`'s arguments).

    Returns:
        The number of frames written.
    """
    with VideoWriter(path, fps, codec, lossless) as writer:
        for image in frames:
            writer.write(image)
    return writer.frames


def prefetch(iterator: Iterator, depth: int = 2) -> Iterator:
    """Run ``iterator`` in a background thread, ``depth`` items ahead, so decoding overlaps what the caller
    does with each item (``s3k track``, ``s3k stream``); an error in the thread is raised in the caller."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def worker() -> None:
        try:
            for item in iterator:
                while not stop.is_set():
                    try:
                        q.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put((done, None))
        except BaseException as exc:  # re-raised in the consumer
            q.put((done, exc))

    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    try:
        while True:
            item, exc = q.get()
            if item is done:
                if exc is not None:
                    raise exc
                return
            yield item
    finally:
        stop.set()
        thread.join(timeout=5)
