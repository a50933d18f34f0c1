"""A calibration file's content: :class:`Rig` (camera names, image sizes, world units, the file's metadata and
the cameras as one :class:`s3k.geometry.Cameras`).

Readers of calibration formats (:mod:`s3k.data.formats.anipose`) return a ``Rig``; tracking, importing and
recalibration take one. The cameras are the one camera type of s3k, in float64 (``rig.cameras.numpy()``
gives NumPy arrays for OpenCV).
"""

from __future__ import annotations

import unicodedata
from dataclasses import dataclass, field

import numpy as np
import torch

from s3k.base.errors import UserError
from s3k.data.cameras import camera_defects
from s3k.geometry import Cameras
from s3k.geometry.warp import resize_crop


def check_camera_name(name: object, where: str) -> str:
    """``name`` if it is a camera name s3k accepts, else a one-line error naming ``where`` (``"--videos"``, a
    file and its section): a camera's name becomes a file name (``s3k track --overlay DIR`` writes
    ``DIR/<camera>.mp4``) and a line of a TOML file, so it is a non-empty text without a path separator,
    without a control character (a newline, a tab) and other than ``.`` and ``..``."""
    if not isinstance(name, str) or not name:
        raise UserError(f"{where}: a camera's name must be a non-empty text, got {name!r}")
    bad = [c for c in name if c in "/\\" or unicodedata.category(c) in ("Cc", "Zl", "Zp")]
    if bad or name in (".", ".."):
        what = f"holds {bad[0]!r}" if bad else "is a folder's name"
        raise UserError(f"{where}: camera name {name!r} {what}; a camera's name is a file name (no path "
                        "separator, no control character, not . or ..)", hint="rename the camera")
    return name


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

    def checked(self, source: str | object) -> Rig:
        """This rig, after refusing (:class:`s3k.base.errors.UserError` naming ``source``, the camera and the
        field) a camera name that is not a file name (:func:`check_camera_name`), a value that is not
        finite, a singular ``K`` or an ``R`` that is not a rotation (a Rodrigues vector of 1e300, a scaled
        matrix)."""
        for name in self.names:
            check_camera_name(name, str(source))
        a = self.cameras.numpy()
        for name, defects in zip(self.names, camera_defects(a["K"], a["dist"], a["R"], a["t"])):
            if defects:
                what, message = defects[0]
                field = {"R": "rotation", "t": "translation", "K": "matrix", "dist": "distortions"}[what]
                raise UserError(f"{source}: camera {name}: {field} ({what}) {message}")
        return self

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

    def with_sizes(self, sizes: dict[str, tuple[int, int]]) -> Rig:
        """A copy where cameras whose image size the file does not give (size 0, e.g. JARVIS and DeepFly3D
        calibrations) take ``sizes[name]`` (their videos' sizes)."""
        size = self.size.copy()
        for c, name in enumerate(self.names):
            if (size[c] <= 0).any() and name in sizes:
                size[c] = sizes[name]
        return Rig(list(self.names), self.cameras, size, self.units, dict(self.metadata))

    def with_video_regions(self, regions: dict[str, tuple[float, float, float, float]]) -> Rig:
        """A copy whose camera ``name`` has the image that region ``(x0, y0, x1, y1)`` (pixel edge coordinates
        of the calibrated image) of its calibrated image becomes: size ``(x1 - x0, y1 - y0)`` and intrinsics
        ``K' = M K`` (:func:`s3k.geometry.warp.resize_crop`). A video of 1080 rows calibrated at 1088, the
        encoder's 8 rows of padding cut at the bottom, is region ``(0, 0, W, 1080)``; a region reaching
        outside the calibrated image declares padding added to the video.

        Raises:
            KeyError: an unknown camera. ValueError: a region of fractional or non-positive size.
        """
        arrays = self.cameras.numpy()
        size = self.size.copy()
        for name, box in regions.items():
            c = self.index(name)
            x0, y0, x1, y1 = (float(v) for v in box)
            w, h = x1 - x0, y1 - y0
            if w <= 0 or h <= 0 or w != int(w) or h != int(h):
                raise ValueError(f"camera {name!r}: region {box} must have a positive whole-pixel size")
            arrays["K"][c] = resize_crop(None, arrays["K"][c], (x0, y0, x1, y1), (int(w), int(h)))[1]
            size[c] = (int(w), int(h))
        cams = Cameras.from_numpy(arrays["K"], arrays["dist"], arrays["R"], arrays["t"], dtype=torch.float64)
        return Rig(list(self.names), cams, size, self.units, dict(self.metadata))
