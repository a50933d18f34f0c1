"""3D figures on a dataset without 3D truth: the labels triangulated from every labelled view are the
reference.

- :func:`triangulate_labels`: each keypoint labelled in >= 2 views of a frame, triangulated (unit weights, the
  dataset's pixels and cameras); the model's 3D points are scored against these in ``s3k evaluate``.
- :func:`leave_one_view_out`: each labelled view against the labels of the others (>= 2 of them) triangulated
  and reprojected into it: how well labels and calibration agree, the floor under any 2D error.
- :func:`bootstrap_ci`: a percentile bootstrap interval of a statistic over frames (frames are resampled, not
  points, since the keypoints of a frame share its errors).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from s3k.geometry import Cameras, project, triangulate_pixels

__all__ = ["bootstrap_ci", "label_reference_metrics", "leave_one_view_out", "triangulate_labels"]

BOOTSTRAP_SAMPLES = 1000


def triangulate_labels(cams: Cameras, uv: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cams (B, C)``, labels ``uv (B, C, K, 2)`` with ``mask (B, C, K)`` -> ``(X (B, K, 3), valid (B, K))``,
    valid where >= 2 views are labelled and the triangulation is not degenerate."""
    mask = np.asarray(mask, dtype=bool)
    X, valid = triangulate_pixels(cams.to(dtype=torch.float64), torch.from_numpy(np.nan_to_num(uv)).double(),
                                  torch.from_numpy(mask * 1.0))
    return X.numpy(), valid.numpy() & (mask.sum(1) >= 2)


def leave_one_view_out(cams: Cameras, uv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(B, C, K)`` pixel distance between each labelled view's label and the point triangulated from the
    other labelled views (>= 2 of them) reprojected into it; NaN elsewhere."""
    mask = np.asarray(mask, dtype=bool)
    B, C, K = mask.shape
    out = np.full((B, C, K), np.nan)
    cams64 = cams.to(dtype=torch.float64)
    for c in range(C):
        others = mask.copy()
        others[:, c] = False
        X, valid = triangulate_labels(cams64, uv, others)
        proj, depth = project(cams64[:, c: c + 1], torch.from_numpy(X)[:, None])  # (B, 1, K, 2)
        ok = valid & mask[:, c] & (depth[:, 0].numpy() > 0)
        d = np.linalg.norm(proj[:, 0].numpy() - uv[:, c], axis=-1)
        out[:, c] = np.where(ok, d, np.nan)
    return out


def bootstrap_ci(err: np.ndarray, stat=np.mean, samples: int = BOOTSTRAP_SAMPLES, level: float = 0.95,
                 seed: int = 0) -> tuple[float, float] | None:
    """Percentile bootstrap interval of ``stat`` over the finite entries of ``err (B, ...)``, resampling the
    frames (rows). None without a finite entry."""
    err = np.asarray(err, dtype=np.float64).reshape(len(err), -1)
    rows = np.isfinite(err).any(1)
    err = err[rows]
    if not len(err):
        return None
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(samples):
        pick = err[rng.integers(0, len(err), len(err))]
        values.append(stat(pick[np.isfinite(pick)]))
    lo, hi = np.percentile(values, [50 * (1 - level), 50 * (1 + level)])
    return float(lo), float(hi)


def _summary(err: np.ndarray) -> dict[str, Any]:
    """median, mean, RMS, their 95% intervals (frames resampled) and the count of ``err (B, K)``."""
    finite = err[np.isfinite(err)]
    if not finite.size:
        return {"median": None, "mean": None, "rms": None, "ci95_median": None, "ci95_mean": None, "n": 0}
    return {"median": float(np.median(finite)), "mean": float(finite.mean()),
            "rms": float(np.sqrt(np.mean(finite**2))), "ci95_median": bootstrap_ci(err, np.median),
            "ci95_mean": bootstrap_ci(err, np.mean), "n": int(finite.size)}


def label_reference_metrics(arrays: dict[str, Any], unit_mm: float, keypoints: list[str]) -> dict[str, Any]:
    """The figures of a dataset without 3D truth, overall and per keypoint: the distance (mm, or the rig's
    unit when it is unknown) between the model's points ``X (B, K, 3)`` (valid ``X_valid``) and the
    triangulated labels ``lab_X`` (valid ``lab_valid``), and the labels' leave-one-view-out reprojection error
    ``loo_px (B, C, K)`` (pixels of the dataset's images); ``arrays`` holds these."""
    X, X_valid, X_lab, lab_valid, loo_px = (np.asarray(arrays[k]) for k in
                                            ("X", "X_valid", "lab_X", "lab_valid", "loo_px"))
    scale = unit_mm if np.isfinite(unit_mm) else 1.0
    d = np.where(X_valid & lab_valid, np.linalg.norm(X - X_lab, axis=-1) * scale, np.nan)  # (B, K)
    out: dict[str, Any] = {
        "reference": "labels triangulated from every labelled view (>= 2 views), unit weights",
        "unit": "mm" if np.isfinite(unit_mm) else "the rig's unit",
        "model_to_labels_3d": _summary(d),
        "labels_leave_one_view_out_px": _summary(loo_px.reshape(len(loo_px), -1)),
        "per_keypoint": {},
    }
    for k, name in enumerate(keypoints):
        out["per_keypoint"][name] = {"model_to_labels_3d": _summary(d[:, k: k + 1]),
                                     "labels_leave_one_view_out_px": _summary(loo_px[:, :, k])}
    return out


def _ci(s: dict) -> str:
    if s["median"] is None:
        return f"{'-':>8} {'':>17} {'-':>8} {'':>17}"
    lo, hi = s["ci95_median"]
    mlo, mhi = s["ci95_mean"]
    return f"{s['median']:>8.2f} [{lo:>6.2f}, {hi:>6.2f}] {s['mean']:>8.2f} [{mlo:>6.2f}, {mhi:>6.2f}]"


def format_label_reference(ref: dict[str, Any]) -> str:
    """The table of :func:`label_reference_metrics`: per keypoint and overall, median and mean with their
    95% intervals."""
    unit = ref["unit"]
    head = (f"{'':<16}{'median':>8} {'95% CI':>17} {'mean':>8} {'95% CI':>17}")
    lines = [f"3D distance to the labels triangulated from every labelled view ({unit}; 95% CI: bootstrap "
             "over frames) | labels' leave-one-view-out reprojection (px)",
             head + "   |" + head[16:]]
    rows = [("all", ref), *ref["per_keypoint"].items()]
    for name, r in rows:
        lines.append(f"{name:<16}{_ci(r['model_to_labels_3d'])}   |{_ci(r['labels_leave_one_view_out_px'])}")
    n = ref["model_to_labels_3d"]["n"]
    n_loo = ref["labels_leave_one_view_out_px"]["n"]
    lines.append(f"{n} keypoints with labels in >= 2 views; {n_loo} labelled views with >= 2 other labelled "
                 "views")
    return "\n".join(lines)
