"""The one module that crops and resizes images and maps the cameras with them (``K' = M K``): a crop box
onto an output size (:func:`crop_resize_matrix`, :func:`resize_crop`: the dataset's resize, OpenCV or torch),
batched crop maps and crops cut around the reprojection of a 3D point at a metric size
(:func:`metric_crop_boxes`, :func:`crop_maps`, :func:`crop_images`: the refining pass's crops), and a
region resampled onto a network's input on any device (:func:`resample_regions`).

The one function that resizes or crops images and updates the intrinsics with them.

Convention (docs/method.md#conventions): pixel ``(0, 0)`` is the centre of the top-left pixel, so pixel
column ``i`` covers ``[i - 0.5, i + 0.5]`` in pixel coordinates. A crop box ``(x0, y0, x1, y1)`` is given in
pixel *edge* coordinates, where column ``i`` covers ``[i, i + 1)``: the whole image is ``(0, 0, W, H)`` and
an integer box keeps columns ``x0 .. x1 - 1`` and rows ``y0 .. y1 - 1``. Mapping the box onto an output of
``(w, h)`` pixels scales by ``s_x = w / (x1 - x0)``, ``s_y = h / (y1 - y0)`` and sends a pixel coordinate
``u`` to

    u' = s_x (u + 0.5 - x0) - 0.5,

so for a plain resize (``x0 = 0``) a scale ``s`` maps ``u -> s (u + 0.5) - 0.5``. Written as a 3x3 matrix
``M`` acting on homogeneous pixels, the new intrinsics are exactly ``K' = M @ K``; lens distortion acts on
normalized coordinates before ``K`` and is unchanged.

Scale-normalized crops: every camera gets a crop centred on a 3D estimate's reprojection whose side covers
``extent`` world units at the estimate's depth; resampled to the network's input size, the object has the same
size in every crop whatever the camera's distance or focal length.

Shapes: ``L`` the leading dims of a camera set (``(B, C)`` per frame), ``N`` images.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from s3k.geometry.cameras import Cameras
from s3k.geometry.projection import project

__all__ = ["Box", "crop_images", "crop_maps", "crop_resize_matrix", "metric_crop_boxes", "model_image_size",
           "region_around", "regions_around", "resample_regions", "resize_crop", "transform_points"]

Box = Sequence[float]


def _check_box(crop_box: Box | None, in_size: tuple[int, int]) -> tuple[float, float, float, float]:
    W, H = in_size
    if crop_box is None:
        return 0.0, 0.0, float(W), float(H)
    if len(crop_box) != 4:
        raise ValueError(f"crop_box must be (x0, y0, x1, y1), got {crop_box!r}")
    x0, y0, x1, y1 = (float(c) for c in crop_box)
    if not all(np.isfinite([x0, y0, x1, y1])):
        raise ValueError(f"crop_box must be finite, got {crop_box!r}")
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"crop_box must have x1 > x0 and y1 > y0, got {crop_box!r}")
    return x0, y0, x1, y1


def _check_out_size(
    out_size: Sequence[int] | None, box: tuple[float, float, float, float]
) -> tuple[int, int]:
    if out_size is None:
        w, h = box[2] - box[0], box[3] - box[1]
        if w != int(w) or h != int(h):
            raise ValueError(f"out_size is needed when the crop box {box} has a fractional size")
        return int(w), int(h)
    if len(out_size) != 2 or int(out_size[0]) != out_size[0] or int(out_size[1]) != out_size[1]:
        raise ValueError(f"out_size must be (W, H) integers, got {out_size!r}")
    w, h = int(out_size[0]), int(out_size[1])
    if w <= 0 or h <= 0:
        raise ValueError(f"out_size must be positive, got {out_size!r}")
    return w, h


def crop_resize_matrix(crop_box: Box, out_size: Sequence[int]) -> np.ndarray:
    """The 3x3 pixel map ``M`` of a crop box onto an output image (float64).

    Args:
        crop_box: ``(x0, y0, x1, y1)`` in pixel edge coordinates (whole image: ``(0, 0, W, H)``).
        out_size: output ``(w, h)``.

    Returns:
        ``M (3, 3)`` with ``[u', v', 1] = M @ [u, v, 1]`` in the pixel-centre convention.

    Example:
        >>> (crop_resize_matrix((0, 0, 4, 4), (2, 2)) @ [0.5, 0.5, 1.0]).tolist()  # centre of a 2x2 block
        [0.0, 0.0, 1.0]
    """
    x0, y0, x1, y1 = _check_box(crop_box, (1, 1))
    w, h = _check_out_size(out_size, (x0, y0, x1, y1))
    sx, sy = w / (x1 - x0), h / (y1 - y0)
    return np.array(
        [[sx, 0.0, sx * (0.5 - x0) - 0.5], [0.0, sy, sy * (0.5 - y0) - 0.5], [0.0, 0.0, 1.0]],
        dtype=np.float64,
    )


def _is_plain_crop(box: tuple[float, float, float, float], in_size: tuple[int, int]) -> bool:
    """An integer box inside the image: the crop is a slice and the resize can use area averaging."""
    W, H = in_size
    x0, y0, x1, y1 = box
    integral = all(float(c).is_integer() for c in box)
    return integral and x0 >= 0 and y0 >= 0 and x1 <= W and y1 <= H


def _warp_numpy(img: np.ndarray, box, in_size, out_size, M: np.ndarray) -> np.ndarray:
    w, h = out_size
    if _is_plain_crop(box, in_size):
        x0, y0, x1, y1 = (int(c) for c in box)
        sub = img[y0:y1, x0:x1]
        if (x1 - x0, y1 - y0) == (w, h):
            return np.ascontiguousarray(sub)
        # Both OpenCV modes follow the pixel-centre convention: INTER_LINEAR samples at s^-1 (u' + 0.5) - 0.5,
        # INTER_AREA averages the footprint [u' / s, (u' + 1) / s) in edge coordinates.
        shrinking = w <= (x1 - x0) and h <= (y1 - y0)
        interp = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
        return cv2.resize(np.ascontiguousarray(sub), (w, h), interpolation=interp)
    # warpAffine uses integer pixel centres too, so the same M applies; outside the image is black.
    return cv2.warpAffine(
        img, M[:2], (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )


def _warp_torch(images, box, in_size, out_size, M: np.ndarray):
    lead = images.shape[:-3]
    H, W = images.shape[-3], images.shape[-2]
    w, h = out_size
    x = images.reshape(-1, H, W, images.shape[-1]).permute(0, 3, 1, 2)
    work = x if x.is_floating_point() else x.float()
    if _is_plain_crop(box, in_size):
        x0, y0, x1, y1 = (int(c) for c in box)
        work = work[:, :, y0:y1, x0:x1]
        if (x1 - x0, y1 - y0) != (w, h):
            shrinking = w < (x1 - x0) or h < (y1 - y0)
            # align_corners=False is the pixel-centre convention; antialias averages when shrinking.
            work = F.interpolate(work, size=(h, w), mode="bilinear", align_corners=False, antialias=shrinking)
    else:
        Minv = np.linalg.inv(M)
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        src = np.einsum("ij,jhw->ihw", Minv, np.stack([uu, vv, np.ones_like(uu)]))
        # grid_sample with align_corners=False: normalized x = (2 u + 1) / W - 1 for pixel-centre u.
        gx = (2 * src[0] + 1) / W - 1
        gy = (2 * src[1] + 1) / H - 1
        grid = torch.as_tensor(np.stack([gx, gy], -1), dtype=work.dtype, device=work.device)
        grid = grid.expand(work.shape[0], h, w, 2)
        work = F.grid_sample(work, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    if not images.is_floating_point():
        info = torch.iinfo(images.dtype)
        work = work.round().clamp(info.min, info.max).to(images.dtype)
    return work.permute(0, 2, 3, 1).reshape(*lead, h, w, images.shape[-1]).contiguous()


def resize_crop(images, K=None, crop_box: Box | None = None, out_size: Sequence[int] | None = None):
    """Crop ``images`` to ``crop_box`` and resize to ``out_size``, updating the intrinsics exactly.

    Works on numpy arrays (OpenCV; area averaging when shrinking with an integer box) and on torch tensors
    (``F.interpolate`` / ``F.grid_sample``); the output has the input's type and dtype. A box reaching outside
    the image pads with zeros.

    Args:
        images: ``(..., H, W, 3)`` images (uint8 or float), numpy or torch; may be None to update ``K`` only.
        K: ``(..., 3, 3)`` intrinsics, numpy or torch (any leading dims), or None.
        crop_box: ``(x0, y0, x1, y1)`` in pixel edge coordinates; None keeps the whole image. With
            ``images=None`` a box is required.
        out_size: output ``(w, h)``; None keeps the box size (which must then be integral).

    Returns:
        ``(images (..., h, w, 3), K' (..., 3, 3))`` with ``K' = M @ K`` for
        ``M = crop_resize_matrix(box, out)`` (``K'`` is None when ``K`` is None).

    Example:
        >>> img = np.zeros((48, 64, 3), np.uint8)
        >>> K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
        >>> small, K2 = resize_crop(img, K, None, (32, 24))
        >>> small.shape, float(K2[0, 0]), float(K2[0, 2])
        ((24, 32, 3), 25.0, 15.5)
    """
    if images is None:
        if crop_box is None:
            raise ValueError("resize_crop without images needs an explicit crop_box")
        in_size = (1, 1)
    else:
        if images.ndim < 3:
            raise ValueError(f"images must have shape (..., H, W, 3), got {tuple(images.shape)}")
        in_size = (int(images.shape[-2]), int(images.shape[-3]))
    box = _check_box(crop_box, in_size)
    out = _check_out_size(out_size, box)
    M = crop_resize_matrix(box, out)

    new_K: Any = None
    if K is not None:
        if tuple(K.shape[-2:]) != (3, 3):
            raise ValueError(f"K must have shape (..., 3, 3), got {tuple(K.shape)}")
        if isinstance(K, torch.Tensor):
            new_K = torch.as_tensor(M, dtype=K.dtype, device=K.device) @ K
        else:
            new_K = (M @ np.asarray(K, dtype=np.float64)).astype(np.result_type(K.dtype, np.float32))

    if images is None:
        return None, new_K
    if isinstance(images, torch.Tensor):
        return _warp_torch(images, box, in_size, out, M), new_K
    images = np.asarray(images)
    lead = images.shape[:-3]
    flat = images.reshape(-1, *images.shape[-3:])
    result = np.empty((flat.shape[0], out[1], out[0], images.shape[-1]), dtype=images.dtype)
    for i in range(flat.shape[0]):
        result[i] = _warp_numpy(flat[i], box, in_size, out, M).reshape(result.shape[1:])
    return result.reshape(*lead, out[1], out[0], images.shape[-1]), new_K


def transform_points(uv, M: np.ndarray):
    """Apply a pixel map ``M (3, 3)`` (e.g. from :func:`crop_resize_matrix`) to pixels ``uv (..., 2)``."""
    uv = np.asarray(uv, dtype=np.float64)
    return uv @ M[:2, :2].T + M[:2, 2]


def metric_crop_boxes(
    cams: Cameras, centres: Tensor, extent: float, eps: float = 1e-6
) -> tuple[Tensor, Tensor]:
    """Square-in-metres crop boxes centred on the reprojection of 3D points.

    The half-side of the box is ``f * extent / (2 z)`` pixels (``f`` the focal length along each axis, ``z``
    the point's depth), so a crop resampled to a fixed size shows ``extent`` metres whatever the camera.

    Args:
        cams: cameras with leading dims ``L`` (e.g. ``(B, C)``).
        centres: ``(*L', 3)`` world points that broadcast against ``L`` (e.g. ``(B, 1, 3)`` for one point per
            frame seen by every camera).
        extent: side of the crop in world units at the point's depth (> 0).
        eps: depths at or below this are "behind the camera".

    Returns:
        ``boxes (*L, 4)`` as ``(x0, y0, x1, y1)`` in pixel edge coordinates and ``in_front (*L)``: False where
        the point is behind the camera (its box is then the unit box at the origin and must not be used).

    Example:
        >>> cams = Cameras(K=torch.tensor([[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]]), dist=None,
        ...                R=torch.eye(3), t=torch.tensor([0.0, 0.0, 2.0]))
        >>> boxes, ok = metric_crop_boxes(cams, torch.zeros(3), extent=0.4)
        >>> boxes.tolist(), bool(ok)
        ([40.0, 40.0, 60.0, 60.0], True)
    """
    if not extent > 0:
        raise ValueError(f"extent: must be > 0, got {extent}")
    if centres.shape[-1:] != (3,):
        raise ValueError(f"centres: expected shape (*, 3), got {tuple(centres.shape)}")
    centres = centres.to(cams.dtype)
    uv, depth = project(cams, centres[..., None, :])  # (*L, 1, 2), (*L, 1)
    uv, depth = uv[..., 0, :], depth[..., 0]
    in_front = depth > eps
    z = torch.where(in_front, depth, torch.ones_like(depth))
    half = 0.5 * extent * torch.stack([cams.K[..., 0, 0], cams.K[..., 1, 1]], -1).abs() / z[..., None]
    centre_edge = uv + 0.5  # pixel-centre -> edge coordinates
    boxes = torch.cat([centre_edge - half, centre_edge + half], -1)
    unit = torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=boxes.dtype, device=boxes.device)
    return torch.where(in_front[..., None], boxes, unit), in_front


def crop_maps(boxes: Tensor, out_size: Sequence[int]) -> Tensor:
    """The pixel maps ``M`` of crop boxes onto an output of ``(w, h)`` pixels, batched.

    Same map as :func:`s3k.geometry.warp.crop_resize_matrix`: ``u' = s_x (u + 0.5 - x0) - 0.5`` with
    ``s_x = w / (x1 - x0)``; the crop's intrinsics are ``K' = M @ K``.

    Args:
        boxes: ``(*, 4)`` crop boxes ``(x0, y0, x1, y1)`` in pixel edge coordinates.
        out_size: ``(w, h)``.

    Returns:
        ``M (*, 3, 3)`` in the boxes' dtype.
    """
    w, h = (int(s) for s in out_size)
    x0, y0, x1, y1 = boxes.unbind(-1)
    if bool(((x1 <= x0) | (y1 <= y0)).any()):
        raise ValueError("boxes: every box needs x1 > x0 and y1 > y0")
    sx, sy = w / (x1 - x0), h / (y1 - y0)
    zero, one = torch.zeros_like(sx), torch.ones_like(sx)
    rows = [
        torch.stack([sx, zero, sx * (0.5 - x0) - 0.5], -1),
        torch.stack([zero, sy, sy * (0.5 - y0) - 0.5], -1),
        torch.stack([zero, zero, one], -1),
    ]
    return torch.stack(rows, -2)


def region_around(v: Tensor, box: Tensor, size: Sequence[int]) -> tuple[Tensor, Tensor]:
    """``(frames (B, H', W', 3), boxes (B, 4))``: the frames cut to the region around their boxes and the
    boxes in its pixels (the whole frames when the boxes reach past them). The region starts at a multiple of
    the coarsest mip level's block (:func:`crop_images`) and keeps a block of margin, so the
    resampling sees exactly the pixels it would in the whole frame; only that region is made float.

    ``v (B, H, W, 3)``: frames; ``box (B, 4)``: their boxes in pixel edge coordinates; ``size``: the output
    ``(w, h)`` the boxes are resampled to."""
    H, W = v.shape[1], v.shape[2]
    shrink = float(torch.maximum((box[:, 2] - box[:, 0]) / size[0], (box[:, 3] - box[:, 1]) / size[1]).max())
    align = 2 ** (max(0, math.floor(math.log2(max(shrink, 1.0)))) + 1)
    lo = torch.floor((box[:, :2].min(dim=0).values - align) / align) * align
    hi = torch.ceil((box[:, 2:].max(dim=0).values + align) / align) * align
    x0, y0 = max(0, int(lo[0])), max(0, int(lo[1]))
    x1, y1 = min(W, int(hi[0])), min(H, int(hi[1]))
    if x1 <= x0 or y1 <= y0 or (x0, y0, x1, y1) == (0, 0, W, H):
        return v, box
    return v[:, y0:y1, x0:x1], box - box.new_tensor([x0, y0, x0, y0])


def regions_around(views: Sequence[Tensor], boxes: Tensor,
                   size: Sequence[int]) -> tuple[Tensor, Tensor] | None:
    """:func:`region_around` of every camera at once, the regions of one common size: ``(regions (B, C, H',
    W', 3), boxes (B, C, 4))``, the boxes in their region's pixels, ready for one :func:`crop_images` call
    over all views. None where the cameras' frames differ in size or a common region cannot start on the mip
    block (then cut each camera with :func:`region_around`).

    ``views``: ``C`` frames ``(B, H, W, 3)``; ``boxes (B, C, 4)``; ``size``: the output ``(w, h)``. Each
    camera's region starts where :func:`region_around`'s does (moved back only as far as the frame's far edge
    needs) and every region takes the largest one's size, so each sees the pixels it would in the whole frame.
    """
    if len({tuple(v.shape) for v in views}) != 1:
        return None
    H, W = int(views[0].shape[1]), int(views[0].shape[2])
    shrink = float(torch.maximum((boxes[..., 2] - boxes[..., 0]) / size[0],
                                 (boxes[..., 3] - boxes[..., 1]) / size[1]).max())
    align = 2 ** (max(0, math.floor(math.log2(max(shrink, 1.0)))) + 1)
    lo = (torch.floor((boxes[..., :2].amin(dim=0) - align) / align) * align).clamp_min(0)  # (C, 2)
    hi = torch.minimum(torch.ceil((boxes[..., 2:].amax(dim=0) + align) / align) * align,
                       boxes.new_tensor([W, H]))
    extent = (hi - lo).amax(dim=0)  # (2,) the common region's width and height
    if bool((extent <= 0).any()):
        return None
    Wr, Hr = min(W, int(extent[0])), min(H, int(extent[1]))
    starts = torch.minimum(lo, boxes.new_tensor([W - Wr, H - Hr])).to(torch.int64).tolist()
    if any(x % align or y % align for x, y in starts):  # moved back off the mip block
        return None
    regions = torch.stack([v[:, y:y + Hr, x:x + Wr] for v, (x, y) in zip(views, starts)], 1)
    origin = boxes.new_tensor(starts).repeat(1, 2)  # (C, 4)
    return regions, boxes - origin


def crop_images(images: Tensor, boxes: Tensor, out_size: Sequence[int]) -> Tensor:
    """Cut one box from each image and resample it to ``out_size`` (bilinear, zeros outside the image).

    A box much larger than the output would alias under plain bilinear sampling, so each image is first
    averaged down by the largest power of two that keeps the box at least as large as the output (a level of
    a mip pyramid), then sampled bilinearly; the pixel-centre convention holds at every level
    (``u_level = (u + 0.5) / 2**level - 0.5``).

    Args:
        images: ``(N, ch, H, W)`` floating images.
        boxes: ``(N, 4)`` crop boxes in pixel edge coordinates of the full image.
        out_size: ``(w, h)``.

    Returns:
        ``(N, ch, h, w)`` crops; pixel ``(u', v')`` of crop ``n`` samples the image at
        ``M_n^-1 [u', v', 1]`` with ``M_n = crop_maps(boxes)[n]``.
    """
    if images.ndim != 4 or not images.is_floating_point():
        raise ValueError(f"images: expected floating (N, ch, H, W), got {tuple(images.shape)} {images.dtype}")
    if boxes.shape != (images.shape[0], 4):
        raise ValueError(f"boxes: expected shape ({images.shape[0]}, 4), got {tuple(boxes.shape)}")
    w, h = (int(s) for s in out_size)
    boxes = boxes.to(images.dtype)
    shrink = torch.minimum((boxes[:, 2] - boxes[:, 0]) / w, (boxes[:, 3] - boxes[:, 1]) / h)
    levels = torch.floor(torch.log2(shrink.clamp(min=1.0))).to(torch.int64)
    # no level below 2 pixels on a side
    top = max(0, int(torch.log2(torch.tensor(float(min(images.shape[-2:])))).floor()) - 1)
    levels = levels.clamp(max=top)
    out = None
    t_u = (torch.arange(w, dtype=images.dtype, device=images.device) + 0.5) / w
    t_v = (torch.arange(h, dtype=images.dtype, device=images.device) + 0.5) / h
    level_image = images
    for level in range(int(levels.max()) + 1 if len(levels) else 0):
        if level > 0:
            level_image = F.avg_pool2d(level_image, 2, ceil_mode=True, count_include_pad=False)
        pick = levels == level
        if not bool(pick.any()):
            continue
        whole = bool(pick.all())  # every image at this level: no masked copies
        b = (boxes if whole else boxes[pick]) / 2.0**level  # edge coordinates at this level
        Hl, Wl = level_image.shape[-2:]
        # crop pixel centres in level edge coordinates, then grid_sample's [-1, 1] (align_corners=False:
        # edge coordinate e is normalized 2 e / W - 1)
        gx = 2 * (b[:, 0:1] + t_u[None] * (b[:, 2:3] - b[:, 0:1])) / Wl - 1  # (n, w)
        gy = 2 * (b[:, 1:2] + t_v[None] * (b[:, 3:4] - b[:, 1:2])) / Hl - 1  # (n, h)
        grid = torch.stack(torch.broadcast_tensors(gx[:, None, :], gy[:, :, None]), -1)  # (n, h, w, 2)
        sampled = F.grid_sample(level_image if whole else level_image[pick], grid, mode="bilinear",
                                padding_mode="zeros", align_corners=False)
        if whole:
            return sampled
        if out is None:
            out = images.new_zeros(images.shape[0], images.shape[1], h, w)
        out[pick] = sampled
    return out if out is not None else images.new_zeros(images.shape[0], images.shape[1], h, w)


def _area_weights(start: Tensor, scale: Tensor, n_out: int, n_in: int) -> Tensor:
    """``(N, n_out, n_in)`` weights of area averaging along one axis: output pixel ``j`` of image ``n`` covers
    ``[start + j scale, start + (j + 1) scale)`` in edge coordinates; each input pixel ``[i, i + 1)``
    weighs by its overlap, the weights normalized to sum 1."""
    j = torch.arange(n_out, dtype=start.dtype, device=start.device)
    lo = start[:, None] + j[None] * scale[:, None]  # (N, n_out)
    hi = lo + scale[:, None]
    i = torch.arange(n_in, dtype=start.dtype, device=start.device)
    overlap = (torch.minimum(hi[..., None], i + 1) - torch.maximum(lo[..., None], i)).clamp_min(0)
    return overlap / overlap.sum(-1, keepdim=True).clamp_min(1e-12)


def resample_regions(images: Tensor, boxes: Tensor, out_size: Sequence[int]) -> Tensor:
    """Each image's region ``boxes (N, 4)`` resampled to ``out_size`` ``(w, h)``: the one warp of a view
    onto a network's input.

    A region inside its image that shrinks is averaged over each output pixel's footprint (area
    resampling, as OpenCV's ``INTER_AREA`` and so the resized images of :meth:`s3k.data.Dataset.resized`
    that networks train on); any other region goes through :func:`crop_images` (mip level, then bilinear;
    zeros outside the image), as the refining pass's crops do.

    Args:
        images: ``(N, ch, H, W)`` floating images.
        boxes: ``(N, 4)`` regions in pixel edge coordinates.
        out_size: ``(w, h)``.

    Returns:
        ``(N, ch, h, w)``.
    """
    w, h = (int(s) for s in out_size)
    H, W = images.shape[-2:]
    b = boxes.to(images.dtype)
    inside = bool(((b[:, 0] >= 0) & (b[:, 1] >= 0) & (b[:, 2] <= W) & (b[:, 3] <= H)).all())
    sx, sy = (b[:, 2] - b[:, 0]) / w, (b[:, 3] - b[:, 1]) / h
    if not inside or bool(((sx < 1) | (sy < 1)).any()):
        return crop_images(images, boxes, out_size)
    box = b[0].tolist()
    k = (box[2] - box[0]) / w
    if all(float(v).is_integer() for v in box) and k.is_integer() and (box[3] - box[1]) / h == k \
            and bool((b == b[0]).all()):  # one integer region shrunk by an integer factor: a plain mean
        x0, y0, x1, y1 = (int(v) for v in box)
        region = images[..., y0:y1, x0:x1]
        return region if k == 1 else F.avg_pool2d(region, int(k))
    Ax = _area_weights(b[:, 0], sx, w, W)  # (N, w, W)
    Ay = _area_weights(b[:, 1], sy, h, H)  # (N, h, H)
    return torch.einsum("nyv,ncvu,nxu->ncyx", Ay, images, Ax)


def model_image_size(src_size: tuple[int, int], image_size: int, stride: int) -> tuple[int, int]:
    """The network input size (W, H) for dataset images of ``src_size``.

    Args:
        src_size: dataset image size (W, H).
        image_size: wanted longer side in pixels; 0 keeps the dataset's size.
        stride: heatmap stride; both sides are rounded to a multiple of it.

    Returns:
        (W, H), positive multiples of ``stride``.
    """
    W, H = int(src_size[0]), int(src_size[1])
    s = 1.0 if image_size <= 0 else image_size / max(W, H)
    w = max(stride, int(round(W * s / stride)) * stride)
    h = max(stride, int(round(H * s / stride)) * stride)
    return w, h
