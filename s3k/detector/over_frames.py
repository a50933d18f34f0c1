"""A detector over a dataset's frames: :func:`detect_store` (every frame of a
:class:`s3k.data.frames.FrameStore` through a :class:`s3k.detector.Detector`), :func:`evaluate_store` (the
metrics of :mod:`s3k.base.metrics` on them) and :func:`split_frames`; what ``s3k predict``, ``s3k evaluate``,
validation in training and a two-pass training's coarse estimates read frames with."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from s3k.base.label_reference import label_reference_metrics, leave_one_view_out, triangulate_labels
from s3k.base.metrics import compute_metrics, ground_truth_2d, keypoint_order, mm_per_unit, pixel_sizes_mm
from s3k.data.frames import FrameBatch, FrameStore
from s3k.data.protocol import DatasetLike
from s3k.data.tables import SPLITS
from s3k.detector.detector import Detection, Detector, TwoPassDetector

__all__ = ["detect_store", "evaluate_store", "scored_views", "split_frames"]


def detect_store(detector: Detector, store: FrameStore, batch_size: int = 16,
                 keep_heatmaps: bool = False) -> Iterator[tuple[FrameBatch, Detection]]:
    """Run ``detector`` over every frame of ``store`` (frames at the dataset's own size, its cameras);
    yields ``(FrameBatch, Detection)`` on the CPU, in the dataset's pixels."""
    for batch in store.batches(batch_size):
        yield batch, detector(batch.images, batch.cams, keep_heatmaps=keep_heatmaps).cpu()


def split_frames(dataset: DatasetLike, split: str) -> np.ndarray:
    """Frame ids of a split, or of every split for 'all' (labelled, unlabelled, then test frames)."""
    return np.asarray(dataset.frames(SPLITS if split == "all" else split))


COLUMNS = ("pred_uv", "reproj_uv", "gt_uv", "gt_mask", "X", "X_valid", "X_gt", "X_gt_mask", "weight",
           "confidence", "frame_ids", "mm_per_px", "image_err", "placed", "fallback", "lab_X", "lab_valid",
           "loo_px")


def _to_network(uv: np.ndarray, maps: np.ndarray) -> np.ndarray:
    """Pixels ``(B, C, K, 2)`` of the frames -> the network's input pixels by ``maps (B, C, 3, 3)``."""
    return np.einsum("bcij,bckj->bcki", maps[..., :2, :2], uv) + maps[:, :, None, :2, 2]


def _columns(batch, pred: Detection, order: np.ndarray, units: str) -> dict[str, Any]:
    """One batch's columns of :func:`evaluate_store`: detections and ground truth in the network's pixels."""
    assert pred.pixel_maps is not None
    maps = pred.pixel_maps.numpy()
    w, h = pred.input_size
    gt_img, gt_mask = ground_truth_2d(batch, None)
    gt_img, gt_mask = gt_img[:, :, order], gt_mask[:, :, order]
    gt_uv = _to_network(np.nan_to_num(gt_img), maps)
    inside = ((gt_uv >= -0.5) & (gt_uv <= np.array([w - 0.5, h - 0.5]))).all(-1)
    uv = pred.uv.numpy()
    row = {"pred_uv": _to_network(uv, maps), "reproj_uv": _to_network(pred.reproj.numpy(), maps),
           "gt_uv": gt_uv, "gt_mask": gt_mask & inside, "X": pred.X.numpy(), "X_valid": pred.valid.numpy(),
           "weight": pred.weights.numpy(), "confidence": pred.confidence.numpy(),
           "frame_ids": np.asarray(batch.frame_ids),
           "mm_per_px": pixel_sizes_mm(pred.network_cameras(), mm_per_unit(units)),
           "placed": np.ones(len(uv), bool) if pred.placed is None else pred.placed.numpy(),
           "fallback": np.zeros(len(uv), bool) if pred.fallback is None else pred.fallback.numpy(),
           "image_err": np.where(gt_mask & inside, np.linalg.norm(uv - gt_img, axis=-1), np.nan)}
    if batch.points is not None and batch.points_mask is not None:
        row["X_gt"], row["X_gt_mask"] = batch.points.numpy()[:, order], batch.points_mask.numpy()[:, order]
    else:  # no 3D truth: the labels triangulated from every labelled view are the reference
        row["lab_X"], row["lab_valid"] = triangulate_labels(batch.cams, gt_img, gt_mask)
        row["loo_px"] = leave_one_view_out(batch.cams, gt_img, gt_mask)
    return row


def scored_views(arrays: dict[str, Any], within_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The views of :func:`evaluate_store`'s ``arrays`` that have a truth: ``(weight (n,), confidence (n,),
    right (n,))``, ``right`` where the detection lies within ``within_px`` network-input pixels of the truth
    (what the confidence is calibrated against, :mod:`s3k.readout.confidence`)."""
    mask = arrays["gt_mask"] & np.isfinite(arrays["weight"])
    err = np.linalg.norm(arrays["pred_uv"] - arrays["gt_uv"], axis=-1)
    right = np.isfinite(err) & (err <= within_px)
    return arrays["weight"][mask], arrays["confidence"][mask], right[mask]


def evaluate_store(detector: Detector, store: FrameStore, batch_size: int = 16, units: str = "m",
                   keep: int = 0, label_reference: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """Detect every frame of ``store`` and compute :func:`s3k.base.metrics.compute_metrics`.

    Args:
        detector: the detector.
        store: a ``FrameStore`` of a dataset at its own size, serving labels and/or 3D points.
        batch_size: frames per forward pass.
        units: world units of the dataset.
        keep: keep the network inputs and heatmaps of the first ``keep`` frames (for overlays).
        label_reference: without 3D truth, add ``labels_3d``: the 3D distance to the triangulated labels and
            the labels' leave-one-view-out error, per keypoint, with bootstrap intervals
            (:func:`s3k.base.label_reference.label_reference_metrics`).

    The ground truth's keypoints are matched to the detector's by name (:func:`keypoint_order`).

    Returns:
        ``(metrics, arrays)``; arrays holds the concatenated predictions and ground truth (numpy, in the
        network's pixels) and the kept network inputs (uint8) and heatmaps.
    """
    cols: dict[str, list] = {k: [] for k in COLUMNS}
    kept_images: list[np.ndarray] = []
    kept_probs: list[np.ndarray] = []
    order = keypoint_order(detector.keypoints, store.dataset.keypoints)
    for batch, pred in detect_store(detector, store, batch_size, keep_heatmaps=keep > 0):
        for k, v in _columns(batch, pred, order, units).items():
            cols[k].append(v)
        n_kept = sum(len(x) for x in kept_images)
        if n_kept < keep and pred.inputs is not None and pred.probs is not None:
            inputs = pred.inputs[: keep - n_kept].mul(255).round().to(torch.uint8).permute(0, 1, 3, 4, 2)
            kept_images.append(inputs.numpy())
            kept_probs.append(pred.probs[: keep - n_kept].float().numpy())
    arrays = {k: np.concatenate(v) if v else None for k, v in cols.items()}
    from_labels = len(cols["X_gt"]) != len(cols["X"]) and len(cols["lab_X"]) == len(cols["X"])
    if from_labels:  # the report's and the metrics' 3D columns measure against the triangulated labels
        arrays["X_gt"], arrays["X_gt_mask"] = arrays["lab_X"], arrays["lab_valid"]
    elif len(cols["X_gt"]) != len(cols["X"]):
        arrays["X_gt"] = arrays["X_gt_mask"] = None
    arrays["images"] = np.concatenate(kept_images) if kept_images else None
    arrays["probs"] = np.concatenate(kept_probs) if kept_probs else None
    metrics = compute_metrics(arrays["pred_uv"], arrays["reproj_uv"], arrays["gt_uv"], arrays["gt_mask"],
                              arrays["X"], arrays["X_valid"], arrays["X_gt"], arrays["X_gt_mask"],
                              mm_per_unit(units), detector.keypoints, store.dataset.cameras)
    metrics["reference_3d"] = "triangulated labels" if from_labels else (
        "3D points" if arrays["X_gt"] is not None else None)
    if from_labels and label_reference:
        metrics["labels_3d"] = label_reference_metrics(arrays, mm_per_unit(units), list(detector.keypoints))
    sizes, image_err = arrays["mm_per_px"], arrays["image_err"]
    finite = sizes[np.isfinite(sizes)] if sizes is not None else np.zeros(0)
    metrics["mm_per_px"] = float(np.median(finite)) if finite.size else None
    errs = image_err[np.isfinite(image_err)] if image_err is not None else np.zeros(0)
    metrics["rms_px_image"] = float(np.sqrt(np.mean(errs**2))) if errs.size else None
    if isinstance(detector, TwoPassDetector):
        rule = detector.rule
        metrics["two_pass"] = {"extent": rule.extent, "size": rule.size, "margin": rule.margin,
                               "coarse_frames_placed": sum(int(p.sum()) for p in cols["placed"]),
                               "coarse_fallback_frames": sum(int(f.sum()) for f in cols["fallback"])}
    return metrics, arrays
