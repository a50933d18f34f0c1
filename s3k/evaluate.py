"""``s3k evaluate``: a trained detector's metrics (docs/method.md#metrics) on a dataset split, and a report.

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

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from s3k.draw import draw_views
from s3k.errors import UserError

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
    if X_gt is not None:
        X_gt = np.asarray(X_gt, dtype=np.float64)
        known = np.ones((B, K), bool) if X_gt_mask is None else np.asarray(X_gt_mask, dtype=bool)
        err3d = np.linalg.norm(X - X_gt, axis=-1) * unit_mm  # (B, K)
        mask3d = known & X_valid & np.isfinite(err3d)
        denom3d = known
    else:
        err3d = np.zeros((B, K))
        mask3d = np.zeros((B, K), bool)
        denom3d = X_valid | ~X_valid

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
    out["n_frames"] = int(B)
    out["n_2d"] = int(mask2d.sum())
    out["n_3d"] = int(mask3d.sum())
    n_known = int(denom3d.sum())
    out["triangulated_fraction"] = float((X_valid & denom3d).sum() / n_known) if n_known else None
    out["per_keypoint"] = {}
    for k, name in enumerate(keypoints):
        sel = np.zeros(K, bool)
        sel[k] = True
        d = block(sel)
        d["n_2d"], d["n_3d"] = int((mask2d & sel).sum()), int((mask3d & sel).sum())
        out["per_keypoint"][name] = d
    out["per_camera"] = {}
    for c, name in enumerate(cameras):
        selc = np.zeros((B, C, K), bool)
        selc[:, c] = True
        out["per_camera"][name] = {"rms_px": _rms(err2d[mask2d & selc]),
                                   "rms_px_reproj": _rms(errre[maskre & selc]),
                                   "n_2d": int((mask2d & selc).sum())}
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
    import torch

    from s3k.geometry import project, triangulate_pixels

    cams = cams.to(torch.float64)
    principal = cams.K[..., :2, 2][..., None, :]  # (*L, 1, 2)
    centre, valid = triangulate_pixels(cams, principal)  # (*L[:-1], 1, 3)
    _, depth = project(cams, centre[..., None, :, :])  # (*L, 1)
    focal = torch.sqrt(cams.K[..., 0, 0].abs() * cams.K[..., 1, 1].abs())
    size = depth[..., 0] / focal * unit_mm
    ok = valid[..., None, 0] & (depth[..., 0] > 0)
    return torch.where(ok, size, torch.full_like(size, float("nan"))).numpy()


def ground_truth_2d(batch, image_size: tuple[int, int]):
    """Ground-truth 2D of a ``FrameBatch``: projections of its 3D points, else its labels.

    Returns:
        ``(gt_uv (B, C, K, 2), gt_mask (B, C, K))`` numpy arrays; the mask keeps points in front of the camera
        and inside ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.
    """
    import torch

    from s3k.geometry import project

    W, H = image_size
    if batch.points is not None:
        uv_t, depth = project(batch.cams.to(dtype=torch.float64), batch.points.double()[:, None])
        mask_t = (depth > 1e-6) & batch.points_mask[:, None, :]
        uv, mask = uv_t.numpy(), mask_t.numpy()
    elif batch.labels_uv is not None and batch.labels_mask is not None:
        uv, mask = batch.labels_uv.double().numpy(), batch.labels_mask.numpy().copy()
    else:
        raise UserError("evaluation needs ground-truth 3D points or 2D labels for the split")
    inside = (uv[..., 0] >= -0.5) & (uv[..., 0] <= W - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= H - 0.5)
    return uv, mask & inside & np.isfinite(uv).all(-1)


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


def evaluate_store(model, meta, store, device="cpu", batch_size: int = 16, units: str = "m",
                   keep: int = 0) -> tuple[dict[str, Any], dict[str, Any]]:
    """Predict every frame of ``store`` and compute :func:`compute_metrics`.

    Args:
        model: trained network (eval mode).
        meta: its ``DetectorMeta``.
        store: a ``FrameStore`` serving labels and/or 3D points.
        device: model device.
        batch_size: frames per forward pass.
        units: world units of the dataset.
        keep: keep the images and heatmaps of the first ``keep`` frames (for overlays).

    The ground truth's keypoints are matched to the model's by name (:func:`keypoint_order`).

    Returns:
        ``(metrics, arrays)``; arrays holds the concatenated predictions and ground truth (numpy) and the
        kept images / heatmaps.
    """
    from s3k.predict import predict_store

    cols: dict[str, list] = {k: [] for k in ("pred_uv", "reproj_uv", "gt_uv", "gt_mask", "X", "X_valid",
                                             "X_gt", "X_gt_mask", "weight", "frame_ids", "mm_per_px")}
    kept_images: list[np.ndarray] = []
    kept_probs: list[np.ndarray] = []
    has3d = True
    order = keypoint_order(meta.keypoints, store.dataset.keypoints)
    for batch, pred in predict_store(model, meta, store, batch_size, device, keep_heatmaps=keep > 0):
        gt_uv, gt_mask = ground_truth_2d(batch, store.out_size)
        gt_uv, gt_mask = gt_uv[:, :, order], gt_mask[:, :, order]
        cols["pred_uv"].append(pred.uv.numpy())
        cols["reproj_uv"].append(pred.reproj.numpy())
        cols["gt_uv"].append(gt_uv)
        cols["gt_mask"].append(gt_mask)
        cols["X"].append(pred.X.numpy())
        cols["X_valid"].append(pred.valid.numpy())
        cols["weight"].append(pred.weights.numpy())
        cols["frame_ids"].append(np.asarray(batch.frame_ids))
        cols["mm_per_px"].append(pixel_sizes_mm(batch.cams, mm_per_unit(units)))
        if batch.points is None or batch.points_mask is None:
            has3d = False
        else:
            cols["X_gt"].append(batch.points.numpy()[:, order])
            cols["X_gt_mask"].append(batch.points_mask.numpy()[:, order])
        n_kept = sum(len(x) for x in kept_images)
        if n_kept < keep:
            kept_images.append(batch.images[: keep - n_kept].numpy())
            assert pred.probs is not None  # asked for with keep_heatmaps
            kept_probs.append(pred.probs[: keep - n_kept].float().numpy())
    arrays = {k: np.concatenate(v) if v else None for k, v in cols.items()}
    if not has3d:
        arrays["X_gt"] = arrays["X_gt_mask"] = None
    arrays["images"] = np.concatenate(kept_images) if kept_images else None
    arrays["probs"] = np.concatenate(kept_probs) if kept_probs else None
    metrics = compute_metrics(arrays["pred_uv"], arrays["reproj_uv"], arrays["gt_uv"], arrays["gt_mask"],
                              arrays["X"], arrays["X_valid"], arrays["X_gt"], arrays["X_gt_mask"],
                              mm_per_unit(units), meta.keypoints, store.dataset.cameras)
    sizes = arrays["mm_per_px"]
    finite = sizes[np.isfinite(sizes)] if sizes is not None else np.zeros(0)
    metrics["mm_per_px"] = float(np.median(finite)) if finite.size else None
    return metrics, arrays


def _fmt(v) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"


def format_table(metrics: dict[str, Any]) -> str:
    """Human-readable table of a metrics dict."""
    lines = [f"{'':<16}" + "".join(f"{m:>15}" for m in METRICS)]
    lines.append(f"{'all':<16}" + "".join(f"{_fmt(metrics[m]):>15}" for m in METRICS))
    for name, d in metrics["per_keypoint"].items():
        lines.append(f"{'kp ' + name:<16}" + "".join(f"{_fmt(d.get(m)):>15}" for m in METRICS))
    for name, d in metrics["per_camera"].items():
        lines.append(f"{'cam ' + name:<16}" + "".join(f"{_fmt(d.get(m)):>15}" for m in METRICS))
    lines.append(f"frames {metrics['n_frames']}, 2D terms {metrics['n_2d']}, 3D terms {metrics['n_3d']}, "
                 f"triangulated {_fmt(metrics['triangulated_fraction'])}, "
                 f"mm_per_px {_fmt(metrics.get('mm_per_px'))}")
    return "\n".join(lines)


def write_report(out_dir: str | Path, metrics: dict[str, Any], arrays: dict[str, Any], unit_mm: float,
                 title: str = "") -> list[Path]:
    """Write metrics.json, plots (error histograms, per-keypoint errors) and view overlays to ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import cv2
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    written.append(out / "metrics.json")

    err2d = np.linalg.norm(arrays["pred_uv"] - arrays["gt_uv"], axis=-1)[arrays["gt_mask"]]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    axes[0].hist(err2d, bins=50, color="tab:blue")
    axes[0].set_xlabel("2D error per view (px)")
    axes[0].set_ylabel("count")
    axes[0].set_title(f"rms_px {_fmt(metrics['rms_px'])}")
    if arrays.get("X_gt") is not None:
        e3 = np.linalg.norm(arrays["X"] - arrays["X_gt"], axis=-1) * unit_mm
        sel = arrays["X_valid"] & arrays["X_gt_mask"]
        axes[1].hist(e3[sel], bins=50, color="tab:orange")
        axes[1].set_xlabel("3D error (mm)")
        axes[1].set_title(f"median_mm {_fmt(metrics['median_mm'])}, rms_mm {_fmt(metrics['rms_mm'])}")
    else:
        axes[1].set_axis_off()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out / "errors_hist.png", dpi=100)
    plt.close(fig)
    written.append(out / "errors_hist.png")

    names = list(metrics["per_keypoint"])
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    x = np.arange(len(names))
    for i, m in enumerate(("rms_px", "rms_px_reproj")):
        axes[0].bar(x + (i - 0.5) * 0.4, [metrics["per_keypoint"][n][m] or 0 for n in names], 0.4, label=m)
    axes[0].set_xticks(x, names, rotation=30)
    axes[0].set_ylabel("px")
    axes[0].legend()
    for i, m in enumerate(("median_mm", "rms_mm")):
        axes[1].bar(x + (i - 0.5) * 0.4, [metrics["per_keypoint"][n][m] or 0 for n in names], 0.4, label=m)
    axes[1].set_xticks(x, names, rotation=30)
    axes[1].set_ylabel("mm")
    axes[1].legend()
    fig.suptitle(f"per-keypoint errors {title}")
    fig.tight_layout()
    fig.savefig(out / "per_keypoint.png", dpi=100)
    plt.close(fig)
    written.append(out / "per_keypoint.png")

    if arrays.get("images") is not None:
        for i in range(len(arrays["images"])):
            img = draw_views(arrays["images"][i], arrays["probs"][i], arrays["pred_uv"][i],
                             arrays["gt_uv"][i], arrays["gt_mask"][i])
            path = out / f"overlay_{i:02d}_frame_{arrays['frame_ids'][i]}.png"
            cv2.imwrite(str(path), img[..., ::-1])
            written.append(path)
    return written


