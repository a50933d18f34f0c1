"""The image geometry a detector was trained on, recorded in its run, and the check of its inputs against it.

A detector knows only the images it was shown: which part of each camera's full frame (the crop box of
``s3k import --crop``, kept in the dataset's ``s3k.json`` under ``source.crop_boxes``), resized to the
network's input. Shown another part of the frame (the uncropped dataset, the whole video) it returns
confident nonsense. So ``s3k train`` records the geometry in the run (:class:`s3k.detector.DetectorMeta`'s
``geometry``, :func:`training_geometry`) with the training dataset's identity, and the consumers apply it or
refuse:

- ``s3k track`` without ``--crop`` crops each video to the recorded box (:func:`track_crops`);
- ``s3k evaluate RUN --data OTHER`` and ``s3k label OTHER --run RUN`` refuse a dataset whose images show
  another part of the frames (:func:`check_dataset`), naming the cameras, the boxes, the import options that
  make a matching dataset, and ``--ignore-geometry``.

A dataset's geometry (:func:`dataset_geometry`) is, per camera, the box of the full frame its images show,
in the frame's pixels, and the frame's size ``(W, H)``; for a dataset not imported from videos (simulated,
written directly) the frame is the stored image. Two geometries match when every camera they share shows
the same part of its frame (the boxes equal as fractions of the frame, to :data:`TOLERANCE`); the scale then
follows, since every consumer resizes what a camera shows to the network's input.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.choices import FIT_MODES, Fit
from s3k.base.errors import UserError
from s3k.data import Dataset
from s3k.data.protocol import DatasetLike
from s3k.geometry.warp import crop_resize_matrix
from s3k.run_folder import RunFolder

__all__ = ["TOLERANCE", "Box", "check_dataset", "check_images", "dataset_geometry",
           "fit_box", "frame_calibration", "input_boxes", "mismatches", "recorded_geometry", "run_geometry",
           "track_crops", "training_geometry"]

TOLERANCE = 2e-3
"""Largest difference between two boxes, as a fraction of the frame's width or height, that still matches."""


def _box_text(box) -> str:
    return ",".join(f"{v:g}" for v in box)


def dataset_geometry(ds: DatasetLike) -> dict[str, Any]:
    """``{"cameras": {camera: {"box": [x0, y0, x1, y1], "frame_size": [W, H]}}, "image_size": [W, H]}`` of an
    opened :class:`s3k.data.Dataset`: the part of each camera's full frame its stored images show (pixel edge
    coordinates of the frame; the import's crop box, composed with any crop the dataset was opened with)."""
    source = (ds.metadata or {}).get("source") or {}
    boxes, sizes = source.get("crop_boxes") or {}, source.get("source_image_size") or {}
    Ws, Hs = (float(v) for v in ds.source_image_size)
    cx0, cy0, cx1, cy1 = (float(v) for v in ds.crop_box)
    cameras = {}
    for cam in ds.cameras:
        if cam in boxes and cam in sizes:
            x0, y0, x1, y1 = (float(v) for v in boxes[cam])
            frame = [int(v) for v in sizes[cam]]
        else:
            x0, y0, x1, y1, frame = 0.0, 0.0, Ws, Hs, [int(Ws), int(Hs)]
        sx, sy = (x1 - x0) / Ws, (y1 - y0) / Hs  # frame pixels per stored pixel
        box = [x0 + cx0 * sx, y0 + cy0 * sy, x0 + cx1 * sx, y0 + cy1 * sy]
        cameras[cam] = {"box": box, "frame_size": frame}
    return {"cameras": cameras, "image_size": [int(Ws), int(Hs)]}


def training_geometry(ds: DatasetLike) -> dict[str, Any]:
    """What a run records of its training dataset ``ds``: :func:`dataset_geometry`, ``"dataset"``, its
    path and identity (keypoints, cameras and fingerprint, as ``--resume`` checks them), and a static rig's
    ``"calibration"`` in frame pixels (:func:`frame_calibration`)."""
    identity = {"path": str(Path(ds.path).resolve()), **dataset_identity(ds)}
    record = {**dataset_geometry(ds), "dataset": identity}
    calibration = frame_calibration(ds)
    if calibration is not None:
        record["calibration"] = calibration
    return record


