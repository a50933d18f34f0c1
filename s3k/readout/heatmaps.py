"""Heatmaps: the cell-to-pixel map, Gaussian targets, spatial softmax, moments and confidence weights.

Every function here works in image pixels (docs/method.md#conventions: pixel (0, 0) is the centre of the
top-left pixel, u to the right, v down) even when the heatmap is at a reduced stride. The only place that
converts a heatmap cell index into an image pixel is :func:`cell_centres`; targets and moments both go
through it, so a Gaussian rendered at ``uv`` has its softmax mean at ``uv`` at every stride.

Shapes: ``*`` any leading dimensions (typically ``(B, C, K)``), ``h w`` heatmap size, ``H W`` image size.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "peak_window_mean",
    "cell_centres",
    "heatmap_size",
    "gaussian_targets",
    "spatial_log_softmax",
    "spatial_softmax",
    "heatmap_moments",
    "confidence_weight",
]


def _check_stride(stride: int) -> int:
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f"heatmaps: stride must be a positive int, got {stride!r}")
    return stride


def _check_heatmap(name: str, x: Tensor) -> None:
    if not isinstance(x, Tensor):
        raise ValueError(f"heatmaps: {name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 2:
        raise ValueError(f"heatmaps: {name} must have shape (*, h, w), got {tuple(x.shape)}")
    if x.shape[-1] < 1 or x.shape[-2] < 1:
        raise ValueError(f"heatmaps: {name} has an empty heatmap, shape {tuple(x.shape)}")


def cell_centres(
    h: int,
    w: int,
    stride: int,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[Tensor, Tensor]:
    """Image-pixel coordinates of the centres of heatmap cells: THE map from heatmap cell to image pixel.

    Cell ``j`` covers image pixels ``stride * j ... stride * j + stride - 1``, so its centre is
    ``u = stride * j + (stride - 1) / 2`` (and the same for rows). At stride 1 cells are pixels.

    Args:
        h: heatmap height (rows).
        w: heatmap width (columns).
        stride: image pixels per heatmap cell along each axis.
        device: device of the returned tensors.
        dtype: floating dtype of the returned tensors.

    Returns:
        ``(u (w,), v (h,))``: column centres and row centres in image pixels.

    Example:
        >>> cell_centres(2, 3, 2)[0]
        tensor([0.5000, 2.5000, 4.5000])
    """
    stride = _check_stride(stride)
    if h < 1 or w < 1:
        raise ValueError(f"heatmaps: cell_centres needs h, w >= 1, got h={h}, w={w}")
    offset = (stride - 1) / 2.0
    u = torch.arange(w, device=device, dtype=dtype) * stride + offset
    v = torch.arange(h, device=device, dtype=dtype) * stride + offset
    return u, v


def heatmap_size(H: int, W: int, stride: int) -> tuple[int, int]:
    """Heatmap size for an image of ``H x W`` pixels at ``stride``.

    The image must tile exactly into cells, so that the heatmap extent equals the image extent
    (``[-0.5, W - 0.5] x [-0.5, H - 0.5]``) and no pixel is dropped.

    Args:
        H: image height in pixels.
        W: image width in pixels.
        stride: image pixels per heatmap cell.

    Returns:
        ``(h, w) = (H // stride, W // stride)``.

    Raises:
        ValueError: if ``H`` or ``W`` is not a positive multiple of ``stride``.
    """
    stride = _check_stride(stride)
    if H < 1 or W < 1 or H % stride or W % stride:
        raise ValueError(
            f"heatmaps: image size H={H}, W={W} must be positive multiples of the heatmap stride {stride}; "
            "resize or crop the images (s3k.geometry.warp.resize_crop)"
        )
    return H // stride, W // stride


def gaussian_targets(
    uv: Tensor, valid: Tensor | None, h: int, w: int, stride: int, sigma: float
) -> tuple[Tensor, Tensor]:
    """Normalized Gaussian target heatmaps centred on image points (docs/method.md#targets).

    ``target[..., i, j]`` is proportional to ``exp(-((u_j - u)^2 + (v_i - v)^2) / (2 sigma^2))`` with
    ``(u_j, v_i)`` the cell centres of :func:`cell_centres`, and sums to 1 over the heatmap. It is computed as
    the outer product of two 1D softmaxes (the Gaussian is separable), so it never underflows to all zeros,
    however far the point lies from every cell centre.

    A term is masked (``mask`` False, target all zeros) when ``valid`` is False, when ``uv`` is not finite, or
    when ``uv`` lies off the heatmap extent ``[-0.5, stride * w - 0.5] x [-0.5, stride * h - 0.5]``.

    Args:
        uv: ``(*, 2)`` point in image pixels.
        valid: ``(*)`` bool, or None for all valid (e.g. ``depth > eps`` from ``geometry.project``).
        h: heatmap height.
        w: heatmap width.
        stride: image pixels per heatmap cell.
        sigma: Gaussian width in image pixels (> 0).

    Returns:
        ``(target (*, h, w), mask (*))``: target has the dtype of ``uv``; mask is bool.

    Example:
        >>> t, m = gaussian_targets(torch.tensor([[10.0, 6.0]]), None, 8, 8, 2, 2.0)
        >>> t.shape, bool(m[0]), round(float(t.sum()), 6)
        (torch.Size([1, 8, 8]), True, 1.0)
    """
    stride = _check_stride(stride)
    if not isinstance(uv, Tensor) or uv.ndim < 1 or uv.shape[-1] != 2:
        shape = tuple(uv.shape) if isinstance(uv, Tensor) else type(uv).__name__
        raise ValueError(f"heatmaps: gaussian_targets uv must have shape (*, 2), got {shape}")
    if not uv.is_floating_point():
        raise ValueError(f"heatmaps: gaussian_targets uv must be floating point, got {uv.dtype}")
    if not (isinstance(sigma, (int, float)) and sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f"heatmaps: gaussian_targets sigma must be a positive number, got {sigma!r}")
    if h < 1 or w < 1:
        raise ValueError(f"heatmaps: gaussian_targets needs h, w >= 1, got h={h}, w={w}")
    batch = uv.shape[:-1]
    if valid is None:
        valid = torch.ones(batch, dtype=torch.bool, device=uv.device)
    elif not isinstance(valid, Tensor) or valid.shape != batch:
        shape = tuple(valid.shape) if isinstance(valid, Tensor) else type(valid).__name__
        raise ValueError(
            f"heatmaps: gaussian_targets valid must have shape {tuple(batch)} (uv[..., 0]), got {shape}"
        )

    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= -0.5) & (u <= stride * w - 0.5) & (v >= -0.5) & (v <= stride * h - 0.5)
    mask = valid.to(torch.bool) & torch.isfinite(uv).all(dim=-1) & inside
    # Masked points are moved to the origin before rendering so that nothing below sees NaN or inf
    # (a NaN would otherwise leak into gradients through the discarded branch of `where`).
    uv_safe = torch.where(mask[..., None], uv, torch.zeros_like(uv))
    cu, cv = cell_centres(h, w, stride, device=uv.device, dtype=uv.dtype)
    scale = -0.5 / float(sigma) ** 2
    pu = torch.softmax(scale * (cu - uv_safe[..., 0:1]) ** 2, dim=-1)  # (*, w)
    pv = torch.softmax(scale * (cv - uv_safe[..., 1:2]) ** 2, dim=-1)  # (*, h)
    target = pv[..., :, None] * pu[..., None, :]
    target = target * mask[..., None, None].to(target.dtype)
    return target, mask


def spatial_log_softmax(logits: Tensor) -> Tensor:
    """Log-softmax over the last two (spatial) dimensions.

    Args:
        logits: ``(*, h, w)``.

    Returns:
        ``(*, h, w)`` log-probabilities, same dtype; ``exp`` sums to 1 over each heatmap.
    """
    _check_heatmap("logits", logits)
    flat = logits.reshape(*logits.shape[:-2], -1)
    return torch.log_softmax(flat, dim=-1).reshape(logits.shape)


def spatial_softmax(logits: Tensor) -> Tensor:
    """Softmax over the last two (spatial) dimensions: ``P_ck`` of docs/method.md#heatmaps.

    Args:
        logits: ``(*, h, w)``.

    Returns:
        ``(*, h, w)`` probabilities summing to 1 over each heatmap, same dtype.
    """
    _check_heatmap("logits", logits)
    flat = logits.reshape(*logits.shape[:-2], -1)
    return torch.softmax(flat, dim=-1).reshape(logits.shape)


def heatmap_moments(probs: Tensor, stride: int) -> tuple[Tensor, Tensor]:
    """Mean and spread of heatmap distributions, in image pixels (docs/method.md#heatmaps).

    ``mean = sum P (u, v)``; ``var = (var_u + var_v) / 2``, the mean of the per-axis variances, so a Gaussian
    of width ``sigma`` gives ``sqrt(var) = sigma``. Both are computed from the row and column marginals, with
    the variance taken about the mean (no cancellation of large squares).

    Args:
        probs: ``(*, h, w)`` probabilities (e.g. :func:`spatial_softmax`), each heatmap summing to 1.
        stride: image pixels per heatmap cell.

    Returns:
        ``(mean_uv (*, 2), var (*))`` in image pixels and squared image pixels.

    Example:
        >>> t, _ = gaussian_targets(torch.tensor([20.3, 30.7]), None, 32, 32, 2, 3.0)
        >>> m, var = heatmap_moments(t, 2)
        >>> [round(x, 3) for x in m.tolist()], round(float(var.sqrt()), 3)
        ([20.3, 30.7], 3.0)
    """
    _check_heatmap("probs", probs)
    h, w = probs.shape[-2:]
    cu, cv = cell_centres(h, w, stride, device=probs.device, dtype=probs.dtype)
    pu = probs.sum(dim=-2)  # (*, w) column marginal
    pv = probs.sum(dim=-1)  # (*, h) row marginal
    mu = (pu * cu).sum(dim=-1)
    mv = (pv * cv).sum(dim=-1)
    var_u = (pu * (cu - mu[..., None]) ** 2).sum(dim=-1)
    var_v = (pv * (cv - mv[..., None]) ** 2).sum(dim=-1)
    return torch.stack((mu, mv), dim=-1), 0.5 * (var_u + var_v)


def peak_window_mean(probs: Tensor, stride: int, radius: int, peak: Tensor | None = None) -> Tensor:
    """Mean of each heatmap within ``radius`` cells of its most probable cell (or of the cell ``peak``), in
    image pixels.

    The whole heatmap's mean (:func:`heatmap_moments`) is pulled towards the heatmap's centre by whatever
    probability is spread over the rest of it: 5% of the mass spread evenly moves the mean 5% of the way to
    the centre. Restricted to a window around the peak (the probabilities in it renormalized), the mean keeps
    its sub-pixel precision without that pull. A window cut by the heatmap's edge keeps what is inside.

    Args:
        probs: ``(*, h, w)`` probabilities.
        stride: image pixels per heatmap cell.
        radius: half-side of the square window, cells (>= 1).
        peak: ``(*)`` flat cell index (``row * w + col``) of each window's centre; None: the most probable
            cell.

    Returns:
        ``mean_uv (*, 2)`` in image pixels.

    Example:
        >>> t, _ = gaussian_targets(torch.tensor([20.3, 30.7]), None, 32, 32, 2, 3.0)
        >>> spread = 0.9 * t + 0.1 / t.numel()  # 10% of the mass spread evenly
        >>> [round(x, 2) for x in heatmap_moments(spread, 2)[0].tolist()]
        [21.42, 30.78]
        >>> [round(x, 2) for x in peak_window_mean(spread, 2, 5).tolist()]
        [20.3, 30.7]
    """
    _check_heatmap("probs", probs)
    if radius < 1:
        raise ValueError(f"peak_window_mean: radius must be >= 1 cell, got {radius}")
    h, w = probs.shape[-2:]
    if peak is None:
        peak = probs.flatten(-2).argmax(dim=-1)  # (*)
    # Only the window's cells are read: gathered by index (cells past the heatmap's edge clamped onto it and
    # given zero weight), the moments of the (2 radius + 1)^2 window instead of the whole masked heatmap.
    lead = probs.shape[:-2]
    flat = probs.reshape(-1, h * w)
    peak = peak.reshape(-1)
    offsets = torch.arange(-radius, radius + 1, device=probs.device)
    rows = torch.div(peak, w, rounding_mode="floor")[:, None] + offsets  # (N, S)
    cols = (peak % w)[:, None] + offsets
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]  # (N, S, S)
    rows, cols = rows.clamp(0, h - 1), cols.clamp(0, w - 1)
    side = offsets.numel()
    window = flat.gather(1, (rows[:, :, None] * w + cols[:, None, :]).reshape(-1, side * side))
    window = window.reshape(-1, side, side) * inside
    window = window / window.sum(dim=(-2, -1), keepdim=True).clamp_min(torch.finfo(probs.dtype).tiny)
    cu, cv = cell_centres(h, w, stride, device=probs.device, dtype=probs.dtype)
    mu = (window.sum(dim=-2) * cu[cols]).sum(dim=-1)
    mv = (window.sum(dim=-1) * cv[rows]).sum(dim=-1)
    return torch.stack((mu, mv), dim=-1).reshape(*lead, 2)


def confidence_weight(var: Tensor, sigma: float) -> Tensor:
    """Per-view confidence from a heatmap's spread (paper sec. 3.2.1, docs/method.md#confidence).

    ``w = sigmoid(3 tanh(5 (1 - sqrt(var) / (2 sigma))))``: 0.5 at a spread of ``2 sigma``, about 0.95 at or
    below ``sigma``, towards ``sigmoid(-3) = 0.047`` for wide heatmaps. ``var`` is clamped at 1e-12 px^2
    so that the gradient of ``sqrt`` stays finite for a degenerate one-cell heatmap.

    Args:
        var: ``(*)`` heatmap variance in squared image pixels (:func:`heatmap_moments`).
        sigma: target Gaussian width in image pixels (> 0).

    Returns:
        ``(*)`` weights in ``(0, 1)``, same dtype as ``var``.
    """
    if not isinstance(var, Tensor):
        raise ValueError(f"heatmaps: confidence_weight var must be a torch.Tensor, got {type(var).__name__}")
    if not (isinstance(sigma, (int, float)) and sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f"heatmaps: confidence_weight sigma must be a positive number, got {sigma!r}")
    spread = var.clamp_min(1e-12).sqrt()
    return torch.sigmoid(3.0 * torch.tanh(5.0 * (1.0 - spread / (2.0 * float(sigma)))))
