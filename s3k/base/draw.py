"""Drawing keypoints on images: one colour per keypoint, the skeleton's edges in white, shared by every
picture s3k makes.

:func:`draw_overlay` marks one camera's detections and reprojected 3D points on a video frame (``s3k track
--overlay``); :func:`draw_views` puts a frame's camera views side by side with their heatmaps, predicted and
true keypoints (``s3k evaluate --report``, training's validation images). Images are ``uint8 (H, W, 3)`` RGB;
pixel (0, 0) is the centre of the top-left pixel, for s3k and for OpenCV's drawing alike.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

__all__ = ["draw_edges", "draw_overlay", "draw_views", "edge_indices", "keypoint_colours"]

SKELETON_COLOUR = (255, 255, 255)


def edge_indices(skeleton: Sequence[Sequence[str]], keypoints: Sequence[str]) -> np.ndarray:
    """``(E, 2)`` int keypoint indices of the skeleton's edges (those naming another keypoint left out)."""
    index = {k: i for i, k in enumerate(keypoints)}
    pairs = [(index[a], index[b]) for a, b in skeleton if a in index and b in index]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def draw_edges(image: np.ndarray, uv: np.ndarray, edges: np.ndarray, colour=SKELETON_COLOUR,
               thickness: int = 1, scale: float = 1.0) -> None:
    """Draw the skeleton's ``edges (E, 2)`` between the points ``uv (K, 2)`` (pixels; an edge with a NaN or
    far-off end is skipped) on ``image`` in place, ``scale`` times the pixel coordinates."""

    shift = 4
    for a, b in np.asarray(edges, dtype=np.int64).reshape(-1, 2):
        ends = np.asarray(uv, dtype=np.float64)[[a, b]]
        if not np.isfinite(ends).all() or np.abs(ends).max() > 1e5:
            continue
        p, q = (tuple(int(round(((v + 0.5) * scale - 0.5) * (1 << shift))) for v in end) for end in ends)
        cv2.line(image, p, q, colour, thickness, cv2.LINE_AA, shift)


def keypoint_colours(n: int) -> list[tuple[int, int, int]]:
    """``n`` distinct saturated RGB colours (hues evenly spaced)."""
    hsv = np.array([[[int(180 * k / max(n, 1)), 230, 255] for k in range(n)]], dtype=np.uint8)
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]
    return [(int(c[0]), int(c[1]), int(c[2])) for c in rgb]


def draw_overlay(image: np.ndarray, reproj: np.ndarray, uv: np.ndarray, used: np.ndarray,
                 colours: Sequence[tuple[int, int, int]], edges: np.ndarray | None = None) -> np.ndarray:
    """Draw one camera's keypoints on a copy of ``image`` (H, W, 3) RGB.

    Args:
        image: the original video frame.
        reproj: ``(K, 2)`` reprojected 3D keypoints (NaN where invalid): filled discs.
        uv: ``(K, 2)`` the view's own detections: crosses, thick where the view was used.
        used: ``(K,)`` whether the view entered the triangulation.
        colours: one RGB colour per keypoint.
        edges: ``(E, 2)`` skeleton edges (:func:`edge_indices`), drawn between the reprojected points.
    """
    out = np.ascontiguousarray(image).copy()
    H, W = out.shape[:2]
    r = max(2, round(min(H, W) / 80))
    if edges is not None and len(edges):
        draw_edges(out, reproj, edges, (0, 0, 0), max(2, r // 2) + 2)  # a dark rim: seen on any background
        draw_edges(out, reproj, edges, SKELETON_COLOUR, max(2, r // 2))
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    for k, colour in enumerate(colours):
        # Pixel (0, 0) is the centre of the top-left pixel for s3k and for OpenCV's drawing alike.
        if np.all(np.isfinite(uv[k])):
            cx, cy = (int(round(v * (1 << shift))) for v in uv[k])
            s = (r + 1) << shift
            thick = 2 if used[k] else 1
            cv2.line(out, (cx - s, cy), (cx + s, cy), colour, thick, cv2.LINE_AA, shift)
            cv2.line(out, (cx, cy - s), (cx, cy + s), colour, thick, cv2.LINE_AA, shift)
        if np.all(np.isfinite(reproj[k])) and np.all(np.abs(reproj[k]) < 1e5):
            centre = tuple(int(round(v * (1 << shift))) for v in reproj[k])
            cv2.circle(out, centre, r << shift, colour, -1, cv2.LINE_AA, shift)
            cv2.circle(out, centre, r << shift, (0, 0, 0), 1, cv2.LINE_AA, shift)
    return out


def draw_views(images: np.ndarray, probs: np.ndarray | None, pred_uv: np.ndarray, true_uv: np.ndarray | None,
               true_mask: np.ndarray | None = None, scale: int = 3,
               edges: np.ndarray | None = None) -> np.ndarray:
    """One frame's views side by side with heatmaps, predicted (cross) and true (circle) keypoints.

    Args:
        images: (C, H, W, 3) uint8 RGB.
        probs: (C, K, h, w) heatmaps (softmax) or None; their per-pixel maximum over K is overlaid.
        pred_uv: (C, K, 2) predictions, pixels.
        true_uv: (C, K, 2) ground truth, or None.
        true_mask: (C, K) bool, or None (all shown).
        scale: upscaling factor for legibility.
        edges: ``(E, 2)`` skeleton edges (:func:`edge_indices`), drawn between the predicted points.

    Returns:
        (scale * H, C * scale * W, 3) uint8 RGB image.
    """
    C, H, W, _ = images.shape
    colours = keypoint_colours(pred_uv.shape[1])
    tiles = []
    for c in range(C):
        tile = cv2.resize(np.ascontiguousarray(images[c]), (W * scale, H * scale),
                          interpolation=cv2.INTER_NEAREST)
        if probs is not None:
            heat = probs[c].max(axis=0)
            heat = heat / max(float(heat.max()), 1e-12)
            heat = cv2.resize(heat.astype(np.float32), (W * scale, H * scale), interpolation=cv2.INTER_LINEAR)
            coloured = cv2.applyColorMap((heat * 255).astype(np.uint8), cv2.COLORMAP_JET)[..., ::-1]
            alpha = (0.6 * heat)[..., None]
            tile = (tile * (1 - alpha) + coloured * alpha).astype(np.uint8)
        tile = np.ascontiguousarray(tile)
        if edges is not None and len(edges):
            draw_edges(tile, pred_uv[c], edges, SKELETON_COLOUR, 1, scale)
        for k in range(pred_uv.shape[1]):
            col = colours[k]

            def px(uv):
                return int(round((uv[0] + 0.5) * scale - 0.5)), int(round((uv[1] + 0.5) * scale - 0.5))

            show_true = true_uv is not None and (true_mask is None or bool(true_mask[c, k]))
            if true_uv is not None and show_true and np.isfinite(true_uv[c, k]).all():
                cv2.circle(tile, px(true_uv[c, k]), 3 * scale, col, 1, cv2.LINE_AA)
            if np.isfinite(pred_uv[c, k]).all():
                cv2.drawMarker(tile, px(pred_uv[c, k]), col, cv2.MARKER_TILTED_CROSS, 3 * scale, 1,
                               cv2.LINE_AA)
        cv2.rectangle(tile, (0, 0), (W * scale - 1, H * scale - 1), (255, 255, 255), 1)
        tiles.append(tile)
    return np.concatenate(tiles, axis=1)
