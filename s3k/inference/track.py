"""``s3k track``: 3D keypoints from synchronized videos of a calibrated rig, written in anipose's CSV layout.

Pipeline, per frame (the same read-out as training, ``s3k predict`` and ``s3k evaluate``):

1. The C videos are decoded in lockstep (:func:`s3k.data.video.synchronized_frames`): frame ``i`` of every
   video is one instant (anipose's assumption for a synchronized rig).
2. Each image is mapped onto the detector's input size with :func:`s3k.geometry.warp.resize_crop` (the crop
   box follows ``crops`` or ``fit``), whose pixel map ``M`` also gives the network's intrinsics ``K' = M K``.
3. The shared network gives one heatmap per camera and keypoint; :func:`s3k.readout.read_out` turns them into
   detections in the original video pixels (through ``M^-1``), confidence weights, and the
   confidence-weighted triangulation of the views above ``min_weight`` in the calibration's own cameras (lens
   distortion included), so the 3D points are in the calibration's world frame and units.

The CSV is :mod:`s3k.data.tracks_csv`'s (``error`` in pixels of the original video, ``fnum`` the video frame
index). With ``overlay`` one MP4 per camera (``DIR/<camera>.mp4``) shows, on the original frames, the
reprojected 3D keypoints (filled discs) and the per-view detections (crosses), one colour per keypoint
(:func:`s3k.draw.draw_overlay`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from s3k.choices import Device
from s3k.data import imageseq, video
from s3k.data.formats.calibration_files import read_calibration
from s3k.data.rig import check_camera_name
from s3k.data.tracks_csv import array_rows, check_output, csv_rows, write_csv
from s3k.detector import Detector
from s3k.draw import draw_overlay, edge_indices, keypoint_colours
from s3k.errors import UserError
from s3k.geometry import Cameras
from s3k.geometry.warp import crop_resize_matrix
from s3k.inference.kalman import FilterSettings
from s3k.inference.rig_check import calibration_notes
from s3k.inference.track_filter import doubt, doubt_path, filter_track, layout_shape_of, raw_path, write_doubt
from s3k.readout import DEFAULT_MIN_WEIGHT

log = logging.getLogger(__name__)

__all__ = ["FIT_MODES", "CameraInput", "TrackSummary", "empty_result_hint", "fit_box", "limb_indices",
           "prepare_cameras", "track_videos"]

FIT_MODES = ("pad", "crop", "stretch")


# ------------------------------------------------------------------------------------------------------------
# Geometry of the inputs


def fit_box(video_size: tuple[int, int], net_size: tuple[int, int], mode: str = "pad") -> tuple[float, ...]:
    """The crop box (pixel edge coordinates) of a video frame that is mapped onto the network input.

    Args:
        video_size: ``(W, H)`` of the video.
        net_size: ``(w, h)`` of the network input.
        mode: ``"pad"`` keeps the whole frame and the aspect ratio, padding with black (a box larger than the
            frame, centred); ``"crop"`` keeps the aspect ratio and cuts the frame's excess, centred;
            ``"stretch"`` maps the whole frame onto the input (scales differ per axis when the aspect ratios
            do). All three are the same when the aspect ratios agree.

    Returns:
        ``(x0, y0, x1, y1)``.
    """
    W, H = float(video_size[0]), float(video_size[1])
    w, h = float(net_size[0]), float(net_size[1])
    if mode not in FIT_MODES:
        raise UserError(f"--fit must be one of {', '.join(FIT_MODES)}, got {mode!r}")
    if mode == "stretch" or W * h == H * w:
        return 0.0, 0.0, W, H
    # Box of the network's aspect ratio, as wide as the frame or as tall as it.
    wide = W * h > H * w  # the frame is wider than the network input
    if (mode == "pad") == wide:
        bw, bh = W, W * h / w
    else:
        bw, bh = H * w / h, H
    x0, y0 = (W - bw) / 2, (H - bh) / 2
    return x0, y0, x0 + bw, y0 + bh


@dataclass
class CameraInput:
    """One camera of the rig and its video.

    Attributes:
        name: camera name (as in the calibration).
        path: video file.
        video_size: ``(W, H)`` of the video.
        fps: frame rate of the video.
        box: crop box mapped onto the network input (pixel edge coordinates of the video).
        M: ``(3, 3)`` pixel map from video pixels to network-input pixels (``crop_resize_matrix``).
    """

    name: str
    path: Path
    video_size: tuple[int, int]
    fps: float
    box: tuple[float, ...]
    M: np.ndarray


def prepare_cameras(videos: dict[str, Path], calibration, net_size: tuple[int, int], fit: str = "pad",
                    crops: dict[str, tuple[float, ...]] | None = None) -> tuple[list[CameraInput], Cameras]:
    """Match videos to calibrated cameras and compute each camera's map onto the network input.

    Args:
        videos: ``{camera: video path}``; the order is the camera order of the outputs.
        calibration: a :class:`s3k.data.rig.Rig` (``s3k.data.formats.anipose.read_anipose_calibration``).
        net_size: ``(w, h)`` network input size.
        fit: see :func:`fit_box` (for cameras without an explicit crop box).
        crops: optional ``{camera: (x0, y0, x1, y1)}`` boxes, as given to ``s3k import --crop``.

    Returns:
        ``(inputs, cams)``: one :class:`CameraInput` per video, and the calibration's cameras ``(C,)`` in
        float64, in original video pixels.

    Raises:
        UserError: a camera missing from the calibration, or a video whose size is not the calibrated image
            size.
        ValueError: an unreadable video.
        FileNotFoundError: a missing video file.
    """
    known = list(calibration.names)
    unknown = [c for c in videos if c not in known]
    if unknown:
        raise UserError(
            f"--videos: camera {', '.join(repr(c) for c in unknown)} is not in the calibration "
            f"(its cameras are {', '.join(known)})"
        )
    rig = calibration.select(list(videos))
    crops = crops or {}
    inputs = []
    for c, (name, path) in enumerate(videos.items()):
        if not video.exists(path):
            raise FileNotFoundError(f"--videos {name}={path}: no such video file, image folder or image "
                                    "pattern")
        size = video.frame_size(path)
        calib_size = (int(rig.size[c][0]), int(rig.size[c][1]))
        if size != calib_size:
            raise UserError(
                f"camera {name!r}: video {path} is {size[0]}x{size[1]} pixels but the calibration gives "
                f"{calib_size[0]}x{calib_size[1]}; the intrinsics apply only to images of the calibrated "
                "size", hint="if the video is the calibrated image cropped or padded by a few pixels, "
                f"declare it with --video-region {name}=X0,Y0,X1,Y1",
            )
        box = tuple(float(v) for v in crops.get(name, fit_box(size, net_size, fit)))
        inputs.append(CameraInput(name, Path(path), size, video.frame_rate(path), box,
                                  crop_resize_matrix(box, net_size)))
    return inputs, rig.cameras


# ------------------------------------------------------------------------------------------------------------
# Video in, video and CSV out


@dataclass
class TrackSummary:
    """What :func:`track_videos` did.

    Attributes:
        frames: frames tracked.
        keypoints: keypoint names.
        valid_fraction: per keypoint, the fraction of frames with a 3D point.
        median_error_px: per keypoint, the median reprojection error (original video pixels).
        passing_fraction: per keypoint, the fraction of frames with at least two views above ``min_weight``.
        min_weight: the threshold used.
        units: world unit of the calibration.
        path: the CSV written (the filtered points when a filter ran).
        raw: the CSV of the unfiltered points when a filter ran (:func:`s3k.inference.track_filter.raw_path`),
            else None (``path`` holds them).
        doubt: the frames ranked by doubt (:func:`s3k.inference.track_filter.write_doubt`).
        filter: the filter's settings and what it fitted and did, or None.
        fps: the videos' frame rate (None where they differ or an image sequence records none).
    """

    frames: int
    keypoints: list[str]
    valid_fraction: list[float]
    median_error_px: list[float]
    passing_fraction: list[float]
    min_weight: float
    units: str
    path: Path
    fps: float | None = None
    raw: Path | None = None
    doubt: Path | None = None
    filter: dict | None = None


def _frame_batches(inputs: list[CameraInput], batch: int, start: int, stop: int | None):
    """Yield ``(fnums, frames)`` from the synchronized videos: ``frames`` a list of ``B`` lists of ``C`` uint8
    images at the videos' own sizes."""
    fnums, frames = [], []
    for i, views in video.synchronized_frames([c.path for c in inputs], start, stop):
        fnums.append(i)
        frames.append(views)
        if len(fnums) == batch:
            yield fnums, frames
            fnums, frames = [], []
    if fnums:
        yield fnums, frames


