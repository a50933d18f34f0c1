"""Frames of a dataset split, resized to the network's input size, served as batches of tensors.

Training, evaluation and prediction read frames through :class:`FrameStore` so that all three see the images
at the same size and with the same intrinsics (``Dataset.open(image_size=...)``, which resizes with
``s3k.geometry.warp.resize_crop``, ``K' = M K``). When a
split fits in ``preload_mb`` it is decoded up front into the dataset's uint8 image cache and the store serves
batches straight from that cache (no copy of its own), which keeps data loading a small fraction of a
training step; otherwise each batch is read from the dataset on demand.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from s3k.data.dataset import Dataset
from s3k.data.protocol import DatasetLike
from s3k.geometry import Cameras


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
    """Open a dataset, resized to ``out_size`` (W, H) when given (intrinsics and labels follow exactly);
    ``path`` may also be a dataset already open (e.g. :class:`s3k.data.crops.CropDataset`)."""
    ds = Dataset.open(os.fspath(path), cache=cache) if isinstance(path, (str, os.PathLike)) else path
    return ds if out_size is None else ds.resized(out_size)


_ON_DEVICE: dict[tuple, Tensor] = {}
"""Dataset caches copied to a device by :meth:`FrameStore.to`, shared by the stores that serve them."""


class FrameStore:
    """Frames ``frame_ids`` of ``dataset``, served as tensors.

    A preloaded store keeps every image at hand without copying it: its images are the dataset's own cache
    (``Dataset.cached_images``, a memmap with ``cache="disk"``), so training holds each image once however
    many stores (labelled, unlabelled, validation) serve it. Only a dataset opened with ``cache="none"``
    gets its images copied into the store. Cameras, labels and points are read once into small arrays.

    Args:
        dataset: an opened ``s3k.data.Dataset`` at the network's input size (:func:`open_dataset`).
        frame_ids: frame ids to serve.
        preload_mb: decode everything up front when it takes at most this many MiB.
        labels: also serve 2D labels.
        points: also serve ground-truth 3D points when the dataset has them.
        chunk: frames per read while preloading without a dataset cache.
    """

    def __init__(self, dataset: DatasetLike, frame_ids, preload_mb: int = 2048, labels: bool = False,
                 points: bool = False, chunk: int = 64) -> None:
        self.dataset = dataset
        self.frame_ids = np.asarray(frame_ids, dtype=np.int64)
        self.out_size = (int(dataset.image_size[0]), int(dataset.image_size[1]))
        self.want_labels, self.want_points = labels, points
        C = len(dataset.cameras)
        nbytes = len(self.frame_ids) * C * self.out_size[0] * self.out_size[1] * 3
        # Preloaded: every frame but the images, and the images as (N, C, H, W, 3) with the row of each
        # frame in it (the dataset's cache and its rows, or a copy in frame order).
        self._cache: FrameBatch | None = None
        self._image_rows = np.arange(len(self.frame_ids))
        if len(self.frame_ids) and nbytes <= preload_mb * 2**20:
            shared = dataset.cached_images(self.frame_ids)
            if shared is None:
                W, H = self.out_size
                images = torch.empty((len(self.frame_ids), C, H, W, 3), dtype=torch.uint8)
                for i in range(0, len(self.frame_ids), chunk):
                    images[i:i + chunk] = torch.from_numpy(dataset.images(self.frame_ids[i:i + chunk]))
            else:
                array, self._image_rows = shared
                images = torch.from_numpy(array)
            self._cache = self._read(self.frame_ids, images)

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def preloaded(self) -> bool:
        return self._cache is not None

    @property
    def image_array(self) -> Tensor | None:
        """A preloaded store's images, ``uint8 (N, C, H, W, 3)`` (the dataset's cache when it has one); None
        when each batch is read from the dataset."""
        return None if self._cache is None else self._cache.images

    def _read(self, ids: np.ndarray, images: Tensor | None = None) -> FrameBatch:
        """Frames ``ids``, their images read from the dataset unless given."""
        ds = self.dataset
        if images is None:
            images = torch.from_numpy(np.ascontiguousarray(ds.images(ids)))
        cams = ds.calibration(ids)
        if cams.dtype != torch.float32:
            cams = cams.to(dtype=torch.float32)
        batch = FrameBatch(frame_ids=np.asarray(ids), images=images, cams=cams)
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
        """Frames at ``positions`` (indices into ``frame_ids``); the images are a copy."""
        positions = np.asarray(positions, dtype=np.int64)
        if self._cache is None:
            return self._read(self.frame_ids[positions])
        c = self._cache
        idx = torch.from_numpy(positions).to(c.cams.K.device)
        return FrameBatch(
            frame_ids=c.frame_ids[positions],
            images=c.images[torch.from_numpy(self._image_rows[positions]).to(c.images.device)],
            cams=c.cams[idx],
            labels_uv=None if c.labels_uv is None else c.labels_uv[idx],
            labels_mask=None if c.labels_mask is None else c.labels_mask[idx],
            points=None if c.points is None else c.points[idx],
            points_mask=None if c.points_mask is None else c.points_mask[idx],
        )

    def to(self, device: torch.device | str) -> FrameStore:
        """Hold a preloaded store's frames on ``device`` (uint8 images, cameras, labels), so that a batch is
        drawn there without a copy from host memory; stores whose images are one dataset cache share one
        copy of it on the device. A store read batch by batch stays on the host. Returns ``self``."""
        device = torch.device(device)
        c = self._cache
        if c is None or c.images.device == device:
            return self
        key = (c.images.data_ptr(), tuple(c.images.shape), str(device))
        images = _ON_DEVICE.get(key)
        if images is None:
            images = _ON_DEVICE[key] = c.images.to(device)
        self._cache = FrameBatch(
            frame_ids=c.frame_ids, images=images, cams=c.cams.to(device=device),
            **{name: None if getattr(c, name) is None else getattr(c, name).to(device)
               for name in ("labels_uv", "labels_mask", "points", "points_mask")})
        return self

    def batches(self, batch_size: int):
        """Iterate over all frames in order, ``batch_size`` at a time."""
        for i in range(0, len(self), batch_size):
            yield self.get(np.arange(i, min(i + batch_size, len(self))))
