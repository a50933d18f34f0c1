"""The choices ``s3k import`` makes about a recording's frames and images: the dataset's image size
(:func:`output_size`, with small differences between cameras padded away, :func:`pad_to_one_size`), the
labels that fall outside the images (:func:`drop_outside`), and which frames are labelled, test or unlabelled
(:func:`labelled_count`, :func:`split_frames`)."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from s3k.base.errors import UserError

log = logging.getLogger(__name__)

Box = tuple[float, float, float, float]  # x0, y0, x1, y1 in pixel edge coordinates


def output_size(boxes: Sequence[Box], size: int | tuple[int, int] | None,
                scale: float | None) -> tuple[int, int]:
    """The dataset's image size ``(W, H)`` for crops ``boxes``: ``size`` as ``(W, H)`` or as the longer side
    (aspect kept; crops must share it), or the crop size times ``scale``, or the crop size itself."""
    widths = {b[2] - b[0] for b in boxes}
    heights = {b[3] - b[1] for b in boxes}
    if scale is not None:
        if scale <= 0:
            raise UserError(f"--scale must be positive, got {scale}")
        if len(widths) > 1 or len(heights) > 1:
            raise UserError(f"--scale {scale}: the images have different sizes ({_sizes(boxes)})",
                            hint="give the dataset's size instead: --size W,H")
        return max(1, round(widths.pop() * scale)), max(1, round(heights.pop() * scale))
    if isinstance(size, int):
        if size <= 0:
            raise UserError(f"--size {size}: must be positive")
        # One number: the longer side, aspect ratio kept (crops must share it).
        if len({round((b[2] - b[0]) / (b[3] - b[1]), 6) for b in boxes}) > 1:
            raise UserError(f"--size {size}: the images have different aspect ratios ({_sizes(boxes)})",
                            hint="give both sides: --size W,H")
        w, h = boxes[0][2] - boxes[0][0], boxes[0][3] - boxes[0][1]
        s = size / max(w, h)
        return max(1, round(w * s)), max(1, round(h * s))
    if size is not None:
        if len(size) != 2 or min(size) <= 0:
            raise UserError(f"--size {size}: expected two positive integers W,H")
        return int(size[0]), int(size[1])
    if len(widths) > 1 or len(heights) > 1:
        raise UserError(f"images of different sizes ({_sizes(boxes)}) need one size in the dataset",
                        hint=f"give it with --size W,H, e.g. --size {max(widths):g},{max(heights):g}")
    w, h = widths.pop(), heights.pop()
    if w != int(w) or h != int(h):
        raise UserError("a crop with a fractional size needs --size")
    return int(w), int(h)


def _sizes(boxes: Sequence[Box]) -> str:
    return ", ".join(sorted({f"{b[2] - b[0]:g}x{b[3] - b[1]:g}" for b in boxes}))


PADDING_PX = 16
"""Sizes this close (per side, in pixels) differ by an encoder's padding: a video of 1080 rows calibrated at
1088, or cameras whose images differ so little that the smaller ones are padded to the largest."""


def pad_to_one_size(boxes: list[Box], cameras: list[str]) -> list[Box]:
    """Whole-image boxes of sizes within :data:`PADDING_PX` of each other, grown at the right and bottom to
    the largest (black pixels; intrinsics and labels unchanged), said in a note; other boxes as they are."""
    widths = [b[2] - b[0] for b in boxes]
    heights = [b[3] - b[1] for b in boxes]
    W, H = max(widths), max(heights)
    if (len(set(widths)) == 1 and len(set(heights)) == 1) or W - min(widths) > PADDING_PX \
            or H - min(heights) > PADDING_PX:
        return boxes
    grown = [cam for cam, w, h in zip(cameras, widths, heights) if (w, h) != (W, H)]
    log.info(f"note: the images of {', '.join(grown)} are padded with black at the right and bottom to "
          f"{W:g}x{H:g}, the largest camera's size (--size W,H resizes instead)")
    return [(b[0], b[1], b[0] + W, b[1] + H) for b in boxes]


def split_frames(
    candidates: np.ndarray, all_frames: np.ndarray, n_labelled: int | str, n_test: int, seed: int, stride: int
) -> dict[int, str]:
    """Random labelled / test frames among ``candidates``; the rest (every ``stride``-th) unlabelled.
    ``n_labelled`` is a count or ``"all"``."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(candidates)
    if n_test < 0:
        raise UserError(f"--test must be >= 0, got {n_test}")
    if n_test > len(order):
        raise UserError(f"--test {n_test}: only {len(order)} frames have a keypoint labelled in >= 2 views")
    test = order[:n_test]
    rest = order[n_test:]
    if str(n_labelled) == "all":
        labelled = rest
    else:
        n = int(n_labelled)
        if n < 0 or n > len(rest):
            raise UserError(
                f"--labelled {n}: {len(rest)} frames with a keypoint labelled in >= 2 views remain after "
                f"{n_test} test frames"
            )
        labelled = rest[:n]
    splits = {int(f): "unlabelled" for f in all_frames if f % stride == 0}
    splits.update({int(f): "test" for f in test})
    splits.update({int(f): "labelled" for f in labelled})
    return dict(sorted(splits.items()))


