"""A rigid object's layout at read-out: keypoints that break the labelled distances, the search for them
where the layout puts them, and the layout fitted onto the kept keypoints (docs/method.md, "A rigid
object's layout")."""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass

import torch
from torch import Tensor

from s3k.geometry import Cameras, project
from s3k.readout.heatmaps import peak_window_mean
from s3k.readout.views import DTYPE

__all__ = ["LAYOUT_SAMPLES", "LayoutPrior", "fit_layout", "layout_locus", "layout_shape", "reject_layout",
           "search_layout", "settle_ties"]


def _pairs(X: Tensor, valid: Tensor, distances: Tensor, tol: float) -> tuple[Tensor, Tensor, Tensor]:
    """``(rel, checked, broken)``, each ``(B, K, K)``: every pair's relative deviation from its reference
    distance (NaN where the reference is unknown), whether the pair is checked and whether it breaks
    ``tol``."""
    K = valid.shape[1]
    ref = distances.to(device=X.device, dtype=DTYPE)
    P = torch.nan_to_num(X.to(DTYPE))
    rel = (torch.cdist(P, P) - ref).abs() / ref
    off_diagonal = ~torch.eye(K, dtype=torch.bool, device=X.device)
    checked = valid[:, :, None] & valid[:, None, :] & off_diagonal & torch.isfinite(rel)
    return rel, checked, checked & (rel > tol)


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
    K = valid.shape[1]
    rel, checked, broken = _pairs(X, valid, distances, tol)
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


Found = tuple[int, int, Tensor, Tensor, Tensor, float]
"""A keypoint :func:`search_layout` found again: ``(frame, keypoint, uv (C, 2), used (C,), place (3,),
score)``."""

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


@dataclass(frozen=True)
class LayoutPrior:
    """Heatmaps of the same frames from another network, whose evidence joins the views' when
    :func:`search_layout` scores places: a two-pass detector's coarse pass, which saw the whole object. Where
    the refining views are flat (a pose they were not trained on), every place on a keypoint's locus scores
    alike and the best one is as likely the keypoint's mirror image across the other two; the coarse
    heatmaps still tell the side.

    Attributes:
        probs: ``(B, C, K, h, w)`` heatmaps (softmax).
        cams: cameras ``(B, C)`` or ``(C,)`` of that network's input pixels.
        stride: its heatmap stride.
    """

    probs: Tensor
    cams: Cameras
    stride: int


