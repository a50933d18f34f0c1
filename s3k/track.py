"""``s3k track``: 3D keypoints from synchronized videos of a calibrated rig, written in anipose's CSV layout.

Pipeline, per frame (DESIGN 1; the same maths as training and ``s3k predict``):

1. The C videos are decoded in lockstep with PyAV: frame ``i`` of every video is one instant (anipose's
   assumption for a synchronized rig).
2. Each image is mapped onto the detector's input size with :func:`s3k.data.transforms.resize_crop` (the crop
   box follows ``--crop`` or ``--fit``), whose pixel map ``M`` also gives the network's intrinsics
   ``K' = M K``.
3. The shared network gives one heatmap per camera and keypoint; its softmax mean is the 2D detection and its
   spread the confidence weight ``w`` (:func:`s3k.heatmaps.confidence_weight`). Detections are mapped back to
   the original video pixels with ``M^-1``.
4. Views whose weight is at most ``--min-weight`` are dropped; the others enter the confidence-weighted
   triangulation (:func:`s3k.geometry.triangulate_pixels`) with their weight ``w``, in the calibration's own
   cameras (lens distortion included), so the 3D points are in the calibration's world frame and units.

CSV columns (anipose's 3D layout), one row per frame::

    <kp>_x, <kp>_y, <kp>_z, <kp>_error, <kp>_ncams, <kp>_score   for every keypoint, then fnum

``error`` is the mean reprojection error, in pixels of the original video, over the cameras used; ``ncams``
the number of cameras used (weight above ``--min-weight``); ``score`` the mean confidence weight over all
cameras; ``fnum`` the video frame index. Where the triangulation is degenerate (fewer than 2 cameras used,
near-parallel rays) ``x, y, z`` and ``error`` are ``nan``.

With ``--overlay DIR`` one MP4 per camera (``DIR/<camera>.mp4``) shows, on the original frames, the
reprojected 3D keypoints (filled discs) and the per-view detections (crosses), one colour per keypoint.
"""

from __future__ import annotations

import argparse
import csv
import queue
import sys
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from s3k.geometry import Cameras, project, triangulate_pixels
from s3k.heatmaps import confidence_weight, heatmap_moments, spatial_softmax

__all__ = [
    "DEFAULT_MIN_WEIGHT",
    "CameraInput",
    "Tracked",
    "csv_header",
    "fit_box",
    "points_from_logits",
    "prepare_cameras",
    "read_csv",
    "synchronized_frames",
    "track_videos",
]

DEFAULT_MIN_WEIGHT = 0.5
"""Views with a confidence weight at or below this are not used (0.5 is a heatmap spread of 2 sigma)."""

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
        raise ValueError(f"--fit must be one of {', '.join(FIT_MODES)}, got {mode!r}")
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


def parse_videos(values: Sequence[str]) -> dict[str, Path]:
    """``["CAM=FILE", ...]`` -> ``{camera: path}`` with errors naming the bad value."""
    out: dict[str, Path] = {}
    for value in values:
        cam, sep, path = value.partition("=")
        if not sep or not cam or not path:
            raise ValueError(f"--videos {value!r}: expected CAMERA=FILE")
        if cam in out:
            raise ValueError(f"--videos: camera {cam!r} is given twice")
        out[cam] = Path(path)
    if len(out) < 2:
        names = ", ".join(out)
        raise ValueError(f"--videos: triangulation needs at least 2 cameras, got {len(out)} ({names})")
    return out


