"""The labelling app's check of labels that disagree over the whole dataset (``GET /api/disagreements``): each
camera's median residual over the frames with labels, and the frames with a label more than
:data:`~s3k.label.solve.DISAGREE_PX` from where the other views put it (docs/tracks.md, "Labels that
disagree"); the rules themselves are :mod:`s3k.label.solve`'s."""

from __future__ import annotations

from typing import Any

import numpy as np

from s3k.data import Dataset
from s3k.label.solve import DISAGREE_PX, GREEN_FACTOR, GREEN_FLOOR_PX, label_residuals
from s3k.label.store import LabelStore

__all__ = ["LabelAgreement", "dataset_agreement"]


class LabelAgreement:
    """The labels' agreement over a dataset's frames with a keypoint labelled in two views or more
    (``LabelAgreement(dataset, store)()``: :func:`dataset_agreement` of the store's labels as they are now).
    Each frame's :func:`~s3k.label.solve.label_residuals` are kept and computed again only for the frames
    whose labels changed (thousands of labelled frames take about a second at once)."""

    def __init__(self, dataset: Dataset, store: LabelStore) -> None:
        self.dataset, self.store = dataset, store
        self._frames: dict[int, tuple[bytes, np.ndarray, np.ndarray]] = {}  # frame -> (labels, res., offset)

    def __call__(self) -> dict[str, Any]:
        self.store.refresh()
        s = self.store
        mask = s.present & s.visible
        rows = np.flatnonzero((mask.sum(axis=1) >= 2).any(axis=-1))
        ids = [int(f) for f in s.frames.ids[rows]]
        residual, offset = self.residuals(ids, s.uv[rows], mask[rows])
        return dataset_agreement(residual, offset, ids, s.frames.splits[rows], self.dataset.cameras,
                                 self.dataset.keypoints)

    def residuals(self, frames: list[int], uv: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(residual, offset)``, each ``(B, C, K)``, of ``frames`` with labels ``uv (B, C, K, 2)``, ``mask
        (B, C, K)``."""
        keys = [np.where(mask[i, ..., None], uv[i], 0.0).tobytes() + mask[i].tobytes()
                for i in range(len(frames))]
        stale = [i for i, f in enumerate(frames) if self._frames.get(f, (b"",))[0] != keys[i]]
        if stale:
            cams = self.dataset.calibration([frames[i] for i in stale], np.float64)
            residual, offset = label_residuals(cams, uv[stale], mask[stale])
            for j, i in enumerate(stale):
                self._frames[frames[i]] = (keys[i], residual[j], offset[j])
        if not frames:
            return np.full(mask.shape, np.nan), np.full(mask.shape, np.nan)
        kept = [self._frames[f] for f in frames]
        return np.stack([k[1] for k in kept]), np.stack([k[2] for k in kept])


def dataset_agreement(residual: np.ndarray, offset: np.ndarray, frames: list[int], splits: np.ndarray,
                      cameras: list[str], keypoints: list[str]) -> dict[str, Any]:
    """The labels' agreement over a dataset's ``frames`` (their splits ``splits``), from their
    :func:`~s3k.label.solve.label_residuals` ``residual`` and ``offset`` ``(B, C, K)``.

    Returns:
        ``{"threshold_px", "green_factor", "green_floor_px", "cameras": {camera: {"median_px": px | None,
        "labels": n}}, "frames": [{"frame", "split", "worst_px", "labels": [{"camera", "keypoint",
        "offset_px", "residual_px"}]}]}``: per camera the median residual of its labels and their count; the
        frames with a label more than :data:`DISAGREE_PX` from where the other views put it, worst first,
        each with those labels, worst first.
    """
    medians = {}
    for c, cam in enumerate(cameras):
        r = residual[:, c][np.isfinite(residual[:, c])]
        medians[cam] = {"median_px": float(np.median(r)) if r.size else None, "labels": int(r.size)}
    listed = []
    for i in np.flatnonzero((np.nan_to_num(offset, nan=0.0) > DISAGREE_PX).any(axis=(1, 2))):
        far = np.argwhere(np.nan_to_num(offset[i], nan=0.0) > DISAGREE_PX)
        labels = sorted(({"camera": cameras[c], "keypoint": keypoints[k], "offset_px": float(offset[i, c, k]),
                          "residual_px": float(residual[i, c, k])} for c, k in far),
                        key=lambda x: -x["offset_px"])
        listed.append({"frame": int(frames[i]), "split": str(splits[i]), "worst_px": labels[0]["offset_px"],
                       "labels": labels})
    listed.sort(key=lambda x: -x["worst_px"])
    return {"threshold_px": DISAGREE_PX, "green_factor": GREEN_FACTOR, "green_floor_px": GREEN_FLOOR_PX,
            "cameras": medians, "frames": listed}
