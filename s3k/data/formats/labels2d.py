"""2D labels of one camera as the importers return them: :class:`LabelTable`, and frame numbers from image
file names (:func:`frame_id_from_path`).

Pixels are s3k's (0, 0 the centre of the top-left pixel): each reader converts its format's convention
(:mod:`s3k.data.formats.pixels`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from s3k.base.errors import UserError


@dataclass
class LabelTable:
    """2D keypoints of one camera.

    Attributes:
        keypoints: ``K`` names.
        frame_ids: ``(F,)`` int64 video frame indices, increasing.
        uv: ``(F, K, 2)`` float64 pixels; NaN where unlabelled.
        source: the file it came from (for messages).
        unseen: keypoints the format's documented rule says this camera cannot see (left unlabelled without
            a warning of their own: :func:`coverage_warnings`).
        skeleton: edges between keypoints that the source gives (``[]`` where it gives none), and
            ``skeleton_source`` the file they came from.
    """

    keypoints: list[str]
    frame_ids: np.ndarray
    uv: np.ndarray
    source: str = ""
    unseen: list[str] = field(default_factory=list)
    skeleton: list[tuple[str, str]] = field(default_factory=list)
    skeleton_source: str = ""

    def dense(self, num_frames: int, keypoints: list[str] | None = None) -> np.ndarray:
        """``(num_frames, K', 2)`` indexed by frame id (NaN where absent), keypoints in the given order."""
        keypoints = self.keypoints if keypoints is None else keypoints
        order = []
        for name in keypoints:
            if name not in self.keypoints:
                raise UserError(f"{self.source}: no keypoint {name!r} (it has {', '.join(self.keypoints)})")
            order.append(self.keypoints.index(name))
        out = np.full((num_frames, len(keypoints), 2), np.nan)
        keep = self.frame_ids < num_frames
        out[self.frame_ids[keep]] = self.uv[keep][:, order]
        return out


def unique_edges(edges: Iterable[Sequence[str]]) -> list[tuple[str, str]]:
    """``edges`` as ``(a, b)`` tuples, each undirected edge once (the first seen), self-loops dropped."""
    out: list[tuple[str, str]] = []
    seen: set[frozenset[str]] = set()
    for a, b in edges:
        key = frozenset((str(a), str(b)))
        if len(key) == 2 and key not in seen:
            seen.add(key)
            out.append((str(a), str(b)))
    return out


_DIGITS = re.compile(r"(\d+)")


def frame_id_from_path(image_path: str) -> int | None:
    """The frame index in an image path: the last run of digits in the file's stem (``img0042.png`` -> 42)."""
    stem = Path(image_path.replace("\\", "/")).stem
    runs = _DIGITS.findall(stem)
    return int(runs[-1]) if runs else None



def coverage_warnings(mask: np.ndarray, cameras: list[str], keypoints: list[str],
                      sources: dict[str, str] | None = None,
                      unseen: dict[str, list[str]] | None = None) -> list[str]:
    """One line per camera without any label, per keypoint without a label in any camera, and per camera
    missing some keypoints that other cameras have (what an importer prints before writing a dataset).

    Args:
        mask: ``(F, C, K)`` bool, labelled.
        cameras, keypoints: the ``C`` and ``K`` names.
        sources: ``{camera: label file}`` to name in the lines.
        unseen: ``{camera: keypoints}`` that the label format says the camera cannot see: not reported as
            missing there (the importer says the rule once).
    """
    sources = sources or {}
    unseen = unseen or {}
    lines = []
    per_camera = np.asarray(mask, dtype=bool).any(axis=0).reshape(len(cameras), len(keypoints))
    for c, cam in enumerate(cameras):
        where = f" in {sources[cam]}" if cam in sources else " (no label file)"
        if not per_camera[c].any():
            lines.append(f"warning: camera {cam} has no labels{where}")
            continue
        missing = [k for i, k in enumerate(keypoints) if not per_camera[c, i] and per_camera[:, i].any()
                   and k not in unseen.get(cam, ())]
        if missing:
            lines.append(f"warning: camera {cam}: keypoints {', '.join(missing)} have no labels{where}")
    for i, k in enumerate(keypoints):
        if not per_camera[:, i].any():
            lines.append(f"warning: keypoint {k} has no labels in any camera")
    return lines