def frame_calibration(ds: DatasetLike) -> dict[str, Any] | None:
    """``{"units", "cameras": {camera: {"K", "dist", "R", "t", "frame_size"}}}``: a static dataset's cameras
    in the pixels of its cameras' full frames (:func:`dataset_geometry`), as a run records them for the
    check of the calibration it is given at tracking time; None for a per-frame calibration."""
    if not isinstance(ds, Dataset) or not ds.static_calibration:  # crops never share one static rig
        return None
    geometry = dataset_geometry(ds)
    arrays = ds.rig(np.float64).numpy()
    cameras = {}
    for c, cam in enumerate(ds.cameras):
        entry = geometry["cameras"][cam]
        M = crop_resize_matrix(tuple(entry["box"]), tuple(ds.image_size))
        cameras[cam] = {"K": (np.linalg.inv(M) @ arrays["K"][c]).tolist(), "dist": arrays["dist"][c].tolist(),
                        "R": arrays["R"][c].tolist(), "t": arrays["t"][c].tolist(),
                        "frame_size": list(entry["frame_size"])}
    return {"units": str(ds.units), "cameras": cameras}


def run_geometry(run_dir: str | Path) -> dict[str, Any] | None:
    """The geometry recorded in a run folder (of its coarse detector for a two-pass run); None when the run
    predates the record or holds none."""
    meta = RunFolder(run_dir).meta()
    return recorded_geometry(meta.get("geometry") if meta is not None else None)


def recorded_geometry(geometry: Any) -> dict[str, Any] | None:
    """A run's recorded ``geometry`` (:attr:`s3k.detector.DetectorMeta.geometry`) when it holds the cameras'
    boxes, else None (a run trained before the record)."""
    return geometry if isinstance(geometry, dict) and isinstance(geometry.get("cameras"), dict) else None


def _fraction(entry: dict[str, Any]) -> list[float]:
    W, H = (float(v) for v in entry["frame_size"])
    x0, y0, x1, y1 = (float(v) for v in entry["box"])
    return [x0 / W, y0 / H, x1 / W, y1 / H]


def mismatches(recorded: dict[str, Any], actual: dict[str, Any]) -> list[str]:
    """The cameras present in both geometries whose boxes differ (as fractions of their frames)."""
    out = []
    for cam, entry in actual["cameras"].items():
        want = recorded["cameras"].get(cam)
        if want is None:
            continue
        if max(abs(a - b) for a, b in zip(_fraction(entry), _fraction(want))) > TOLERANCE:
            out.append(cam)
    return out


def check_dataset(run_dir: str | Path, data: str | Path, option: str = "--ignore-geometry") -> None:
    """Refuse the dataset ``data`` for the run ``run_dir`` when its images show another part of the cameras'
    frames than the run was trained on (nothing to check for a run without a record).

    Raises:
        UserError: naming the first camera, both boxes, the import options that give a matching dataset and
            ``option``.
    """
    check_images(run_geometry(run_dir), run_dir, Dataset.open(data, cache="none"), option)


def check_images(recorded: dict[str, Any] | None, run_dir: str | Path, ds: DatasetLike,
                 option: str = "--ignore-geometry") -> None:
    """:func:`check_dataset` of an opened dataset ``ds`` against the geometry ``recorded`` in the run
    ``run_dir`` (:func:`recorded_geometry`; None: nothing to check)."""
    if recorded is None:
        return
    data = ds.path
    actual = dataset_geometry(ds)
    bad = mismatches(recorded, actual)
    if not bad:
        return
    cam = bad[0]
    have, want = actual["cameras"][cam], recorded["cameras"][cam]
    W, H = want["frame_size"]
    crops = " ".join(f"{c}={_box_text(e['box'])}" for c, e in recorded["cameras"].items())
    size = ",".join(str(v) for v in recorded["image_size"])
    trained_on = (recorded.get("dataset") or {}).get("path", "its dataset")
    raise UserError(
        f"{data}: camera {cam}'s images show {_box_text(have['box'])} of its {have['frame_size'][0]}x"
        f"{have['frame_size'][1]} frames but the run {run_dir} was trained on {_box_text(want['box'])} of "
        f"its {W}x{H} frames ({trained_on}); {len(bad)} camera(s) differ, and the detector's results there "
        "would be wrong", hint=f"import the recording again with --crop {crops} --size {size}, or pass "
        f"{option} to use these images as they are")


