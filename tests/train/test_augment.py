"""Augmentation keeps the geometry exact: a 3D point projected with K' = M K lands on the warped dot."""

from __future__ import annotations

import math

import pytest
import torch

from s3k.train.augment import (
    Augmentation,
    photometric,
    random_warps,
    similarity_matrices,
    warp_images,
    warp_points,
)


def _project(K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """Pinhole projection without distortion: (..., 3, 3), (..., 3, 3), (..., 3), (N, 3) -> (..., N, 2)."""
    x = X @ R.transpose(-1, -2) + t[..., None, :]
    p = x @ K.transpose(-1, -2)
    return p[..., :2] / p[..., 2:3]


def _dot_image(uv: torch.Tensor, H: int, W: int, sigma: float = 1.5) -> torch.Tensor:
    """(N, 2) dot centres -> (N, 3, H, W) images with a Gaussian dot at each centre."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                          indexing="ij")
    d2 = (u - uv[:, 0, None, None]) ** 2 + (v - uv[:, 1, None, None]) ** 2
    img = torch.exp(-d2 / (2 * sigma**2))
    return img[:, None].expand(-1, 3, -1, -1).float().contiguous()


def _centroid(img: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) -> (N, 2) intensity centroid of channel 0."""
    m = img[:, 0].double()
    H, W = m.shape[-2:]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                          indexing="ij")
    s = m.sum(dim=(-1, -2))
    return torch.stack([(m * u).sum(dim=(-1, -2)) / s, (m * v).sum(dim=(-1, -2)) / s], dim=-1)


