"""The pixel conventions of the formats s3k reads and writes, and the conversion at their boundary.

s3k's convention is OpenCV's: pixel ``(0, 0)`` is the *centre* of the top-left pixel, and an image of
``W x H`` pixels covers ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` (``"centre"``). Other tools put ``(0, 0)`` at
the top-left *corner* of the image, so that the top-left pixel's centre is ``(0.5, 0.5)`` (``"corner"``): the
same point then has coordinates 0.5 px larger in x and y than in s3k. A reader converts its format's
coordinates into s3k's with :func:`to_s3k` (labels) or :func:`intrinsics_to_s3k` (a calibration's ``K``), a
writer of a format of the other convention with :func:`from_s3k` (every format s3k writes is of its own).
:data:`FORMATS` says which convention each format uses and where that is said; ``s3k import --label-pixels``
and ``--calibration-pixels`` declare a file that does not follow its format's (:func:`relabel`,
:func:`rig_to_s3k`). docs/dataset-format.md and docs/calibration.md show it as a table.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Literal

import numpy as np
import torch

from s3k.data.rig import Rig
from s3k.geometry import Cameras

Convention = Literal["centre", "corner"]

# format -> (its convention, what says so). "centre" where the format's documentation does not say and the
# tool's own pipeline is OpenCV's; the tables in the docs name those cases.
FORMATS: dict[str, tuple[Convention, str]] = {
    "sleap": ("centre", "SLEAP's midpoint coordinates (talmolab/sleap#296; its GUI draws a frame shifted by "
                        "-0.5 px; sleap-io shifts points of projects older than format 1.1 by -0.5 on read)"),
    "deeplabcut": ("centre", "DeepLabCut's labelling GUIs draw frames with matplotlib's imshow and napari, "
                             "whose pixel centres lie at integer coordinates"),
    "lightning-pose": ("centre", "DeepLabCut's CSV layout and convention"),
    "nwb": ("centre", "not stated by ndx-pose; s3k writes its own convention and says so in the file"),
    "openpose": ("corner", "OpenPose's peak finder adds half a pixel to every peak ('+0.5 to both to keep "
                           "Matlab format', nmsBase)"),
    "mmpose": ("centre", "not stated by MMPose"),
    "deepfly3d": ("centre", "not stated; its pixels are its fractions times the image size, and its "
                            "calibration is fitted to the same pixels"),
    "anipose": ("centre", "aniposelib finds board corners with OpenCV and calibrates with OpenCV, no offset"),
    "opencv": ("centre", "OpenCV (opencv/opencv#10130)"),
    "qualisys": ("centre", "not stated; read as Pose2Sim converts it"),
}


def shift(convention: Convention) -> float:
    """How much larger a point's coordinates are in ``convention`` than in s3k's (0 or 0.5 px)."""
    if convention not in ("centre", "corner"):
        raise ValueError(f"unknown pixel convention {convention!r}; use 'centre' or 'corner'")
    return 0.5 if convention == "corner" else 0.0


def to_s3k(uv: np.ndarray, convention: Convention) -> np.ndarray:
    """``(..., 2)`` pixels of ``convention`` -> s3k's (NaN stays NaN)."""
    return np.asarray(uv, dtype=np.float64) - shift(convention)


def from_s3k(uv: np.ndarray, convention: Convention) -> np.ndarray:
    """``(..., 2)`` s3k pixels -> ``convention``'s."""
    return np.asarray(uv, dtype=np.float64) + shift(convention)


def intrinsics_to_s3k(K: np.ndarray, convention: Convention) -> np.ndarray:
    """``(..., 3, 3)`` intrinsics projecting into ``convention``'s pixels -> into s3k's (``K' = M K`` with
    ``M`` the shift, so that skew and a general last row stay exact)."""
    M = np.eye(3)
    M[:2, 2] = -shift(convention)
    return M @ np.asarray(K, dtype=np.float64)


def rig_to_s3k(rig: Rig, convention: Convention | None) -> Rig:
    """A calibration read as s3k's pixels, when its file projects into ``convention``'s (None: as read)."""
    if convention is None or not shift(convention):
        return rig
    a = rig.cameras.numpy()
    cams = Cameras.from_numpy(intrinsics_to_s3k(a["K"], convention), a["dist"], a["R"], a["t"],
                              dtype=torch.float64)
    return replace(rig, cameras=cams)


def relabel(uv: np.ndarray, read_as: Convention, actual: Convention) -> np.ndarray:
    """Labels converted into s3k's pixels as if in ``read_as``'s convention, converted as ``actual``'s."""
    return np.asarray(uv, dtype=np.float64) + shift(read_as) - shift(actual)