def _stack_views(frames: list[list[np.ndarray]]) -> np.ndarray | list[np.ndarray]:
    """``B`` frames of ``C`` images -> one array ``(B, C, H, W, 3)`` when the cameras' sizes agree, else ``C``
    arrays ``(B, H_c, W_c, 3)`` (:class:`s3k.detector.Detector`)."""
    if len({f.shape for frame in frames for f in frame}) == 1:
        return np.stack([np.stack(frame) for frame in frames])
    return [np.stack([f[c] for f in frames]) for c in range(len(frames[0]))]


def _check_inputs(videos: dict[str, Path], batch: int, start: int, stop: int | None,
                  min_weight: float) -> None:
    if len(videos) < 2:
        raise UserError(f"--videos: triangulation needs at least 2 cameras, got {len(videos)} "
                        f"({', '.join(videos)})")
    if batch < 1:
        raise UserError(f"--batch must be >= 1, got {batch}")
    if start < 0 or (stop is not None and stop <= start):
        raise UserError(f"--start/--stop: need 0 <= start < stop, got start={start}, stop={stop}")
    if not 0 <= min_weight < 1:
        raise UserError(f"--min-weight must be in [0, 1), got {min_weight}")


def _frame_range(inputs: list[CameraInput], start: int, stop: int | None) -> int:
    """The frame index to stop before; warns about videos of different lengths or frame rates."""
    counts = {c.name: video.frame_count(c.path) for c in inputs}
    n_video = min(counts.values())
    if len(set(counts.values())) > 1:
        lengths = ", ".join(f"{k}: {v}" for k, v in counts.items())
        log.warning(f"the videos have different lengths ({lengths}); tracking the first {n_video} frames "
                    "of each")
    rates = {c.name: c.fps for c in inputs}
    if max(rates.values()) - min(rates.values()) > 1e-3 * max(rates.values()):
        log.warning(f"the videos have different frame rates ({rates}); frames are paired by index")
    if start >= n_video:
        raise UserError(f"--start {start}: the videos have {n_video} frames")
    return n_video if stop is None else min(stop, n_video)


