"""Image sequences: a camera's frames as one image file per frame, where a video would otherwise be.

A sequence is given as a folder (every ``.png``, ``.jpg``, ``.jpeg``, ``.bmp``, ``.tif`` or ``.tiff`` file in
it), a glob pattern (``cam0/*.jpg``) or a printf pattern (``cam0/img_%05d.png``, numbered from 0 or from 1
without gaps). Files are ordered by name with numbers compared as numbers (``img2`` before ``img10``), and
frame ``i`` is the ``i``-th file, as frame ``i`` of a video is its ``i``-th frame.

:mod:`s3k.data.video`'s functions accept a sequence wherever they accept a video file.
"""

from __future__ import annotations

import glob
import re
from pathlib import Path

from s3k.base.errors import UserError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
_PRINTF = re.compile(r"%0?(\d*)d")
_NUMBERS = re.compile(r"(\d+)")


def _natural_key(path: Path) -> list:
    return [int(p) if p.isdigit() else p.lower() for p in _NUMBERS.split(path.name)]


def is_sequence(path: str | Path) -> bool:
    """True when ``path`` names an image sequence (a folder, a glob or a printf pattern), not a file."""
    text = str(path)
    if Path(text).is_dir():
        return True
    if Path(text).is_file():
        return False
    return bool(_PRINTF.search(text)) or any(ch in text for ch in "*?[")


def sequence_files(path: str | Path) -> list[Path]:
    """The image files of a sequence, in frame order.

    Raises:
        UserError: a folder or pattern that matches no image file (naming it).
    """
    text = str(path)
    if Path(text).is_dir():
        files = [p for p in Path(text).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
        if not files:
            raise UserError(f"{text}: folder has no image files ({', '.join(IMAGE_SUFFIXES)})")
        return sorted(files, key=_natural_key)
    if _PRINTF.search(text):
        def name(i: int) -> Path:
            return Path(_PRINTF.sub(lambda m: f"{i:0{m.group(1) or 0}d}", text))

        files = []
        for start in (0, 1):
            i = start
            while name(i).is_file():
                files.append(name(i))
                i += 1
            if files:
                return files
        raise UserError(f"{text}: no image file matches the pattern (numbered from 0 or 1)")
    files = [Path(p) for p in glob.glob(text) if Path(p).is_file()]
    if not files:
        raise UserError(f"{text}: no image file matches the pattern")
    return sorted(files, key=_natural_key)