def evaluate_run(run_dir, data, split: str = "test", device: str = "auto", batch_size: int = 16,
                 report: str | Path | None = None, overlays: int = 6) -> dict[str, Any]:
    """Load a run, evaluate it on ``data``'s ``split`` and optionally write a report; returns the metrics.

    A two-pass run (``s3k train --two-pass``) is evaluated through both passes (:mod:`s3k.two_pass`)."""
    from s3k.two_pass import evaluate_two_pass, is_two_pass

    if is_two_pass(run_dir):
        return evaluate_two_pass(run_dir, data, split, device, batch_size, report, overlays)
    from s3k.frames import FrameStore, open_dataset
    from s3k.predict import pick_device
    from s3k.run import load_detector

    dev = pick_device(device)
    model, meta = load_detector(run_dir, dev)
    ds = open_dataset(data, meta.image_size)
    keypoint_order(meta.keypoints, ds.keypoints)  # refuse a mismatch before predicting anything
    ids = np.asarray(ds.frames(split))
    if len(ids) == 0:
        raise UserError(f"{data}: split {split!r} has no frames", hint="choose another --split")
    store = FrameStore(ds, ids, preload_mb=0, labels=True, points=True)
    metrics, arrays = evaluate_store(model, meta, store, dev, batch_size, ds.units,
                                     keep=overlays if report else 0)
    metrics["split"] = split
    metrics["image_size"] = list(meta.image_size)
    if report:
        write_report(report, metrics, arrays, mm_per_unit(ds.units), title=f"{Path(run_dir).name} ({split})")
    return metrics
