"""The read-out: heatmap logits -> 2D detections, confidences and 3D keypoints (everything after the network).

Every caller uses these functions: ``s3k predict``, ``s3k evaluate``, ``s3k track``, ``s3k export
--with-moments``, :func:`s3k.model.detect`, the self-supervised loss (:mod:`s3k.losses`) and the inference
benchmarks, so what is trained, scored and shipped is the same maths (docs/method.md, "Heatmaps",
"Confidence", "Triangulation"). Per view ``c`` and keypoint ``k``:

1. :func:`moments`: the spatial softmax ``P_ck`` of the logits, its mean ``m_ck`` within a window around
   its most probable cell (the 2D detection, in the network-input pixels, pixel (0, 0) the centre of the
   top-left pixel) and its variance ``var_ck`` over the whole heatmap.
2. :func:`s3k.heatmaps.confidence_weight`: the confidence weight ``w_ck`` from the spread.
3. :func:`select_views`: which views enter the triangulation.
4. :func:`triangulate`: the confidence-weighted triangulation of the selected views (lens distortion
   included), valid where at least two views are used and the rays are not near-parallel.
5. :func:`read_out` also maps the detections into the cameras' own pixels (``pixel_maps``), reprojects the
   3D point into every camera and measures the reprojection residuals.

Window: the whole heatmap's mean is pulled towards the heatmap's centre by whatever probability is spread over
the rest of it (a second bright spot, a diffuse tail), so every read-out takes the mean within
:func:`window_cells` of the peak: ``WINDOW_SIGMAS`` target widths, which holds all of a well-formed peak
(a narrower window cut into it would pull the mean towards the peak's cell). Training's pseudo-labels do
the same (``--pseudo_window``). The variance, and so the confidence, stays the whole heatmap's: spread mass
is what makes a view uncertain.

Precision: float64 from the softmax on, whatever the logits' dtype. The mean is a sum over ``h * w`` cells
and the triangulation solves normal equations whose conditioning degrades with near-parallel rays; float64
makes both independent of summation order and of the runtime (PyTorch, ONNX Runtime, TorchScript give the
same points up to their logits), and its cost is negligible next to the network. Results are float64.

View selection: a view is used when its mean and weight are finite and its weight is above ``min_weight``;
used views are weighted by their confidence ``w``. The default ``min_weight = 0`` uses every view, weighted:
the paper's rule and the one training's self-supervised target uses, so that ``s3k evaluate`` scores exactly
the points ``s3k predict`` and ``s3k track`` write. A higher threshold (``s3k track --min-weight``) drops
uncertain views outright instead of down-weighting them (the weight is 0.5 at a spread of 2 sigma).
:func:`reject_outliers` (``max_residual_px``) also drops views that miss the other views' consensus;
:func:`reject_layout` drops 3D keypoints whose distances to the others break a rigid object's layout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from s3k.geometry import Cameras, project, triangulate_pixels
from s3k.heatmaps import confidence_weight, heatmap_moments, peak_window_mean, spatial_softmax

__all__ = [
    "DEFAULT_MIN_WEIGHT",
    "DTYPE",
    "ReadOut",
    "WINDOW_SIGMAS",
    "moments",
    "read_out",
    "reject_layout",
    "reject_outliers",
    "fit_layout",
    "layout_locus",
    "layout_shape",
    "search_layout",
    "select_views",
    "triangulate",
    "window_cells",
]

DTYPE = torch.float64
"""Precision of the read-out (see the module docstring)."""

DEFAULT_MIN_WEIGHT = 0.0
"""Views with a confidence weight at or below this are not used; 0 uses every view, weighted."""

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
            (:func:`s3k.heatmaps.peak_window_mean`). The variance is always the whole heatmap's.

    Returns:
        ``(probs (*, h, w), mean_uv (*, 2), var (*))``: the heatmaps, their means in network-input pixels and
        their variances in squared pixels (:func:`s3k.heatmaps.heatmap_moments`).
    """
    probs = spatial_softmax(logits.to(DTYPE))
    mean_uv, var = heatmap_moments(probs, stride)
    if window:
        mean_uv = peak_window_mean(probs, stride, window)
    return probs, mean_uv, var


