"""Crop boxes around the object, found by a trained detector: the boxes ``s3k import --crop`` takes (``s3k
crops``).

A rig films the object in a part of each camera's frame. A detector trained briefly on whole frames (one pass,
or the coarse pass of a two-pass run) finds that part: it runs over a dataset's frames, each view keeps the
keypoints it detects with a calibrated confidence above ``min_confidence``, and per camera the box holding
them is taken over the frames whose view kept at least ``min_keypoints`` of the keypoints. The box's edges
are quantiles of the frames' extents (``quantile`` of them lie inside, so that a few wrong frames do not
stretch it), grown by a margin (``margin`` of its side and at least ``min_margin_px``), made of one aspect
(``aspect``: W/H, square by default), of one size for every camera (so that ``s3k import --scale`` applies to
all), rounded to ``multiple`` pixels and moved into the frame. Every label of the dataset must fall inside
its camera's box: a label outside the box the detections give grows it (``outside="grow"``, said in a note
naming the labels) or is refused (``outside="refuse"``).

Boxes are in each camera's full-resolution frame, pixel edge coordinates, as ``--crop`` takes them: the
dataset's own pixels are mapped back through its import's crop box and size
(:func:`s3k.detector.geometry_record.dataset_geometry`, as ``s3k add-frames`` cuts frames like the dataset's).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.base.messages import NOTE
from s3k.data import Dataset
from s3k.data.frames import FrameStore
from s3k.detector import Detector
from s3k.detector.geometry_record import dataset_geometry
from s3k.geometry.warp import crop_resize_matrix, transform_points

__all__ = ["CameraBox", "CropBoxes", "CropOptions", "OutsideLabel", "dataset_crop_boxes", "detected_points",
           "find_boxes", "frame_pixels", "label_points", "pick_frames"]

log = logging.getLogger(__name__)

Outside = Literal["grow", "refuse"]

MANY_OUTSIDE = 0.1
"""Share of a camera's labels outside the detections' box above which the detector is said to miss the
object (a warning: the run needs more training)."""


@dataclass(frozen=True)
class CropOptions:
    """How the boxes are drawn around the detections (the options of ``s3k crops``)."""

    margin: float = 0.25
    """Grow each side by this fraction of the box's width (left, right) or height (top, bottom)."""
    min_margin_px: float = 16.0
    """...and by at least this many full-resolution pixels."""
    quantile: float = 0.98
    """Share of the frames whose keypoints lie inside the box before the margin (1: every frame)."""
    min_confidence: float = 0.5
    """A view's detections at or below this calibrated confidence are left out."""
    min_keypoints: float = 0.5
    """A frame's view counts when it keeps at least this share of the keypoints (and one)."""
    aspect: float | None = 1.0
    """Width / height of every box (None: the detections' own shape)."""
    same_size: bool = True
    """Give every camera the size of the largest box (so that ``s3k import --scale`` applies)."""
    multiple: int = 16
    """Round the sides up to a multiple of this many pixels."""
    outside: Outside = "grow"
    """A label outside its camera's box grows the box (``"grow"``) or is refused (``"refuse"``)."""


@dataclass
class OutsideLabel:
    """A label of the dataset outside the box its camera's detections gave (full-resolution pixels)."""

    camera: str
    frame: int
    keypoint: str
    u: float
    v: float

    def __str__(self) -> str:
        return f"{self.camera} frame {self.frame} {self.keypoint} at {self.u:.0f},{self.v:.0f}"


@dataclass
class CameraBox:
    """One camera's box and how it was found."""

    camera: str
    box: tuple[int, int, int, int]
    """``(x0, y0, x1, y1)`` in the camera's full frame, pixel edge coordinates."""
    frame_size: tuple[int, int]
    frames: int
    """Frames whose detections count."""
    extent: tuple[float, float, float, float]
    """The detections' box (the quantiles, before the margin), pixel edge coordinates."""
    outside: list[OutsideLabel] = field(default_factory=list)
    labels: int = 0
    """The dataset's labels in this camera (checked against the box)."""
    clamped: bool = False
    """The box was cut to the frame (larger than the frame along a side)."""

    def text(self) -> str:
        return f"{self.camera}=" + ",".join(str(v) for v in self.box)