def prepare_cameras(videos: dict[str, Path], calibration, net_size: tuple[int, int], fit: str = "pad",
                    crops: dict[str, tuple[float, ...]] | None = None) -> tuple[list[CameraInput], Cameras]:
    """Match videos to calibrated cameras and compute each camera's map onto the network input.

    Args:
        videos: ``{camera: video path}``; the order is the camera order of the outputs.
        calibration: a :class:`s3k.data.rig.Rig` (``s3k.data.anipose.read_anipose_calibration``).
        net_size: ``(w, h)`` network input size.
        fit: see :func:`fit_box` (for cameras without an explicit crop box).
        crops: optional ``{camera: (x0, y0, x1, y1)}`` boxes, as given to ``s3k import --crop``.

    Returns:
        ``(inputs, cams)``: one :class:`CameraInput` per video, and the calibration's cameras ``(C,)`` in
        float64, in original video pixels.

    Raises:
        ValueError: a camera missing from the calibration, an unreadable video, or a video whose size is not
            the calibrated image size.
        FileNotFoundError: a missing video file.
    """
    from s3k.data import video
    from s3k.data.transforms import crop_resize_matrix

    known = list(calibration.names)
    unknown = [c for c in videos if c not in known]
    if unknown:
        raise ValueError(
            f"--videos: camera {', '.join(repr(c) for c in unknown)} is not in the calibration "
            f"(its cameras are {', '.join(known)})"
        )
    rig = calibration.select(list(videos))
    crops = crops or {}
    inputs = []
    for c, (name, path) in enumerate(videos.items()):
        if not Path(path).is_file():
            raise FileNotFoundError(f"--videos {name}={path}: video file not found")
        size = video.frame_size(path)
        calib_size = (int(rig.size[c][0]), int(rig.size[c][1]))
        if size != calib_size:
            raise ValueError(
                f"camera {name!r}: video {path} is {size[0]}x{size[1]} pixels but the calibration gives "
                f"{calib_size[0]}x{calib_size[1]}; the intrinsics apply only to images of the calibrated size"
            )
        box = tuple(float(v) for v in crops.get(name, fit_box(size, net_size, fit)))
        inputs.append(CameraInput(name, Path(path), size, video.frame_rate(path), box,
                                  crop_resize_matrix(box, net_size)))
    return inputs, rig.cameras


# ------------------------------------------------------------------------------------------------------------
# After the network: heatmaps -> 3D


@dataclass
class Tracked:
    """3D keypoints of a batch of frames, with per-view detections (all in original video pixels).

    Attributes:
        X: ``(B, K, 3)`` world points in the calibration's units, NaN where invalid.
        valid: ``(B, K)`` bool, the triangulation is defined (>= 2 cameras used, rays not parallel).
        error: ``(B, K)`` mean reprojection error in pixels over the cameras used, NaN where invalid.
        ncams: ``(B, K)`` int, cameras used (confidence weight above the threshold).
        score: ``(B, K)`` mean confidence weight over all cameras.
        uv: ``(B, C, K, 2)`` per-view 2D detections (softmax means).
        weight: ``(B, C, K)`` per-view confidence weights.
        used: ``(B, C, K)`` bool, the view entered the triangulation.
        reproj: ``(B, C, K, 2)`` reprojection of ``X`` into every camera, NaN where invalid.
    """

    X: np.ndarray
    valid: np.ndarray
    error: np.ndarray
    ncams: np.ndarray
    score: np.ndarray
    uv: np.ndarray
    weight: np.ndarray
    used: np.ndarray
    reproj: np.ndarray


def points_from_logits(logits: Tensor, cams: Cameras, pixel_maps: np.ndarray | Tensor, stride: int,
                       sigma: float, min_weight: float = DEFAULT_MIN_WEIGHT) -> Tracked:
    """Heatmap logits of a batch of synchronized frames -> 3D keypoints (everything after the network).

    Args:
        logits: ``(B, C, K, h, w)`` network outputs.
        cams: ``(C,)`` calibrated cameras in original video pixels.
        pixel_maps: ``(C, 3, 3)`` maps from video pixels to network-input pixels (``CameraInput.M``).
        stride: heatmap stride (network-input pixels per cell).
        sigma: target width in network-input pixels (the confidence weight's scale).
        min_weight: views with a confidence weight at or below this are dropped.

    Returns:
        A :class:`Tracked` (numpy, float64).
    """
    if not isinstance(logits, Tensor) or logits.ndim != 5:
        shape = tuple(logits.shape) if isinstance(logits, Tensor) else type(logits).__name__
        raise ValueError(f"points_from_logits: logits must be (B, C, K, h, w), got {shape}")
    B, C, K = logits.shape[:3]
    if tuple(cams.shape) != (C,):
        raise ValueError(f"points_from_logits: cams must be ({C},) for logits {tuple(logits.shape)}, "
                         f"got {tuple(cams.shape)}")
    maps = torch.as_tensor(np.asarray(pixel_maps, dtype=np.float64), device=logits.device)
    if maps.shape != (C, 3, 3):
        raise ValueError(f"points_from_logits: pixel_maps must be ({C}, 3, 3), got {tuple(maps.shape)}")
    # Moments in float64: the mean is a sum over h * w cells, and the geometry below wants the precision.
    uv_net, var = heatmap_moments(spatial_softmax(logits.to(torch.float64)), stride)
    w = confidence_weight(var, sigma)
    Minv = torch.linalg.inv(maps)  # (C, 3, 3) network pixels -> video pixels (affine)
    uv = uv_net @ Minv[:, :2, :2].transpose(-1, -2) + Minv[:, None, :2, 2]  # (B, C, K, 2)
    used = w > min_weight
    ncams = used.sum(dim=1)
    cams = cams.to(device=logits.device, dtype=torch.float64)
    X, valid = triangulate_pixels(cams, uv, torch.where(used, w, torch.zeros_like(w)))
    valid = valid & (ncams >= 2)
    reproj, _depth = project(cams, X[:, None])  # (B, C, K, 2)
    dist = torch.linalg.vector_norm(reproj - uv, dim=-1)
    error = (dist * used).sum(dim=1) / ncams.clamp_min(1)
    nan = torch.tensor(float("nan"), dtype=torch.float64, device=X.device)
    X = torch.where(valid[..., None], X, nan)
    error = torch.where(valid, error, nan)
    reproj = torch.where(valid[:, None, :, None], reproj, nan)
    return Tracked(X=X.cpu().numpy(), valid=valid.cpu().numpy(), error=error.cpu().numpy(),
                   ncams=ncams.cpu().numpy().astype(np.int64), score=w.mean(dim=1).cpu().numpy(),
                   uv=uv.cpu().numpy(), weight=w.cpu().numpy(), used=used.cpu().numpy(),
                   reproj=reproj.cpu().numpy())


