"""Tests for s3k.readout.heatmaps: cell map, Gaussian targets, spatial softmax, moments, confidence weight."""

from __future__ import annotations

import math

import pytest
import torch

from s3k.readout.heatmaps import (
    cell_centres,
    confidence_weight,
    gaussian_targets,
    heatmap_moments,
    heatmap_size,
    spatial_log_softmax,
    spatial_softmax,
)


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_cell_centres_are_centres_of_pixel_blocks(stride):
    h, w = 3, 5
    u, v = cell_centres(h, w, stride)
    assert u.shape == (w,) and v.shape == (h,)
    pixels = torch.arange(w * stride, dtype=torch.float32).reshape(w, stride)
    torch.testing.assert_close(u, pixels.mean(dim=1))
    rows = torch.arange(h * stride, dtype=torch.float32).reshape(h, stride)
    torch.testing.assert_close(v, rows.mean(dim=1))


def test_cell_centres_dtype_and_errors():
    u, v = cell_centres(2, 2, 2, dtype=torch.float64)
    assert u.dtype == v.dtype == torch.float64
    with pytest.raises(ValueError, match="stride"):
        cell_centres(2, 2, 0)
    with pytest.raises(ValueError, match="h, w"):
        cell_centres(0, 2, 1)


def test_heatmap_size():
    assert heatmap_size(128, 96, 2) == (64, 48)
    assert heatmap_size(128, 128, 4) == (32, 32)
    assert heatmap_size(7, 5, 1) == (7, 5)
    with pytest.raises(ValueError, match="multiples of the heatmap stride 4"):
        heatmap_size(130, 128, 4)


def _dense_gaussian(uv, h, w, stride, sigma):
    """Reference: evaluate the unnormalized Gaussian at every cell centre, then normalize."""
    u, v = cell_centres(h, w, stride, dtype=torch.float64)
    d2 = (u[None, :] - float(uv[0])) ** 2 + (v[:, None] - float(uv[1])) ** 2
    g = torch.exp(-d2 / (2 * sigma**2))
    return g / g.sum()


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_gaussian_targets_match_dense_formula(stride):
    h, w, sigma = 12, 10, 1.7 * stride
    uv = torch.tensor([[7.3, 11.2], [0.1, 5.0], [-0.1, -0.1]], dtype=torch.float64) * stride  # inside, edges
    target, mask = gaussian_targets(uv, None, h, w, stride, sigma)
    assert target.shape == (3, h, w) and mask.all()
    for i in range(3):
        torch.testing.assert_close(target[i], _dense_gaussian(uv[i], h, w, stride, sigma))


def test_gaussian_targets_broadcast_over_leading_dims():
    B, C, K, h, w = 2, 3, 4, 8, 6
    uv = torch.rand(B, C, K, 2) * torch.tensor([2 * w - 1, 2 * h - 1])
    target, mask = gaussian_targets(uv, torch.ones(B, C, K, dtype=torch.bool), h, w, 2, 2.0)
    assert target.shape == (B, C, K, h, w) and mask.shape == (B, C, K)
    torch.testing.assert_close(target.sum(dim=(-1, -2)), torch.ones(B, C, K))
    single, _ = gaussian_targets(uv[1, 2, 3], None, h, w, 2, 2.0)
    torch.testing.assert_close(target[1, 2, 3], single)


def test_gaussian_targets_masks_give_zeros_not_nan():
    h, w, stride = 8, 8, 2  # image extent [-0.5, 15.5]
    uv = torch.tensor(
        [
            [5.0, 5.0],  # fine
            [5.0, 5.0],  # invalid (e.g. behind the camera)
            [15.6, 5.0],  # just off the right edge
            [5.0, -0.6],  # just off the top edge
            [float("nan"), 3.0],
            [float("inf"), 3.0],
            [15.5, -0.5],  # exactly on the corner of the extent: kept
            [1e30, 1e30],
        ],
        requires_grad=True,
    )
    valid = torch.tensor([True, False, True, True, True, True, True, True])
    target, mask = gaussian_targets(uv, valid, h, w, stride, 1.5)
    assert mask.tolist() == [True, False, False, False, False, False, True, False]
    assert torch.isfinite(target).all()
    assert (target[~mask] == 0).all()
    torch.testing.assert_close(target[mask].sum(dim=(-1, -2)), torch.ones(2))
    (target * torch.rand_like(target)).sum().backward()
    assert torch.isfinite(uv.grad).all()
    assert (uv.grad[~mask] == 0).all()