Box = tuple[float, ...]
"""A box ``(x0, y0, x1, y1)`` in pixel edge coordinates."""


def fit_box(video_size: tuple[int, int], net_size: tuple[int, int], mode: Fit = "pad") -> Box:
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


def input_boxes(recorded: dict[str, Any] | None, frame_sizes: dict[str, tuple[int, int]],
                crops: dict[str, Box] | None, fit: Fit | None,
                net_size: tuple[int, int]) -> tuple[np.ndarray, list[str]]:
    """``(C, 4)`` each camera's box onto a detector's input of ``net_size``, in the order of
    ``frame_sizes``: :func:`track_crops`' boxes, and :func:`fit_box` by ``fit`` (None: ``"pad"``) where
    there is none; and the lines that say so."""
    chosen, notes = track_crops(recorded, frame_sizes, crops, fit_given=fit is not None)
    boxes = [chosen.get(n, fit_box(size, net_size, fit or "pad")) for n, size in frame_sizes.items()]
    return np.array(boxes, dtype=np.float64), notes


def track_crops(recorded: dict[str, Any] | None, frame_sizes: dict[str, tuple[int, int]],
                crops: dict[str, Box] | None, fit_given: bool) -> tuple[dict[str, Box], list[str]]:
    """The crop box of each video for ``s3k track``: ``--crop`` where given, else the box the run was trained
    on (scaled to the video's size), unless ``--fit`` was given; and the lines that say so.

    Args:
        recorded: the geometry the run recorded (:func:`recorded_geometry`), or None.
        frame_sizes: ``{camera: (W, H)}`` of the videos.
        crops: the ``--crop`` boxes, or None.
        fit_given: ``--fit`` was given: cameras without ``--crop`` follow it, not the record.

    Returns:
        ``(crops, notes)``: the boxes to use, and lines for the user (``warning: ...`` where the input differs
        from what the run was trained on).
    """
    crops = dict(crops or {})
    if recorded is None:
        return crops, []
    notes, applied = [], []
    for cam, (W, H) in frame_sizes.items():
        want = recorded["cameras"].get(cam)
        if want is None:
            notes.append(f"warning: camera {cam} is not among the cameras {', '.join(recorded['cameras'])} "
                         "the run was trained on; its frames are mapped by --fit")
            continue
        fx0, fy0, fx1, fy1 = _fraction(want)
        box = (fx0 * W, fy0 * H, fx1 * W, fy1 * H)
        if cam in crops:
            given = {"box": list(crops[cam]), "frame_size": [W, H]}
            if mismatches({"cameras": {cam: want}}, {"cameras": {cam: given}}):
                notes.append(f"warning: --crop {cam}={_box_text(crops[cam])} differs from the box the run "
                             f"was trained on, {cam}={_box_text(box)}; its results there may be wrong")
        elif not fit_given:
            crops[cam] = box
            applied.append(f"{cam}={_box_text(box)}")
    if applied:
        notes.insert(0, f"crop boxes the run was trained on (--crop or --fit overrides): {' '.join(applied)}")
    return crops, notes


def dataset_identity(ds: DatasetLike) -> dict[str, Any]:
    """What must stay the same for a run to be resumed on a dataset: keypoint and camera names and a
    fingerprint (SHA-256 of the metadata, the frame ids and their splits, the labels and the calibration)."""
    ids = ds.frames()
    h = hashlib.sha256()
    h.update(json.dumps(ds.metadata, sort_keys=True, default=str).encode())
    h.update(np.asarray(ids, dtype=np.int64).tobytes())
    h.update("\n".join(map(str, ds.split_of(ids))).encode())
    uv, mask = ds.labels(ids)
    h.update(np.ascontiguousarray(uv, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(mask, dtype=bool).tobytes())
    for name, part in sorted(ds.calibration(ids, dtype=np.float64).numpy().items()):
        h.update(name.encode() + np.ascontiguousarray(part).tobytes())
    return {"keypoints": list(ds.keypoints), "cameras": list(ds.cameras), "fingerprint": h.hexdigest()[:32]}