def select_views(uv: Tensor, weights: Tensor, min_weight: float = DEFAULT_MIN_WEIGHT) -> Tensor:
    """The views that enter the triangulation: finite ``uv (*, 2)`` and ``weights (*)`` above ``min_weight``.

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
    if cams.dtype != DTYPE or cams.K.device != uv.device:
        cams = cams.to(device=uv.device, dtype=DTYPE)
    uv, w = uv.to(DTYPE), weights.to(DTYPE)
    if not bool(used.all()):  # the common case, every view used, skips the masking
        # Unused views get a harmless pixel and zero weight: NaN must not reach the solver.
        zero = torch.zeros((), dtype=DTYPE, device=uv.device)
        uv, w = torch.where(used[..., None], uv, zero), torch.where(used, w, zero)
    X, valid = triangulate_pixels(cams, uv, w)
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
    C = uv.shape[1]
    used = used.clone()
    # the read-out's precision once, not per round
    cams = cams.to(device=uv.device, dtype=DTYPE)
    uv, weights = uv.to(DTYPE), weights.to(DTYPE)
    for _ in range(max(0, C - min_views)):
        X, valid = triangulate(cams, uv, weights, used)
        reproj, _ = project(cams, X[:, None])
        residual = torch.linalg.vector_norm(reproj - uv, dim=-1)  # (B, C, K)
        residual = torch.where(used & valid[:, None], residual, torch.full_like(residual, -1.0))
        worst, c_worst = residual.max(dim=1)  # (B, K)
        drop = (worst > max_residual_px) & (used.sum(dim=1) > min_views)
        if not bool(drop.any()):
            break
        hit = torch.nn.functional.one_hot(c_worst, C).permute(0, 2, 1).bool() & drop[:, None]
        used = used & ~hit
    return used


def reject_layout(X: Tensor, valid: Tensor, distances: Tensor, tol: float) -> Tensor:
    """Drop the 3D keypoints that break a rigid object's layout; ``valid (B, K)`` with them removed.

    A network that has not learnt a pose can detect several keypoints on one spot, sharply and consistently
    in every view: the views agree, so neither the confidence nor :func:`reject_outliers` sees it, and a
    pseudo-label made of such points teaches the collapse. A pair of keypoints breaks the layout when its
    distance differs from the reference ``distances`` by more than ``tol`` of it. In every frame the keypoint
    in the most broken pairs (then the largest relative deviation) is dropped, one at a time, until no
    broken pair is left; a keypoint that was in a broken pair and is left with no intact one is dropped too
    (its place cannot be vouched for). Pairs whose reference is NaN are not checked, so a keypoint with
    nothing to check against is kept.

    Args:
        X: ``(B, K, 3)`` points (NaN where invalid).
        valid: ``(B, K)`` bool.
        distances: ``(K, K)`` reference distances (``s3k.train.labelled_distances``), NaN where unknown.
        tol: largest relative deviation a pair may have (e.g. 0.2).
    """
    B, K = valid.shape
    ref = distances.to(device=X.device, dtype=DTYPE)
    P = torch.nan_to_num(X.to(DTYPE))
    rel = (torch.cdist(P, P) - ref).abs() / ref  # NaN where the reference is unknown
    off_diagonal = ~torch.eye(K, dtype=torch.bool, device=X.device)
    checked = valid[:, :, None] & valid[:, None, :] & off_diagonal & torch.isfinite(rel)
    broken = checked & (rel > tol)
    keep = valid.clone()
    rel = torch.nan_to_num(rel)
    for _ in range(K):
        live = broken & keep[:, :, None] & keep[:, None, :]
        count = live.sum(dim=-1)  # (B, K)
        if not bool(count.any()):
            break
        excess = (rel * live).sum(dim=-1)
        worst = (count + excess / (1.0 + excess)).argmax(dim=-1)  # count first, the deviation breaks ties
        drop = count.amax(dim=-1) > 0
        keep[drop, worst[drop]] = False
    intact = checked & ~broken & keep[:, :, None] & keep[:, None, :]
    return keep & ~(broken.any(dim=-1) & ~intact.any(dim=-1))


LAYOUT_SAMPLES = 720
"""Places on a broken keypoint's locus that :func:`search_layout` scores (every half degree of the circle)."""

