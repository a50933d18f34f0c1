"""Decoding one image file: :func:`decode_image` (sizes read from headers first, :func:`header_size`), and
:class:`ImageReadError`, which names a file (or video
frame) that cannot be read. Image sources (:mod:`s3k.data.sources`) and video I/O (:mod:`s3k.data.video`)
both decode through it.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from s3k.base.errors import UserError
from s3k.data.problems import Problem

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


MAX_PIXELS = 1 << 28
"""The most pixels an image may have (16384 x 16384): a larger one is refused before it is decoded."""

_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def header_size(path: str | Path) -> tuple[int, int] | None:
    """``(W, H)`` of a PNG or JPEG file from its header, without decoding (a few bytes read); None for
    another format or a header that cannot be read."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            if head[:2] != b"\xff\xd8":
                return None
            f.seek(2)
            for _ in range(10_000):  # markers up to the frame header
                marker = f.read(2)
                if len(marker) < 2 or marker[0] != 0xFF:
                    return None
                if marker[1] in (0x01, *range(0xD0, 0xD8)):  # no length
                    continue
                length = int.from_bytes(f.read(2), "big")
                if marker[1] in _JPEG_SOF:
                    seg = f.read(5)
                    return (int.from_bytes(seg[3:5], "big"), int.from_bytes(seg[1:3], "big")) \
                        if len(seg) == 5 else None
                if length < 2:
                    return None
                f.seek(length - 2, os.SEEK_CUR)
    except OSError:
        return None
    return None


_READ_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)
"""OpenCV 4.10's flag that decodes straight to RGB, the same pixels as decoding to BGR and swapping."""


def decode_image(path: str | Path, name: str | None = None) -> np.ndarray:
    """Decode an image file to ``uint8 (H, W, 3)`` RGB; one larger than :data:`MAX_PIXELS` (by its header)
    is refused before it is decoded.

    Raises:
        ImageReadError: naming the file (as ``name``, e.g. its path in the dataset, when given).
    """
    name = str(path) if name is None else name
    size = header_size(path)
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise ImageReadError(name, f"image is {size[0]}x{size[1]}, more pixels than s3k reads ({MAX_PIXELS})")
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise ImageReadError(name, f"cannot read ({exc.strerror or exc})") from exc
    flag = cv2.IMREAD_COLOR if _READ_RGB is None else _READ_RGB
    image = cv2.imdecode(data, flag) if data.size else None
    if image is None:
        raise ImageReadError(name, "cannot decode as an image (truncated or not an image file)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if _READ_RGB is None else image
