"""DeepFly3D's pickles: the calibration (``calib.pkl``, and the same per-camera entries inside a
``df3d_result*.pkl``) and the 2D pose of a ``df3d_result*.pkl``.

Layout (DeepFly3D's documentation): a dict whose integer keys ``0 .. 6`` are the cameras, each
``{"R": (3, 3) world->camera, "tvec": (3,), "intr": (3, 3), "distort": (5,)}`` in the OpenCV model; a pose
result also holds ``points2d (C, T, J, 2)``, each point ``(row, column)`` as a fraction of the image height
and width, and ``camera_ordering``. Camera ``i`` is named ``camera_i`` (DeepFly3D's ``camera_i.mp4``). The
pickles are read with :func:`s3k.data.safe_pickle.load_pickle` (arrays and containers only). Image sizes
are not in the files: they come from the videos.

DeepFly3D predicts all 38 joints in every camera, but each camera sees one side of the fly: its rule
(``camera_see_joint``) keeps the joints of the near side, for the middle camera 3 only the outer leg joints
and the antennae, and drops the stripes in cameras 2 and 4. :func:`read_deepfly3d_pose` applies it, so a
joint a camera cannot see is unlabelled there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from s3k.data.labels2d import LabelTable
from s3k.data.rig import Rig
from s3k.data.safe_pickle import load_pickle
from s3k.errors import UserError
from s3k.geometry import Cameras

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


def read_deepfly3d_pose(path: str | Path, sizes: dict[str, tuple[int, int]]) -> dict[str, LabelTable]:
    """2D joints of a ``df3d_result*.pkl`` per camera ``camera_<i>`` (index ``i`` of ``points2d``), in the
    pixels of an image of ``sizes[camera] = (W, H)``; joints the camera cannot see (:func:`camera_sees_joint`,
    for the 38-joint fly) and non-finite points are unlabelled. Cameras without a size are skipped."""
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
    tables = {}
    for c in range(C):
        cam = f"camera_{c}"
        if cam not in sizes:
            continue
        W, H = sizes[cam]
        uv = np.stack([points[c, :, :, 1] * W, points[c, :, :, 0] * H], axis=-1)  # (row, col) fractions
        if J == len(JOINTS):
            seen = np.array([camera_sees_joint(c if c < 7 else 3, j) for j in range(J)])
            uv[:, ~seen] = np.nan
        uv[~np.isfinite(uv).all(-1)] = np.nan
        # DeepFly3D writes zeros for joints it has no estimate of.
        uv[(points[c] == 0).all(-1)] = np.nan
        tables[cam] = LabelTable(list(names), np.arange(T, dtype=np.int64), uv, f"{path} camera {c}")
    return tables