def track_videos(run_dir: str | Path, videos: dict[str, Path], calibration: str | Path, out: str | Path,
                 overlay: str | Path | None = None, batch: int = 8, start: int = 0, stop: int | None = None,
                 min_weight: float = DEFAULT_MIN_WEIGHT, fit: str = "pad",
                 crops: dict[str, tuple[float, ...]] | None = None, device: Device = "auto",
                 units: str | None = None, progress: bool = True, overwrite: bool = False,
                 video_regions: dict[str, tuple[float, ...]] | None = None,
                 filter_settings: FilterSettings | None = None,
                 skeleton: Sequence[tuple[str, str]] | None = None) -> TrackSummary:
    """Track synchronized videos to 3D keypoints and write anipose's 3D CSV (see the module docstring).

    Args:
        run_dir: run folder of ``s3k train``, one pass or two (:class:`s3k.detector.Detector`).
        videos: ``{camera: video or image sequence}``; camera names as in the calibration, at least two.
        calibration: a calibration file of any format
            :func:`s3k.data.formats.calibration_files.read_calibration` reads.
        out: CSV file to write.
        overlay: folder for one MP4 per camera with the keypoints drawn, or None.
        batch: frames per forward pass (each has C images).
        start: first frame index.
        stop: frame index to stop before (None: to the end of the shortest video).
        min_weight: views with a confidence weight at or below this are not used (:mod:`s3k.readout`).
        fit: how frames map onto the network input when aspect ratios differ (:func:`fit_box`).
        crops: per-camera crop boxes (as for ``s3k import --crop``), overriding ``fit``.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``...
        units: world unit of the calibration when the file does not say.
        progress: show a tqdm progress bar.
        overwrite: replace an existing ``out``.
        video_regions: ``{camera: (x0, y0, x1, y1)}``, the region of the calibrated image each video shows
            (:meth:`s3k.data.rig.Rig.with_video_regions`).
        filter_settings: filter the points over time (:mod:`s3k.inference.kalman`; the raw points go to
            ``<stem>.raw.csv``), or None / ``method="none"``: no filter.
        skeleton: the limbs a filter holds near their lengths, pairs of keypoint names (None: the skeleton
            the run recorded from its dataset).

    Returns:
        A :class:`TrackSummary`; the frames ranked by doubt are written to ``<stem>.doubt.csv``.
    """
    _check_inputs(videos, batch, start, stop, min_weight)
    out = check_output(out, overwrite)
    filtering = filter_settings is not None and filter_settings.check().method != "none"
    raw = check_output(raw_path(out), overwrite) if filtering else out
    check_output(doubt_path(out), overwrite)
    calib = read_calibration(calibration, units=units)
    calib = calib.with_sizes({cam: video.frame_size(p) for cam, p in videos.items()
                              if cam in calib.names and video.exists(p)})
    if video_regions:
        try:
            calib = calib.with_video_regions(video_regions)  # type: ignore[arg-type]
        except (KeyError, ValueError) as exc:
            raise UserError(f"--video-region: {exc.args[0]}") from None
    say_calibration(run_dir, calib, [c for c in videos if c in calib.names], calibration)
    detector = Detector.load(run_dir, device)
    inputs, cams = prepare_cameras(videos, calib, detector.input_size, fit, crops)
    end = _frame_range(inputs, start, stop)
    boxes = np.array([c.box for c in inputs], dtype=np.float64)
    frames = video.prefetch(_frame_batches(inputs, batch, start, end))
    limbs = detector.meta.recorded_skeleton() if skeleton is None else skeleton
    edges = limb_indices(limbs, detector.keypoints)
    got = _track(detector, frames, cams, boxes, min_weight, raw, overlay, inputs, end - start, progress)
    n, keypoints, valid, error, passing = _summary_of(got, detector.keypoints)
    summary = TrackSummary(n, keypoints, valid, error, passing, min_weight, calib.units, out,
                           _common_rate(inputs))
    rejected = None
    if filtering:
        assert filter_settings is not None
        rejected = _write_filtered(got, cams, filter_settings, detector, edges, out)
        summary.raw, summary.filter = raw, {"settings": filter_settings.to_dict(), **rejected.info}
    summary.doubt = write_doubt(doubt_path(out), got.fnums,
                                doubt(got.weights, got.residual, got.valid.astype(bool),
                                      None if rejected is None else rejected.rejected),
                                detector.keypoints, None if rejected is None else rejected.rejected)
    return summary


