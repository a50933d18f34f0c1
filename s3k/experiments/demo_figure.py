"""The picture of ``s3k demo``'s report (``DIR/report/demo.png``): what a person reads at a glance.

Top: test frames of every camera, each view zoomed on the object, with the true keypoints (open circles) and
where each model placed them (S3K: crosses; labels only: plus signs), one colour per keypoint. Bottom left:
the distribution of both models' 3D errors over every test keypoint (log scale, the 5 and 10 mm marks).
Bottom right: the comparison table.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from s3k.base.draw import keypoint_colours
from s3k.detector import Detector
from s3k.geometry import project

__all__ = ["MARKERS", "demo_figure", "frame_detections"]

#: How each model's detections are drawn (matplotlib marker, size).
MARKERS = {"S3K": ("x", 70), "labels only": ("+", 90)}


def frame_detections(run: str | Path, data: Any, frame_ids: Sequence[int]) -> np.ndarray:
    """The detections ``(B, C, K, 2)`` of the run's detector in the frames' own pixels (NaN where none)."""

    detector = Detector.load(run, "cpu")
    images = torch.from_numpy(np.ascontiguousarray(data.images(frame_ids)))
    return detector(images, data.calibration(frame_ids)).cpu().uv.numpy().astype(np.float64)


def _zoom(true_uv: np.ndarray, size: tuple[int, int], margin: float = 0.6) -> tuple[float, ...]:
    """A square box around one view's true keypoints (``(K, 2)``), ``margin`` of their extent added."""
    W, H = size
    ok = np.isfinite(true_uv).all(-1)
    if not ok.any():
        return 0.0, float(W), 0.0, float(H)
    lo, hi = true_uv[ok].min(0), true_uv[ok].max(0)
    side = max(float((hi - lo).max()) * (1 + 2 * margin), 0.15 * max(W, H))
    cx, cy = (lo + hi) / 2
    return cx - side / 2, cx + side / 2, cy - side / 2, cy + side / 2


def demo_figure(out: str | Path, data: Any, frame_ids: Sequence[int], detections: Mapping[str, np.ndarray],
                errors_mm: Mapping[str, np.ndarray], table: Sequence[Sequence[str]], title: str = "") -> Path:
    """Draw the demo's picture (module docstring) to ``out``.

    Args:
        out: PNG file.
        data: the dataset (:class:`s3k.data.Dataset`) the test frames come from, with ground truth.
        frame_ids: the test frames shown.
        detections: ``{model: (B, C, K, 2)}`` detections in the frames' pixels (:func:`frame_detections`).
        errors_mm: ``{model: (N,)}`` 3D errors of every test keypoint, mm.
        table: rows of the comparison table, the first one its header.
        title: the figure's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    images = data.images(frame_ids)  # (B, C, H, W, 3)
    B, C = images.shape[:2]
    X, mask = data.points3d(frame_ids)
    cams = data.calibration(frame_ids, np.float64)
    projected, _ = project(cams, torch.as_tensor(X, dtype=torch.float64)[:, None])
    true_uv = np.where(mask[:, None, :, None], projected.numpy(), np.nan)
    colours = [(r / 255, g / 255, b / 255) for r, g, b in keypoint_colours(len(data.keypoints))]
    fig = plt.figure(figsize=(2.6 * C, 2.6 * B + 3.6))
    grid = fig.add_gridspec(B + 1, C, height_ratios=[1] * B + [1.35])
    for b in range(B):
        for c in range(C):
            ax = fig.add_subplot(grid[b, c])
            ax.imshow(images[b, c])
            x0, x1, y0, y1 = _zoom(true_uv[b, c], data.image_size)
            ax.set_xlim(x0, x1)
            ax.set_ylim(y1, y0)
            ax.set_xticks([])
            ax.set_yticks([])
            for k, colour in enumerate(colours):
                u, v = true_uv[b, c, k]
                ax.scatter([u], [v], s=120, facecolors="none", edgecolors=[colour], linewidths=1.5)
                for name, uv in detections.items():
                    marker, size = MARKERS.get(name, ("o", 30))
                    ax.scatter([uv[b, c, k, 0]], [uv[b, c, k, 1]], s=size, marker=marker, color=colour,
                               linewidths=1.5)
            if b == 0:
                ax.set_title(data.cameras[c], fontsize=9)
            if c == 0:
                ax.set_ylabel(f"test frame {int(frame_ids[b])}", fontsize=9)
    half = max(C // 2, 1)
    ax = fig.add_subplot(grid[B, :half])
    bins = np.logspace(-1, 3, 41).tolist()
    for name, err in errors_mm.items():
        err = np.clip(np.asarray(err, dtype=float), bins[0], bins[-1])
        ax.hist(err, bins=bins, histtype="step", linewidth=1.8, label=f"{name} ({len(err)} keypoints)")
    for mark in (5, 10):
        ax.axvline(mark, color="grey", linestyle=":", linewidth=1)
    ax.set_xscale("log")
    ax.set_xlabel("3D error per test keypoint (mm)")
    ax.set_ylabel("keypoints")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(grid[B, half:])
    ax.axis("off")
    shown = ax.table(cellText=[list(r) for r in table[1:]], colLabels=list(table[0]), loc="center",
                     cellLoc="center")
    shown.auto_set_font_size(False)
    shown.set_fontsize(9)
    shown.scale(1.0, 1.6)
    drawn = {"x": "crosses", "+": "plus signs"}
    legend = "circles: truth; " + "; ".join(f"{m}: {drawn.get(MARKERS.get(m, ('o', 0))[0], 'dots')}"
                                              for m in detections)
    fig.suptitle(f"{title}\n{legend}" if title else legend, fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