@dataclass
class CropBoxes:
    """Every camera's box (:func:`dataset_crop_boxes`)."""

    cameras: list[CameraBox]
    frames: int
    """Frames the detector ran on."""
    options: CropOptions

    def boxes(self) -> dict[str, tuple[int, int, int, int]]:
        return {c.camera: c.box for c in self.cameras}

    def argument(self) -> str:
        """``--crop CAM=X0,Y0,X1,Y1 ...``, as ``s3k import`` and ``s3k track`` take it."""
        return "--crop " + " ".join(c.text() for c in self.cameras)

    def to_dict(self) -> dict[str, Any]:
        return {"crop": {c.camera: list(c.box) for c in self.cameras}, "argument": self.argument(),
                "frames": self.frames, "options": asdict(self.options),
                "cameras": {c.camera: {"box": list(c.box), "frame_size": list(c.frame_size),
                                       "frames": c.frames, "extent": [round(v, 2) for v in c.extent],
                                       "clamped": c.clamped, "labels": c.labels,
                                       "labels_outside": [asdict(o) for o in c.outside]}
                            for c in self.cameras}}


def pick_frames(ds: Dataset, split: str | list[str] | None = None, max_frames: int = 0,
                session: str | None = None) -> np.ndarray:
    """The dataset's frame ids of ``split`` (None: every frame), at most ``max_frames`` of them (0: all)
    spread evenly over them."""
    ids = np.asarray(ds.frames(split, session=session))
    if max_frames and len(ids) > max_frames:
        ids = ids[np.unique(np.linspace(0, len(ids) - 1, max_frames).round().astype(np.int64))]
    return ids


def detected_points(detector: Detector, ds: Dataset, frame_ids: np.ndarray, min_confidence: float = 0.5,
                    batch_size: int = 16) -> np.ndarray:
    """``(N, C, K, 2)``: each view's detected keypoints whose calibrated confidence is above
    ``min_confidence``, in the dataset's pixels; NaN elsewhere. The keypoints are the detector's, the cameras
    the dataset's. A view's detections need no calibration: a camera calibrated wrongly still gets its box."""
    out = []
    store = FrameStore(ds, frame_ids, preload_mb=0)
    for batch in store.batches(batch_size):
        pred = detector(batch.images, batch.cams).cpu()
        uv = pred.uv.to(torch.float64)
        keep = (pred.confidence > min_confidence) & torch.isfinite(uv).all(-1)
        out.append(np.where(keep.numpy()[..., None], uv.numpy(), np.nan))
    C, K = len(ds.cameras), len(detector.keypoints)
    return np.concatenate(out) if out else np.zeros((0, C, K, 2))


