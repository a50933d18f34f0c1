"""What the training loop samples with: random batches of frames, augmented and moved to the device."""

from __future__ import annotations

import torch

from s3k.data.frames import FrameBatch, FrameStore, images_to_float
from s3k.geometry import Cameras
from s3k.train.augment import Augmentation, NoiseBank, augment_frames


def draw_batch(store: FrameStore, n: int, gen: torch.Generator, distinct: bool) -> FrameBatch:
    """``n`` random frames of ``store``, drawn with ``gen`` (the same generator state gives the same frames).

    Args:
        store: the frames to draw from.
        n: frames to draw.
        gen: CPU random generator; it is advanced by the draw.
        distinct: draw without repeats (when the store holds at least ``n`` frames); otherwise frames are
            drawn independently, with repeats.

    Returns:
        A :class:`FrameBatch` of ``n`` frames (B = n).
    """
    if distinct and len(store) >= n:
        pos = torch.randperm(len(store), generator=gen)[:n]
    else:
        pos = torch.randint(len(store), (n,), generator=gen)
    return store.get(pos.numpy())


def prepare(batch: FrameBatch, device: torch.device, aug: Augmentation | None, gen: torch.Generator,
            labels: bool, noise_bank: NoiseBank | None = None
            ) -> tuple[torch.Tensor, Cameras, torch.Tensor | None, torch.Tensor | None]:
    """Images (B, C, 3, H, W) float on ``device``, cameras (B, C) and labels (B, C, K, 2), (B, C, K) or None,
    augmented when ``aug`` is given (the intrinsics and labels follow the images exactly)."""
    cams = batch.cams.to(device=device)
    uv = batch.labels_uv.to(device) if labels and batch.labels_uv is not None else None
    mask = batch.labels_mask.to(device) if labels and batch.labels_mask is not None else None
    if aug is not None:
        images, K, uv, _ = augment_frames(batch.images, cams.K, aug, gen, uv=uv, device=device,
                                          noise_bank=noise_bank)
        cams = Cameras(K, cams.dist, cams.R, cams.t)
    else:
        images = images_to_float(batch.images, device)
    return images, cams, uv, mask