def limb_indices(skeleton: Sequence[tuple[str, str]], keypoints: list[str]) -> list[tuple[int, int]]:
    """The skeleton's limbs as keypoint index pairs; a name the run does not have is refused."""
    out = []
    for a, b in skeleton:
        for name in (a, b):
            if name not in keypoints:
                raise UserError(f"--filter-limbs: keypoint {name!r} is not one of the run's "
                                f"({', '.join(keypoints)})")
        out.append((keypoints.index(a), keypoints.index(b)))
    return out


def _write_filtered(got: _Collected, cams: Cameras, settings: FilterSettings, detector, edges, out: Path):
    """Filter the collected track and write its CSV to ``out``; returns the filter's result."""
    shape = layout_shape_of(detector.meta.layout)
    res = filter_track(got.X, got.error, got.score, got.used.astype(bool), cams.numpy(), settings, shape,
                       edges)
    with write_csv(out, detector.keypoints) as writer:
        ncams = np.where(res.measured, got.ncams, 0)  # 0: no measurement entered the filter there
        writer.writerows(array_rows(got.fnums.tolist(), res.X, got.error, ncams, got.score))
    return res


def say_calibration(run_dir, calib, names: list[str], source) -> None:
    """Log as warnings what :func:`s3k.inference.rig_check.calibration_notes` finds in the calibration of
    the cameras ``names``: copies, and how it differs from the run's."""
    rig = calib.select(names)
    sizes = {n: (int(w), int(h)) for n, (w, h) in zip(rig.names, rig.size)}
    for line in calibration_notes(run_dir, rig.cameras, rig.names, rig.units, sizes, source):
        log.warning(line.removeprefix("warning: "))


def _common_rate(inputs: list[CameraInput]) -> float | None:
    """The frame rate every video declares (None where they differ or an image sequence records none)."""
    if any(imageseq.is_sequence(c.path) for c in inputs):
        return None
    rates = [float(c.fps) for c in inputs]
    return rates[0] if rates and max(rates) - min(rates) <= 1e-3 * max(rates) else None


@dataclass
class _Collected:
    """What :func:`_track` keeps of every frame for the filter and the doubt ranking: ``fnums (T,)``, ``X (T,
    K, 3)``, ``error``, ``ncams``, ``score``, ``valid`` ``(T, K)``, ``used``, ``weights``, ``residual`` ``(T,
    C, K)``."""

    fnums: np.ndarray
    X: np.ndarray
    error: np.ndarray
    ncams: np.ndarray
    score: np.ndarray
    valid: np.ndarray
    used: np.ndarray
    weights: np.ndarray
    residual: np.ndarray