def label_points(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """``(frame ids (M,), uv (M, C, K, 2))``: the labels of the labelled and test frames in the dataset's
    pixels, NaN where there is none."""
    ids = np.asarray(ds.frames(["labelled", "test"]))
    if not len(ids):
        return ids, np.zeros((0, len(ds.cameras), len(ds.keypoints), 2))
    uv, mask = ds.labels(ids, dtype=np.float64)
    return ids, np.where(mask[..., None], uv, np.nan)


def frame_pixels(ds: Dataset, uv: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Pixels ``uv (..., C, K, 2)`` of the opened dataset -> each camera's full-frame pixels, through the
    import's crop box and size; and each camera's frame size ``(W, H)``."""
    geometry = dataset_geometry(ds)
    out = np.array(uv, dtype=np.float64, copy=True)
    sizes = []
    for c, cam in enumerate(ds.cameras):
        entry = geometry["cameras"][cam]
        back = np.linalg.inv(crop_resize_matrix(tuple(entry["box"]), tuple(ds.image_size)))
        out[..., c, :, :] = transform_points(uv[..., c, :, :], back)
        sizes.append((int(entry["frame_size"][0]), int(entry["frame_size"][1])))
    return out, sizes


def _extent(points: np.ndarray, opts: CropOptions) -> tuple[np.ndarray, int]:
    """The box ``(x0, y0, x1, y1)`` (edges) of one camera's points ``(N, K, 2)`` over the frames that placed
    enough keypoints, and how many did."""
    placed = np.isfinite(points).all(-1)
    need = max(1, math.ceil(opts.min_keypoints * points.shape[1] - 1e-9))
    counted = points[placed.sum(-1) >= need]
    if not len(counted):
        return np.full(4, np.nan), 0
    lo, hi = np.nanmin(counted, axis=1), np.nanmax(counted, axis=1)  # (n, 2)
    q = opts.quantile
    # a pixel centre u lies at edge coordinate u + 0.5 (the pixel of centre 0 spans edges 0 to 1)
    box = np.concatenate([np.quantile(lo, 1 - q, axis=0), np.quantile(hi, q, axis=0)]) + 0.5
    return box, len(counted)


def _grown(box: np.ndarray, opts: CropOptions) -> np.ndarray:
    size = box[2:] - box[:2]
    pad = np.maximum(opts.margin * size, opts.min_margin_px)
    return np.concatenate([box[:2] - pad, box[2:] + pad])


def _outside(box: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``(M, K)`` labels ``(M, K, 2)`` whose pixel centre lies outside the box (edges)."""
    known = np.isfinite(labels).all(-1)
    with np.errstate(invalid="ignore"):
        inside = ((labels >= box[:2] - 0.5) & (labels <= box[2:] - 0.5)).all(-1)
    return known & ~inside


def _with_labels(box: np.ndarray, labels: np.ndarray, outside: np.ndarray, opts: CropOptions) -> np.ndarray:
    """The box grown to hold the labels outside it, with ``min_margin_px`` around them."""
    pts = labels[outside]
    pad = opts.min_margin_px
    return np.concatenate([np.minimum(box[:2], pts.min(0) + 0.5 - pad),
                           np.maximum(box[2:], pts.max(0) + 0.5 + pad)])


def _sized(box: np.ndarray, size: np.ndarray,
           frame: tuple[int, int]) -> tuple[tuple[int, int, int, int], bool]:
    """A box of ``size`` (integers) around ``box``'s centre holding ``box``, moved into the frame (cut to it
    where larger)."""
    out, clamped = [], False
    for axis in range(2):
        a, b, side, limit = box[axis], box[axis + 2], int(size[axis]), frame[axis]
        if side >= limit:
            out.append((0, limit))
            clamped = clamped or side > limit
            continue
        x0 = math.floor((a + b - side) / 2)
        x0 = max(min(x0, math.floor(a)), math.ceil(b) - side)
        x0 = min(max(x0, 0), limit - side)
        out.append((x0, x0 + side))
    (x0, x1), (y0, y1) = out
    return (x0, y0, x1, y1), clamped


def _size(box: np.ndarray, opts: CropOptions) -> np.ndarray:
    """``(W, H)`` the box needs (integer edges around it), of the aspect asked."""
    need = np.array([math.ceil(box[2]) - math.floor(box[0]), math.ceil(box[3]) - math.floor(box[1])], float)
    if opts.aspect is not None:
        need = np.maximum(need, [need[1] * opts.aspect, need[0] / opts.aspect])
    return need


def _round_up(size: np.ndarray, opts: CropOptions) -> np.ndarray:
    m = max(1, opts.multiple)
    if opts.aspect is None:
        return np.ceil(size / m - 1e-9) * m
    # one side a multiple, the other from the aspect (rounded up), so that the aspect stays as close as it can
    w = math.ceil(max(size[0], size[1] * opts.aspect) / m - 1e-9) * m
    h = max(math.ceil(w / opts.aspect - 1e-9), math.ceil(size[1] - 1e-9))
    return np.array([w, h], float)


def find_boxes(points: np.ndarray, frame_sizes: list[tuple[int, int]], cameras: list[str],
               labels: np.ndarray | None = None, label_ids: np.ndarray | None = None,
               keypoints: list[str] | None = None, opts: CropOptions | None = None) -> CropBoxes:
    """Each camera's box around ``points``.

    Args:
        points: ``(N, C, K, 2)`` the detected keypoints of N frames in each camera's full-frame pixels, NaN
            where none.
        frame_sizes: each camera's frame ``(W, H)``.
        cameras: the cameras' names.
        labels: ``(M, C, K', 2)`` the dataset's labels in full-frame pixels (NaN where none), checked
            against the boxes.
        label_ids: the labels' frame ids, for the messages.
        keypoints: the labels' keypoint names, for the messages.
        opts: the settings.

    Raises:
        UserError: a camera with no frame that placed enough keypoints, or (``opts.outside == "refuse"``)
            labels outside the boxes, naming them.
    """
    opts = opts or CropOptions()
    C = len(cameras)
    M = 0 if labels is None else len(labels)
    labels = np.zeros((0, C, 0, 2)) if labels is None else labels
    label_ids = np.arange(M) if label_ids is None else np.asarray(label_ids)
    names = keypoints or [f"kp{k}" for k in range(labels.shape[2])]
    needed, found = [], []
    for c, cam in enumerate(cameras):
        extent, n = _extent(points[:, c], opts)
        if n == 0:
            raise UserError(f"camera {cam}: the detector placed {opts.min_keypoints:g} of the keypoints with "
                            f"confidence above {opts.min_confidence:g} in none of its {len(points)} views",
                            hint="train the run longer, or lower --min-confidence or --min-keypoints")
        box = _grown(extent, opts)
        out = _outside(box, labels[:, c])
        outside = [OutsideLabel(cam, int(label_ids[m]), names[k], *(float(v) for v in labels[m, c, k]))
                   for m, k in np.argwhere(out)]
        if outside and opts.outside == "grow":
            box = _with_labels(box, labels[:, c], out, opts)
        needed.append(box)
        x0, y0, x1, y1 = (float(v) for v in extent)
        labelled = int(np.isfinite(labels[:, c]).all(-1).sum())
        found.append(CameraBox(cam, (0, 0, 0, 0), frame_sizes[c], n, (x0, y0, x1, y1), outside, labelled))
    missed = [o for f in found for o in f.outside]
    if missed and opts.outside == "refuse":
        raise UserError(f"{len(missed)} label(s) of the dataset fall outside the crop boxes the detections "
                        "give "
                        f"({'; '.join(map(str, missed[:5]))}{' ...' if len(missed) > 5 else ''})",
                        hint="pass --outside grow to grow the boxes around them, or a larger --margin")
    sizes = [_size(b, opts) for b in needed]
    if opts.same_size:
        common = np.max(sizes, axis=0)
        sizes = [common] * C
    for c, f in enumerate(found):
        f.box, f.clamped = _sized(needed[c], _round_up(sizes[c], opts), f.frame_size)
    boxes = CropBoxes(found, len(points), opts)
    _say(boxes)
    return boxes


def dataset_crop_boxes(detector: Detector, ds: Dataset, opts: CropOptions | None = None,
                       split: str | list[str] | None = None, max_frames: int = 0, batch_size: int = 16,
                       session: str | None = None) -> CropBoxes:
    """The crop boxes of the dataset's cameras: ``detector`` over its frames of ``split`` (None: every
    frame; at most ``max_frames``, 0: all), the boxes around the keypoints it places
    (:func:`find_boxes`) in full-resolution pixels, checked against the labels of the dataset."""
    opts = opts or CropOptions()
    ids = pick_frames(ds, split, max_frames, session)
    if not len(ids):
        raise UserError(f"{ds.path}: no frame in split {split}", hint="pass another --split")
    points, sizes = frame_pixels(ds, detected_points(detector, ds, ids, opts.min_confidence, batch_size))
    label_ids, labels = label_points(ds)
    labels, _ = frame_pixels(ds, labels)
    return find_boxes(points, sizes, list(ds.cameras), labels, label_ids, list(ds.keypoints), opts)


def _say(found: CropBoxes) -> None:
    for c in found.cameras:
        x0, y0, x1, y1 = c.box
        e = c.extent
        log.log(NOTE, f"{c.camera}: {x1 - x0}x{y1 - y0} box at {x0},{y0} of the {c.frame_size[0]}x"
                      f"{c.frame_size[1]} frame, around the keypoints of {c.frames} of {found.frames} frames "
                      f"(their extent {e[2] - e[0]:.0f}x{e[3] - e[1]:.0f} px)")
        if c.outside:
            log.log(NOTE, f"{c.camera}: grown to hold {len(c.outside)} label(s) outside the detections' box: "
                          + "; ".join(map(str, c.outside[:5])) + (" ..." if len(c.outside) > 5 else ""))
        if len(c.outside) > MANY_OUTSIDE * c.labels:
            log.warning(f"{c.camera}: {len(c.outside)} of its {c.labels} labels lie outside the box of the "
                        "detections, which miss much of the object: train the run longer (the box holds the "
                        "labels, not the frames without them)")
        if c.clamped:
            log.warning(f"{c.camera}: the box is larger than the {c.frame_size[0]}x{c.frame_size[1]} frame "
                        "and is cut to it; import with --size W,H rather than --scale if the boxes' sizes "
                        "differ")