def test_gaussian_targets_far_from_every_cell_centre_does_not_underflow():
    # A point inside the extent but many sigmas from any other centre: the target is a one-hot, not 0/0.
    target, mask = gaussian_targets(torch.tensor([0.0, 0.0]), None, 4, 4, 4, 0.05)
    assert mask and torch.isfinite(target).all()
    assert float(target[0, 0]) == pytest.approx(1.0)


def test_gaussian_targets_errors():
    with pytest.raises(ValueError, match="uv"):
        gaussian_targets(torch.zeros(3, 3), None, 4, 4, 1, 1.0)
    with pytest.raises(ValueError, match="valid"):
        gaussian_targets(torch.zeros(3, 2), torch.ones(2, dtype=torch.bool), 4, 4, 1, 1.0)
    with pytest.raises(ValueError, match="sigma"):
        gaussian_targets(torch.zeros(3, 2), None, 4, 4, 1, 0.0)
    with pytest.raises(ValueError, match="floating"):
        gaussian_targets(torch.zeros(3, 2, dtype=torch.long), None, 4, 4, 1, 1.0)


def test_spatial_softmax_normalizes_over_both_axes():
    logits = torch.randn(2, 3, 5, 7, dtype=torch.float64)
    p = spatial_softmax(logits)
    torch.testing.assert_close(p.sum(dim=(-1, -2)), torch.ones(2, 3, dtype=torch.float64))
    torch.testing.assert_close(spatial_log_softmax(logits).exp(), p)
    torch.testing.assert_close(spatial_softmax(logits + 100.0), p)  # shift invariant, no overflow
    with pytest.raises(ValueError, match="logits"):
        spatial_softmax(torch.zeros(5))


@pytest.mark.parametrize("stride", [1, 2, 4])
@pytest.mark.parametrize("sigma_cells", [1.0, 1.5, 3.0])
def test_moments_of_gaussian_target_give_back_centre_and_sigma(stride, sigma_cells):
    h, w = 64, 60
    sigma = sigma_cells * stride
    gen = torch.Generator().manual_seed(stride * 10 + int(sigma_cells * 2))
    # Sub-pixel centres kept 6 sigma from the edges, so truncation by the border is negligible (e^-18).
    lo = torch.tensor([6 * sigma, 6 * sigma])
    hi = torch.tensor([w * stride - 1 - 6 * sigma, h * stride - 1 - 6 * sigma])
    uv = (lo + (hi - lo) * torch.rand(16, 2, generator=gen)).double()
    target, mask = gaussian_targets(uv, None, h, w, stride, sigma)
    mean, var = heatmap_moments(target, stride)
    assert mask.all()
    torch.testing.assert_close(mean, uv, atol=1e-6, rtol=0)
    torch.testing.assert_close(var.sqrt(), torch.full((16,), sigma, dtype=torch.float64), atol=1e-6, rtol=0)


def test_moments_closed_forms():
    h, w, s = 6, 10, 2
    one_hot = torch.zeros(h, w)
    one_hot[4, 7] = 1.0
    mean, var = heatmap_moments(one_hot, s)
    u, v = cell_centres(h, w, s)
    torch.testing.assert_close(mean, torch.stack([u[7], v[4]]))
    assert float(var) == 0.0
    # Uniform heatmap: mean at the image centre, variance of a discrete uniform with spacing s per axis.
    mean, var = heatmap_moments(torch.full((h, w), 1.0 / (h * w)), s)
    torch.testing.assert_close(mean, torch.tensor([(w * s - 1) / 2, (h * s - 1) / 2]))
    expected = 0.5 * (s**2 * (w**2 - 1) / 12 + s**2 * (h**2 - 1) / 12)
    assert float(var) == pytest.approx(expected, rel=1e-5)


def test_moments_shapes_and_errors():
    probs = spatial_softmax(torch.randn(2, 3, 4, 5, 6))
    mean, var = heatmap_moments(probs, 4)
    assert mean.shape == (2, 3, 4, 2) and var.shape == (2, 3, 4)
    assert (var > 0).all()
    with pytest.raises(ValueError, match="probs"):
        heatmap_moments(torch.zeros(4), 1)
    with pytest.raises(ValueError, match="stride"):
        heatmap_moments(probs, 3.0)


@pytest.mark.parametrize("stride", [1, 2])
def test_moments_gradcheck(stride):
    logits = torch.randn(2, 5, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: heatmap_moments(spatial_softmax(x), stride), (logits,))
    assert torch.autograd.gradgradcheck(lambda x: heatmap_moments(spatial_softmax(x), stride), (logits,))