# ------------------------------------------------------------------------------------------------------------
# Video in, video and CSV out


def synchronized_frames(paths: Sequence[str | Path], start: int = 0,
                        stop: int | None = None) -> Iterator[tuple[int, list[np.ndarray]]]:
    """Decode several videos in lockstep: yields ``(i, [image (H, W, 3) uint8 RGB per video])``.

    Frames before ``start`` are decoded but not converted. Stops at ``stop`` (exclusive) or when the shortest
    video ends.
    """
    import av

    containers = []
    try:
        decoders = []
        for path in paths:
            container = av.open(str(path))
            containers.append(container)
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            decoders.append(container.decode(stream))
        for i, frames in enumerate(zip(*decoders)):
            if stop is not None and i >= stop:
                return
            if i >= start:
                yield i, [f.to_ndarray(format="rgb24") for f in frames]
    finally:
        for container in containers:
            container.close()


def _prefetch(iterator: Iterator, depth: int = 2) -> Iterator:
    """Run ``iterator`` in a background thread, ``depth`` items ahead (decoding overlaps inference)."""
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


class Mp4Writer:
    """Incremental H.264 MP4 encoder (PyAV) for RGB frames of one size (odd sizes are padded by a pixel)."""

    def __init__(self, path: str | Path, fps: float) -> None:
        import av

        self.path = Path(path)
        self._container = av.open(str(self.path), mode="w")
        self._rate = Fraction(fps).limit_denominator(1001) if fps > 0 else Fraction(30)
        self._stream: av.VideoStream | None = None
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        import av

        H, W = image.shape[:2]
        image = np.pad(image, ((0, H % 2), (0, W % 2), (0, 0)), mode="edge") if (H % 2 or W % 2) else image
        if self._stream is None:
            self._stream = self._container.add_stream("libx264", rate=self._rate)
            self._stream.width, self._stream.height = image.shape[1], image.shape[0]
            self._stream.pix_fmt = "yuv420p"
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        if self._stream is not None:
            for packet in self._stream.encode():
                self._container.mux(packet)
        self._container.close()


def keypoint_colours(n: int) -> list[tuple[int, int, int]]:
    """``n`` distinct saturated RGB colours (hues evenly spaced)."""
    import cv2

    hsv = np.array([[[int(180 * k / max(n, 1)), 230, 255] for k in range(n)]], dtype=np.uint8)
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]
    return [(int(c[0]), int(c[1]), int(c[2])) for c in rgb]