def _look_at_rig(C: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """C cameras on a circle at 1 m looking at the origin; K for 64 x 48 images with a little skew."""
    Rs, ts = [], []
    for c in range(C):
        a = 2 * math.pi * c / C
        centre = torch.tensor([math.cos(a), math.sin(a), 0.5], dtype=torch.float64)
        z = -centre / centre.norm()
        x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        Rs.append(R)
        ts.append(-R @ centre)
    K = torch.tensor([[60.0, 0.3, 31.5], [0.0, 61.0, 23.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return K.expand(C, 3, 3).clone(), torch.stack(Rs), torch.stack(ts)


def test_similarity_identity_and_centre():
    M = similarity_matrices(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                            torch.zeros(2, 2, dtype=torch.float64), (64, 48))
    torch.testing.assert_close(M, torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    # a pure rotation keeps the image centre ((W-1)/2, (H-1)/2) fixed
    M = similarity_matrices(torch.tensor([0.7]), torch.tensor([1.1]), torch.zeros(1, 2), (64, 48))
    c = torch.tensor([[[31.5, 23.5]]])
    torch.testing.assert_close(warp_points(c, M), c)


def test_warp_identity_keeps_image():
    img = torch.rand(3, 3, 20, 30)
    out = warp_images(img, torch.eye(3).expand(3, 3, 3))
    torch.testing.assert_close(out, img, atol=1e-5, rtol=0)


def test_warp_integer_shift_moves_pixels_exactly():
    img = torch.rand(1, 3, 16, 16)
    M = torch.eye(3)[None].clone()
    M[0, 0, 2], M[0, 1, 2] = 3.0, -2.0  # source (u, v) lands at (u + 3, v - 2)
    out = warp_images(img, M)
    torch.testing.assert_close(out[0, :, 0:14, 3:16], img[0, :, 2:16, 0:13], atol=1e-5, rtol=0)
    assert out[0, :, :, :2].abs().max() == 0  # came from outside: zero padding
    assert out[0, :, :, 2].abs().max() < 1e-5


def test_random_warps_ranges():
    gen = torch.Generator().manual_seed(0)
    M = random_warps(2000, (96, 96), 30.0, 0.2, 10.0, gen)
    scale = torch.linalg.det(M[:, :2, :2]).sqrt()
    angle = torch.atan2(M[:, 1, 0], M[:, 0, 0]).rad2deg()
    assert scale.min() >= 0.8 - 1e-9 and scale.max() <= 1.2 + 1e-9 and scale.max() > 1.15
    assert angle.abs().max() <= 30 + 1e-9 and angle.abs().max() > 28
    shift = warp_points(torch.tensor([[47.5, 47.5]], dtype=torch.float64), M)[:, 0] - 47.5
    assert shift.abs().max() <= 10 + 1e-9 and shift.abs().max() > 9


def test_photometric_in_range_and_reproducible():
    img = torch.rand(4, 3, 8, 8)
    aug = Augmentation(brightness=0.5, contrast=0.5, colour=0.5, noise=0.1)
    a = photometric(img, aug, torch.Generator().manual_seed(3))
    b = photometric(img, aug, torch.Generator().manual_seed(3))
    assert a.min() >= 0 and a.max() <= 1
    torch.testing.assert_close(a, b)
    assert (a - img).abs().mean() > 0.01


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="uv"):
        warp_points(torch.rand(5, 3), torch.eye(3))


def test_stretch_is_along_a_random_direction_and_zero_draws_nothing_more():
    gen = torch.Generator().manual_seed(0)
    plain = random_warps(500, (96, 96), 30.0, 0.2, 10.0, gen)
    after_plain = torch.rand(3, generator=gen)
    gen = torch.Generator().manual_seed(0)
    torch.testing.assert_close(random_warps(500, (96, 96), 30.0, 0.2, 10.0, gen, stretch=0.0), plain)
    torch.testing.assert_close(torch.rand(3, generator=gen), after_plain)  # the same stream onwards
    gen = torch.Generator().manual_seed(0)
    M = random_warps(500, (96, 96), 30.0, 0.2, 10.0, gen, stretch=0.4)
    # the same similarities after a stretch by a factor a in [0.6, 1.4]: the area changes by a, the
    # singular values' ratio is max(a, 1 / a)
    a = torch.linalg.det(M[:, :2, :2]) / torch.linalg.det(plain[:, :2, :2])
    assert a.min() >= 0.6 - 1e-9 and a.max() <= 1.4 + 1e-9 and a.min() < 0.65 and a.max() > 1.35
    sv = torch.linalg.svdvals(M[:, :2, :2])
    torch.testing.assert_close(sv[:, 0] / sv[:, 1], torch.maximum(a, 1 / a))
    torch.testing.assert_close(M[:, 2], plain[:, 2])  # still affine
    # a stretch keeps the image centre and the line across its direction
    from s3k.train.augment import stretch_matrices

    S = stretch_matrices(torch.tensor([0.0, math.pi / 2]), torch.tensor([0.5, 2.0]), (64, 48))
    c = torch.tensor([31.5, 23.5])
    pts = torch.stack([c, c + torch.tensor([10.0, 0.0]), c + torch.tensor([0.0, 10.0])])
    torch.testing.assert_close(warp_points(pts.expand(2, 3, 2), S),
                               torch.stack([torch.stack([c, c + torch.tensor([5.0, 0.0]), pts[2]]),
                                            torch.stack([c, pts[1], c + torch.tensor([0.0, 20.0])])]))


@pytest.mark.parametrize("seed,stretch", [(0, 0.0), (1, 0.0), (2, 0.4)])
def test_uint8_frames_path_matches_geometry_and_float_path(seed, stretch):
    """augment_frames (OpenCV on uint8) puts the dot where K' = M K projects it, like the grid_sample path."""
    from s3k.train.augment import augment_frames, warp_images_uint8

    gen = torch.Generator().manual_seed(seed)
    H, W, C, B = 48, 64, 4, 2
    K, R, t = _look_at_rig(C)
    X = (torch.rand(B, 1, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.1
    uv = torch.stack([_project(K, R, t, X[b]) for b in range(B)])
    dots = _dot_image(uv.reshape(B * C, 2), H, W, sigma=2.0)
    u8 = (dots * 255).round().to(torch.uint8).permute(0, 2, 3, 1).reshape(B, C, H, W, 3).contiguous()
    aug = Augmentation(rotation_deg=180, scale=0.2, shift_px=5, stretch=stretch, brightness=0, contrast=0,
                       colour=0, noise=0)
    out, K_new, uv_moved, M = augment_frames(u8, K.expand(B, C, 3, 3).clone(), aug, gen, uv=uv)
    assert out.shape == (B, C, 3, H, W) and out.dtype == torch.float32
    uv_new = torch.stack([_project(K_new[b], R, t, X[b]) for b in range(B)])
    torch.testing.assert_close(uv_new, uv_moved)
    found = _centroid(out.reshape(B * C, 3, H, W)).reshape(B, C, 1, 2)
    u, v = uv_new[..., 0], uv_new[..., 1]
    inside = (u > 7) & (u < W - 8) & (v > 7) & (v < H - 8)
    assert inside.sum() >= 4
    assert (found - uv_new).norm(dim=-1)[inside].max() < 0.05
    # the OpenCV warp agrees with the grid_sample warp up to uint8 rounding
    flat = u8.reshape(B * C, H, W, 3)
    a = warp_images_uint8(flat, M.reshape(-1, 3, 3)).permute(0, 3, 1, 2).float()
    b = warp_images(flat.permute(0, 3, 1, 2).float(), M.reshape(-1, 3, 3).float())
    assert (a - b).abs().max() <= 2.0


def test_noise_bank_is_reproducible_and_scaled():
    from s3k.train.augment import NoiseBank

    img = torch.full((6, 3, 8, 8), 0.5)
    aug = Augmentation(brightness=0, contrast=0, colour=0, noise=0.1)
    a = photometric(img, aug, torch.Generator().manual_seed(1), NoiseBank(seed=3))
    b = photometric(img, aug, torch.Generator().manual_seed(1), NoiseBank(seed=3))
    torch.testing.assert_close(a, b)
    assert 0 < (a - 0.5).std() < 0.1
