"""3D keypoints for a controller: a trained s3k run on rendered views, through s3k's one read-out.

A :class:`RunDetector` is a callable ``(images (C, H, W, 3) uint8, K (C, 3, 3), R (C, 3, 3), t (C, 3)) ->
(X (N, 3), valid (N,))`` for the keypoint names it was asked for, in that order. Images of another size than
the network's input are resized first with :func:`s3k.data.transforms.resize_crop` (``K' = M K``); the
detections go through :func:`s3k.predict.infer` (heatmap moments, confidence weights, weighted
triangulation), exactly as ``s3k predict`` and ``s3k track`` read them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from s3k.data.transforms import resize_crop
from s3k.errors import UserError
from s3k.frames import images_to_float
from s3k.geometry import Cameras
from s3k.predict import infer
from s3k.run import load_detector


class RunDetector:
    """The detector of run ``run_dir`` giving the 3D points of ``keypoints`` (names the run must know).

    Args:
        run_dir: a trained s3k run folder.
        keypoints: the names wanted, in the order wanted.
        device: torch device.
    """

    def __init__(self, run_dir: str | Path, keypoints: Sequence[str], device: str = "cpu"):
        self.model, self.meta = load_detector(run_dir, device=device)
        missing = [k for k in keypoints if k not in self.meta.keypoints]
        if missing:
            raise UserError(f"run {run_dir}: its detector has no keypoint {', '.join(map(repr, missing))} "
                            f"(it has {', '.join(self.meta.keypoints)})",
                            hint="give a run trained on the scene's keypoints")
        self.index = [self.meta.keypoints.index(k) for k in keypoints]
        self.device = torch.device(device)

    @property
    def image_size(self) -> tuple[int, int]:
        """The network's input ``(W, H)``: render at this size to skip the resize."""
        return (int(self.meta.image_size[0]), int(self.meta.image_size[1]))

    @torch.no_grad()
    def __call__(self, images: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """3D keypoints ``X (N, 3)`` (NaN where not triangulated) and ``valid (N,)`` of one multi-view
        frame."""
        W, H = self.image_size
        if images.shape[1:3] != (H, W):
            images, K = resize_crop(images, K, None, (W, H))
        cams = Cameras.from_numpy(K[None], None, R[None], t[None], dtype=torch.float32).to(self.device)
        x = images_to_float(torch.from_numpy(np.ascontiguousarray(images))[None], self.device)
        out = infer(self.model, self.meta, x, cams)
        X = out.X[0].double().cpu().numpy()[self.index]
        valid = out.valid[0].cpu().numpy()[self.index]
        return np.where(valid[:, None], X, np.nan), valid
