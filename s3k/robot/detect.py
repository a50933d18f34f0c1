"""3D keypoints for a controller: a trained s3k run (one pass or two) on rendered views.

A :class:`RunDetector` is a callable ``(images (C, H, W, 3) uint8, K (C, 3, 3), R (C, 3, 3), t (C, 3)) ->
(X (N, 3), valid (N,))`` for the keypoint names it was asked for, in that order: the run's
:class:`s3k.detector.Detector` on the views at their rendered size, exactly as ``s3k predict``, ``s3k track``
and ``s3k stream`` read them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from s3k.base.choices import Device
from s3k.base.errors import UserError
from s3k.detector import Detector, TwoPassDetector
from s3k.geometry import Cameras


class RunDetector:
    """The detector of run ``run_dir`` giving the 3D points of ``keypoints`` (names the run must know).

    Args:
        run_dir: a trained s3k run folder (one pass or ``--two-pass``).
        keypoints: the names wanted, in the order wanted.
        device: torch device.
    """

    def __init__(self, run_dir: str | Path, keypoints: Sequence[str], device: Device = "cpu"):
        self.detector = Detector.load(run_dir, device)
        have = self.detector.keypoints
        missing = [k for k in keypoints if k not in have]
        if missing:
            raise UserError(f"run {run_dir}: its detector has no keypoint {', '.join(map(repr, missing))} "
                            f"(it has {', '.join(have)})", hint="give a run trained on the scene's keypoints")
        self.index = [have.index(k) for k in keypoints]
        self.device = torch.device(device)

    @property
    def image_size(self) -> tuple[int, int]:
        """The size ``(W, H)`` to render at: a one-pass detector's input (no resampling needed); for a
        two-pass one, the size of the images it was trained on, since its refining pass cuts its crops from
        the rendered views."""
        if isinstance(self.detector, TwoPassDetector) and self.detector.coarse.meta.source_image_size:
            W, H = self.detector.coarse.meta.source_image_size
            return int(W), int(H)
        return self.detector.input_size

    def __call__(self, images: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """3D keypoints ``X (N, 3)`` (NaN where not triangulated) and ``valid (N,)`` of one multi-view
        frame."""
        cams = Cameras.from_numpy(K, None, R, t, dtype=torch.float64)
        out = self.detector(images, cams)
        X = out.X[0].numpy()[self.index]
        valid = out.valid[0].numpy()[self.index]
        return np.where(valid[:, None], X, np.nan), valid