def test_confidence_weight_values():
    sigma = 2.0
    var = torch.tensor([0.0, sigma**2, (2 * sigma) ** 2, (10 * sigma) ** 2], dtype=torch.float64)
    w = confidence_weight(var, sigma)

    def sig(x):
        return 1 / (1 + math.exp(-x))

    expected = [sig(3 * math.tanh(5.0)), sig(3 * math.tanh(2.5)), 0.5, sig(3 * math.tanh(5 * (1 - 5)))]
    torch.testing.assert_close(w, torch.tensor(expected, dtype=torch.float64))
    # Monotone: wider heatmaps are never more confident.
    grid = torch.linspace(0, 100, 200, dtype=torch.float64)
    assert (confidence_weight(grid, sigma).diff() <= 0).all()
    with pytest.raises(ValueError, match="sigma"):
        confidence_weight(var, -1.0)


def test_confidence_weight_gradcheck_and_finite_at_zero():
    var = (torch.rand(7, dtype=torch.float64) * 40 + 0.1).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: confidence_weight(x, 2.5), (var,))
    zero = torch.zeros(3, requires_grad=True)
    confidence_weight(zero, 1.0).sum().backward()
    assert torch.isfinite(zero.grad).all()


def test_confidence_weight_through_moments_gradcheck():
    logits = torch.randn(3, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x: confidence_weight(heatmap_moments(spatial_softmax(x), 2)[1], 1.5), (logits,)
    )


def test_peak_window_mean_removes_the_pull_of_spread_probability():
    """Probability spread evenly over the heatmap pulls the whole mean towards the centre in proportion to the
    spread and the distance; the mean within a window around the peak stays on the Gaussian's centre."""
    from s3k.readout.heatmaps import peak_window_mean

    uv = torch.tensor([[14.3, 48.6], [40.0, 31.5], [48.8, 16.2]], dtype=torch.float64)
    target, _ = gaussian_targets(uv, None, 32, 32, 2, 3.0)
    centre = torch.tensor([31.5, 31.5], dtype=torch.float64)
    for spread in (0.0, 0.05, 0.2):
        probs = (1 - spread) * target + spread / (32 * 32)
        whole, _ = heatmap_moments(probs, 2)
        torch.testing.assert_close(whole, uv + spread * (centre - uv), atol=1e-3, rtol=0)
        # what spread stays inside the window pulls towards the peak cell: a few hundredths of a pixel
        torch.testing.assert_close(peak_window_mean(probs, 2, 5), uv, atol=0.05, rtol=0)
    # a second mode far away moves the whole mean, not the windowed one
    far, _ = gaussian_targets(torch.tensor([5.0, 5.0], dtype=torch.float64), None, 32, 32, 2, 3.0)
    two = 0.7 * target[1] + 0.3 * far
    assert (heatmap_moments(two, 2)[0] - uv[1]).norm() > 5
    torch.testing.assert_close(peak_window_mean(two, 2, 5), uv[1], atol=5e-3, rtol=0)
    with pytest.raises(ValueError, match="radius"):
        peak_window_mean(target, 2, 0)


def test_peak_window_mean_reads_the_window_as_the_masked_heatmap_does():
    """The window is gathered by index; its mean equals that of the whole heatmap with every cell outside
    the window set to zero, at the edges (the window cut by the border) and for a window wider than the
    heatmap, with and without a given peak."""
    from s3k.readout.heatmaps import peak_window_mean

    def masked(probs, stride, radius, peak):
        h, w = probs.shape[-2:]
        rows, cols = torch.arange(h), torch.arange(w)
        in_rows = (rows - torch.div(peak, w, rounding_mode="floor")[..., None]).abs() <= radius
        in_cols = (cols - (peak % w)[..., None]).abs() <= radius
        win = probs * (in_rows[..., :, None] & in_cols[..., None, :])
        return heatmap_moments(win / win.sum(dim=(-2, -1), keepdim=True), stride)[0]

    g = torch.Generator().manual_seed(3)
    probs = spatial_softmax(torch.randn(2, 3, 12, 10, generator=g, dtype=torch.float64) * 2)
    corner = torch.tensor([[0, 9, 119], [110, 55, 0]])  # top-left, top-right, bottom-right corners
    for radius in (1, 3, 20):
        for peak in (None, corner):
            want = masked(probs, 2, radius, probs.flatten(-2).argmax(-1) if peak is None else peak)
            got = peak_window_mean(probs, 2, radius, peak)
            assert got.shape == (2, 3, 2)
            torch.testing.assert_close(got, want, atol=1e-12, rtol=0)
    assert float((peak_window_mean(probs, 2, 1) - peak_window_mean(probs, 2, 20)).abs().max()) > 0.1