def image_areas(boxes: Sequence[Box], image_sizes, size: tuple[int, int]) -> np.ndarray:
    """``(C, 4)``: per camera, the part of the dataset's image of ``size`` that shows the camera's image of
    ``image_sizes[c] = (W, H)`` cut by ``boxes[c]``, as ``u0, v0, u1, v1`` in pixel-centre coordinates (a box
    reaching beyond the image, as when padding, leaves black pixels outside it)."""
    out = []
    for (x0, y0, x1, y1), (W, H) in zip(boxes, image_sizes):
        sx, sy = size[0] / (x1 - x0), size[1] / (y1 - y0)
        out.append([max(0.0, -x0 * sx), max(0.0, -y0 * sy), min(size[0], (W - x0) * sx),
                    min(size[1], (H - y0) * sy)])
    return np.asarray(out, dtype=np.float64) - 0.5


def drop_outside(uv: np.ndarray, areas: np.ndarray, cameras: list[str], names: list[str]) -> str:
    """Set the labels ``uv (F, C, K, 2)`` outside the images' ``areas`` (:func:`image_areas`) to NaN; the
    sentence saying how many were dropped, with an example (empty when none was), printed as a note, or as a
    warning when most were."""
    u0, v0, u1, v1 = (areas[None, :, None, i] for i in range(4))
    inside = (uv[..., 0] >= u0) & (uv[..., 0] <= u1) & (uv[..., 1] >= v0) & (uv[..., 1] <= v1)
    known = np.isfinite(uv).all(-1)
    outside = known & ~inside
    if not outside.any():
        return ""
    f, c, k = np.argwhere(outside)[0]
    u, v = uv[f, c, k]
    W, H = areas[c, 2:] - areas[c, :2]
    text = (f"{int(outside.sum())} of {int(known.sum())} labels fall outside the (cropped) images and are "
            f"dropped (e.g. camera {cameras[c]} frame {f} {names[k]} at x {u:.0f}, y {v:.0f} in {W:g}x{H:g})")
    uv[~inside] = np.nan
    if outside.sum() <= known.sum() / 2:
        log.info(f"note: {text}")
        return ""
    log.warning(text)
    return text


DEFAULT_LABELLED = 10


def labelled_count(candidates: np.ndarray, labelled: int | str | None, test: int, min_views: int,
                    dropped: str) -> int | str:
    """The number of labelled frames: ``labelled`` as given, or (None) :data:`DEFAULT_LABELLED`, or every
    frame left after the test frames when fewer are, said in a note. Refuses a recording where no frame can
    be labelled, with the reason when most labels fell outside the images."""
    if not len(candidates) or (dropped and len(candidates) < test + (
            DEFAULT_LABELLED if labelled is None else 0 if labelled == "all" else int(labelled))):
        kept = f"{len(candidates)} frames keep a keypoint labelled in >= {min_views} cameras"
        raise UserError(
            f"{dropped}: {kept}" if dropped else f"no frame has a keypoint labelled in >= {min_views} "
            "cameras",
            hint="the labels are not in the videos' pixels: check the label format's layout, --video-region "
                 "and --crop (docs/importing.md)" if dropped else
                 "label a keypoint in two cameras of a frame, and check that each label file is the camera's")
    if labelled is not None:
        return labelled
    left = max(len(candidates) - max(test, 0), 0)
    if left < DEFAULT_LABELLED:
        log.info(f"note: {len(candidates)} frames have a keypoint labelled in >= {min_views} cameras: "
              f"{left} labelled, {test} test (--labelled N and --test N choose)")
    return min(DEFAULT_LABELLED, left)
