"""``s3k stream``: live 3D keypoints from synchronized sources, one JSON line per frame.

Sources are cameras opened with OpenCV (an index such as ``0`` or a device such as ``/dev/video2``), video
files or image sequences (as for ``s3k track``); frame ``i`` of every source is one instant. Each frame of
``C`` views goes through the run's :class:`s3k.detector.Detector` (one pass or two) as soon as it is read,
and one line is written::

    {"frame": 12, "time": 0.48, "points": {"nose": [x, y, z], "tail": null}, "valid": {...},
     "latency_ms": 9.7}

With a filter (``s3k stream --filter kalman``: the causal Kalman filter of :mod:`s3k.inference.kalman`, from
this frame and the ones before it only) ``points`` and ``valid`` are the filtered points, ``raw`` the
detector's and ``rejected`` the keypoints whose jump the filter rejected; ``latency_ms`` includes the filter.

``time`` is seconds since the stream started, when the frame was read; ``points`` are in the calibration's
world frame and units (null where not triangulated); ``latency_ms`` is the time from reading the frame to
its points. Live cameras run at their own rate: when the detector is slower, the stream says on stderr how
many frames behind it is (it reads the newest frame, so it never lags further). Files are read as fast as
the detector goes. With ``rerun`` the cameras, the views (JPEG, downscaled), the detections, the 3D points
with their skeleton and confidence are logged to a Rerun viewer or file (``rerun-sdk``, ``pip install
s3k[stream]``; :mod:`s3k.inference.rerun_log`). Ctrl-C stops the stream between two frames.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import IO, Any

import cv2
import numpy as np

from s3k.base.errors import UserError
from s3k.base.messages import note
from s3k.data import imageseq, video
from s3k.data.video import prefetch
from s3k.inference.rerun_log import RerunLog, recording_summary
from s3k.inference.session import RigSession
from s3k.inference.track import limb_indices
from s3k.inference.track_config import TrackConfig
from s3k.inference.track_filter import StreamFilter, layout_shape_of
from s3k.readout import DEFAULT_MIN_WEIGHT

log = logging.getLogger(__name__)

__all__ = ["Source", "StreamSummary", "open_source", "open_sources", "pace_line", "rerun_logger", "stream",
           "stream_filter", "stream_session"]


class Source:
    """One camera's frames: ``read()`` gives the next ``uint8 (H, W, 3)`` RGB frame, or None at the end.

    Attributes:
        spec: what the user gave.
        size: ``(W, H)``.
        fps: frames per second (0 when unknown).
        live: a camera (frames arrive at its rate) rather than a file.
    """

    spec: str
    size: tuple[int, int]
    fps: float
    live: bool

    def read(self) -> np.ndarray | None:
        raise NotImplementedError

    def close(self) -> None:
        pass


class FileSource(Source):
    """A video file or an image sequence (:mod:`s3k.data.video`)."""

    def __init__(self, spec: str) -> None:
        self.spec, self.live = spec, False
        self.size = video.frame_size(spec)
        # an image sequence records no frame rate: unknown (0) unless ``s3k stream --fps`` gives it
        self.fps = 0.0 if imageseq.is_sequence(spec) else video.frame_rate(spec)
        self._frames: Iterator[tuple[int, np.ndarray]] = video.iter_frames(spec)

    def read(self) -> np.ndarray | None:
        return next(self._frames, (0, None))[1]


class CameraSource(Source):
    """A camera opened with OpenCV (``cv2.VideoCapture``)."""

    def __init__(self, spec: str) -> None:
        self.spec, self.live = spec, True
        self._cap = cv2.VideoCapture(int(spec) if spec.isdigit() else spec)
        if not self._cap.isOpened():
            raise UserError(f"--sources {spec}: no camera could be opened there",
                            hint="check the index or device (ls /dev/video*) and that no other program "
                                 "holds it")
        ok, first = self._cap.read()
        if not ok:
            raise UserError(f"--sources {spec}: the camera opened but gave no frame")
        self._first: np.ndarray | None = first[..., ::-1].copy()
        self.size = (int(first.shape[1]), int(first.shape[0]))
        self.fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)

    def read(self) -> np.ndarray | None:
        if self._first is not None:
            frame, self._first = self._first, None
            return frame
        ok, frame = self._cap.read()
        return frame[..., ::-1].copy() if ok else None

    def close(self) -> None:
        self._cap.release()


def open_sources(specs: dict[str, str], fps: float | None = None) -> dict[str, Source]:
    """``{camera: Source}`` of ``{camera: spec}`` (:func:`open_source`); ``fps`` is the rate of those that
    record none (image sequences)."""
    sources = {name: open_source(spec) for name, spec in specs.items()}
    for source in sources.values():
        source.fps = source.fps or float(fps or 0.0)
    return sources


def open_source(spec: str) -> Source:
    """A camera (an index, or a ``/dev/video*`` device) or a video file / image sequence."""
    if spec.isdigit() or spec.startswith("/dev/video"):
        return CameraSource(spec)
    if not video.exists(spec):
        raise UserError(f"--sources {spec}: no such camera, video file, image folder or image pattern")
    return FileSource(spec)


@dataclass
class StreamSummary:
    """What :func:`stream` did: ``frames`` in ``seconds`` (``fps``), the sources' own rate (0: unknown) and
    the most frames the stream was behind live sources."""

    frames: int
    seconds: float
    fps: float
    source_fps: float
    behind: int
    interrupted: bool


def _frames(sources: list[Source]) -> Iterator[list[np.ndarray]]:
    """The sources' frames in lockstep, until one ends."""
    while True:
        views = [s.read() for s in sources]
        if any(v is None for v in views):
            return
        yield views  # type: ignore[misc]


