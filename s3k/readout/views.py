"""Per-view steps of the read-out: heatmap moments, the window around the peak, view selection, outlier
views and the confidence-weighted triangulation (the package docstring tells the whole read-out)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from s3k.geometry import Cameras, pixel_rays, project, triangulate_rays
from s3k.geometry.triangulation import SMALL_BATCH, ray_projectors, solve_projected
from s3k.readout.heatmaps import heatmap_moments, peak_window_mean, spatial_softmax

__all__ = ["DEFAULT_MIN_WEIGHT", "DTYPE", "WINDOW_SIGMAS", "Rays", "moments", "outliers_and_points",
           "reject_outliers", "select_views", "triangulate", "triangulate_views", "view_rays", "window_cells"]

DTYPE = torch.float64
"""Precision of the read-out (see the module docstring)."""

DEFAULT_MIN_WEIGHT = 0.0
"""Views with a (calibrated) confidence at or below this are not used; 0 uses every view, weighted."""

WINDOW_SIGMAS = 6.0
"""Half-side of the window around each heatmap's peak whose mean is the detection, in target widths (see the
module docstring and :func:`window_cells`)."""


def window_cells(sigma: float, stride: int, window: int | None = None) -> int:
    """The read-out's window, cells each side of the peak, for a target width ``sigma`` in image pixels and a
    heatmap ``stride``: ``WINDOW_SIGMAS`` target widths rounded up (6 cells for a target of one cell), or
    ``window`` when it is given (0: the whole heatmap).

    Example:
        >>> window_cells(2.0, 2), window_cells(3.0, 2), window_cells(2.0, 1)
        (6, 9, 12)
    """
    if window is not None:
        return window
    if not sigma > 0 or stride < 1:
        raise ValueError(f"window_cells: sigma must be > 0 and stride >= 1, got {sigma} and {stride}")
    return max(1, math.ceil(WINDOW_SIGMAS * sigma / stride - 1e-9))


def moments(logits: Tensor, stride: int, window: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """Spatial softmax of logits ``(*, h, w)`` and its moments, in float64.

    Args:
        logits: ``(*, h, w)``.
        stride: heatmap stride.
        window: 0 for the whole heatmap's mean; else the mean within this many cells of the peak
            (:func:`s3k.readout.heatmaps.peak_window_mean`). The variance is always the whole heatmap's.

    Returns:
        ``(probs (*, h, w), mean_uv (*, 2), var (*))``: the heatmaps, their means in network-input pixels and
        their variances in squared pixels (:func:`s3k.readout.heatmaps.heatmap_moments`).
    """
    probs = spatial_softmax(logits.to(DTYPE))
    mean_uv, var = heatmap_moments(probs, stride)
    if window:  # the softmax keeps the order of the logits: their argmax is the peak, read in half the bytes
        mean_uv = peak_window_mean(probs, stride, window, logits.flatten(-2).argmax(dim=-1))
    return probs, mean_uv, var


def select_views(uv: Tensor, weights: Tensor, min_weight: float = DEFAULT_MIN_WEIGHT) -> Tensor:
    """The views that enter the triangulation: finite ``uv (*, 2)`` and ``weights (*)`` above ``min_weight``
    (:func:`s3k.readout.read_out` passes the calibrated confidences, :mod:`s3k.readout.confidence`).

    Returns:
        ``(*)`` bool.
    """
    return torch.isfinite(uv).all(dim=-1) & torch.isfinite(weights) & (weights > min_weight)


def triangulate(cams: Cameras, uv: Tensor, weights: Tensor, used: Tensor) -> tuple[Tensor, Tensor]:
    """Confidence-weighted triangulation of the used views, in float64.

    Args:
        cams: cameras ``(B, C)`` or ``(C,)`` (shared by the frames) in the pixels of ``uv``.
        uv: ``(B, C, K, 2)`` detections.
        weights: ``(B, C, K)`` confidence weights.
        used: ``(B, C, K)`` bool (:func:`select_views`); the other views get weight zero.

    Returns:
        ``(X (B, K, 3), valid (B, K))``: float64 points, zeros where invalid (fewer than two used views,
        near-parallel rays).
    """
    return triangulate_views(view_rays(cams, uv, used), weights, used)


class Rays(NamedTuple):
    """The rays of every view's detection (:func:`view_rays`), float64 ``(B, K, C, ...)``: ``origins`` and
    ``directions`` ``(..., 3)``, and for batches the small-batch solve takes, their ``projectors`` ``(..., 3,
    3)`` (:func:`s3k.geometry.triangulation.ray_projectors`), else None."""

    origins: Tensor
    directions: Tensor
    projectors: Tensor | None


def view_rays(cams: Cameras, uv: Tensor, used: Tensor) -> Rays:
    """The rays of the detections ``uv (B, C, K, 2)`` in ``cams``, float64, laid out for
    :func:`triangulate_views`; a view not ``used`` gets the ray of a harmless pixel (NaN must not reach the
    solver: its weight is zero there). The rays do not depend on the weights, so one set serves every
    triangulation of the same detections (:func:`reject_outliers`' rounds and the final one)."""
    if cams.dtype != DTYPE or cams.K.device != uv.device:
        cams = cams.to(device=uv.device, dtype=DTYPE)
    uv = uv.to(DTYPE)
    if not bool(used.all()):  # the common case, every view used, skips the masking
        uv = torch.where(used[..., None], uv, torch.zeros((), dtype=DTYPE, device=uv.device))
    lead = torch.broadcast_shapes(uv.shape[:-2], cams.shape)
    o, d = pixel_rays(cams, uv)
    o = o.expand(lead + o.shape[-2:]).transpose(-2, -3)
    d = d.expand(lead + d.shape[-2:]).transpose(-2, -3)
    small = math.prod(o.shape[:-2]) < SMALL_BATCH  # points: triangulate_rays' matrix form
    return Rays(o, d, ray_projectors(d) if small else None)


def triangulate_views(rays: Rays, weights: Tensor, used: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`triangulate` of the views' rays (:func:`view_rays`): the used views, weighted, the others
    with weight zero; ``(X (B, K, 3), valid (B, K))``, the same as :func:`s3k.geometry.triangulate_rays`
    gives."""
    w = weights.to(DTYPE)
    if not bool(used.all()):
        w = torch.where(used, w, torch.zeros((), dtype=DTYPE, device=w.device))
    w = w.expand(used.shape).transpose(-1, -2)
    if rays.projectors is not None:
        X, valid = solve_projected(rays.origins, rays.projectors, w)
    else:
        X, valid = triangulate_rays(rays.origins, rays.directions, w)
    return X, valid & (used.sum(dim=1) >= 2)


def reject_outliers(cams: Cameras, uv: Tensor, weights: Tensor, used: Tensor, max_residual_px: float,
                    min_views: int = 2) -> Tensor:
    """Drop, one at a time, the used view that misses the others' consensus by more than ``max_residual_px``.

    A view whose detection lies on the wrong object (an occluded keypoint, a symmetric corner) pulls the
    weighted least-squares point towards its own ray however small its weight; its confidence does not show
    it (a confused heatmap can be sharp), but its reprojection residual does. Each round triangulates the
    used views, and in every (frame, keypoint) whose largest residual exceeds the threshold drops that view,
    as long as more than ``min_views`` remain; at most ``C - min_views`` rounds.

    Args:
        cams, uv, weights, used: as for :func:`triangulate`.
        max_residual_px: largest reprojection residual a view may keep, in the pixels of ``uv``.
        min_views: never drop below this many views.

    Returns:
        ``used (B, C, K)`` with the outlying views removed.
    """
    cams = cams.to(device=uv.device, dtype=DTYPE)  # the read-out's precision once, not per round
    return outliers_and_points(cams, uv, weights, used, max_residual_px, min_views)[0]


def outliers_and_points(cams: Cameras, uv: Tensor, weights: Tensor, used: Tensor, max_residual_px: float,
                        min_views: int = 2, rays: Rays | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`reject_outliers` and the triangulation of the views it keeps: ``(used, X, valid)`` as
    :func:`triangulate` gives them for the returned ``used``.

    The rays are cast once for every round (only the weights change between rounds), and the last round's
    points are the answer when it dropped nothing. ``rays``: the views' rays to triangulate instead of those
    of ``uv`` in ``cams`` (:func:`view_rays`; e.g. the same detections in another image's pixels, whose
    points are the same), ``cams``/``uv`` then serve for the residuals only.
    """
    C = uv.shape[1]
    if cams.dtype != DTYPE or cams.K.device != uv.device:
        cams = cams.to(device=uv.device, dtype=DTYPE)
    uv, weights = uv.to(DTYPE), weights.to(DTYPE)
    if rays is None:
        rays = view_rays(cams, uv, used)
    X, valid = triangulate_views(rays, weights, used)
    for _ in range(max(0, C - min_views)):
        reproj, _ = project(cams, X[:, None])
        residual = torch.linalg.vector_norm(reproj - uv, dim=-1)  # (B, C, K)
        residual = torch.where(used & valid[:, None], residual, torch.full_like(residual, -1.0))
        worst, c_worst = residual.max(dim=1)  # (B, K)
        drop = (worst > max_residual_px) & (used.sum(dim=1) > min_views)
        if not bool(drop.any()):
            break
        hit = torch.nn.functional.one_hot(c_worst, C).permute(0, 2, 1).bool() & drop[:, None]
        used = used & ~hit
        X, valid = triangulate_views(rays, weights, used)
    return used, X, valid
