import math

import numpy as np
import pytest
import torch

from s3k.geometry import Cameras, project
from s3k.geometry.warp import crop_images, crop_maps, crop_resize_matrix, metric_crop_boxes


def _rig(distances, f=247.0, size=96, dtype=torch.float64):
    """Cameras on a circle around the origin at the given distances, all looking at the origin."""
    Ks, Rs, ts = [], [], []
    for i, d in enumerate(distances):
        a = 2 * math.pi * i / len(distances)
        centre = torch.tensor([d * math.cos(a), d * math.sin(a), 0.3 * d], dtype=dtype)
        z = -centre / centre.norm()
        x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=dtype))
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        Ks.append(torch.tensor([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]], dtype=dtype))
        Rs.append(R)
        ts.append(-R @ centre)
    return Cameras(K=torch.stack(Ks), dist=None, R=torch.stack(Rs), t=torch.stack(ts))


def test_point_lands_on_the_same_crop_pixel_through_K_prime_and_through_the_map():
    torch.manual_seed(0)
    cams = _rig([0.6, 1.0, 1.5, 2.5])
    centre = torch.tensor([0.01, -0.02, 0.03], dtype=torch.float64)
    boxes, ok = metric_crop_boxes(cams, centre, extent=0.25)
    assert ok.all()
    M = crop_maps(boxes, (64, 64))  # (C, 3, 3)
    crop_cams = Cameras(K=M @ cams.K, dist=None, R=cams.R, t=cams.t)
    X = centre + 0.05 * torch.randn(20, 3, dtype=torch.float64)
    uv_full, _ = project(cams, X)
    uv_crop, _ = project(crop_cams, X)
    mapped = uv_full @ M[:, :2, :2].transpose(-1, -2) + M[:, None, :2, 2]
    torch.testing.assert_close(uv_crop, mapped, rtol=0, atol=1e-9)
    # the batched map is the data layer's map, box by box
    for c in range(4):
        np.testing.assert_allclose(M[c].numpy(), crop_resize_matrix(boxes[c].tolist(), (64, 64)), atol=1e-12)
    # and the centre itself lands in the middle of the crop
    centre_crop, _ = project(crop_cams, centre[None])
    torch.testing.assert_close(centre_crop[:, 0], torch.full((4, 2), 31.5, dtype=torch.float64), atol=1e-9,
                               rtol=0)


@pytest.mark.parametrize("f", [150.0, 400.0])
def test_crop_size_follows_the_metric_extent_at_any_distance_and_focal_length(f):
    cams = _rig([0.5, 1.0, 2.0, 4.0], f=f)
    boxes, _ = metric_crop_boxes(cams, torch.zeros(3, dtype=torch.float64), extent=0.2)
    width = boxes[:, 2] - boxes[:, 0]
    depth = (cams.R @ torch.zeros(3, dtype=torch.float64) + cams.t)[:, 2]
    torch.testing.assert_close(width, f * 0.2 / depth)  # pixels shrink with distance, grow with f
    # in the resampled crop a 0.1 m segment at the centre, across the view, has the same length everywhere
    M = crop_maps(boxes, (80, 80))
    crop_cams = Cameras(K=M @ cams.K, dist=None, R=cams.R, t=cams.t)
    right = cams.R[:, 0]  # each camera's x axis in world coordinates
    ends = torch.stack([-0.05 * right, 0.05 * right], 1)  # (C, 2, 3)
    uv, _ = project(crop_cams, ends)
    length = (uv[:, 1] - uv[:, 0]).norm(dim=-1)
    torch.testing.assert_close(length, torch.full((4,), 40.0, dtype=torch.float64), rtol=1e-3, atol=0)


def test_point_behind_the_camera_is_flagged():
    cams = _rig([1.0])
    behind = 2.0 * cams.centres()[0]  # the camera looks at the origin: twice its centre is behind it
    _, ok = metric_crop_boxes(cams, behind, extent=0.2)
    assert not ok.any()
    with pytest.raises(ValueError, match="extent"):
        metric_crop_boxes(cams, torch.zeros(3), extent=0.0)


@pytest.mark.parametrize("shrink", [1, 3, 6])
def test_crop_images_samples_where_the_map_says(shrink):
    H = W = 192
    img = torch.zeros(1, 1, H, W, dtype=torch.float64)
    # a smooth blob at a non-integer pixel
    u0, v0 = 101.3, 77.8
    vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    img[0, 0] = torch.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * (3.0 * shrink) ** 2))
    out = 24
    side = out * shrink + 0.37
    box = torch.tensor([[u0 + 0.5 - side / 2 + 1.7, v0 + 0.5 - side / 2 - 2.1, 0, 0]], dtype=torch.float64)
    box[0, 2:] = box[0, :2] + side
    crop = crop_images(img, box, (out, out))
    M = crop_maps(box, (out, out))[0]
    expected = M[:2, :2] @ torch.tensor([u0, v0], dtype=torch.float64) + M[:2, 2]
    ys, xs = torch.meshgrid(torch.arange(out, dtype=torch.float64), torch.arange(out, dtype=torch.float64),
                            indexing="ij")
    p = crop[0, 0] / crop[0, 0].sum()
    mean = torch.stack([(p * xs).sum(), (p * ys).sum()])
    torch.testing.assert_close(mean, expected, atol=0.05, rtol=0)


def test_outside_the_image_is_black():
    img = torch.ones(2, 3, 32, 32)
    box = torch.tensor([[-64.0, -64.0, -32.0, -32.0], [0.0, 0.0, 32.0, 32.0]])
    crop = crop_images(img, box, (8, 8))
    assert crop[0].abs().max() == 0
    torch.testing.assert_close(crop[1], torch.ones(3, 8, 8))