def _points(keypoints: list[str], X: np.ndarray, valid: np.ndarray) -> dict[str, Any]:
    return {k: [round(float(v), 7) for v in X[j]] if valid[j] else None for j, k in enumerate(keypoints)}


def _frame_line(i: int, t: float, keypoints: list[str], X: np.ndarray, valid: np.ndarray,
                latency: float, filtered: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> str:
    """One frame's JSON line; with ``filtered`` (the causal filter's ``X, valid, rejected``) ``points`` and
    ``valid`` are the filter's, ``raw`` the detector's points and ``rejected`` the keypoints whose jump the
    filter rejected."""
    line: dict[str, Any] = {"frame": i, "time": round(t, 6)}
    if filtered is None:
        line["points"] = _points(keypoints, X, valid)
        line["valid"] = {k: bool(valid[j]) for j, k in enumerate(keypoints)}
    else:
        line["points"] = _points(keypoints, filtered[0], filtered[1])
        line["valid"] = {k: bool(filtered[1][j]) for j, k in enumerate(keypoints)}
        line["raw"] = _points(keypoints, X, valid)
        line["rejected"] = [k for j, k in enumerate(keypoints) if filtered[2][j]]
    line["latency_ms"] = round(1000 * latency, 3)
    return json.dumps(line)


def stream(detector, sources: dict[str, Source], cams, boxes: np.ndarray | None = None,
           out: IO[str] = sys.stdout, min_weight: float = DEFAULT_MIN_WEIGHT, max_frames: int | None = None,
           log: Callable[[int, list[np.ndarray], Any], None] | None = None,
           say: Callable[[str], None] | None = None,
           filter: Callable[[Any], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None) -> StreamSummary:
    """Detect every frame of the synchronized ``sources`` and write one JSON line per frame to ``out``
    (module docstring).

    Args:
        detector: a :class:`s3k.detector.Detector`.
        sources: ``{camera: Source}`` in the order of ``cams``.
        cams: the calibration's cameras ``(C,)`` in the sources' pixels.
        boxes: ``(C, 4)`` region of each view the (first) network sees (default the whole frame).
        out: where the lines go.
        min_weight: as for :func:`s3k.readout.read_out`.
        max_frames: stop after this many frames (default: at the end of the shortest source).
        log: called with ``(frame, views, detection)`` after each frame (the Rerun logger).
        say: where the notes on keeping up go (default: logged at ``s3k.base.messages.NOTE``).
        filter: the causal filter over time (:class:`s3k.inference.track_filter.StreamFilter`), or None: the
            lines hold its points, from this frame and the ones before it only.
    """
    say = say or note
    keypoints = detector.keypoints
    live = any(s.live for s in sources.values())
    rates = [s.fps for s in sources.values() if s.fps > 0]
    rate = min(rates) if rates else 0.0
    start = time.perf_counter()
    i, behind, said, interrupted = 0, 0, start, False
    frames = _frames(list(sources.values()))
    if not live:  # files: the next frame is decoded while this one is detected (a camera's is read fresh)
        frames = prefetch(frames, depth=2)
    try:
        while max_frames is None or i < max_frames:
            views = next(frames, None)
            if views is None:
                break
            read = time.perf_counter()
            det = detector([v[None] for v in views], cams, boxes, min_weight)  # type: ignore[index]
            filtered = filter(det) if filter is not None else None
            done = time.perf_counter()
            out.write(_frame_line(i, read - start, keypoints, det.X[0].numpy(), det.valid[0].numpy(),
                                  done - read, filtered) + "\n")
            i += 1  # counted as soon as its line is written: Ctrl-C in the flush or the logger keeps it
            out.flush()
            if log is not None:
                log(i - 1, views, det)  # type: ignore[arg-type]
            if live and rate > 0:
                lag = int((done - start) * rate) - i
                behind = max(behind, lag)
                if lag > 1 and done - said > 2.0:
                    say(f"s3k stream: {lag} frames behind the cameras ({i / (done - start):.1f} of {rate:g} "
                        "frames/s); the newest frame is read each time")
                    said = done
    except KeyboardInterrupt:
        interrupted = True
    finally:
        for s in sources.values():
            s.close()
    seconds = time.perf_counter() - start
    return StreamSummary(i, seconds, i / seconds if seconds > 0 else 0.0, rate, behind, interrupted)


def stream_filter(session: RigSession, config: TrackConfig) -> StreamFilter | None:
    """The causal filter of ``config`` on the session's rig, or None (``filter="none"``)."""
    if not config.filtering_on:
        return None
    detector = session.detector
    limbs = config.limb_pairs()
    limbs = detector.meta.recorded_skeleton() if limbs is None else limbs
    assert session.cameras is not None
    return StreamFilter(config.filter_settings(), len(detector.keypoints), session.cameras.numpy(),
                        layout_shape_of(detector.meta.layout), limb_indices(limbs, detector.keypoints))


def stream_session(session: RigSession, sources: dict[str, Source], config: TrackConfig,
                   out: IO[str] = sys.stdout, max_frames: int | None = None,
                   log: Callable[[int, list[np.ndarray], Any], None] | None = None) -> StreamSummary:
    """:func:`stream` of the session's detector on its rig, with the read-out and the filter of
    ``config``."""
    return stream(session.detector, sources, session.cameras, session.boxes, out, config.readout.min_weight,
                  max_frames, log, filter=stream_filter(session, config))


def pace_line(summary: StreamSummary, sources: dict[str, Source]) -> str:
    """The line that says how fast the stream went, and how fast its sources run."""
    unknown = [name for name, s in sources.items() if not s.fps]
    pace = (f"; the sources run at {summary.source_fps:g} frames/s" if summary.source_fps else
            f"; the frame rate of {', '.join(unknown)} is unknown (--fps gives it)")
    if summary.behind > 1:
        pace += f", up to {summary.behind} frames behind"
    return (f"s3k stream: {summary.frames} frames in {summary.seconds:.2f} s, {summary.fps:.1f} "
            f"frames/s{pace}" + (" (stopped by Ctrl-C)" if summary.interrupted else ""))


def rerun_logger(session: RigSession, sources: dict[str, Source], target: str, image_scale: float = 0.5,
                 jpeg_quality: int = 75) -> tuple[Callable, Callable[[bool], None]]:
    """A ``log`` for :func:`stream` that sends the rig's cameras, the views (downscaled by ``image_scale``,
    JPEG), the detections, the 3D points with their skeleton and confidence, and their reprojections to Rerun
    (:class:`s3k.inference.rerun_log.RerunLog`): ``target`` "spawn" (a viewer), or a ``.rrd`` file to write.
    Returns ``(log, close)``; ``close(keep)`` completes the file and says what it holds (or, ``keep=False``,
    removes it)."""

    detector = session.detector
    rec = RerunLog("s3k stream", target, detector.keypoints, session.names, detector.meta.recorded_skeleton(),
                   image_scale=image_scale, jpeg_quality=jpeg_quality, units=detector.units)
    rec.cameras_at(session.cameras, [s.size for s in sources.values()])

    def log(i: int, views: list[np.ndarray], det) -> None:
        rec.detection(i, views, det.cpu())

    def close(keep: bool) -> None:
        rec.close(keep)
        if keep and target != "spawn":
            saved = recording_summary(target)
            note(f"s3k stream: wrote {target}: {len(saved['frames'])} frames, {saved['bytes'] / 1e6:.2f} MB "
                 f"({saved['bytes_per_frame'] / 1e6:.3f} MB a frame)")

    return log, close
