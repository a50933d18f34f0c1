"""The geometry the labelling app shows, computed with s3k's own cameras and triangulation.

For one frame, from its 2D labels: each keypoint labelled (visible) in two or more views is triangulated with
unit weights, as the supervised loss does (:func:`s3k.geometry.triangulate_labels`), and reprojected into
every camera (:func:`s3k.geometry.project`, lens distortion included), with the residual of each labelled
view; a keypoint labelled in one view gets its epipolar curve in every other view: the projection of the
view ray of the click (:func:`s3k.geometry.pixel_rays`), a straight line without distortion and a curve with
it.

The app's check of labels that disagree (:func:`label_residuals`, :func:`agreement_level`): a label more than
:data:`DISAGREE_PX` pixels from where the other views put it (the point triangulated from the other labelled
views, two or more, reprojected into its view: docs/tracks.md, "Labels that disagree") disagrees; a residual
up to :data:`GREEN_FACTOR` times its camera's median residual over the dataset's labelled frames (and at least
up to :data:`GREEN_FLOOR_PX`) is as good as the camera's labels usually are.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from s3k.geometry import Cameras, pixel_rays, project
from s3k.geometry import triangulate_labels as geometry_triangulate_labels
from s3k.readout import DTYPE

__all__ = ["DISAGREE_PX", "GREEN_FACTOR", "GREEN_FLOOR_PX", "agreement_level", "epipolar_curves",
           "frame_geometry", "label_residuals", "triangulate_labels"]

EPIPOLAR_SAMPLES = 160
DISAGREE_PX = 40.0
"""A label farther than this (pixels of the dataset's images) from where the other views put it disagrees."""
GREEN_FACTOR = 3.0
"""A residual up to this many times its camera's median residual is usual for the camera (green)."""
GREEN_FLOOR_PX = 2.0
"""...and one up to this many pixels always is: a click's own error, where the labels agree to a fraction."""


def triangulate_labels(cams: Cameras, uv: np.ndarray, mask: np.ndarray) -> dict[str, np.ndarray]:
    """Unit-weight triangulation of one frame's labels (:func:`s3k.geometry.triangulate_labels`) and their
    reprojection.

    Args:
        cams: ``(C,)`` cameras of the frame, in the labels' pixels.
        uv: ``(C, K, 2)`` labels (anything where masked).
        mask: ``(C, K)`` bool, the visible labels.

    Returns:
        ``X (K, 3)`` (NaN where invalid), ``valid (K,)``, ``reproj (C, K, 2)`` (NaN where invalid or behind
        the camera), ``residual (C, K)`` pixels between label and reprojection (NaN where either is missing).
    """
    cams = cams.to(dtype=DTYPE)
    uv_t = torch.as_tensor(np.nan_to_num(np.asarray(uv, dtype=np.float64)))[None]
    used = torch.as_tensor(np.asarray(mask, dtype=bool))[None]
    X_t, valid_t = geometry_triangulate_labels(cams, uv_t, used)
    reproj_t, depth_t = project(cams, X_t[:, None].expand(1, len(cams.K), -1, -1))
    X, valid, reproj, depth = X_t[0].numpy(), valid_t[0].numpy(), reproj_t[0].numpy(), depth_t[0].numpy()
    ok = valid[None, :] & (depth > 1e-6)
    reproj = np.where(ok[..., None], reproj, np.nan)
    X = np.where(valid[:, None], X, np.nan)
    residual = np.where(mask, np.linalg.norm(reproj - np.asarray(uv, dtype=np.float64), axis=-1), np.nan)
    return {"X": X, "valid": valid, "reproj": reproj, "residual": residual}


def _reprojected(cams: Cameras, uv: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """``(B, C, K, 2)``: the points triangulated from the ``mask``-ed labels reprojected into every camera
    (NaN where not triangulated or behind the camera)."""
    X, valid = geometry_triangulate_labels(cams, uv, mask)
    C = cams.K.shape[-3]
    reproj, depth = project(cams, X[..., None, :, :].expand(*X.shape[:-2], C, -1, -1))
    ok = valid[..., None, :] & (depth > 1e-6)
    return np.where(ok[..., None].numpy(), reproj.numpy(), np.nan)


def label_residuals(cams: Cameras, uv: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each visible label's residual and its distance from the other views' agreement, in pixels.

    Args:
        cams: ``(B, C)`` cameras of the frames, in the labels' pixels.
        uv: ``(B, C, K, 2)`` labels (anything where masked).
        mask: ``(B, C, K)`` bool, the visible labels.

    Returns:
        ``residual (B, C, K)``: to the reprojection of the point triangulated from every labelled view (what
        the app shows), and ``offset (B, C, K)``: to the reprojection of the point triangulated from the
        other labelled views, two or more (the check of labels that disagree); NaN where not told.
    """
    cams = cams.to(dtype=DTYPE)
    uv = np.asarray(uv, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    uv_t, mask_t = torch.as_tensor(np.nan_to_num(uv)), torch.as_tensor(mask)
    residual = np.linalg.norm(_reprojected(cams, uv_t, mask_t) - uv, axis=-1)
    offset = np.full(mask.shape, np.nan)
    for c in range(mask.shape[1]):
        others = mask_t.clone()
        others[:, c] = False
        offset[:, c] = np.linalg.norm(_reprojected(cams, uv_t, others)[:, c] - uv[:, c], axis=-1)
    return np.where(mask, residual, np.nan), np.where(mask, offset, np.nan)


def agreement_level(residual: float | None, offset: float | None, median: float | None) -> str | None:
    """How a label's residual is shown: ``"disagrees"`` (red) when it lies more than :data:`DISAGREE_PX` from
    the other views' agreement, ``"high"`` (amber) when its residual is over :data:`GREEN_FACTOR` times its
    camera's ``median`` residual (and over :data:`GREEN_FLOOR_PX`), else ``"ok"`` (green); None without a
    residual."""
    if residual is None:
        return None
    if offset is not None and offset > DISAGREE_PX:
        return "disagrees"
    usual = max(GREEN_FLOOR_PX, GREEN_FACTOR * median) if median is not None else GREEN_FLOOR_PX
    return "high" if residual > usual else "ok"


def epipolar_curves(cams: Cameras, source: int, uv: np.ndarray,
                    image_size: tuple[int, int]) -> list[list[list[float]]]:
    """The view ray of pixel ``uv`` of camera ``source`` as every camera sees it: one polyline per camera
    (empty for ``source`` itself).

    Points of the ray are taken at distances spaced geometrically from 1/100 to 100 times the largest
    distance between ``source`` and another camera centre, projected (with distortion) into each camera, and
    those in front of it and near its image (within one image size of it) kept, so that the curve reaches
    the image's borders: a straight line without distortion, a curve with it.
    """
    cams = cams.to(dtype=DTYPE)
    click = torch.as_tensor(np.asarray(uv, dtype=np.float64)).reshape(1, 2)
    origin, direction = pixel_rays(cams[source], click)
    centres = cams.centres()
    baseline = float(torch.linalg.vector_norm(centres - centres[source], dim=-1).max())
    scale = baseline if baseline > 0 else 1.0
    s = torch.logspace(-2, 2, EPIPOLAR_SAMPLES, dtype=DTYPE) * scale
    X = origin[0] + s[:, None] * direction[0]
    C = len(cams.K)
    pix_t, depth_t = project(cams, X.expand(C, -1, -1))  # every camera at once
    W, H = image_size
    pix, depth = pix_t.numpy(), depth_t.numpy()
    near = (pix[..., 0] > -W) & (pix[..., 0] < 2 * W) & (pix[..., 1] > -H) & (pix[..., 1] < 2 * H)
    keep = (depth > 1e-6) & near
    return [[] if c == source else pix[c][keep[c]].tolist() for c in range(C)]


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def frame_geometry(cams: Cameras, uv: np.ndarray, mask: np.ndarray, keypoints: list[str], cameras: list[str],
                   image_size: tuple[int, int], medians: dict[str, float | None] | None = None
                   ) -> dict[str, Any]:
    """What the app draws for a frame, per keypoint: the 3D point, its reprojections and residuals (with each
    label's distance from the other views' agreement and how its residual is shown, :func:`agreement_level`
    by ``medians``, each camera's median residual), or the epipolar curves of a keypoint labelled in one view.

    Returns:
        ``{keypoint: {"point": [x, y, z] | None, "views": {camera: {"reproj": [u, v] | None,
        "residual": px | None, "offset": px | None, "level": "ok" | "high" | "disagrees" | None}},
        "epipolar": {camera: [[u, v], ...]}}}``.
    """
    tri = triangulate_labels(cams, uv, mask)
    offset = label_residuals(cams.reshape(1, -1), np.asarray(uv)[None], np.asarray(mask)[None])[1][0]
    medians = medians or {}
    out: dict[str, Any] = {}
    for k, kp in enumerate(keypoints):
        views = {}
        for c, cam in enumerate(cameras):
            r = tri["reproj"][c, k]
            res, off = _num(tri["residual"][c, k]), _num(offset[c, k])
            views[cam] = {"reproj": None if not np.isfinite(r).all() else [float(r[0]), float(r[1])],
                          "residual": res, "offset": off,
                          "level": agreement_level(res, off, medians.get(cam))}
        item: dict[str, Any] = {"point": [float(x) for x in tri["X"][k]] if tri["valid"][k] else None,
                                "views": views, "epipolar": {}}
        seen = np.flatnonzero(mask[:, k])
        if len(seen) == 1:
            c0 = int(seen[0])
            curves = epipolar_curves(cams, c0, uv[c0, k], image_size)
            item["epipolar"] = {cam: curves[c] for c, cam in enumerate(cameras) if c != c0}
            item["epipolar_from"] = cameras[c0]
        out[kp] = item
    return out
