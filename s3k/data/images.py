"""Decoding one image file: :func:`decode_image`, and :class:`ImageReadError`, which names a file (or video
frame) that cannot be read. Image sources (:mod:`s3k.data.sources`) and video I/O (:mod:`s3k.data.video`)
both decode through it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from s3k.data.problems import Problem
from s3k.errors import UserError

# OpenCV's decoders print their own WARN/ERROR lines (and libpng's) for a corrupt file; s3k reports each
# unreadable image once, naming the file, so the decoder's lines would only repeat it without the name.
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


class ImageReadError(UserError):
    """An image (or video frame) that cannot be read or decoded; names the file and, when known, the frame
    and camera."""

    def __init__(self, file: str, reason: str, frame: int | None = None, camera: str | None = None) -> None:
        self.file, self.reason, self.frame, self.camera = file, reason, frame, camera
        super().__init__(str(self.problem()))

    def problem(self) -> Problem:
        return Problem("error", self.file, "image", self.reason, frame=self.frame, camera=self.camera)


def decode_image(path: str | Path, name: str | None = None) -> np.ndarray:
    """Decode an image file to ``uint8 (H, W, 3)`` RGB.

    Raises:
        ImageReadError: naming the file (as ``name``, e.g. its path in the dataset, when given).
    """
    name = str(path) if name is None else name
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise ImageReadError(name, f"cannot read ({exc.strerror or exc})") from exc
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise ImageReadError(name, "cannot decode as an image (truncated or not an image file)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