LOG_FLOOR = math.log(1e-6)
"""The least log-probability a view gives a place in :func:`search_layout`: a view whose heatmap is sure of
another place (or that does not see the place) cannot veto what the other views agree on."""


def layout_locus(a: Tensor, b: Tensor, ra: float, rb: float, n: int = LAYOUT_SAMPLES) -> Tensor:
    """``(n, 3)`` places at distance ``ra`` from ``a (3,)`` and ``rb`` from ``b (3,)``: the circle where the
    two spheres meet, ``n`` evenly spaced places on it (the nearest circle, in the plane between them, when
    the spheres do not meet).

    Example:
        >>> a, b = torch.zeros(3, dtype=torch.float64), torch.tensor([2.0, 0, 0], dtype=torch.float64)
        >>> P = layout_locus(a, b, math.sqrt(2), math.sqrt(2), 8)
        >>> torch.allclose(P.norm(dim=-1), torch.full((8,), math.sqrt(2), dtype=torch.float64))
        True
    """
    axis = b - a
    d = float(torch.linalg.vector_norm(axis))
    e = axis / max(d, 1e-12)
    along = (d * d + ra * ra - rb * rb) / (2 * max(d, 1e-12))
    radius = math.sqrt(max(ra * ra - along * along, 0.0))
    helper = torch.zeros_like(e)
    helper[int(torch.argmin(e.abs()))] = 1.0
    u = torch.linalg.cross(e, helper)
    u = u / torch.linalg.vector_norm(u)
    v = torch.linalg.cross(e, u)
    theta = torch.arange(n, dtype=a.dtype, device=a.device) * (2 * math.pi / n)
    return a + along * e + radius * (torch.cos(theta)[:, None] * u + torch.sin(theta)[:, None] * v)