def draw_overlay(image: np.ndarray, reproj: np.ndarray, uv: np.ndarray, used: np.ndarray,
                 colours: Sequence[tuple[int, int, int]]) -> np.ndarray:
    """Draw one camera's keypoints on a copy of ``image`` (H, W, 3) RGB.

    Args:
        image: the original video frame.
        reproj: ``(K, 2)`` reprojected 3D keypoints (NaN where invalid): filled discs.
        uv: ``(K, 2)`` the view's own detections: crosses, thick where the view was used.
        used: ``(K,)`` whether the view entered the triangulation.
        colours: one RGB colour per keypoint.
    """
    import cv2

    out = np.ascontiguousarray(image).copy()
    H, W = out.shape[:2]
    r = max(2, round(min(H, W) / 80))
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    for k, colour in enumerate(colours):
        # Pixel (0, 0) is the centre of the top-left pixel for s3k and for OpenCV's drawing alike.
        if np.all(np.isfinite(uv[k])):
            cx, cy = (int(round(v * (1 << shift))) for v in uv[k])
            s = (r + 1) << shift
            thick = 2 if used[k] else 1
            cv2.line(out, (cx - s, cy), (cx + s, cy), colour, thick, cv2.LINE_AA, shift)
            cv2.line(out, (cx, cy - s), (cx, cy + s), colour, thick, cv2.LINE_AA, shift)
        if np.all(np.isfinite(reproj[k])) and np.all(np.abs(reproj[k]) < 1e5):
            centre = tuple(int(round(v * (1 << shift))) for v in reproj[k])
            cv2.circle(out, centre, r << shift, colour, -1, cv2.LINE_AA, shift)
            cv2.circle(out, centre, r << shift, (0, 0, 0), 1, cv2.LINE_AA, shift)
    return out


def csv_header(keypoints: Sequence[str]) -> list[str]:
    """anipose's 3D CSV columns: ``<kp>_x, _y, _z, _error, _ncams, _score`` per keypoint, then ``fnum``."""
    cols = []
    for kp in keypoints:
        cols += [f"{kp}_x", f"{kp}_y", f"{kp}_z", f"{kp}_error", f"{kp}_ncams", f"{kp}_score"]
    return cols + ["fnum"]


def _fmt(v: float) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.8g}"


def csv_rows(fnums: Sequence[int], tracked: Tracked) -> list[list[str]]:
    """One anipose CSV row per frame of ``tracked`` (columns of :func:`csv_header`)."""
    rows = []
    for b, fnum in enumerate(fnums):
        row: list[str] = []
        for k in range(tracked.X.shape[1]):
            row += [_fmt(v) for v in tracked.X[b, k]]
            row += [_fmt(tracked.error[b, k]), str(int(tracked.ncams[b, k])), f"{tracked.score[b, k]:.6f}"]
        rows.append(row + [str(int(fnum))])
    return rows


