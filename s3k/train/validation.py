"""Periodic validation during training, the reference quantities it compares against, and the calibration of
the confidence at the end.

Every ``val_every`` steps the validation frames are predicted: the metrics (``s3k.inference.evaluate``),
an image of predicted vs true keypoints with heatmaps (TensorBoard), and a collapse check: a warning when the
mean pairwise distance between the triangulated keypoints falls below ``collapse_fraction`` of the labelled
layout's (:func:`labelled_layout`). At the last step the same frames calibrate the confidence
(:func:`calibrate`, :mod:`s3k.readout.confidence`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any

import numpy as np
import torch
from torch import nn

from s3k.base.draw import draw_views
from s3k.base.messages import NOTE
from s3k.config import TrainConfig
from s3k.data.frames import FrameStore
from s3k.data.protocol import DatasetLike
from s3k.detector import DetectorMeta, OnePassDetector, detect_store, evaluate_store, scored_views
from s3k.geometry import triangulate_labels
from s3k.readout import CALIBRATION_SIGMAS, fit_confidence

log = logging.getLogger(__name__)  # under "s3k.train", which a run logs to (run_setup)


def mean_pairwise_distance(X: torch.Tensor, valid: torch.Tensor) -> float:
    """Mean distance over all pairs of valid keypoints of every frame.

    Args:
        X: (B, K, 3) points.
        valid: (B, K) bool.

    Returns:
        The mean (NaN when no frame has two valid keypoints).
    """
    d = torch.cdist(X.double(), X.double())  # (B, K, K)
    K = X.shape[1]
    pair = valid[:, :, None] & valid[:, None, :] & torch.triu(torch.ones(K, K, dtype=torch.bool), 1)
    return float(d[pair].mean()) if pair.any() else float("nan")


def _labelled_points(dataset: DatasetLike, frame_ids: np.ndarray, chunk: int = 256):
    """``(X (B, K, 3), valid (B, K))`` per chunk of ``frame_ids``: the keypoints triangulated from the labels.

    Reads labels and calibration only (no image); a keypoint labelled in >= 2 cameras is triangulated with
    unit weights, as the supervised loss does.
    """
    for i in range(0, len(frame_ids), chunk):
        ids = frame_ids[i:i + chunk]
        uv, mask = dataset.labels(ids)
        # float32 as the network's batches hold them (frames.FrameStore), solved in float64
        cams = dataset.calibration(ids).to(dtype=torch.float64)
        uv_t = torch.from_numpy(np.asarray(uv, dtype=np.float32)).double()
        yield triangulate_labels(cams, uv_t, torch.from_numpy(np.asarray(mask, dtype=bool)))


def layout_size(distances: torch.Tensor) -> float:
    """Mean over the pairs of keypoints of their reference distance (:func:`labelled_distances`), NaN when
    no pair has one: the size of the labelled layout that the collapse check compares against."""
    K = distances.shape[0]
    upper = distances[torch.triu(torch.ones(K, K, dtype=torch.bool), 1)]
    upper = upper[torch.isfinite(upper)]
    return float(upper.mean()) if len(upper) else float("nan")


def labelled_layout(dataset: DatasetLike, frame_ids: np.ndarray, chunk: int = 256) -> float:
    """The size of the layout triangulated from the labels (:func:`layout_size` of
    :func:`labelled_distances`)."""
    return layout_size(labelled_distances(dataset, frame_ids, chunk))


def labelled_distances(dataset: DatasetLike, frame_ids: np.ndarray, chunk: int = 256) -> torch.Tensor:
    """``(K, K)`` float64: for every pair of keypoints the median over the labelled frames of their distance,
    triangulated from the labels (NaN for a pair no frame has both of, and on the diagonal); the rigid layout
    that ``--layout-tol`` holds pseudo-labels to."""
    K = len(dataset.keypoints)
    rows = []
    for X, valid in _labelled_points(dataset, frame_ids, chunk):
        d = torch.cdist(torch.nan_to_num(X), torch.nan_to_num(X))
        pair = valid[:, :, None] & valid[:, None, :]
        rows.append(torch.where(pair, d, torch.full_like(d, float("nan"))))
    if not rows:
        return torch.full((K, K), float("nan"), dtype=torch.float64)
    out = torch.nanmedian(torch.cat(rows), dim=0).values
    out.fill_diagonal_(float("nan"))
    return out


def validate(net: nn.Module, meta: DetectorMeta, store: FrameStore | None, device: torch.device,
             ref_layout: float, cfg: TrainConfig, step: int, writer=None) -> dict[str, Any]:
    """Predict the validation frames: metrics, collapse check, overlay image; returns a record."""
    record: dict[str, Any] = {"step": step}
    if store is None or len(store) == 0:
        return record
    net.eval()
    # the network as it is now, on the store's frames; the plain path: a frozen graph would be traced anew
    # at every validation
    detector = OnePassDetector(net, meta, device, fast=False)
    detector.check_frames = False  # a refining pass's crops: their principal points lie anywhere
    try:
        metrics, arrays = evaluate_store(detector, store, 16, meta.units, keep=1)
        X, valid = torch.from_numpy(arrays["X"]), torch.from_numpy(arrays["X_valid"])
        for m in ("rms_px", "rms_px_reproj", "median_mm", "rms_mm"):
            record[m] = metrics[m]
    except ValueError:  # no ground truth on this split: collapse check only
        preds = list(detect_store(detector, store, 16, keep_heatmaps=True))
        X = torch.cat([p.X for _, p in preds])
        valid = torch.cat([p.valid for _, p in preds])
        first = preds[0][1]
        assert first.probs is not None
        arrays = {"images": preds[0][0].images[:1].numpy(), "probs": first.probs[:1].numpy(),
                  "pred_uv": first.uv[:1].numpy(), "gt_uv": None, "gt_mask": None}
    layout = mean_pairwise_distance(X, valid)
    ratio = layout / ref_layout if ref_layout and math.isfinite(ref_layout) else float("nan")
    record["layout_ratio"] = ratio
    record["triangulated"] = float(valid.float().mean())
    shown = ", ".join(f"{k} {v:.3g}" for k, v in record.items() if k != "step" and v is not None)
    log.info("step %d validation: %s", step, shown)
    # A network that has not learnt yet also puts every keypoint at the image centre; warn only once the
    # self-supervised term, which can lock such a state in, is on.
    threshold = cfg.monitoring.collapse_fraction
    if math.isfinite(ratio) and ratio < threshold and cfg.alpha_at(step - 1) > 0:
        log.warning("step %d: possible collapse: triangulated keypoints are %.0f%% as far apart as in the "
                    "labelled layout (threshold %.0f%%)", step, 100 * ratio, 100 * threshold)
    if writer is not None:
        for k, v in record.items():
            if k != "step" and v is not None and math.isfinite(v):
                writer.add_scalar(f"val/{k}", v, step)
        gt = arrays["gt_uv"][0] if arrays.get("gt_uv") is not None else None
        gm = arrays["gt_mask"][0] if arrays.get("gt_mask") is not None else None
        img = draw_views(arrays["images"][0], arrays["probs"][0], arrays["pred_uv"][0], gt, gm, scale=2)
        writer.add_image("val/keypoints", img, step, dataformats="HWC")
        writer.flush()
    return record


def calibrate(net: nn.Module, meta: DetectorMeta, store: FrameStore | None,
              device: torch.device) -> dict[str, Any] | None:
    """The confidence map (:func:`s3k.readout.fit_confidence`, as a dict for ``meta.calibration``) of the
    network as it is on the validation frames ``store``: each view with a truth is right when its detection
    lies within ``CALIBRATION_SIGMAS`` target widths of it, in the network's input pixels. None, with a
    note, where the frames have no truth or too few views: the run's thresholds then compare the raw
    weight."""
    if store is None or len(store) == 0:
        log.log(NOTE, "no validation frames: the confidence is not calibrated (thresholds compare the raw "
                "weight)")
        return None
    net.eval()
    detector = OnePassDetector(net, dataclasses.replace(meta, calibration=None), device, fast=False)
    detector.check_frames = False  # a refining pass's crops: their principal points lie anywhere
    within = CALIBRATION_SIGMAS * meta.sigma
    try:
        _, arrays = evaluate_store(detector, store, 16, meta.units)
    except ValueError:  # no labels or 3D points on the validation split
        fitted = None
    else:
        weights, _, right = scored_views(arrays, within)
        fitted = fit_confidence(weights, right, within)
    if fitted is None:
        log.log(NOTE, "the validation frames have too few views with a truth to calibrate the confidence "
                "(thresholds compare the raw weight); label them or give --val-split test frames with labels")
        return None
    steps = ", ".join(f"{w:.3g}->{c:.2f}" for w, c in zip(fitted.weights, fitted.confidence))
    log.info("confidence calibrated on %d views of %d validation frames (right: within %.3g px): weight->"
             "confidence %s", fitted.views, len(store), within, steps)
    return fitted.to_dict()