def _log_prob_at(hm: Tensor, cams: Cameras, stride: int, places: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Each view's log-probability (at least ``LOG_FLOOR``) of ``places (n, 3)`` under heatmaps
    ``hm (C, h, w)`` seen by ``cams (C,)``: ``(logp (C, n), inside (C, n), cell (C, n))``, ``cell`` the
    row-major index of the place's cell and ``inside`` whether the view's image holds it (in front of the
    camera)."""
    C, h, w = hm.shape
    uv, depth = project(cams, places[None].expand(C, -1, -1))  # (C, n, 2)
    col = torch.round((uv[..., 0] - (stride - 1) / 2) / stride).long()
    row = torch.round((uv[..., 1] - (stride - 1) / 2) / stride).long()
    inside = (depth > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    cell = hm[torch.arange(C)[:, None], row.clamp(0, h - 1), col.clamp(0, w - 1)]
    logp = torch.where(inside, cell.clamp_min(1e-300).log().clamp_min(LOG_FLOOR),
                       torch.full_like(cell, LOG_FLOOR))
    return logp, inside, row.clamp(0, h - 1) * w + col.clamp(0, w - 1)


def search_layout(probs: Tensor, cams: Cameras, stride: int, X: Tensor, kept: Tensor, distances: Tensor,
                  tol: float, window: int, prior: LayoutPrior | None = None,
                  frames: Collection[int] | None = None) -> list[Found]:
    """For every keypoint the layout check left out (``~kept``) in a frame with two keypoints it kept, look
    for it again where the rigid layout puts it.

    Two kept keypoints ``i``, ``j`` (the pair farthest apart by the reference) place it on the circle at its
    reference distances from them (:func:`layout_locus`); places that break its distance to another kept
    keypoint by more than ``tol`` are left out. Each place is scored by the sum over the views of its
    heatmap's log-probability at the place's projection (at least ``LOG_FLOOR``), plus the same sum over the
    ``prior``'s views when one is given, and each view's detection is then its heatmap's mean within
    ``window`` cells of the best place's cell (a view whose image does not hold that cell is not used).

    Args:
        probs: ``(B, C, K, h, w)`` heatmaps.
        cams: cameras ``(B, C)`` or ``(C,)`` of the network-input pixels.
        stride: heatmap stride.
        X: ``(B, K, 3)`` points; kept: ``(B, K)`` bool, the keypoints the layout check kept.
        distances: ``(K, K)`` reference distances (NaN where unknown).
        tol: the layout check's relative tolerance.
        window: the read-out's window, cells (>= 1).
        prior: another network's heatmaps of the same frames (:class:`LayoutPrior`), or None.
        frames: look only in these frames (None: all).

    Returns:
        ``[(b, k, uv (C, 2), used (C,), place (3,), score), ...]``: for the keypoints found again, the new
        detections in network-input pixels, the best place itself and its score.
    """
    ref = distances.to(device=X.device, dtype=DTYPE)
    found = []
    for b, k in (~kept).nonzero().tolist():
        if frames is not None and b not in frames:
            continue
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
        score, inside, cell = _evidence(probs, cams, stride, prior, b, k, places)
        best = int(score.argmax())
        uv = peak_window_mean(probs[b, :, k], stride, window, cell[:, best])
        found.append((b, k, uv, inside[:, best], places[best], float(score[best])))
    return found


def _evidence(probs: Tensor, cams: Cameras, stride: int, prior: LayoutPrior | None, b: int, k: int,
              places: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """How well frame ``b``'s heatmaps of keypoint ``k`` (and the ``prior``'s) support ``places (n, 3)``:
    ``(score (n,), inside (C, n), cell (C, n))``, the score the sum of :func:`_log_prob_at` over the views and
    ``inside``, ``cell`` those of ``probs``' views."""
    frame_cams = cams if len(cams.shape) == 1 else cams[b]
    logp, inside, cell = _log_prob_at(probs[b, :, k], frame_cams, stride, places)
    score = logp.sum(dim=0)
    if prior is not None:
        prior_cams = prior.cams if len(prior.cams.shape) == 1 else prior.cams[b]
        score = score + _log_prob_at(prior.probs[b, :, k], prior_cams, prior.stride, places)[0].sum(dim=0)
    return score, inside, cell


def settle_ties(probs: Tensor, cams: Cameras, stride: int, X: Tensor, valid: Tensor, kept: Tensor,
                distances: Tensor, tol: float, window: int,
                prior: LayoutPrior | None = None) -> tuple[Tensor, dict[int, list[Found]]]:
    """``kept`` (:func:`reject_layout`'s) with its ties settled by the heatmaps' evidence, and the search's
    results in the frames settled.

    When a frame's one broken pair is two keypoints with no other pair against them, the distances cannot
    tell which of the two is off, and the check drops the first. Both ways are tried here: the keypoint left
    out is looked for where the layout puts it (:func:`search_layout`), the other stays where it was
    triangulated, and the way whose two keypoints the heatmaps support better (the search's score plus the
    other's sum over the views of :func:`_log_prob_at` at its point) is kept. Arguments as
    :func:`search_layout`'s, with ``valid (B, K)`` the triangulation's.

    Returns:
        ``(kept, {frame: found})``: ``found`` is :func:`search_layout`'s list for that frame under the
        ``kept`` returned, so that the frame need not be searched again.
    """
    kept = kept.clone()
    settled: dict[int, list[Found]] = {}
    _, _, broken = _pairs(X, valid, distances, tol)
    for b in (broken.sum(dim=(1, 2)) == 2).nonzero().flatten().tolist():  # one pair, counted both ways
        i, j = broken[b].nonzero()[0].tolist()
        if bool(kept[b, i]) == bool(kept[b, j]):
            continue
        ways = []
        for out, stay in ((i, j), (j, i)):
            trial = kept.clone()
            trial[b, out], trial[b, stay] = False, True
            found = search_layout(probs, cams, stride, X, trial, distances, tol, window, prior, frames={b})
            searched = [f[5] for f in found if f[1] == out]
            here = _evidence(probs, cams, stride, prior, b, stay, X[b, stay].to(DTYPE)[None])[0]
            ways.append((searched[0] + float(here[0]) if searched else -math.inf, trial, found))
        _, kept, settled[b] = ways[0] if ways[0][0] >= ways[1][0] else ways[1]
    return kept, settled


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
