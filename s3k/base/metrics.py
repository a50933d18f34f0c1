"""The evaluation metrics (docs/method.md#metrics), pure functions of arrays.

Metric names are fixed so results compare across runs and versions:

- ``rms_px``: sqrt of the mean over frames, cameras and keypoints (where the ground truth projects inside the
  image) of the squared distance between the per-view 2D detection and the ground-truth projection, in pixels
  of the image the model saw.
- ``rms_px_reproj``: the same for the reprojection of the confidence-weighted triangulated 3D point.
- ``median_mm``, ``rms_mm``: 3D error of the triangulated point against the ground-truth 3D, millimetres.
- ``pck_5mm``, ``pck_10mm``: share of the keypoints with ground-truth 3D whose triangulated point is within
  5 / 10 mm of it (a failed triangulation counts as a miss).
- ``mm_per_px``: the size of one pixel of the image the model saw at the workspace centre (where the
  cameras' optical axes meet), from the calibration: what turns this rig's pixel errors into millimetres.
- ``per_keypoint`` and ``per_camera`` breakdowns of the above (3D metrics only per keypoint).

The ground truth is the dataset's 3D points projected into every camera; a dataset without 3D points is scored
in 2D against its labels (and the 3D metrics are null). Terms where the triangulation is degenerate are left
out of the reprojection and 3D metrics and counted in ``triangulated_fraction``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.geometry import project, workspace_centre

__all__ = ["METRICS", "UNIT_TO_MM", "compute_metrics", "format_table", "ground_truth_2d", "keypoint_order",
           "mm_per_unit", "pixel_sizes_mm"]

UNIT_TO_MM = {"m": 1000.0, "meter": 1000.0, "meters": 1000.0, "metre": 1000.0, "metres": 1000.0,
              "cm": 10.0, "mm": 1.0, "millimeter": 1.0, "millimetre": 1.0}

METRICS = ("rms_px", "rms_px_reproj", "median_mm", "rms_mm", "pck_5mm", "pck_10mm")


def mm_per_unit(units: str) -> float:
    """Millimetres per world unit; NaN for an unknown unit (3D metrics then stay in that unit's scale)."""
    return UNIT_TO_MM.get(str(units).strip().lower(), float("nan"))


def _rms(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x**2))) if x.size else None


def _median(x: np.ndarray) -> float | None:
    return float(np.median(x)) if x.size else None


def _errors_3d(X: np.ndarray, X_valid: np.ndarray, X_gt, X_gt_mask, unit_mm: float):
    """``(err3d (B, K) mm, where it counts (B, K), the keypoints a PCK counts over (B, K))``; without ground
    truth no term counts and every keypoint is in the denominator."""
    B, K = X_valid.shape
    if X_gt is None:
        return np.zeros((B, K)), np.zeros((B, K), bool), np.ones((B, K), bool)
    known = np.ones((B, K), bool) if X_gt_mask is None else np.asarray(X_gt_mask, dtype=bool)
    err3d = np.linalg.norm(X - np.asarray(X_gt, dtype=np.float64), axis=-1) * unit_mm
    return err3d, known & X_valid & np.isfinite(err3d), known


def point_errors_mm(X: np.ndarray, X_valid: np.ndarray, X_gt, X_gt_mask, unit_mm: float) -> np.ndarray:
    """(B, K) 3D errors in mm of the points the metrics count, NaN elsewhere (no truth, not triangulated)."""
    err3d, counted, _ = _errors_3d(X, np.asarray(X_valid, bool), X_gt, X_gt_mask, unit_mm)
    return np.where(counted, err3d, np.nan)


