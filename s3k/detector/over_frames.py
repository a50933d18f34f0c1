"""A detector over a dataset's frames: :func:`detect_store` (every frame of a
:class:`s3k.data.frames.FrameStore` through a :class:`s3k.detector.Detector`) and :func:`split_frames`; what
``s3k predict``, ``s3k evaluate``, validation in training and a two-pass training's coarse estimates read
frames with."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from s3k.data.frames import FrameBatch, FrameStore
from s3k.data.tables import SPLITS

if TYPE_CHECKING:
    from s3k.detector.detector import Detection, Detector

__all__ = ["detect_store", "split_frames"]


def detect_store(detector: Detector, store: FrameStore, batch_size: int = 16,
                 keep_heatmaps: bool = False) -> Iterator[tuple[FrameBatch, Detection]]:
    """Run ``detector`` over every frame of ``store`` (frames at the dataset's own size, its cameras);
    yields ``(FrameBatch, Detection)`` on the CPU, in the dataset's pixels."""
    for batch in store.batches(batch_size):
        yield batch, detector(batch.images, batch.cams, keep_heatmaps=keep_heatmaps).cpu()


def split_frames(dataset, split: str) -> np.ndarray:
    """Frame ids of a split, or of every split for 'all' (labelled, unlabelled, then test frames)."""
    return np.asarray(dataset.frames(SPLITS if split == "all" else split))
