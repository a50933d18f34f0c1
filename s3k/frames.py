"""Frames of a dataset split, resized to the network's input size, served as batches of tensors.

Training, evaluation and prediction read frames through :class:`FrameStore` so that all three see the images
at the same size and with the same intrinsics (``Dataset.open(image_size=...)``, which resizes with
``s3k.data.transforms.resize_crop``, ``K' = M K``). When a
split fits in ``preload_mb`` it is decoded once into memory, which keeps data loading a small fraction of a
training step; otherwise each batch is read from the dataset on demand (the dataset keeps its own uint8
image cache on disk).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from s3k.geometry import Cameras


def model_image_size(src_size: tuple[int, int], image_size: int, stride: int) -> tuple[int, int]:
    """The network input size (W, H) for dataset images of ``src_size``.

    Args:
        src_size: dataset image size (W, H).
        image_size: wanted longer side in pixels; 0 keeps the dataset's size.
        stride: heatmap stride; both sides are rounded to a multiple of it.

    Returns:
        (W, H), positive multiples of ``stride``.
    """
    W, H = int(src_size[0]), int(src_size[1])
    s = 1.0 if image_size <= 0 else image_size / max(W, H)
    w = max(stride, int(round(W * s / stride)) * stride)
    h = max(stride, int(round(H * s / stride)) * stride)
    return w, h


@dataclass
class FrameBatch:
    """One batch of frames at the network's input size.

    Attributes:
        frame_ids: (B,) dataset frame ids.
        images: (B, C, H, W, 3) uint8.
        cams: cameras (B, C), float32, intrinsics of the resized images.
        labels_uv: (B, C, K, 2) float32 2D labels in resized pixels, or None.
        labels_mask: (B, C, K) bool, or None.
        points: (B, K, 3) float32 ground-truth 3D, or None.
        points_mask: (B, K) bool, or None.
    """

    frame_ids: np.ndarray
    images: Tensor
    cams: Cameras
    labels_uv: Tensor | None = None
    labels_mask: Tensor | None = None
    points: Tensor | None = None
    points_mask: Tensor | None = None


def images_to_float(images: Tensor, device: torch.device | str | None = None) -> Tensor:
    """uint8 (B, C, H, W, 3) -> float32 (B, C, 3, H, W) in [0, 1] on ``device``."""
    x = images.to(device=device, non_blocking=True)
    return x.permute(0, 1, 4, 2, 3).float().div_(255.0)


def open_dataset(path, out_size: tuple[int, int] | None = None, cache: str = "disk"):
    """Open a dataset, resized to ``out_size`` (W, H) when given (intrinsics and labels follow exactly)."""
    from s3k.data import Dataset

    ds = Dataset.open(path, cache=cache)
    return ds if out_size is None else ds.resized(out_size)


class FrameStore:
    """Frames ``frame_ids`` of ``dataset``, served as tensors.

    Args:
        dataset: an opened ``s3k.data.Dataset`` at the network's input size (:func:`open_dataset`).
        frame_ids: frame ids to serve.
        preload_mb: decode everything into memory when it takes at most this many MiB.
        labels: also serve 2D labels.
        points: also serve ground-truth 3D points when the dataset has them.
        chunk: frames per read while preloading.
    """

    def __init__(self, dataset, frame_ids, preload_mb: int = 2048, labels: bool = False, points: bool = False,
                 chunk: int = 64) -> None:
        self.dataset = dataset
        self.frame_ids = np.asarray(frame_ids, dtype=np.int64)
        self.out_size = (int(dataset.image_size[0]), int(dataset.image_size[1]))
        self.want_labels, self.want_points = labels, points
        C = len(dataset.cameras)
        nbytes = len(self.frame_ids) * C * self.out_size[0] * self.out_size[1] * 3
        self._cache: FrameBatch | None = None
        if len(self.frame_ids) and nbytes <= preload_mb * 2**20:
            parts = [self._read(self.frame_ids[i:i + chunk]) for i in range(0, len(self.frame_ids), chunk)]
            self._cache = _concat(parts)

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def preloaded(self) -> bool:
        return self._cache is not None

    def _read(self, ids: np.ndarray) -> FrameBatch:
        ds = self.dataset
        images = np.ascontiguousarray(ds.images(ids))
        cams = ds.calibration(ids)
        if cams.dtype != torch.float32:
            cams = cams.to(dtype=torch.float32)
        batch = FrameBatch(frame_ids=np.asarray(ids), images=torch.from_numpy(images), cams=cams)
        if self.want_labels:
            uv, mask = ds.labels(ids)
            mask = np.asarray(mask, dtype=bool) & np.isfinite(uv).all(axis=-1)
            batch.labels_uv = torch.from_numpy(np.nan_to_num(np.asarray(uv, dtype=np.float32)))
            batch.labels_mask = torch.from_numpy(mask)
        if self.want_points:
            got = ds.points3d(ids)
            if got is not None:
                X, mask = got
                mask = np.asarray(mask, dtype=bool) & np.isfinite(X).all(axis=-1)
                batch.points = torch.from_numpy(np.nan_to_num(np.asarray(X, dtype=np.float32)))
                batch.points_mask = torch.from_numpy(mask)
        return batch

    def get(self, positions) -> FrameBatch:
        """Frames at ``positions`` (indices into ``frame_ids``)."""
        positions = np.asarray(positions, dtype=np.int64)
        if self._cache is None:
            return self._read(self.frame_ids[positions])
        idx = torch.from_numpy(positions)
        c = self._cache
        return FrameBatch(
            frame_ids=c.frame_ids[positions],
            images=c.images[idx],
            cams=c.cams[idx],
            labels_uv=None if c.labels_uv is None else c.labels_uv[idx],
            labels_mask=None if c.labels_mask is None else c.labels_mask[idx],
            points=None if c.points is None else c.points[idx],
            points_mask=None if c.points_mask is None else c.points_mask[idx],
        )

    def batches(self, batch_size: int):
        """Iterate over all frames in order, ``batch_size`` at a time."""
        for i in range(0, len(self), batch_size):
            yield self.get(np.arange(i, min(i + batch_size, len(self))))


def _concat(parts: list[FrameBatch]) -> FrameBatch:
    def cat(name: str) -> Tensor | None:
        vals = [getattr(p, name) for p in parts]
        return None if any(v is None for v in vals) else torch.cat(vals)

    cams = Cameras(*(torch.cat([getattr(p.cams, f) for p in parts]) for f in ("K", "dist", "R", "t")))
    return FrameBatch(
        frame_ids=np.concatenate([p.frame_ids for p in parts]),
        images=torch.cat([p.images for p in parts]),
        cams=cams,
        labels_uv=cat("labels_uv"),
        labels_mask=cat("labels_mask"),
        points=cat("points"),
        points_mask=cat("points_mask"),
    )
