"""Which labels give the supervised loss a target: the check behind ``s3k validate``'s UNUSABLE and the
trainer's refusal to start without a target.

A labelled keypoint of a frame is *usable* when it is labelled (visible, inside the image) in at least two
cameras, its unit-weight triangulation is valid (``geometry.triangulate_labels``: enough weight, rays not
near-parallel), and the triangulated point lies in front of at least one camera and projects inside that
camera's image. That is what the supervised loss needs to render at least one Gaussian target; a dataset
without any usable label trains on a loss that is exactly zero.
"""

from __future__ import annotations

import numpy as np
import torch

from s3k.data.protocol import DatasetLike
from s3k.geometry import project, triangulate_labels

# Camera-frame depth at or below which a point counts as behind the camera (as in the supervised loss).
MIN_DEPTH = 1e-6


def usable_labels(dataset: DatasetLike, split: str = "labelled", chunk: int = 1024) -> np.ndarray:
    """``(N, K)`` bool: keypoint ``k`` of frame ``n`` of ``split`` (in ``dataset.frames(split)`` order) gives
    a supervised target (see the module docstring).

    Args:
        dataset: an opened dataset (any image size: the test scales with the images).
        split: the frames to check.
        chunk: frames triangulated at a time (bounds memory).
    """
    ids = dataset.frames(split)
    out = np.zeros((len(ids), len(dataset.keypoints)), dtype=bool)
    W, H = dataset.image_size
    for start in range(0, len(ids), chunk):
        part = ids[start : start + chunk]
        uv_np, mask_np = dataset.labels(part)
        cams = dataset.calibration(part, dtype=np.float64)  # (B, C)
        X, valid = triangulate_labels(cams, torch.from_numpy(uv_np), torch.from_numpy(mask_np))  # (B, K)
        proj, depth = project(cams, X[:, None])  # (B, C, K, 2), (B, C, K)
        u, v = proj[..., 0], proj[..., 1]
        seen = (depth > MIN_DEPTH) & (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
        out[start : start + len(part)] = (valid & seen.any(dim=1)).numpy()
    return out


def usable_label_count(dataset: DatasetLike, split: str = "labelled") -> int:
    """Number of usable labelled keypoints (frame, keypoint pairs) in ``split``; 0 means nothing to train
    on."""
    return int(usable_labels(dataset, split).sum())
