"""DeepFly3D's pickles: the calibration (``calib.pkl``, and the same per-camera entries inside a
``df3d_result*.pkl``) and the 2D pose of a ``df3d_result*.pkl``.

Layout (DeepFly3D's documentation): a dict whose integer keys ``0 .. 6`` are the cameras, each ``{"R": (3, 3)
world->camera, "tvec": (3,), "intr": (3, 3), "distort": (5,)}`` in the OpenCV model; a pose result also holds
``points2d (C, T, J, 2)``, ``camera_ordering`` and, once calibrated, ``points3d`` (and
``points3d_wo_procrustes``, the triangulation before DeepFly3D aligns it to its template). Camera ``i`` is
named ``camera_i`` (DeepFly3D's ``camera_i.mp4``). The pickles are read with
:func:`s3k.data.formats.safe_pickle.load_pickle` (arrays and containers only). Image sizes are not in the
files: they come from the videos.

``points2d`` comes in two layouts: DeepFly3D's 2D network writes ``(row, column)`` as fractions of the image
height and width, while result files it ships (and files written by other tools) hold ``(x, y)`` pixels.
:func:`points2d_layout` tells them apart: by the reprojection of the 3D points through the cameras where the
file has both, else by the values (fractions lie within 0..1; pixels reach the image size).

DeepFly3D predicts all 38 joints in every camera, but each camera sees one side of the fly: its rule
(``camera_see_joint``) keeps the joints of the near side, for the middle camera 3 only the outer leg joints
and the antennae, and drops the stripes in cameras 2 and 4. :func:`read_deepfly3d_pose` applies it, so a
joint a camera cannot see is unlabelled there.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.data.formats.labels2d import LabelTable
from s3k.data.formats.safe_pickle import load_pickle
from s3k.data.rig import Rig
from s3k.geometry import Cameras, project

log = logging.getLogger(__name__)

_SEGMENTS = ["body_coxa", "coxa_femur", "femur_tibia", "tibia_tarsus", "tarsus_tip"]
# Limbs 0-4 are one side (three legs, antenna, stripes), 5-9 the other.
_LIMBS = [("RF", "leg"), ("RM", "leg"), ("RH", "leg"), ("R", "antenna"), ("R", "stripe"),
          ("LF", "leg"), ("LM", "leg"), ("LH", "leg"), ("L", "antenna"), ("L", "stripe")]


def _joints() -> tuple[list[str], list[int], list[str]]:
    names, limbs, kinds = [], [], []
    for limb, (prefix, kind) in enumerate(_LIMBS):
        parts = _SEGMENTS if kind == "leg" else ["antenna"] if kind == "antenna" else ["stripe_0", "stripe_1",
                                                                                          "stripe_2"]
        for part in parts:
            names.append(f"{prefix}_{part}")
            limbs.append(limb)
            kinds.append(part if kind == "leg" else kind)
    return names, limbs, kinds


JOINTS, _LIMB_OF, _KIND_OF = _joints()  # the 38 joints in DeepFly3D's order


def camera_sees_joint(camera: int, joint: int) -> bool:
    """DeepFly3D's visibility rule for its 7-camera rig (camera 3 in the middle, 0-2 and 4-6 the sides)."""
    limb, kind = _LIMB_OF[joint], _KIND_OF[joint]
    near = limb < 5
    if camera < 3:
        seen = near
    elif camera == 3:
        seen = limb % 5 in (0, 1, 3) and kind not in ("body_coxa", "coxa_femur")
    else:
        seen = not near
    if camera in (2, 4) and kind == "stripe":
        return False
    return seen


def _camera_entries(data: object, path: Path) -> dict[int, dict]:
    if not isinstance(data, dict):
        raise UserError(f"{path}: not a DeepFly3D pickle (expected a dict, found {type(data).__name__})")
    cams = {k: v for k, v in data.items() if isinstance(k, (int, np.integer)) and isinstance(v, dict)}
    if not cams:
        raise UserError(f"{path}: not a DeepFly3D calibration: no camera entries (integer keys 0, 1, ... "
                        "with R, tvec, intr, distort)")
    return {int(k): cams[k] for k in sorted(cams)}


