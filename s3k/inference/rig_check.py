"""What ``s3k predict``, ``track`` and ``stream`` check before they detect: that the run was trained on this
rig and object, and that the calibration given is sound and the one the run was trained with.

- :func:`check_rig` refuses cameras the run was never trained on (another rig) and, for a dataset, other
  keypoints (another object), as ``s3k evaluate`` and ``s3k label`` refuse such a pair; the override is
  named in the message (``--other-rig``).
- :func:`calibration_notes` runs the label-free part of the check ``s3k import`` runs (two cameras with
  identical parameters: a copy error) and says how the calibration differs from the one the run was trained
  with (:func:`s3k.detector.geometry_record.training_geometry` records it in frame pixels; runs trained before
  that record are compared with their training dataset when it is still there): which cameras, by how many
  millimetres (centre), degrees (orientation) and pixels of focal length. Points move with the calibration,
  and the reprojection error cannot tell: only these lines do.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.base.metrics import mm_per_unit
from s3k.data import Dataset
from s3k.detector import DetectorMeta
from s3k.detector.geometry_record import check_images, frame_calibration, recorded_geometry
from s3k.geometry import Cameras
from s3k.geometry.consistency import identical_cameras
from s3k.run_folder import RunFolder

__all__ = ["OVERRIDE", "calibration_notes", "check_dataset_rig", "check_rig", "run_calibration"]

log = logging.getLogger(__name__)

OVERRIDE = "--other-rig"
"""The option of ``s3k predict``, ``track`` and ``stream`` that uses a run on another rig or object anyway."""

CENTRE_MM, ANGLE_DEG, FOCAL_REL = 1.0, 0.1, 0.005
"""Differences from the run's calibration below these (centre in mm, orientation in degrees, focal length as a
fraction) are not reported."""


def check_rig(meta: DetectorMeta, run: str | Path | None, cameras: list[str],
              keypoints: list[str] | None = None, what: str = "--calibration") -> None:
    """Refuse to use the detector of ``meta`` (of the run folder ``run``) on ``cameras`` it was not trained
    on, or (``keypoints``, a dataset's) on other keypoints.

    Raises:
        UserError: naming the cameras or keypoints, the run's, and :data:`OVERRIDE`.
    """
    trained = [str(c) for c in meta.cameras]
    unknown = [c for c in cameras if trained and c not in trained]
    hint = f"use a run trained on this rig and object, or pass {OVERRIDE} to use this one anyway"
    if unknown:
        raise UserError(f"{what}: camera(s) {', '.join(map(repr, unknown))} are not among the cameras "
                        f"{', '.join(trained)} the run {run} was trained on: another rig, where its "
                        "results would be wrong", hint=hint)
    model = [str(k) for k in meta.keypoints]
    if keypoints is not None and model and set(keypoints) != set(model):  # matched by name, in any order
        raise UserError(f"{what}: the dataset's keypoints {', '.join(keypoints)} are not the run's "
                        f"{', '.join(model)} ({run}): another object, whose points would be named after "
                        "the run's keypoints", hint=hint)


def run_calibration(meta: DetectorMeta, run: str | Path | None = None) -> dict[str, Any] | None:
    """The calibration the detector of ``meta`` was trained with, in its cameras' frame pixels: recorded in
    the meta, else read from its training dataset (named in the meta's geometry, or for a run trained before
    that record in the run folder ``run``) when that is still there and static; None when unknown."""
    geometry = meta.geometry if isinstance(meta.geometry, dict) else {}
    recorded = geometry.get("calibration")
    if isinstance(recorded, dict) and isinstance(recorded.get("cameras"), dict):
        return recorded
    path = (geometry.get("dataset") or {}).get("path")
    try:
        path = path or (RunFolder(run).dataset() if run is not None else None)
    except (FileNotFoundError, UserError, ValueError, OSError):
        return None
    if not path or not (Path(path) / "s3k.json").is_file():
        return None
    try:
        return frame_calibration(Dataset.open(path, cache="none"))
    except (ValueError, OSError, KeyError, UserError):
        return None


def _identical(cams: Cameras, names: list[str]) -> list[str]:
    return [f"calibration: {note} (usually a copy error in the calibration file; s3k check-calibration "
            "DATASET --recalibrate CAM recalibrates the copy)" for note in identical_cameras(cams, names)]


def _difference(name: str, want: dict[str, Any], K, R, t, size, scale: float) -> str | None:
    """How camera ``name`` (``K, R, t`` in pixels of frames of ``size``, world units ``scale`` mm each)
    differs from the run's entry ``want``; None when within the tolerances."""
    Kw, Rw, tw = (np.asarray(want[k], dtype=np.float64) for k in ("K", "R", "t"))
    frame = want.get("frame_size") or size
    fw = Kw[0, 0] * (size[0] / frame[0] if frame[0] else 1.0)  # the run's focal at this frame size
    centre = -R.T @ t * scale
    centre_w = -Rw.T @ tw * want["_scale"]
    moved = float(np.linalg.norm(centre - centre_w))
    cos = (np.trace(R @ Rw.T) - 1) / 2
    turned = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    focal = abs(K[0, 0] - fw) / max(abs(fw), 1e-12)
    parts = []
    if not moved <= CENTRE_MM:
        parts.append(f"centre {moved:.3g} mm away")
    if not turned <= ANGLE_DEG:
        parts.append(f"turned {turned:.3g} deg")
    if not focal <= FOCAL_REL:
        parts.append(f"focal {K[0, 0]:.1f} px vs {fw:.1f} px")
    return f"{name} ({', '.join(parts)})" if parts else None


def _differences(want: dict[str, Any], cams: Cameras, names: list[str], units: str,
                 sizes: dict[str, tuple[int, int]]) -> list[str]:
    """How each camera differs from its entry of the run's calibration ``want`` (:func:`_difference`)."""
    scale, want_scale = mm_per_unit(units), mm_per_unit(want.get("units", "unknown"))
    if not (math.isfinite(scale) and math.isfinite(want_scale)):  # one unit unknown: compare as they are
        scale = want_scale = 1.0
    a = cams.numpy()
    diffs = []
    for c, name in enumerate(names):
        entry = want["cameras"].get(name)
        if entry is None:
            continue
        d = _difference(name, {**entry, "_scale": want_scale}, a["K"][c], a["R"][c], a["t"][c],
                        tuple(sizes.get(name, entry.get("frame_size") or (0, 0))), scale)
        if d:
            diffs.append(d)
    return diffs


def calibration_notes(meta: DetectorMeta, run: str | Path | None, cams: Cameras, names: list[str], units: str,
                      sizes: dict[str, tuple[int, int]], source: str | Path) -> list[str]:
    """Warnings (``warning: ...`` lines) on the calibration ``source`` given to a run: cameras with identical
    parameters, and how it differs from the run's own calibration (module docstring).

    Args:
        meta: the detector's meta (:attr:`s3k.detector.Detector.frame_meta`).
        run: its run folder, for the message (and a run trained before its calibration was recorded).
        cams: the cameras ``(C,)`` in the pixels of the frames they see, float64.
        names: their names.
        units: their world unit.
        sizes: ``{camera: (W, H)}`` of those frames.
        source: the calibration's file or dataset, for the message.
    """
    want = run_calibration(meta, run)
    diffs = [] if want is None else _differences(want, cams, names, units, sizes)
    notes = _identical(cams, names)
    if diffs:
        notes.append(f"calibration differs from the one the run {run} was trained with: "
                     f"{'; '.join(diffs)}; the 3D points move with it (and the reprojection error does not "
                     "show it)")
    return [f"warning: {source}: {n}" for n in notes]


def check_dataset_rig(meta: DetectorMeta, run: str | Path | None, ds: Dataset, refuse: bool = True,
                      option: str = OVERRIDE, rig: bool = True) -> None:
    """The checks of a dataset ``ds`` for the detector of ``meta`` (of the run folder ``run``; ``s3k
    predict``, the labelling app's suggestions): with ``refuse``, the images' part of the frames
    (:func:`s3k.detector.geometry_record.check_images`), the cameras and the keypoints (:func:`check_rig`);
    then the dataset's static calibration (:func:`calibration_notes`), logged as warnings. ``rig=False``
    checks the images alone (the labelling app: a run's suggestions on another rig's frames).

    Raises:
        UserError: another rig or object, naming ``option``.
    """
    if refuse:
        check_images(recorded_geometry(meta.geometry), run or "", ds, option=option)
    if refuse and rig:
        check_rig(meta, run, list(ds.cameras), list(ds.keypoints), what=f"--data {ds.path}")
    frames = frame_calibration(ds)
    if frames is None:
        return
    entries = [frames["cameras"][c] for c in ds.cameras]
    K, dist, R, t = (np.stack([e[k] for e in entries]) for k in ("K", "dist", "R", "t"))
    cams = Cameras.from_numpy(K, dist, R, t, dtype=torch.float64)
    sizes = {c: tuple(e["frame_size"]) for c, e in zip(ds.cameras, entries)}
    for line in calibration_notes(meta, run, cams, list(ds.cameras), frames["units"], sizes, ds.path):
        log.warning(line.removeprefix("warning: "))
