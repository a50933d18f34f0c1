"""``s3k evaluate``: a trained detector's metrics (:mod:`s3k.base.metrics`) on a dataset split.

The run's :class:`s3k.detector.Detector` (one pass or two) reads every frame at the dataset's own resolution
with its cameras, as ``s3k predict`` and ``s3k track`` do. The 3D metrics compare its points with the
dataset's ground truth; the pixel metrics are in pixels of the image the (last) network saw: the resized
image of a one-pass detector, each frame's crop of a two-pass one (``rms_px_image`` gives the same error in
the dataset's own pixels).

The confidence is reported beside them (:func:`confidence_report`): the run's calibration distance and, on
the evaluated frames, a reliability table (bins of calibrated confidence against the share of their views
that lie within that distance of the truth; docs/method.md#confidence).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from s3k.base.choices import Device
from s3k.base.draw import edge_indices
from s3k.base.errors import UserError
from s3k.base.metrics import SUMMARY_METRICS, compute_metrics, keypoint_order, mm_per_unit
from s3k.data import Dataset
from s3k.data.frames import FrameStore
from s3k.data.sessions import distance_summary, label_distances
from s3k.detector import Detector, DetectorMeta, evaluate_store, scored_views
from s3k.inference.report import write_report
from s3k.readout import CALIBRATION_SIGMAS, reliability

__all__ = ["confidence_report", "evaluate_run", "evaluate_store", "format_confidence", "per_session"]


def evaluate_run(run_dir, data, split: str = "test", device: Device = "auto", batch_size: int = 16,
                 report: str | Path | None = None, overlays: int = 6) -> dict[str, Any]:
    """Load a run's detector (one pass or two), evaluate it on ``data``'s ``split`` and optionally write a
    report (:mod:`s3k.inference.report`); returns the metrics."""
    detector, ds, metrics, arrays = detect_split(run_dir, data, split, device, batch_size,
                                                 keep=overlays if report else 0)
    metrics["split"] = split
    metrics["image_size"] = list(detector.meta.image_size)
    metrics["label_distance"], metrics["sessions"] = per_session(ds, arrays, detector.keypoints)
    metrics["confidence"] = confidence_report(detector.meta, arrays)
    if report:
        edges = edge_indices(detector.meta.recorded_skeleton() or ds.skeleton, detector.keypoints)
        write_report(report, metrics, arrays, mm_per_unit(ds.units), title=f"{Path(run_dir).name} ({split})",
                     edges=edges)
    return metrics


def detect_split(run_dir, data, split: str = "test", device: Device = "auto", batch_size: int = 16,
                 keep: int = 0) -> tuple[Detector, Dataset, dict[str, Any], dict[str, Any]]:
    """A run's detector read over ``data``'s ``split``: ``(detector, dataset, metrics, arrays)`` as
    :func:`s3k.detector.evaluate_store` gives them (``keep`` frames' images kept for a report)."""
    detector = Detector.load(run_dir, device)
    ds = Dataset.open(data, cache="none")
    keypoint_order(detector.keypoints, ds.keypoints)  # refuse a mismatch before detecting anything
    ids = np.asarray(ds.frames(split))
    if len(ids) == 0:
        raise UserError(f"{data}: split {split!r} has no frames", hint="choose another --split")
    store = FrameStore(ds, ids, preload_mb=0, labels=True, points=True)
    metrics, arrays = evaluate_store(detector, store, batch_size, ds.units, keep=keep, label_reference=True)
    return detector, ds, metrics, arrays


def per_session(ds: Dataset, arrays: dict[str, Any], keypoints) -> tuple[dict, dict[str, dict[str, Any]]]:
    """How far the evaluated frames lie from the nearest labelled frame of their session (``{"median",
    "min"}`` in frames), and per session the metrics of :func:`s3k.base.metrics.compute_metrics` (the summary
    ones), its frame count and the same distances."""
    every = ds.frames()
    far = label_distances(ds.frame_times(every), ds.session_of(every), ds.split_of(every) == "labelled")
    ids = np.asarray(arrays["frame_ids"])
    rows = np.searchsorted(every, ids, sorter=np.argsort(every))
    distance = far[np.argsort(every)[rows]]
    sessions = ds.session_of(ids)
    out: dict[str, dict[str, Any]] = {}
    for name in ds.sessions:
        sel = sessions == name
        if not sel.any():
            continue
        part = {k: (v[sel] if isinstance(v, np.ndarray) and len(v) == len(ids) else None)
                for k, v in arrays.items()}
        metrics = compute_metrics(part["pred_uv"], part["reproj_uv"], part["gt_uv"], part["gt_mask"],
                                  part["X"], part["X_valid"], part["X_gt"], part["X_gt_mask"],
                                  mm_per_unit(ds.units), keypoints, ds.cameras)
        out[name] = {**{k: metrics[k] for k in SUMMARY_METRICS}, "n_frames": int(sel.sum()),
                     "label_distance": distance_summary(distance[sel])}
    return distance_summary(distance), out


def confidence_report(meta: DetectorMeta, arrays: dict[str, Any]) -> dict[str, Any]:
    """The confidence of :func:`s3k.detector.evaluate_store`'s ``arrays`` against their truth:
    ``{"calibrated", "within_px", "fitted_views", "views", "within", "bins"}``: whether the run holds a
    calibration, the distance that counts as right (network-input pixels: the calibration's, else
    ``CALIBRATION_SIGMAS`` target widths), the views it was fitted on, the views evaluated and the share of
    them right, and :func:`s3k.readout.reliability`'s table of calibrated confidence against that share."""
    fitted = meta.confidence_map
    within = fitted.within_px if fitted is not None else CALIBRATION_SIGMAS * meta.sigma
    _, confidence, right = scored_views(arrays, within)
    return {"calibrated": fitted is not None, "within_px": within,
            "fitted_views": fitted.views if fitted is not None else 0, "views": int(len(right)),
            "within": float(right.mean()) if len(right) else None, "bins": reliability(confidence, right)}


def format_confidence(report: dict[str, Any]) -> str:
    """:func:`confidence_report` as lines of text: the distance and the reliability table."""
    head = (f"confidence calibrated on {report['fitted_views']} validation views" if report["calibrated"] else
            "confidence not calibrated (a run trained before runs were calibrated): the raw weight")
    lines = [f"{head}; right: within {report['within_px']:.3g} network-input px of the truth",
             "confidence   views  mean confidence  share within"]
    for row in report["bins"]:
        mean = "-" if row["confidence"] is None else f"{row['confidence']:.2f}"
        share = "-" if row["within"] is None else f"{row['within']:.2f}"
        lines.append(f"{row['from']:.1f}-{row['to']:.1f}  {row['views']:>8d}  {mean:>15}  {share:>12}")
    return "\n".join(lines)