def compute_metrics(pred_uv, reproj_uv, gt_uv, gt_mask, X, X_valid, X_gt=None, X_gt_mask=None,
                    unit_mm: float = 1000.0, keypoints=None, cameras=None) -> dict[str, Any]:
    """The evaluation metrics of a set of predictions (pure function of arrays).

    Args:
        pred_uv: (B, C, K, 2) per-view 2D detections, pixels.
        reproj_uv: (B, C, K, 2) reprojections of the triangulated points, pixels.
        gt_uv: (B, C, K, 2) ground-truth 2D (projection of the true 3D point, or a label).
        gt_mask: (B, C, K) bool, where ``gt_uv`` counts (in front of the camera and inside the image).
        X: (B, K, 3) triangulated points, world units.
        X_valid: (B, K) bool, triangulation not degenerate.
        X_gt: (B, K, 3) ground-truth 3D, or None.
        X_gt_mask: (B, K) bool, or None (all known).
        unit_mm: millimetres per world unit.
        keypoints: K names (default "0", "1", ...).
        cameras: C names (default "0", "1", ...).

    Returns:
        ``{"rms_px", "rms_px_reproj", "median_mm", "rms_mm", "pck_5mm", "pck_10mm",
        "per_keypoint": {name: {...}},
        "per_camera": {name: {"rms_px", "rms_px_reproj", "n_2d"}}, "n_frames", "n_2d", "n_3d",
        "triangulated_fraction"}``; a metric without any term is None.
    """
    pred_uv, reproj_uv, gt_uv = (np.asarray(a, dtype=np.float64) for a in (pred_uv, reproj_uv, gt_uv))
    gt_mask, X_valid = np.asarray(gt_mask, dtype=bool), np.asarray(X_valid, dtype=bool)
    X = np.asarray(X, dtype=np.float64)
    B, C, K = gt_mask.shape
    if pred_uv.shape != (B, C, K, 2) or reproj_uv.shape != (B, C, K, 2) or gt_uv.shape != (B, C, K, 2):
        raise ValueError(f"compute_metrics: pred_uv, reproj_uv, gt_uv must be {(B, C, K, 2)} like gt_mask, "
                         f"got {pred_uv.shape}, {reproj_uv.shape}, {gt_uv.shape}")
    if X.shape != (B, K, 3) or X_valid.shape != (B, K):
        raise ValueError(f"compute_metrics: X must be {(B, K, 3)} and X_valid {(B, K)}, got {X.shape}, "
                         f"{X_valid.shape}")
    keypoints = [str(k) for k in range(K)] if keypoints is None else list(keypoints)
    cameras = [str(c) for c in range(C)] if cameras is None else list(cameras)

    err2d = np.linalg.norm(pred_uv - gt_uv, axis=-1)  # (B, C, K)
    errre = np.linalg.norm(reproj_uv - gt_uv, axis=-1)
    mask2d = gt_mask & np.isfinite(err2d)
    maskre = gt_mask & X_valid[:, None, :] & np.isfinite(errre)
    err3d, mask3d, denom3d = _errors_3d(X, X_valid, X_gt, X_gt_mask, unit_mm)

    def block(sel: np.ndarray) -> dict[str, Any]:
        """The metrics over the keypoints ``sel (K,)``."""
        s2, sr, s3 = mask2d & sel, maskre & sel, mask3d & sel
        n_known = int((denom3d & sel).sum()) if X_gt is not None else 0

        def pck(threshold_mm: float) -> float | None:
            # share of keypoints with known ground truth within the threshold; a failed triangulation misses
            return float((s3 & (err3d <= threshold_mm)).sum() / n_known) if n_known else None

        return {
            "rms_px": _rms(err2d[s2]),
            "rms_px_reproj": _rms(errre[sr]),
            "median_mm": _median(err3d[s3]),
            "rms_mm": _rms(err3d[s3]),
            "pck_5mm": pck(5.0),
            "pck_10mm": pck(10.0),
        }

    out: dict[str, Any] = block(np.ones(K, bool))
    n_known = int(denom3d.sum())
    out.update(n_frames=int(B), n_2d=int(mask2d.sum()), n_3d=int(mask3d.sum()),
               triangulated_fraction=float((X_valid & denom3d).sum() / n_known) if n_known else None)
    out["per_keypoint"] = {}
    for k, name in enumerate(keypoints):
        sel = np.arange(K) == k
        out["per_keypoint"][name] = {**block(sel), "n_2d": int((mask2d & sel).sum()),
                                     "n_3d": int((mask3d & sel).sum())}
    out["per_camera"] = {}
    for c, name in enumerate(cameras):
        s2, sr = mask2d[:, c], maskre[:, c]
        out["per_camera"][name] = {"rms_px": _rms(err2d[:, c][s2]), "rms_px_reproj": _rms(errre[:, c][sr]),
                                   "n_2d": int(s2.sum())}
    return out


def pixel_sizes_mm(cams, unit_mm: float = 1000.0) -> np.ndarray:
    """Size of one image pixel at the workspace centre, in millimetres, per frame and camera.

    The workspace centre is where the cameras look: the point nearest to their optical axes (the rays
    through each principal point), triangulated with unit weights; a pixel there spans ``z / f`` world units
    (``z`` its depth in the camera, ``f`` the geometric mean of the focal lengths). This is ``mm_per_px``:
    what turns a pixel error of this rig into millimetres.

    Args:
        cams: ``Cameras (B, C)`` (or ``(C,)`` for a rig).
        unit_mm: millimetres per world unit.

    Returns:
        ``(B, C)`` (or ``(C,)``) float64, NaN where the axes do not meet (fewer than two cameras, parallel
        axes) or the centre is behind a camera.
    """

    cams = cams.to(torch.float64)
    centre, valid = workspace_centre(cams)  # (*L[:-1], 3)
    _, depth = project(cams, centre[..., None, None, :])  # (*L, 1)
    focal = torch.sqrt(cams.K[..., 0, 0].abs() * cams.K[..., 1, 1].abs())
    size = depth[..., 0] / focal * unit_mm
    ok = valid[..., None] & (depth[..., 0] > 0)
    return torch.where(ok, size, torch.full_like(size, float("nan"))).numpy()