def read_csv(path: str | Path, keypoints: Sequence[str]) -> dict[int, np.ndarray]:
    """The 3D points of a CSV written by :func:`track_videos` (anipose's layout): ``{fnum: (K, 3)}``.

    Args:
        path: the CSV file.
        keypoints: names of the keypoints to read, in the order wanted.

    Returns:
        One ``(K, 3)`` float array per frame number, NaN where a keypoint was not triangulated.

    Raises:
        ValueError: a keypoint's ``_x/_y/_z`` column or ``fnum`` is missing, or a value is not a number;
            the message names the file, the column and the line.
    """
    out: dict[int, np.ndarray] = {}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        wanted = [f"{k}_{a}" for k in keypoints for a in "xyz"] + ["fnum"]
        missing = [c for c in wanted if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; has {reader.fieldnames}")
        for row in reader:
            try:
                xyz = np.array([[float(row[f"{k}_{a}"] or "nan") for a in "xyz"] for k in keypoints])
                out[int(row["fnum"])] = xyz
            except ValueError as e:
                raise ValueError(f"{path}, line {reader.line_num}: {e}") from None
    return out


@dataclass
class TrackSummary:
    """What :func:`track_videos` did: frames, per-keypoint valid fraction and median error (px)."""

    frames: int
    keypoints: list[str]
    valid_fraction: list[float]
    median_error_px: list[float]
    units: str


def _frame_batches(inputs: list[CameraInput], net_size: tuple[int, int], batch: int, start: int,
                   stop: int | None, keep_originals: bool):
    """Yield ``(fnums, images uint8 (B, C, h, w, 3), originals or None)`` from the synchronized videos."""
    from s3k.data.transforms import resize_crop

    fnums, images, originals = [], [], []
    for i, frames in synchronized_frames([c.path for c in inputs], start, stop):
        resized = [resize_crop(img, None, cam.box, net_size)[0] for img, cam in zip(frames, inputs)]
        fnums.append(i)
        images.append(np.stack(resized))
        if keep_originals:
            originals.append(frames)
        if len(fnums) == batch:
            yield fnums, np.stack(images), originals if keep_originals else None
            fnums, images, originals = [], [], []
    if fnums:
        yield fnums, np.stack(images), originals if keep_originals else None


def track_videos(run_dir: str | Path, videos: dict[str, Path], calibration: str | Path, out: str | Path,
                 overlay: str | Path | None = None, batch: int = 8, start: int = 0, stop: int | None = None,
                 min_weight: float = DEFAULT_MIN_WEIGHT, fit: str = "pad",
                 crops: dict[str, tuple[float, ...]] | None = None, device: str = "auto",
                 units: str | None = None, progress: bool = True) -> TrackSummary:
    """Track synchronized videos to 3D keypoints and write anipose's 3D CSV (see the module docstring).

    Args:
        run_dir: run folder of ``s3k train`` (``s3k.run.load_detector``).
        videos: ``{camera: video}``; camera names as in the calibration.
        calibration: anipose ``calibration.toml``.
        out: CSV file to write.
        overlay: folder for one MP4 per camera with the keypoints drawn, or None.
        batch: frames per forward pass (each has C images).
        start: first frame index.
        stop: frame index to stop before (None: to the end of the shortest video).
        min_weight: views with a confidence weight at or below this are not used.
        fit: how frames map onto the network input when aspect ratios differ (:func:`fit_box`).
        crops: per-camera crop boxes (as for ``s3k import --crop``), overriding ``fit``.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``...
        units: world unit of the calibration when the file does not say.
        progress: show a tqdm progress bar.

    Returns:
        A :class:`TrackSummary`.
    """
    from tqdm import tqdm

    from s3k.data import video
    from s3k.data.anipose import read_anipose_calibration
    from s3k.predict import pick_device
    from s3k.run import load_detector

    if batch < 1:
        raise ValueError(f"--batch must be >= 1, got {batch}")
    if start < 0 or (stop is not None and stop <= start):
        raise ValueError(f"--start/--stop: need 0 <= start < stop, got start={start}, stop={stop}")
    if not 0 <= min_weight < 1:
        raise ValueError(f"--min-weight must be in [0, 1), got {min_weight}")
    calib = read_anipose_calibration(calibration, units=units)
    dev = pick_device(device)
    model, meta = load_detector(run_dir, dev)
    net_size = (int(meta.image_size[0]), int(meta.image_size[1]))
    inputs, cams = prepare_cameras(videos, calib, net_size, fit, crops)
    pixel_maps = np.stack([c.M for c in inputs])

    counts = {c.name: video.frame_count(c.path) for c in inputs}
    n_video = min(counts.values())
    if len(set(counts.values())) > 1:
        lengths = ", ".join(f"{k}: {v}" for k, v in counts.items())
        print(f"warning: the videos have different lengths ({lengths}); tracking the first {n_video} frames "
              "of each", file=sys.stderr)
    rates = {c.name: c.fps for c in inputs}
    if max(rates.values()) - min(rates.values()) > 1e-3 * max(rates.values()):
        print(f"warning: the videos have different frame rates ({rates}); frames are paired by index",
              file=sys.stderr)
    end = n_video if stop is None else min(stop, n_video)
    if start >= n_video:
        raise ValueError(f"--start {start}: the videos have {n_video} frames")

    # BatchNorm folded into the convolutions, channels_last: the fast CPU form of the same network.
    net = model.fused().to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # stub lacks it
    writers = []
    if overlay is not None:
        Path(overlay).mkdir(parents=True, exist_ok=True)
        writers = [Mp4Writer(Path(overlay) / f"{c.name}.mp4", c.fps) for c in inputs]
    colours = keypoint_colours(len(meta.keypoints))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    X_valid, errors = [], []
    try:
        with open(out, "w", newline="") as fh, torch.inference_mode():
            writer = csv.writer(fh)
            writer.writerow(csv_header(meta.keypoints))
            bar = tqdm(total=end - start, unit="frame", disable=not progress, desc="track")
            frames = _prefetch(_frame_batches(inputs, net_size, batch, start, end, overlay is not None))
            for fnums, images, originals in frames:
                x = torch.from_numpy(images).to(dev)  # (B, C, h, w, 3) uint8
                B, C = x.shape[:2]
                # The permuted view of HWC data is already channels_last.
                x = x.permute(0, 1, 4, 2, 3).float().div_(255.0).reshape(B * C, 3, net_size[1], net_size[0])
                logits = net(x)
                logits = logits.reshape(B, C, *logits.shape[1:])
                tracked = points_from_logits(logits, cams, pixel_maps, meta.stride, meta.sigma, min_weight)
                writer.writerows(csv_rows(fnums, tracked))
                for c, w in enumerate(writers):
                    for b in range(B):
                        w.write(draw_overlay(originals[b][c], tracked.reproj[b, c], tracked.uv[b, c],
                                             tracked.used[b, c], colours))
                X_valid.append(tracked.valid)
                errors.append(tracked.error)
                n += B
                bar.update(B)
            bar.close()
    finally:
        for w in writers:
            w.close()
    valid = np.concatenate(X_valid) if X_valid else np.zeros((0, len(meta.keypoints)), bool)
    err = np.concatenate(errors) if errors else np.zeros((0, len(meta.keypoints)))
    med = [float(np.median(err[valid[:, k], k])) if valid[:, k].any() else float("nan")
           for k in range(valid.shape[1])]
    frac = [float(valid[:, k].mean()) if len(valid) else 0.0 for k in range(valid.shape[1])]
    return TrackSummary(n, list(meta.keypoints), frac, med, calib.units)


# ------------------------------------------------------------------------------------------------------------
# Command line


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Track synchronized videos of a calibrated rig to 3D keypoints with a trained detector; writes "
        "anipose's 3D CSV (<kp>_x, _y, _z, _error, _ncams, _score per keypoint, then fnum) in the "
        "calibration's units."
    )
    parser.add_argument("run", help="run folder written by 's3k train'")
    parser.add_argument("--videos", nargs="+", required=True, metavar="CAM=FILE",
                        help="one video per camera, camera names as in the calibration")
    parser.add_argument("--calibration", required=True, help="anipose calibration.toml")
    parser.add_argument("--out", required=True, help="CSV file to write")
    parser.add_argument("--overlay", default=None, metavar="DIR",
                        help="write DIR/<camera>.mp4 with the reprojected keypoints drawn")
    parser.add_argument("--batch", type=int, default=8, help="frames per forward pass (default 8)")
    parser.add_argument("--start", type=int, default=0, help="first frame index (default 0)")
    parser.add_argument("--stop", type=int, default=None,
                        help="frame index to stop before (default: the end of the shortest video)")
    parser.add_argument("--min-weight", type=float, default=DEFAULT_MIN_WEIGHT,
                        help="confidence weight a view needs to be used (default 0.5: heatmap spread below "
                        "2 sigma; 0 uses every view, weighted)")
    parser.add_argument("--fit", choices=FIT_MODES, default="pad",
                        help="when the video's aspect ratio differs from the detector's input: pad "
                        "(default), crop or stretch")
    parser.add_argument("--crop", nargs="+", default=None, metavar="[CAM=]X0,Y0,X1,Y1",
                        help="crop box in pixel edge coordinates, as given to 's3k import --crop'")
    parser.add_argument("--units", default=None, help="world unit of the calibration when it does not say")
    parser.add_argument("--device", default="auto", help="'auto', 'cpu', 'cuda' (default: auto)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from s3k.cli.options import parse_crops

    try:
        videos = parse_videos(args.videos)
        crops = parse_crops(args.crop, list(videos)) if args.crop else None
        summary = track_videos(
            args.run, videos, args.calibration, args.out, overlay=args.overlay, batch=args.batch,
            start=args.start, stop=args.stop, min_weight=args.min_weight, fit=args.fit, crops=crops,
            device=args.device, units=args.units, progress=not args.no_progress,
        )
    except (ValueError, FileNotFoundError, KeyError, IndexError) as exc:
        print(f"s3k track: error: {exc}", file=sys.stderr)
        return 1
    parts = [f"{kp}: {100 * f:.0f}% valid, median error {e:.2f} px"
             for kp, f, e in zip(summary.keypoints, summary.valid_fraction, summary.median_error_px)]
    print(f"wrote {summary.frames} frames to {args.out} (units: {summary.units})")
    for p in parts:
        print(f"  {p}")
    if args.overlay:
        print(f"overlay videos in {args.overlay}")
    return 0