def _array(path: Path, cam: int, entry: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    if key not in entry:
        raise UserError(f"{path}: camera {cam} has no {key!r}")
    try:
        value = np.asarray(entry[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{path}: camera {cam} {key!r} is not numbers") from None
    if value.size != int(np.prod(shape)) or not np.isfinite(value).all():
        raise UserError(f"{path}: camera {cam} {key!r} must be {shape} finite numbers, got shape "
                        f"{value.shape}")
    return value.reshape(shape)


def read_deepfly3d_calibration(path: str | Path, units: str | None = None) -> Rig:
    """The cameras of a DeepFly3D calibration or pose-result pickle, named ``camera_<id>``; image sizes 0
    (unknown until the videos give them, :meth:`s3k.data.rig.Rig.with_sizes`); units ``units`` or
    ``"unknown"``."""
    path = Path(path)
    entries = _camera_entries(load_pickle(path), path)
    Ks, dists, Rs, ts = [], [], [], []
    for cam, entry in entries.items():
        K = _array(path, cam, entry, "intr", (3, 3))
        d = np.zeros(5)
        if "distort" in entry:
            raw = np.asarray(entry["distort"], dtype=np.float64).reshape(-1)
            d[: min(5, raw.size)] = raw[:5]
        Ks.append(K / K[2, 2])
        dists.append(d)
        Rs.append(_array(path, cam, entry, "R", (3, 3)))
        ts.append(_array(path, cam, entry, "tvec", (3,)))
    cams = Cameras.from_numpy(np.stack(Ks), np.stack(dists), np.stack(Rs), np.stack(ts), dtype=torch.float64)
    names = [f"camera_{c}" for c in entries]
    return Rig(names, cams, np.zeros((len(names), 2), np.int64), units or "unknown", {"format": "deepfly3d"})


LAYOUTS = {
    "fractions": "(row, column) fractions of the image height and width",
    "xy": "(x, y) pixels",
    "rc": "(row, column) pixels",
}


def _in_pixels(points: np.ndarray, layout: str, W: float, H: float) -> np.ndarray:
    """``points (..., 2)`` of a layout as (x, y) pixels."""
    if layout == "fractions":
        return np.stack([points[..., 1] * W, points[..., 0] * H], axis=-1)
    if layout == "rc":
        return points[..., ::-1].copy()
    return points.astype(np.float64, copy=True)


NO_ESTIMATE = ((0.0, 0.0), (0.0, 1.0))
"""The values DeepFly3D's files write for a joint without an estimate: (0, 0), and (0, 1) in some results
(as fractions, the top-right corner of the image, where no joint lies)."""


def _no_estimate(points: np.ndarray) -> np.ndarray:
    """Points that hold one of :data:`NO_ESTIMATE` exactly."""
    return np.logical_or.reduce([(points == np.asarray(mark)).all(-1) for mark in NO_ESTIMATE])


def _known(points: np.ndarray) -> np.ndarray:
    """Points with an estimate: finite and none of DeepFly3D's :data:`NO_ESTIMATE` marks."""
    return np.isfinite(points).all(-1) & ~_no_estimate(points)


def _reprojection_layout(points: np.ndarray, sizes: dict[str, tuple[int, int]], rig: Rig,
                         points3d: np.ndarray) -> tuple[str, float] | None:
    """The layout whose pixels lie nearest the reprojection of ``points3d (T, J, 3)`` through ``rig``, with
    its median distance (px); None when no layout is clearly the nearest."""
    errors: dict[str, list[np.ndarray]] = {layout: [] for layout in LAYOUTS}
    for c in range(points.shape[0]):
        cam = f"camera_{c}"
        if cam not in sizes or cam not in rig.names or points3d.shape[:2] != points.shape[1:3]:
            continue
        X = np.nan_to_num(points3d.reshape(-1, 3))
        projected, depth = project(rig.cameras[rig.index(cam)], torch.as_tensor(X, dtype=rig.cameras.dtype))
        uv = projected.numpy().reshape(points3d.shape[:2] + (2,))
        ok = _known(points[c]) & np.isfinite(points3d).all(-1) & (depth.numpy() > 0).reshape(uv.shape[:2])
        if not ok.any():
            continue
        W, H = sizes[cam]
        for layout in LAYOUTS:
            errors[layout].append(np.linalg.norm(_in_pixels(points[c], layout, W, H)[ok] - uv[ok], axis=-1))
    medians = {k: float(np.median(np.concatenate(v))) for k, v in errors.items() if v}
    if not medians:
        return None
    best, *others = sorted(medians, key=medians.__getitem__)
    diagonal = float(np.hypot(*np.max([sizes[c] for c in sizes], axis=0)))
    if medians[best] > 0.1 * diagonal or (others and medians[best] > 0.5 * medians[others[0]]):
        return None  # no layout stands out: the 3D points do not belong to these cameras
    return best, medians[best]


def points2d_layout(points: np.ndarray, sizes: dict[str, tuple[int, int]], rig: Rig | None = None,
                    points3d: np.ndarray | None = None) -> tuple[str, str]:
    """``(layout, why)`` of ``points (C, T, J, 2)``: a key of :data:`LAYOUTS` and the evidence, in words.

    With cameras (``rig``, in the videos' pixels) and the file's 3D points, the layout whose pixels lie
    nearest their reprojection wins. Otherwise the values decide: all within 0..1 are fractions; larger ones
    are pixels, (x, y) unless more of them fit the images as (row, column)."""
    if rig is not None and points3d is not None:
        found = _reprojection_layout(points, sizes, rig, points3d)
        if found is not None:
            return found[0], f"they lie {found[1]:.1f} px (median) from the reprojection of the 3D points"
    known = _known(points)
    values = points[known]
    if not values.size or float(np.abs(values).max()) <= 1.5:
        return "fractions", "every value lies within 0..1"
    fit = {"xy": 0, "rc": 0}
    for c in range(points.shape[0]):
        if f"camera_{c}" not in sizes:
            continue
        W, H = sizes[f"camera_{c}"]
        p = points[c][known[c]]
        fit["xy"] += int(((p[:, 0] <= W) & (p[:, 1] <= H)).sum())
        fit["rc"] += int(((p[:, 0] <= H) & (p[:, 1] <= W)).sum())
    layout = "rc" if fit["rc"] > fit["xy"] else "xy"
    return layout, (f"values reach {values[:, 0].max():.0f} and {values[:, 1].max():.0f}, beyond fractions, "
                    f"and fit the images as {LAYOUTS[layout]}")


def read_deepfly3d_pose(path: str | Path, sizes: dict[str, tuple[int, int]],
                        rig: Rig | None = None) -> dict[str, LabelTable]:
    """2D joints of a ``df3d_result*.pkl`` per camera ``camera_<i>`` (index ``i`` of ``points2d``), in the
    pixels of an image of ``sizes[camera] = (W, H)``; joints the camera cannot see (:func:`camera_sees_joint`,
    for the 38-joint fly) and non-finite points are unlabelled. Cameras without a size are skipped. The
    layout of ``points2d`` is :func:`points2d_layout`'s (``rig``: the cameras, for the reprojection of the
    file's 3D points); the import prints which it took and why."""
    path = Path(path)
    data = load_pickle(path)
    if not isinstance(data, dict) or "points2d" not in data:
        raise UserError(f"{path}: not a DeepFly3D pose result (no 'points2d'); give it as --calibration only")
    try:
        points = np.asarray(data["points2d"], dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{path}: 'points2d' is not numbers") from None
    if points.ndim != 4 or points.shape[-1] != 2:
        raise UserError(f"{path}: 'points2d' has shape {points.shape}, expected (cameras, frames, joints, 2)")
    C, T, J, _ = points.shape
    names = JOINTS if J == len(JOINTS) else [f"joint_{j}" for j in range(J)]
    layout, why = points2d_layout(points, sizes, rig, _points3d(data, T, J))
    log.info(f"note: {path}: points2d read as {LAYOUTS[layout]}: {why}")
    marked = _no_estimate(points) & np.isfinite(points).all(-1)
    if marked.any():
        log.info(f"note: {path}: {int(marked.sum())} of {marked.size} points2d hold (0, 0) or (0, 1), "
                 "DeepFly3D's marks for a joint without an estimate: read as unlabelled")
    tables = {}
    for c in range(C):
        cam = f"camera_{c}"
        if cam not in sizes:
            continue
        W, H = sizes[cam]
        uv = _in_pixels(points[c], layout, W, H)
        unseen: list[str] = []
        if J == len(JOINTS):
            seen = np.array([camera_sees_joint(c if c < 7 else 3, j) for j in range(J)])
            uv[:, ~seen] = np.nan
            unseen = [names[j] for j in np.flatnonzero(~seen)]
        uv[~np.isfinite(uv).all(-1)] = np.nan
        uv[~_known(points[c])] = np.nan  # DeepFly3D's marks for joints it has no estimate of
        tables[cam] = LabelTable(list(names), np.arange(T, dtype=np.int64), uv, f"{path} camera {c}", unseen)
    return tables


def _points3d(data: dict, frames: int, joints: int) -> np.ndarray | None:
    """The result's triangulated joints ``(T, J, 3)`` in the cameras' world frame, if it has them: DeepFly3D's
    ``points3d`` is aligned to its template, ``points3d_wo_procrustes`` is not."""
    for key in ("points3d_wo_procrustes", "points3d"):
        try:
            X = np.asarray(data.get(key), dtype=np.float64)
        except (TypeError, ValueError):
            continue
        if X.shape == (frames, joints, 3):
            return X
    return None