def ground_truth_2d(batch, image_size: tuple[int, int] | None):
    """Ground-truth 2D of a ``FrameBatch``: projections of its 3D points, else its labels.

    Returns:
        ``(gt_uv (B, C, K, 2), gt_mask (B, C, K))`` numpy arrays; the mask keeps points in front of the camera
        and, unless ``image_size`` is None, inside ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.
    """

    if batch.points is not None:
        uv_t, depth = project(batch.cams.to(dtype=torch.float64), batch.points.double()[:, None])
        mask_t = (depth > 1e-6) & batch.points_mask[:, None, :]
        uv, mask = uv_t.numpy(), mask_t.numpy()
    elif batch.labels_uv is not None and batch.labels_mask is not None:
        uv, mask = batch.labels_uv.double().numpy(), batch.labels_mask.numpy().copy()
    else:
        raise UserError("evaluation needs ground-truth 3D points or 2D labels for the split")
    mask = mask & np.isfinite(uv).all(-1)
    if image_size is not None:
        W, H = image_size
        mask &= (uv[..., 0] >= -0.5) & (uv[..., 0] <= W - 0.5)
        mask &= (uv[..., 1] >= -0.5) & (uv[..., 1] <= H - 0.5)
    return uv, mask


def keypoint_order(model_keypoints, dataset_keypoints) -> np.ndarray:
    """Index of each of the model's keypoints among the dataset's, matched by name.

    Raises:
        UserError: the names differ, naming the keypoints missing from the dataset and those it has extra.
    """
    model_kp, data_kp = [str(k) for k in model_keypoints], [str(k) for k in dataset_keypoints]
    missing = [k for k in model_kp if k not in data_kp]
    extra = [k for k in data_kp if k not in model_kp]
    if missing or extra:
        parts = ([f"missing {', '.join(missing)}"] if missing else []) + \
                ([f"extra {', '.join(extra)}"] if extra else [])
        raise UserError(f"the dataset's keypoints do not match the model's ({'; '.join(parts)}): the model "
                        f"has {', '.join(model_kp)}; the dataset has {', '.join(data_kp)}")
    return np.array([data_kp.index(k) for k in model_kp], dtype=np.int64)


def format_metric(v) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"


SUMMARY_METRICS = ("rms_px", "rms_px_reproj", "median_mm", "rms_mm", "pck_5mm", "pck_10mm", "n_2d", "n_3d")
"""The metrics of :func:`compute_metrics` that a part of the frames (a session) is summed up by."""


def _distance(d: dict[str, Any] | None) -> str:
    if not d or d.get("median") is None:
        return "no labelled frame in the same session"
    return f"median {d['median']:g}, min {d['min']:g} frames from the nearest labelled frame"


def format_table(metrics: dict[str, Any]) -> str:
    """Human-readable table of a metrics dict (with its sessions' rows when it has several)."""
    lines = [f"{'':<16}" + "".join(f"{m:>15}" for m in METRICS)]
    lines.append(f"{'all':<16}" + "".join(f"{format_metric(metrics[m]):>15}" for m in METRICS))
    sessions = metrics.get("sessions") or {}
    if len(sessions) > 1:
        for name, d in sessions.items():
            cells = "".join(f"{format_metric(d.get(m)):>15}" for m in METRICS)
            lines.append(f"{'session ' + name:<16}{cells}")
    for name, d in metrics["per_keypoint"].items():
        lines.append(f"{'kp ' + name:<16}" + "".join(f"{format_metric(d.get(m)):>15}" for m in METRICS))
    for name, d in metrics["per_camera"].items():
        lines.append(f"{'cam ' + name:<16}" + "".join(f"{format_metric(d.get(m)):>15}" for m in METRICS))
    lines.append(f"frames {metrics['n_frames']}, 2D terms {metrics['n_2d']}, 3D terms {metrics['n_3d']}, "
                 f"triangulated {format_metric(metrics['triangulated_fraction'])}, "
                 f"mm_per_px {format_metric(metrics.get('mm_per_px'))}")
    if "label_distance" in metrics:
        lines.append(f"{metrics.get('split', 'evaluated')} frames lie {_distance(metrics['label_distance'])}"
                     " of their session")
        if len(sessions) > 1:
            lines += [f"  session {name}: {d['n_frames']} frames, {_distance(d.get('label_distance'))}"
                      for name, d in sessions.items()]
    return "\n".join(lines)
