"""Training losses: KL to Gaussian targets, supervised and self-supervised terms, weight decay.

The maths: docs/method.md#losses.

Both heatmap losses are ``sum_c sum_k KL(H_ck || P_ck)`` over the terms that have a target, divided by the
number of frames ``B`` so that the loss scale does not depend on the batch size. They differ only in where
the 3D point behind the targets comes from:

- supervised: 2D labels triangulated with unit weights (>= 2 labelled cameras needed);
- self-supervised: the network's own softmax means, triangulated with the paper's confidence weights, then
  treated as a constant (computed under ``torch.no_grad``, so no gradient can reach it).

The point is then projected into *every* camera, and a term is masked (no target, zero loss) when the
triangulation is invalid, the point is behind that camera, or its projection falls off the heatmap.

Shapes: ``B`` frames, ``C`` cameras, ``K`` keypoints, ``h w`` heatmap size, ``stride`` image pixels per cell.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from s3k import readout
from s3k.geometry import Cameras, project, triangulate_labels
from s3k.readout import ReadoutConfig
from s3k.readout.heatmaps import (
    gaussian_targets,
    heatmap_moments,
    spatial_log_softmax,
    spatial_softmax,
)

__all__ = ["coord_loss", "kl_divergence", "kl_loss", "l2_non_bias", "pseudo_labels",
           "self_supervised_loss", "supervised_loss"]

MIN_DEPTH = 1e-6
"""Camera-frame depth at or below which a projected point counts as behind the camera."""


def _shape(x: object) -> object:
    """Shape of a tensor for error messages, or its type name for anything else."""
    return tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__


def kl_divergence(target: Tensor, logits: Tensor) -> Tensor:
    """``KL(target || softmax(logits))`` per heatmap, in float32 (float64 stays float64).

    ``sum target * (log target - log_softmax(logits))`` with ``0 log 0 = 0``; cells where the target is zero
    contribute exactly zero (also to the gradient), even if their log-probability underflows to ``-inf``.

    Args:
        target: ``(*, h, w)`` distributions (each summing to 1, or all zeros for "no target").
        logits: ``(*, h, w)`` network logits; the same shape.

    Returns:
        ``(*)`` KL divergences (zero for all-zero targets).
    """
    if not isinstance(target, Tensor) or not isinstance(logits, Tensor) or target.shape != logits.shape:
        raise ValueError(
            "kl_divergence: target and logits must be tensors of the same shape (*, h, w), got "
            f"{_shape(target)} and {_shape(logits)}"
        )
    dtype = torch.promote_types(logits.dtype, torch.float32)
    log_p = spatial_log_softmax(logits.to(dtype))
    t = target.to(dtype)
    pos = t > 0
    t_safe = torch.where(pos, t, torch.ones_like(t))
    terms = torch.where(pos, t * (t_safe.log() - log_p), torch.zeros_like(t))
    return terms.sum(dim=(-1, -2))


def kl_loss(target: Tensor, logits: Tensor, mask: Tensor | None = None, normalizer: float = 1.0) -> Tensor:
    """Sum of ``KL(target || softmax(logits))`` over the unmasked heatmaps, divided by ``normalizer``.

    Args:
        target: ``(*, h, w)`` Gaussian targets (``heatmaps.gaussian_targets``).
        logits: ``(*, h, w)`` network logits.
        mask: ``(*)`` bool, True where the term counts; None for all.
        normalizer: divisor, the number of frames ``B`` (so the scale does not depend on the batch size).

    Returns:
        Scalar loss (float32, or float64 for float64 logits). Zero, with zero gradients, when nothing counts.
    """
    kl = kl_divergence(target, logits)
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.shape != kl.shape:
            raise ValueError(
                f"kl_loss: mask must have shape {tuple(kl.shape)} (logits without h, w), got "
                f"{_shape(mask)}"
            )
        kl = torch.where(mask, kl, torch.zeros_like(kl))
    if not (isinstance(normalizer, (int, float)) and normalizer > 0 and math.isfinite(normalizer)):
        raise ValueError(f"kl_loss: normalizer must be a positive number, got {normalizer!r}")
    return kl.sum() / normalizer


def _check_logits(fn: str, logits: Tensor, cams: Cameras) -> tuple[int, int, int, int, int]:
    if not isinstance(logits, Tensor) or logits.ndim != 5:
        raise ValueError(
            f"{fn}: logits must have shape (B, C, K, h, w), got {_shape(logits)}"
        )
    B, C, K, h, w = logits.shape
    if not isinstance(cams, Cameras) or tuple(cams.shape) != (B, C):
        got = tuple(cams.shape) if isinstance(cams, Cameras) else type(cams).__name__
        raise ValueError(f"{fn}: cams must be Cameras of shape (B, C) = {(B, C)} like logits, got {got}")
    if B == 0:
        raise ValueError(f"{fn}: empty batch (B = 0)")
    return B, C, K, h, w


def coord_loss(logits: Tensor, target_uv: Tensor, mask: Tensor, stride: int, sigma: float) -> Tensor:
    """Sum over the unmasked heatmaps of the distance from the softmax mean of ``logits (*, h, w)`` to
    ``target_uv (*, 2)``, in units of ``sigma`` image pixels, divided by the number of frames (dim 0).

    The KL to a Gaussian is minimal when the heatmap is that Gaussian, but a heatmap that misses it by a
    little can keep its mass off-centre: its mean, the detection, is not what the KL measures. This term is;
    its gradient moves the mean towards the target. The distance is smoothed near zero (``sqrt(d^2 + 0.01)``).
    """
    mean_uv, _ = heatmap_moments(spatial_softmax(logits.float()), stride)
    t = torch.where(mask[..., None], target_uv.to(mean_uv.dtype), mean_uv.detach())
    d = torch.sqrt((((mean_uv - t) / sigma) ** 2).sum(dim=-1) + 0.01) - 0.1
    return torch.where(mask, d, torch.zeros_like(d)).sum() / logits.shape[0]


def _reprojection_loss(
    logits: Tensor, X: Tensor, valid: Tensor, cams: Cameras, stride: int, sigma: float,
    coord_weight: float = 0.0, **views: Tensor
) -> tuple[Tensor, dict[str, Tensor]]:
    """The KL of ``logits (B, C, K, h, w)`` to Gaussian targets at the projections of the points
    ``X (B, K, 3)`` (constants) in all cameras ``(B, C)``, plus ``coord_weight`` times :func:`coord_loss`,
    and the losses' ``info`` dict: the points, the per-view tensors ``views`` that gave them, then the
    targets and their mask."""
    B, _, _, h, w = logits.shape
    with torch.no_grad():
        uv, depth = project(cams, X[:, None])  # (B, C, K, 2), (B, C, K)
        in_front = (depth > MIN_DEPTH) & valid[:, None]
        targets, mask = gaussian_targets(uv, in_front, h, w, stride, sigma)
    loss = kl_loss(targets, logits, mask, normalizer=B)
    if coord_weight > 0:
        loss = loss + coord_weight * coord_loss(logits, uv, mask, stride, sigma)
    info = {
        "points": X,
        "points_valid": valid,
        **views,
        "target_uv": uv,
        "depth": depth,
        "mask": mask,
        "targets": targets,
        "num_terms": mask.sum(),
    }
    return loss, info


def supervised_loss(
    logits: Tensor,
    cams: Cameras,
    labels_uv: Tensor,
    label_mask: Tensor,
    stride: int,
    sigma: float,
    coord_weight: float = 0.0,
) -> tuple[Tensor, dict[str, Tensor]]:
    """``L_sup``: triangulate the 2D labels, reproject into every camera, KL to Gaussian targets.

    A keypoint labelled in at least two cameras is triangulated with unit weights (``geometry``'s solver; the
    labels are distorted pixel clicks) and its projection gives a target in all C cameras, labelled or not.
    Keypoints with fewer than two labelled views, degenerate (near-parallel) labelled rays, points behind a
    camera and projections off the heatmap give masked terms.

    Args:
        logits: ``(B, C, K, h, w)`` network logits.
        cams: ``Cameras`` of shape ``(B, C)`` for the images the network saw.
        labels_uv: ``(B, C, K, 2)`` labelled pixels (any value, even NaN, where not labelled).
        label_mask: ``(B, C, K)`` bool, True where labelled.
        stride: heatmap stride (image pixels per cell).
        sigma: target width in image pixels.
        coord_weight: weight of :func:`coord_loss` added to the KL (0: the KL alone).

    Returns:
        ``(loss, info)``: scalar loss (sum of KL over valid terms / B) and a dict of detached tensors:
        ``points (B, K, 3)``, ``points_valid (B, K)``, ``weights (B, C, K)`` (the unit triangulation weights),
        ``target_uv (B, C, K, 2)``, ``depth (B, C, K)``, ``mask (B, C, K)`` (terms that count),
        ``targets (B, C, K, h, w)`` and ``num_terms`` (scalar, number of valid terms).
    """
    fn = "supervised_loss"
    B, C, K, h, w = _check_logits(fn, logits, cams)
    if not isinstance(labels_uv, Tensor) or tuple(labels_uv.shape) != (B, C, K, 2):
        raise ValueError(
            f"{fn}: labels_uv must have shape (B, C, K, 2) = {(B, C, K, 2)}, "
            f"got {_shape(labels_uv)}"
        )
    if not isinstance(label_mask, Tensor) or tuple(label_mask.shape) != (B, C, K):
        raise ValueError(
            f"{fn}: label_mask must have shape (B, C, K) = {(B, C, K)}, "
            f"got {_shape(label_mask)}"
        )
    with torch.no_grad():
        X, valid = triangulate_labels(cams, labels_uv.detach(), label_mask)
        weights = (label_mask.to(torch.bool) & torch.isfinite(labels_uv).all(dim=-1)).to(cams.dtype)
    return _reprojection_loss(logits, X, valid, cams, stride, sigma, coord_weight, weights=weights)


def self_supervised_loss(
    logits: Tensor,
    cams: Cameras,
    stride: int,
    sigma: float,
    weights: Tensor | None = None,
    rule: ReadoutConfig | None = None,
    target_logits: Tensor | None = None,
    coord_weight: float = 0.0,
) -> tuple[Tensor, dict[str, Tensor]]:
    """``L_unsup``: multi-view consistency with the network's own confidence-weighted triangulation.

    The softmax means ``m_ck`` and confidence weights ``w_ck`` (docs/method.md#confidence) give ``x~_k`` by
    weighted triangulation; ``x~`` is a constant (the whole target is computed under ``torch.no_grad``),
    projected into every camera and rendered as a Gaussian; the gradient flows only through ``log P`` in the
    KL. Views with non-finite means or weights get weight zero; invalid triangulations, points behind a
    camera and projections off the heatmap give masked terms.

    Args:
        logits: ``(B, C, K, h, w)`` network logits.
        cams: ``Cameras`` of shape ``(B, C)``.
        stride: heatmap stride (image pixels per cell).
        sigma: target width in image pixels; also the scale of the confidence weight.
        weights: optional ``(B, C, K)`` triangulation weights replacing the confidence weights (e.g. all ones
            for an unweighted ablation).
        rule: which views and keypoints make the pseudo-label, and how a view is read (a
            :class:`s3k.readout.ReadoutConfig` for pseudo-labels; default: every view, the read-out's window,
            no layout).
        target_logits: optional ``(B, C, K, h, w)`` logits of the same images from which the pseudo-label is
            read out instead of ``logits`` (a teacher network's); the KL still trains ``logits``.
        coord_weight: weight of :func:`coord_loss` added to the KL (0: the KL alone).

    Returns:
        ``(loss, info)``: scalar loss (sum of KL over valid terms / B) and a dict of detached tensors:
        ``points (B, K, 3)``, ``points_valid (B, K)``, ``mean_uv (B, C, K, 2)``, ``var (B, C, K)``,
        ``weights (B, C, K)`` (those used), ``target_uv (B, C, K, 2)``, ``depth (B, C, K)``,
        ``mask (B, C, K)``, ``targets (B, C, K, h, w)`` and ``num_terms``.
    """
    fn = "self_supervised_loss"
    B, C, K, h, w = _check_logits(fn, logits, cams)
    if weights is not None and (not isinstance(weights, Tensor) or tuple(weights.shape) != (B, C, K)):
        raise ValueError(
            f"{fn}: weights must have shape (B, C, K) = {(B, C, K)}, "
            f"got {_shape(weights)}"
        )
    if target_logits is not None and tuple(target_logits.shape) != tuple(logits.shape):
        raise ValueError(f"{fn}: target_logits must have the shape of logits {tuple(logits.shape)}, "
                         f"got {_shape(target_logits)}")
    source = logits if target_logits is None else target_logits
    X, valid, mean_uv, var, wts = pseudo_labels(source, cams, stride, sigma, weights, rule)
    return _reprojection_loss(logits, X, valid, cams, stride, sigma, coord_weight, mean_uv=mean_uv, var=var,
                              weights=wts)


@torch.no_grad()
def pseudo_labels(
    logits: Tensor,
    cams: Cameras,
    stride: int,
    sigma: float,
    weights: Tensor | None = None,
    rule: ReadoutConfig | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The pseudo-labels of :func:`self_supervised_loss`, without its loss: the network's own detections of
    ``logits (B, C, K, h, w)`` triangulated by the read-out every command uses (float64, every finite view
    with positive weight; the arguments as there), each point a constant in the cameras' dtype.

    Returns:
        ``(X (B, K, 3), valid (B, K), mean_uv (B, C, K, 2), var (B, C, K), weights (B, C, K))``: the points,
        which of them give a term, the detections, their variances and the weights used (zero for a view left
        out).
    """
    ro = readout.read_out(logits.detach(), cams, stride, sigma, None,
                          rule or ReadoutConfig.for_pseudo_labels(),
                          weights=None if weights is None else weights.detach())
    X = torch.where(ro.valid[..., None], ro.X, torch.zeros_like(ro.X))  # a point that gives no term: 0
    wts = torch.where(ro.used, ro.weights, torch.zeros_like(ro.weights))
    return (X.to(cams.dtype), ro.valid, ro.uv.to(cams.dtype), ro.var.to(cams.dtype), wts.to(cams.dtype))


def l2_non_bias(model: nn.Module) -> Tensor:
    """``||theta_non-bias||^2``: sum of squares of the parameters with ``ndim > 1``.

    Convolution and linear weights count; biases and normalization scales/shifts (all 1D) do not.

    Args:
        model: any module.

    Returns:
        Scalar tensor (zero if the model has no such parameter).
    """
    if not isinstance(model, nn.Module):
        raise ValueError(f"l2_non_bias: model must be an nn.Module, got {type(model).__name__}")
    terms = [p.pow(2).sum() for p in model.parameters() if p.ndim > 1]
    if not terms:
        p = next(model.parameters(), None)
        return torch.zeros((), device=None if p is None else p.device)
    return torch.stack(terms).sum()
