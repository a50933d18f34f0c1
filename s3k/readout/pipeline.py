"""The read-out pipeline: logits of synchronized frames -> :class:`ReadOut` (detections in the cameras'
pixels, confidences, views used, 3D points), composed of :mod:`s3k.readout.views` and
:mod:`s3k.readout.rigid`."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from s3k.geometry import Cameras, project
from s3k.readout.config import ReadoutConfig
from s3k.readout.heatmaps import confidence_weight
from s3k.readout.rigid import (
    Found,
    LayoutPrior,
    fit_layout,
    layout_shape,
    reject_layout,
    search_layout,
    settle_ties,
)
from s3k.readout.views import (
    DTYPE,
    moments,
    outliers_and_points,
    select_views,
    triangulate,
    triangulate_views,
    view_rays,
    window_cells,
)

__all__ = ["ReadOut", "breaks_layout", "coarse_stands_in", "read_out"]


@dataclass
class ReadOut:
    """The read-out of a batch of synchronized frames (float64 tensors, on the logits' device).

    Attributes:
        uv: ``(B, C, K, 2)`` per-view 2D detections (softmax means) in the cameras' pixels.
        var: ``(B, C, K)`` heatmap variances, squared network-input pixels.
        weights: ``(B, C, K)`` confidence weights (the paper's: the triangulation's weights).
        used: ``(B, C, K)`` bool, the view entered the triangulation (:func:`select_views`).
        X: ``(B, K, 3)`` triangulated points in world units, NaN where invalid.
        valid: ``(B, K)`` bool, the triangulation is defined.
        cams: the cameras ``(B, C)`` or ``(C,)`` of ``uv``, float64.
        probs: ``(B, C, K, h, w)`` heatmaps (softmax), or None.
        confidence: ``(B, C, K)`` calibrated confidences (:mod:`s3k.readout.confidence`): about this share of
            views with it lie within the run's calibration distance of the truth; ``weights`` where the
            detector has no calibration (and when not given).

    The reprojections and residuals are computed when first asked for: a caller that wants only the points
    (the per-frame inference benchmark) does not pay for them.
    """

    uv: Tensor
    var: Tensor
    weights: Tensor
    used: Tensor
    X: Tensor
    valid: Tensor
    cams: Cameras
    probs: Tensor | None = None
    confidence: Tensor = None  # type: ignore[assignment]  # filled from weights in __post_init__

    def __post_init__(self) -> None:
        if self.confidence is None:
            self.confidence = self.weights

    @cached_property
    def reproj(self) -> Tensor:
        """``(B, C, K, 2)`` reprojection of ``X`` into every camera, NaN where invalid."""
        reproj, _depth = project(self.cams, self.X[:, None])
        return torch.where(self.valid[:, None, :, None], reproj, torch.full_like(reproj, float("nan")))

    @cached_property
    def residual(self) -> Tensor:
        """``(B, C, K)`` distance between ``reproj`` and ``uv``, pixels, NaN where invalid."""
        return torch.linalg.vector_norm(self.reproj - self.uv, dim=-1)

    @property
    def ncams(self) -> Tensor:
        """``(B, K)`` number of views used."""
        return self.used.sum(dim=1)

    @property
    def score(self) -> Tensor:
        """``(B, K)`` mean confidence weight over all views."""
        return self.weights.mean(dim=1)

    @property
    def error(self) -> Tensor:
        """``(B, K)`` mean reprojection residual over the views used, pixels, NaN where invalid."""
        res = torch.where(self.used, self.residual, torch.zeros_like(self.residual))
        error = res.sum(dim=1) / self.ncams.clamp_min(1)
        return torch.where(self.valid, error, torch.full_like(error, float("nan")))

    def cpu(self) -> ReadOut:
        """The same read-out with every tensor on the CPU."""
        return ReadOut(self.uv.cpu(), self.var.cpu(), self.weights.cpu(), self.used.cpu(), self.X.cpu(),
                       self.valid.cpu(), self.cams.to(device="cpu"),
                       None if self.probs is None else self.probs.cpu(), self.confidence.cpu())


def breaks_layout(X: Tensor, valid: Tensor, layout: Tensor, tol: float) -> Tensor:
    """``(B,)`` bool: a frame whose valid points ``X (B, K, 3)`` break a rigid object's layout, that is
    :func:`s3k.readout.reject_layout` drops one of them."""
    return (valid & ~reject_layout(X, valid, layout, tol)).any(dim=1)


_FRAME_FIELDS = ("uv", "var", "weights", "used", "X", "valid", "confidence")


def coarse_stands_in(fine: ReadOut, coarse: ReadOut, layout: Tensor, tol: float) -> Tensor:
    """A two-pass detector's refining read-out ``fine`` with the coarse read-out in place of every frame
    whose refining points still break the rigid ``layout`` (the rigid read-out found no consistent set to
    fit it to: the refining pass read part of the object elsewhere) where the coarse points, with at least
    as many keypoints valid, hold it. A stood-in frame carries the coarse pass's detections, weights,
    confidences and points (its variances in the coarse network's pixels). Changes ``fine`` in place;
    returns the frames stood in for, ``(B,)`` bool."""
    swap = (breaks_layout(fine.X, fine.valid, layout, tol)
            & ~breaks_layout(coarse.X, coarse.valid, layout, tol)
            & (coarse.valid.sum(dim=1) >= fine.valid.sum(dim=1)))
    if bool(swap.any()):
        for name in _FRAME_FIELDS:
            mine, theirs = getattr(fine, name), getattr(coarse, name)
            where = swap.view(-1, *([1] * (mine.ndim - 1)))
            setattr(fine, name, torch.where(where, theirs.to(device=mine.device, dtype=mine.dtype), mine))
        for cached in ("reproj", "residual"):  # the points changed
            fine.__dict__.pop(cached, None)
    return swap


def _affine_inverse(M: Tensor) -> Tensor:
    """The inverse of affine pixel maps ``(*, 3, 3)`` (last row 0, 0, 1), in closed form: a batched LAPACK
    call for a few 3x3 matrices costs more than the rest of a frame's read-out."""
    a, b, c, d = M[..., 0, 0], M[..., 0, 1], M[..., 1, 0], M[..., 1, 1]
    det = a * d - b * c
    A = torch.stack([torch.stack([d, -b], -1), torch.stack([-c, a], -1)], -2) / det[..., None, None]
    t = -(A @ M[..., :2, 2:3])
    bottom = torch.zeros_like(M[..., 2:3, :])
    bottom[..., 0, 2] = 1.0
    return torch.cat([torch.cat([A, t], -1), bottom], -2)


def _to_camera_pixels(net_uv: Tensor, Minv: Tensor) -> Tensor:
    """Detections ``(B, C, K, 2)`` in network-input pixels mapped by the affine ``Minv`` (``(C, 3, 3)`` or
    ``(B, C, 3, 3)``) into the cameras' own pixels."""
    return net_uv @ Minv[..., :2, :2].transpose(-1, -2) + Minv[..., None, :2, 2]


DEFAULT_CONFIG = ReadoutConfig()
"""The inference read-out without a detector's settings: confident views, no outlier test, no layout."""


def read_out(logits: Tensor, cams: Cameras, stride: int, sigma: float,
             pixel_maps: np.ndarray | Tensor | None = None, config: ReadoutConfig = DEFAULT_CONFIG, *,
             keep_heatmaps: bool = False, weights: Tensor | None = None,
             prior: LayoutPrior | None = None) -> ReadOut:
    """Heatmap logits of a batch of synchronized frames -> detections, weights and 3D points.

    Args:
        logits: ``(B, C, K, h, w)`` network outputs.
        cams: cameras ``(B, C)`` or ``(C,)`` (shared by the frames), in the pixels the results are given in.
        stride: heatmap stride (network-input pixels per cell).
        sigma: target width in network-input pixels (the confidence weight's scale).
        pixel_maps: ``(C, 3, 3)`` or per frame ``(B, C, 3, 3)`` affine maps from the cameras' pixels to the
            network-input pixels (for cameras of the original images that were cropped and resized for the
            network), or None when ``cams`` are the network input's cameras.
        config: every setting in one :class:`ReadoutConfig` (a detector's,
            :meth:`s3k.detector.DetectorMeta.readout_config`, or the pseudo-labels',
            :meth:`ReadoutConfig.for_pseudo_labels`); default: the plain inference read-out.
        keep_heatmaps: also return the softmax heatmaps.
        weights: ``(B, C, K)`` triangulation weights instead of the confidence weights (the calibration maps
            them to the confidences the selection compares).
        prior: another network's heatmaps of the same frames, whose evidence joins the views' in the rigid
            read-out's search (:class:`s3k.readout.LayoutPrior`).

    Returns:
        A :class:`ReadOut`.
    """
    if not isinstance(logits, Tensor) or logits.ndim != 5:
        shape = tuple(logits.shape) if isinstance(logits, Tensor) else type(logits).__name__
        raise ValueError(f"read_out: logits must be (B, C, K, h, w), got {shape}")
    B, C = logits.shape[:2]
    if tuple(cams.shape) not in ((C,), (B, C)):
        raise ValueError(f"read_out: cams must be ({C},) or ({B}, {C}) for logits {tuple(logits.shape)}, "
                         f"got {tuple(cams.shape)}")
    cells = window_cells(sigma, stride, config.window)
    probs, uv, var = moments(logits, stride, cells)
    weights = confidence_weight(var, sigma) if weights is None else weights.to(DTYPE)
    confidence = weights if config.confidence is None else config.confidence(weights)
    used = select_views(uv, confidence, config.min_weight)
    if cams.dtype != DTYPE or cams.K.device != logits.device:
        cams = cams.to(device=logits.device, dtype=DTYPE)
    views = _Views(cams, cams, uv, None)  # the cameras of the network-input pixels and the detections in them
    if pixel_maps is not None:
        maps = torch.as_tensor(np.asarray(pixel_maps, dtype=np.float64), device=logits.device)
        if maps.shape not in ((C, 3, 3), (B, C, 3, 3)):
            raise ValueError(f"read_out: pixel_maps must be ({C}, 3, 3) or ({B}, {C}, 3, 3), "
                             f"got {tuple(maps.shape)}")
        # an affine pixel map: K' = M K
        views = _Views(cams, Cameras(maps @ cams.K, cams.dist, cams.R, cams.t), uv, _affine_inverse(maps))
    uv = views.in_cameras(views.net_uv)
    rays = view_rays(cams, uv, used)  # cast once: the outlier rounds and the points differ in weights only
    if config.max_residual_px is not None:  # residuals in network pixels; points in the cameras' own
        used, X, valid = outliers_and_points(views.net_cams, views.net_uv, weights, used,
                                             config.max_residual_px, rays=rays)
    else:
        X, valid = triangulate_views(rays, weights, used)
    if config.rigid:
        X, valid, uv, used = _rigid(config, views, probs, (weights, confidence), used, X, valid, stride,
                                    cells, prior)
    X = torch.where(valid[..., None], X, torch.full_like(X, float("nan")))
    return ReadOut(uv, var, weights, used, X, valid, cams, probs if keep_heatmaps else None, confidence)


@dataclass
class _Views:
    """The cameras of the results' pixels and of the network's input, the detections in the latter and the
    map back (None: the same pixels)."""

    cams: Cameras
    net_cams: Cameras
    net_uv: Tensor
    Minv: Tensor | None

    def in_cameras(self, net_uv: Tensor) -> Tensor:
        return net_uv if self.Minv is None else _to_camera_pixels(net_uv, self.Minv)


def _rigid(config: ReadoutConfig, views: _Views, probs: Tensor, weighing: tuple[Tensor, Tensor], used: Tensor,
           X: Tensor, valid: Tensor, stride: int, cells: int,
           prior: LayoutPrior | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The rigid read-out (:class:`ReadoutConfig`'s layout fields): ``(X, valid, uv, used)``;
    ``weighing``: the views' triangulation weights and the confidences their selection compares."""
    weights, confidence = weighing
    layout, tol = config.layout, config.layout_tol
    assert layout is not None
    uv = views.in_cameras(views.net_uv)
    kept = reject_layout(X, valid, layout, tol)
    found = []
    if config.layout_search and cells > 0 and not bool(kept.all()):
        settled: dict[int, list[Found]] = {}
        if config.layout_ties:
            kept, settled = settle_ties(probs, views.net_cams, stride, X, valid, kept, layout, tol, cells,
                                        prior)
        rest = set(range(len(X))) - settled.keys() if settled else None  # settled frames were searched
        found = search_layout(probs, views.net_cams, stride, X, kept, layout, tol, cells, prior, rest)
        found += [f for frame in settled.values() for f in frame]
    if found:
        net_uv, used = views.net_uv.clone(), used.clone()
        for b, k, found_uv, found_used, _, _ in found:
            c_k = confidence[b, :, k]
            net_uv[b, :, k] = found_uv
            used[b, :, k] = found_used & torch.isfinite(c_k) & (c_k > config.min_weight)
        uv = views.in_cameras(net_uv)
        X, valid = triangulate(views.cams, uv, weights, used)
        # a detection read next to a stronger wrong peak can still break the layout: then the best place on
        # the locus is the keypoint
        again = reject_layout(X, valid, layout, tol)
        X, valid = X.clone(), valid.clone()
        for b, k, _, _, place, _ in found:
            if not bool(again[b, k]):
                X[b, k], valid[b, k] = place, True
        kept = reject_layout(X, valid, layout, tol)  # the points moved: check them again
    if config.layout_drop:
        valid = valid & kept
    shape = layout_shape(layout) if config.layout_fit != "off" else None
    if shape is not None:
        fit, placed = fit_layout(X, kept, shape)
        if config.layout_fit == "all":
            X, valid = torch.where(placed[..., None], fit, X), valid | placed
        else:
            X = torch.where((placed & valid)[..., None], fit, X)
    return X, valid, uv, used