def search_layout(probs: Tensor, cams: Cameras, stride: int, X: Tensor, kept: Tensor, distances: Tensor,
                  tol: float, window: int) -> list[tuple[int, int, Tensor, Tensor, Tensor]]:
    """For every keypoint the layout check left out (``~kept``) in a frame with two keypoints it kept, look
    for it again where the rigid layout puts it.

    Two kept keypoints ``i``, ``j`` (the pair farthest apart by the reference) place it on the circle at its
    reference distances from them (:func:`layout_locus`); places that break its distance to another kept
    keypoint by more than ``tol`` are left out. Each place is scored by the sum over the views of its
    heatmap's log-probability at the place's projection (at least ``LOG_FLOOR``), and each view's detection is
    then its heatmap's mean within ``window`` cells of the best place's cell (a view whose image does not hold
    that cell is not used).

    Args:
        probs: ``(B, C, K, h, w)`` heatmaps.
        cams: cameras ``(B, C)`` or ``(C,)`` of the network-input pixels.
        stride: heatmap stride.
        X: ``(B, K, 3)`` points; kept: ``(B, K)`` bool, the keypoints the layout check kept.
        distances: ``(K, K)`` reference distances (NaN where unknown).
        tol: the layout check's relative tolerance.
        window: the read-out's window, cells (>= 1).

    Returns:
        ``[(b, k, uv (C, 2), used (C,), place (3,)), ...]``: for the keypoints found again, the new detections
        in network-input pixels and the best place itself.
    """
    B, C, K, h, w = probs.shape
    ref = distances.to(device=X.device, dtype=DTYPE)
    found = []
    for b, k in (~kept).nonzero().tolist():
        others = kept[b].clone()
        others[k] = False
        others &= torch.isfinite(ref[k])
        idx = others.nonzero().flatten()
        if len(idx) < 2:
            continue
        sub = ref[idx][:, idx].nan_to_num(-1.0)
        p, q = divmod(int(sub.argmax()), len(idx))
        i, j = int(idx[p]), int(idx[q])
        places = layout_locus(X[b, i].to(DTYPE), X[b, j].to(DTYPE), float(ref[k, i]), float(ref[k, j]))
        rest = idx[(idx != i) & (idx != j)]
        if len(rest):
            off = (torch.cdist(places, X[b, rest].to(DTYPE)) - ref[k, rest]).abs() / ref[k, rest]
            places = places[(off <= tol).all(dim=1)]
            if not len(places):
                continue
        frame_cams = cams if len(cams.shape) == 1 else cams[b]
        uv, depth = project(frame_cams, places[None].expand(C, -1, -1))  # (C, n, 2)
        col = torch.round((uv[..., 0] - (stride - 1) / 2) / stride).long()
        row = torch.round((uv[..., 1] - (stride - 1) / 2) / stride).long()
        inside = (depth > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        hm = probs[b, :, k]  # (C, h, w)
        cell = hm[torch.arange(C)[:, None], row.clamp(0, h - 1), col.clamp(0, w - 1)]
        logp = torch.where(inside, cell.clamp_min(1e-300).log().clamp_min(LOG_FLOOR),
                           torch.full_like(cell, LOG_FLOOR))
        best = int(logp.sum(dim=0).argmax())
        used = inside[:, best]
        centre = row[:, best].clamp(0, h - 1) * w + col[:, best].clamp(0, w - 1)
        found.append((b, k, peak_window_mean(hm, stride, window, centre), used, places[best]))
    return found


def layout_shape(distances: Tensor) -> Tensor | None:
    """``(K, 3)`` points whose distances are ``distances (K, K)`` as nearly as three dimensions allow
    (classical multidimensional scaling), centred on the origin; None when a distance is unknown (NaN off the
    diagonal) or there are fewer than three keypoints.

    Example:
        >>> d = torch.tensor([[0.0, 3, 5], [3, 0, 4], [5, 4, 0]], dtype=torch.float64)
        >>> Y = layout_shape(d)
        >>> torch.allclose(torch.cdist(Y, Y), d)
        True
    """
    K = distances.shape[0]
    D = distances.to(DTYPE).clone()
    D.fill_diagonal_(0.0)
    if K < 3 or not bool(torch.isfinite(D).all()):
        return None
    J = torch.eye(K, dtype=DTYPE) - 1.0 / K
    gram = -0.5 * J @ (D * D) @ J
    values, vectors = torch.linalg.eigh(gram)  # ascending
    Y = vectors[:, -3:] * values[-3:].clamp_min(0).sqrt()
    return Y - Y.mean(dim=0)


def fit_layout(X: Tensor, valid: Tensor, shape: Tensor) -> tuple[Tensor, Tensor]:
    """The rigid object's ``shape (K, 3)`` moved onto each frame's points ``X (B, K, 3)``: the rotation and
    translation that bring its ``valid (B, K)`` keypoints nearest those points in the least-squares sense
    (Kabsch), the shape or its mirror image, whichever fits better (distances do not tell them apart).

    Frames with fewer than three valid keypoints are left as they are. The other keypoints of a frame are
    placed by the moved shape only when its valid ones span three dimensions: against a plane the shape and
    its mirror image fit alike and put them on either side.

    Returns:
        ``(X', placed (B, K) bool)``: the moved shape's keypoints where ``placed``, ``X`` elsewhere.
    """
    w = valid.to(DTYPE)  # (B, K)
    n = w.sum(dim=1)
    fitted = n >= 3
    P = torch.nan_to_num(X.to(DTYPE))
    out = P.clone()
    if not bool(fitted.any()):
        return out, valid & fitted[:, None]
    n = n.clamp_min(1)[:, None]
    centre = (w[..., None] * P).sum(dim=1) / n  # (B, 3)
    best = torch.full((X.shape[0],), float("inf"), dtype=DTYPE, device=X.device)
    mirror = torch.tensor([1.0, 1.0, -1.0], dtype=DTYPE, device=X.device)
    Y0 = shape.to(device=X.device, dtype=DTYPE)
    # singular values of the valid keypoints' part of the shape (the mirror's are the same): is it flat?
    spread = torch.linalg.svdvals((Y0[None] - ((w[..., None] * Y0).sum(dim=1) / n)[:, None]) * w[..., None])
    for Y in (Y0, Y0 * mirror):
        Yc = (w[..., None] * Y).sum(dim=1) / n  # (B, 3): the shape's centre over the valid keypoints
        A = (Y[None] - Yc[:, None]) * w[..., None]
        H = A.transpose(1, 2) @ (P - centre[:, None])  # (B, 3, 3)
        U, _, Vt = torch.linalg.svd(H)
        flip = torch.sign(torch.linalg.det(Vt.transpose(1, 2) @ U.transpose(1, 2)))
        S = torch.diag_embed(torch.stack([torch.ones_like(flip), torch.ones_like(flip), flip], dim=-1))
        R = Vt.transpose(1, 2) @ S @ U.transpose(1, 2)
        moved = (Y[None] - Yc[:, None]) @ R.transpose(1, 2) + centre[:, None]
        cost = (w * ((moved - P) ** 2).sum(dim=-1)).sum(dim=1)
        better = fitted & (cost < best)
        out = torch.where(better[:, None, None], moved, out)
        best = torch.where(better, cost, best)
    solid = spread[:, 2] > 0.05 * spread[:, 0]
    placed = fitted[:, None] & (valid | solid[:, None])
    return torch.where(placed[..., None], out, P), placed

@dataclass
class ReadOut:
    """The read-out of a batch of synchronized frames (float64 tensors, on the logits' device).

    Attributes:
        uv: ``(B, C, K, 2)`` per-view 2D detections (softmax means) in the cameras' pixels.
        var: ``(B, C, K)`` heatmap variances, squared network-input pixels.
        weights: ``(B, C, K)`` confidence weights.
        used: ``(B, C, K)`` bool, the view entered the triangulation (:func:`select_views`).
        X: ``(B, K, 3)`` triangulated points in world units, NaN where invalid.
        valid: ``(B, K)`` bool, the triangulation is defined.
        cams: the cameras ``(B, C)`` or ``(C,)`` of ``uv``, float64.
        probs: ``(B, C, K, h, w)`` heatmaps (softmax), or None.

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
                       None if self.probs is None else self.probs.cpu())


def _to_camera_pixels(net_uv: Tensor, Minv: Tensor) -> Tensor:
    """Detections ``(B, C, K, 2)`` in network-input pixels mapped by the affine ``Minv`` (``(C, 3, 3)`` or
    ``(B, C, 3, 3)``) into the cameras' own pixels."""
    return net_uv @ Minv[..., :2, :2].transpose(-1, -2) + Minv[..., None, :2, 2]


def read_out(logits: Tensor, cams: Cameras, stride: int, sigma: float,
             pixel_maps: np.ndarray | Tensor | None = None, min_weight: float = DEFAULT_MIN_WEIGHT,
             keep_heatmaps: bool = False, max_residual_px: float | None = None,
             window: int | None = None, layout: Tensor | None = None, layout_tol: float = 0.0) -> ReadOut:
    """Heatmap logits of a batch of synchronized frames -> detections, weights and 3D points.

    Args:
        logits: ``(B, C, K, h, w)`` network outputs.
        cams: cameras ``(B, C)`` or ``(C,)`` (shared by the frames), in the pixels the results are given in.
        stride: heatmap stride (network-input pixels per cell).
        sigma: target width in network-input pixels (the confidence weight's scale).
        pixel_maps: ``(C, 3, 3)`` or per frame ``(B, C, 3, 3)`` affine maps from the cameras' pixels to the
            network-input pixels (for cameras of the original images that were cropped and resized for the
            network), or None when ``cams`` are the network input's cameras.
        min_weight: views with a confidence weight at or below this are not used.
        keep_heatmaps: also return the softmax heatmaps.
        max_residual_px: if given, views whose reprojection residual exceeds it are dropped one at a time
            (:func:`reject_outliers`), in the network-input pixels (the pixels the threshold has at training,
            ``--outlier_px``, whatever the size of the original images).
        window: each detection is its heatmap's mean within this many cells of the peak (:func:`moments`);
            None: :func:`window_cells` of ``sigma`` and ``stride``; 0: the whole heatmap's mean (the paper's).
        layout, layout_tol: a rigid object's ``(K, K)`` reference distances and relative tolerance
            (:func:`reject_layout`); a keypoint that breaks them is looked for again where the layout puts
            it (:func:`search_layout`). None or 0: off.

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
    cells = window_cells(sigma, stride, window)
    probs, uv, var = moments(logits, stride, cells)
    weights = confidence_weight(var, sigma)
    used = select_views(uv, weights, min_weight)
    if cams.dtype != DTYPE or cams.K.device != logits.device:
        cams = cams.to(device=logits.device, dtype=DTYPE)
    net_cams, net_uv = cams, uv  # the cameras of the network-input pixels and the detections in them
    if pixel_maps is not None:
        maps = torch.as_tensor(np.asarray(pixel_maps, dtype=np.float64), device=logits.device)
        if maps.shape not in ((C, 3, 3), (B, C, 3, 3)):
            raise ValueError(f"read_out: pixel_maps must be ({C}, 3, 3) or ({B}, {C}, 3, 3), "
                             f"got {tuple(maps.shape)}")
        Minv = torch.linalg.inv(maps)  # network-input pixels -> the cameras' pixels (affine)
        uv = _to_camera_pixels(uv, Minv)
        net_cams = Cameras(maps @ cams.K, cams.dist, cams.R, cams.t)  # an affine pixel map: K' = M K
    if max_residual_px is not None:
        used = reject_outliers(net_cams, net_uv, weights, used, max_residual_px)
    X, valid = triangulate(cams, uv, weights, used)
    if layout is not None and layout_tol > 0 and cells > 0:
        kept = reject_layout(X, valid, layout, layout_tol)
        found = [] if bool(kept.all()) else search_layout(probs, net_cams, stride, X, kept, layout,
                                                            layout_tol, cells)
        if found:
            net_uv, used = net_uv.clone(), used.clone()
            for b, k, found_uv, found_used, _ in found:
                w_k = weights[b, :, k]
                net_uv[b, :, k] = found_uv
                used[b, :, k] = found_used & torch.isfinite(w_k) & (w_k > min_weight)
            uv = net_uv if pixel_maps is None else _to_camera_pixels(net_uv, Minv)
            X, valid = triangulate(cams, uv, weights, used)
            # a detection read next to a stronger wrong peak can still break the layout: then the best place
            # on the locus is the keypoint
            again = reject_layout(X, valid, layout, layout_tol)
            X, valid = X.clone(), valid.clone()
            for b, k, _, _, place in found:
                if not bool(again[b, k]):
                    X[b, k], valid[b, k] = place, True
            kept = reject_layout(X, valid, layout, layout_tol)  # the points moved: check them again
        rigid_shape = layout_shape(layout)
        if rigid_shape is not None:
            fit, placed = fit_layout(X, kept, rigid_shape)
            X = torch.where(placed[..., None], fit, X)
            valid = valid | placed
    X = torch.where(valid[..., None], X, torch.full_like(X, float("nan")))
    return ReadOut(uv, var, weights, used, X, valid, cams, probs if keep_heatmaps else None)