def overlay_file(folder: str | Path, camera: str) -> Path:
    """The overlay video of ``camera`` in ``folder`` (``folder/<camera>.mp4``), refused (one line) unless it
    lies in ``folder`` itself: a camera's name never leads the file elsewhere."""
    check_camera_name(camera, "--overlay")
    path = Path(folder) / f"{camera}.mp4"
    if path.resolve().parent != Path(folder).resolve():
        raise UserError(f"--overlay {folder}: camera {camera!r} would write its video outside the folder "
                        f"({path})", hint="rename the camera")
    return path


def _track(detector, frames, cams, boxes, min_weight, out, overlay, inputs, total, progress):
    """Detect every batch of ``frames``, write the CSV of the raw points to ``out`` (and overlays); returns
    the :class:`_Collected` arrays."""

    writers = []
    if overlay is not None:
        files = [overlay_file(overlay, c.name) for c in inputs]
        Path(overlay).mkdir(parents=True, exist_ok=True)
        writers = [video.VideoWriter(f, c.fps) for f, c in zip(files, inputs)]
    colours = keypoint_colours(len(detector.keypoints))
    edges = edge_indices(detector.meta.recorded_skeleton(), detector.keypoints)
    parts: dict[str, list[np.ndarray]] = {name: [] for name in _Collected.__dataclass_fields__}
    try:
        with write_csv(out, detector.keypoints) as writer:
            bar = tqdm(total=total, unit="frame", disable=not progress, desc="track")
            for fnums, originals in frames:
                result = detector(_stack_views(originals), cams, boxes, min_weight).cpu()
                writer.writerows(csv_rows(fnums, result))
                reproj, uv, used = result.reproj.numpy(), result.uv.numpy(), result.used.numpy()
                for c, w in enumerate(writers):
                    for b in range(len(fnums)):
                        w.write(draw_overlay(originals[b][c], reproj[b, c], uv[b, c], used[b, c], colours,
                                             edges))
                for name, value in (("fnums", np.asarray(fnums)), ("X", result.X), ("error", result.error),
                                    ("ncams", result.ncams), ("score", result.score), ("valid", result.valid),
                                    ("used", result.used), ("weights", result.weights),
                                    ("residual", result.residual)):
                    parts[name].append(np.asarray(value))
                bar.update(len(fnums))
            bar.close()
    finally:
        for w in writers:
            w.close()
    K, C = len(detector.keypoints), len(inputs)
    empty = {"fnums": (0,), "X": (0, K, 3), "used": (0, C, K), "weights": (0, C, K), "residual": (0, C, K)}
    return _Collected(**{name: np.concatenate(v) if v else np.zeros(empty.get(name, (0, K)))
                         for name, v in parts.items()})


def _summary_of(got: _Collected, keypoints: list[str]):
    """``(frames, keypoints, valid fraction, median error, passing fraction)`` of a
    :class:`TrackSummary`."""
    K = len(keypoints)
    valid, err, ok = got.valid.astype(bool), got.error, got.ncams >= 2
    med = [float(np.median(err[valid[:, k], k])) if valid[:, k].any() else float("nan") for k in range(K)]
    frac = [float(valid[:, k].mean()) if len(valid) else 0.0 for k in range(K)]
    pas = [float(ok[:, k].mean()) if len(ok) else 0.0 for k in range(K)]
    return len(got.fnums), list(keypoints), frac, med, pas


def empty_result_hint(summary: TrackSummary) -> str | None:
    """What to say when no keypoint got a 3D point in any frame (the CSV is all ``nan``), else None."""
    if not summary.frames or any(summary.valid_fraction):
        return None
    if not any(summary.passing_fraction):
        why = ("no keypoint has two views with a confidence weight above --min-weight "
               f"{summary.min_weight:g} in any frame")
    else:
        why = "the views of every keypoint triangulate to no valid point"
    return (f"every keypoint is 0% valid ({why}), so {summary.path} holds only nan: the detector finds "
            "nothing confident in these videos. A briefly trained model does this: train longer (check it "
            "with 's3k evaluate RUN DATASET' first), make sure the videos show what it was trained on, and "
            + ("lower --min-weight (0 uses every view)" if summary.min_weight > 0
               else "check that the calibration matches the videos"))
