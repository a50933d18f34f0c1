"""The report of ``s3k evaluate --report``: metrics.json, error histograms, per-keypoint errors and
overlays of the views with their heatmaps."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from s3k.base.draw import draw_views
from s3k.base.metrics import format_metric

__all__ = ["write_report"]


def write_report(out_dir: str | Path, metrics: dict[str, Any], arrays: dict[str, Any], unit_mm: float,
                 title: str = "", edges: np.ndarray | None = None) -> list[Path]:
    """Write metrics.json, plots (error histograms, per-keypoint errors) and view overlays to ``out_dir``
    (``edges``: the skeleton's ``(E, 2)`` keypoint indices, drawn between the detections)."""
    import matplotlib

    matplotlib.use("Agg")
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
    axes[0].set_title(f"rms_px {format_metric(metrics['rms_px'])}")
    if arrays.get("X_gt") is not None:
        e3 = np.linalg.norm(arrays["X"] - arrays["X_gt"], axis=-1) * unit_mm
        sel = arrays["X_valid"] & arrays["X_gt_mask"]
        axes[1].hist(e3[sel], bins=50, color="tab:orange")
        against_labels = metrics.get("reference_3d") == "triangulated labels"
        axes[1].set_xlabel("3D distance to the triangulated labels (mm)" if against_labels
                           else "3D error (mm)")
        axes[1].set_title(f"median_mm {format_metric(metrics['median_mm'])}, "
                          f"rms_mm {format_metric(metrics['rms_mm'])}")
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
    labels_3d = metrics.get("reference_3d") == "triangulated labels"
    axes[1].set_ylabel("mm, to the triangulated labels" if labels_3d else "mm")
    axes[1].legend()
    fig.suptitle(f"per-keypoint errors {title}")
    fig.tight_layout()
    fig.savefig(out / "per_keypoint.png", dpi=100)
    plt.close(fig)
    written.append(out / "per_keypoint.png")

    if arrays.get("images") is not None:
        for i in range(len(arrays["images"])):
            img = draw_views(arrays["images"][i], arrays["probs"][i], arrays["pred_uv"][i],
                             arrays["gt_uv"][i], arrays["gt_mask"][i], edges=edges)
            path = out / f"overlay_{i:02d}_frame_{arrays['frame_ids'][i]}.png"
            cv2.imwrite(str(path), img[..., ::-1])
            written.append(path)
    return written
