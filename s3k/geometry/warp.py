"""Scale-normalized crops: each view cut around the reprojection of a 3D estimate, sized from a metric extent.

A coarse pass on whole images gives a 3D estimate of the object; every camera then gets a crop centred on the
estimate's reprojection whose side covers ``extent`` metres at the estimate's depth. Cut from the
full-resolution image and resampled to the network's input size, the object has the same size in every crop,
whatever the camera's distance or focal length, and the crop keeps exact geometry through ``K' = M K``
(docs/method.md#conventions), so the refining pass trains and runs with the same losses and read-out.

Boxes use the pixel *edge* coordinates of :mod:`s3k.data.transforms` (the whole image is ``(0, 0, W, H)``);
pixel coordinates use the pixel-centre convention.

Shapes: ``L`` the leading dims of a camera set (``(B, C)`` per frame), ``N`` images.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from s3k.geometry import Cameras, project

__all__ = ["crop_images", "crop_maps", "metric_crop_boxes", "resample_regions"]


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

    Same map as :func:`s3k.data.transforms.crop_resize_matrix`: ``u' = s_x (u + 0.5 - x0) - 0.5`` with
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
    out = images.new_zeros(images.shape[0], images.shape[1], h, w)
    t_u = (torch.arange(w, dtype=images.dtype, device=images.device) + 0.5) / w
    t_v = (torch.arange(h, dtype=images.dtype, device=images.device) + 0.5) / h
    level_image = images
    for level in range(int(levels.max()) + 1 if len(levels) else 0):
        if level > 0:
            level_image = F.avg_pool2d(level_image, 2, ceil_mode=True, count_include_pad=False)
        pick = levels == level
        if not bool(pick.any()):
            continue
        b = boxes[pick] / 2.0**level  # edge coordinates at this level
        Hl, Wl = level_image.shape[-2:]
        # crop pixel centres in level edge coordinates, then grid_sample's [-1, 1] (align_corners=False:
        # edge coordinate e is normalized 2 e / W - 1)
        gx = 2 * (b[:, 0:1] + t_u[None] * (b[:, 2:3] - b[:, 0:1])) / Wl - 1  # (n, w)
        gy = 2 * (b[:, 1:2] + t_v[None] * (b[:, 3:4] - b[:, 1:2])) / Hl - 1  # (n, h)
        grid = torch.stack(torch.broadcast_tensors(gx[:, None, :], gy[:, :, None]), -1)  # (n, h, w, 2)
        out[pick] = F.grid_sample(level_image[pick], grid, mode="bilinear", padding_mode="zeros",
                                  align_corners=False)
    return out


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
