"""The geometry the labelling app shows, computed with s3k's own cameras and triangulation.

For one frame, from its 2D labels: each keypoint labelled (visible) in two or more views is triangulated with
unit weights, as the supervised loss does (:func:`s3k.geometry.triangulate_labels`), and reprojected into
every camera (:func:`s3k.geometry.project`, lens distortion included), with the residual of each labelled
view; a keypoint labelled in one view gets its epipolar curve in every other view: the projection of the
view ray of the click (:func:`s3k.geometry.pixel_rays`), a straight line without distortion and a curve with
it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from s3k.geometry import Cameras, pixel_rays, project
from s3k.geometry import triangulate_labels as geometry_triangulate_labels
from s3k.readout import DTYPE

__all__ = ["epipolar_curves", "frame_geometry", "triangulate_labels"]

EPIPOLAR_SAMPLES = 160


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
                   image_size: tuple[int, int]) -> dict[str, Any]:
    """What the app draws for a frame, per keypoint: the 3D point, its reprojections and residuals, or the
    epipolar curves of a keypoint labelled in one view.

    Returns:
        ``{keypoint: {"point": [x, y, z] | None, "views": {camera: {"reproj": [u, v] | None,
        "residual": px | None}}, "epipolar": {camera: [[u, v], ...]}}}``.
    """
    tri = triangulate_labels(cams, uv, mask)
    out: dict[str, Any] = {}
    for k, kp in enumerate(keypoints):
        views = {}
        for c, cam in enumerate(cameras):
            r = tri["reproj"][c, k]
            views[cam] = {"reproj": None if not np.isfinite(r).all() else [float(r[0]), float(r[1])],
                          "residual": _num(tri["residual"][c, k])}
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
