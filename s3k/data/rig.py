"""A calibration file's content: :class:`Rig` (camera names, image sizes, world units, the file's metadata and
the cameras as one :class:`s3k.geometry.Cameras`).

Readers of calibration formats (:mod:`s3k.data.anipose`) return a ``Rig``; tracking, importing and
recalibration take one. The cameras are the one camera type of s3k, in float64 (``rig.cameras.numpy()``
gives NumPy arrays for OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from s3k.geometry import Cameras


@dataclass
class Rig:
    """A static rig in the OpenCV model, ``x_cam = R @ x_world + t``, at the calibrated image size.

    Attributes:
        names: camera names, ``C`` of them.
        cameras: ``Cameras (C,)`` float64, full-resolution intrinsics, translations in ``units``.
        size: ``(C, 2)`` int image size ``(W, H)`` in pixels.
        units: length unit of the world frame (``"mm"``, ``"m"``, ``"board squares"``, ``"unknown"``...).
        metadata: the file's own extra fields (anipose's board description), kept for writing back.
    """

    names: list[str]
    cameras: Cameras
    size: np.ndarray
    units: str = "unknown"
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if tuple(self.cameras.shape) != (len(self.names),):
            raise ValueError(f"Rig: cameras {tuple(self.cameras.shape)} for {len(self.names)} names")
        self.cameras = self.cameras.to(dtype=torch.float64)
        self.size = np.asarray(self.size, dtype=np.int64).reshape(len(self.names), 2)

    def index(self, name: str) -> int:
        """Position of camera ``name`` (``KeyError`` naming it and the cameras known)."""
        if name not in self.names:
            raise KeyError(f"camera {name!r} is not in the calibration (it has {', '.join(self.names)})")
        return self.names.index(name)

    def select(self, names: list[str]) -> Rig:
        """The cameras ``names``, in that order (``KeyError`` naming the missing camera and those known)."""
        idx = torch.tensor([self.index(name) for name in names], dtype=torch.long)
        return Rig(list(names), self.cameras[idx], self.size[idx.numpy()], self.units, dict(self.metadata))

    def replace_camera(self, name: str, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray) -> Rig:
        """A copy with camera ``name`` set to ``K (3, 3)``, ``dist (5,)``, ``R (3, 3)``, ``t (3,)``."""
        c = self.index(name)
        arrays = self.cameras.numpy()
        for key, value in (("K", K), ("dist", dist), ("R", R), ("t", t)):
            arrays[key][c] = np.asarray(value, dtype=np.float64).reshape(arrays[key][c].shape)
        cams = Cameras.from_numpy(arrays["K"], arrays["dist"], arrays["R"], arrays["t"], dtype=torch.float64)
        return Rig(list(self.names), cams, self.size.copy(), self.units, dict(self.metadata))
