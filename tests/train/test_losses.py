"""Tests for s3k.train.losses: KL, supervised and self-supervised multi-view terms, weight decay."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from s3k.geometry import Cameras, project, triangulate_pixels
from s3k.model import UNet
from s3k.readout import ReadoutConfig, window_cells
from s3k.readout.heatmaps import (
    confidence_weight,
    gaussian_targets,
    heatmap_moments,
    peak_window_mean,
    spatial_softmax,
)
from s3k.train.losses import (
    kl_divergence,
    kl_loss,
    l2_non_bias,
    self_supervised_loss,
    supervised_loss,
)

H = W = 64
STRIDE = 2
h, w = H // STRIDE, W // STRIDE
SIGMA = 3.0  # image pixels, 1.5 cells


def _look_at(positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV R, t of cameras at ``positions (*, 3)`` looking at the world origin, world z up."""
    z = -positions / positions.norm(dim=-1, keepdim=True)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=positions.dtype).expand_as(z)
    x = torch.linalg.cross(z, up)
    x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z], dim=-2)
    t = -(R @ positions[..., None])[..., 0]
    return R, t


def _rig(B: int = 2, C: int = 4, dtype=torch.float64) -> Cameras:
    """C cameras around the origin at about 1 m, 60 degree field of view over 64 px, jittered per frame."""
    gen = torch.Generator().manual_seed(0)
    az = torch.linspace(0, 2 * torch.pi, C + 1, dtype=dtype)[:-1]
    az = az + 0.3 * torch.rand(B, C, generator=gen, dtype=dtype)
    el = 0.4 + 0.3 * torch.rand(B, C, generator=gen, dtype=dtype)
    pos = torch.stack([az.cos() * el.cos(), az.sin() * el.cos(), el.sin()], dim=-1)
    R, t = _look_at(pos)
    f = (H / 2) / torch.tan(torch.tensor(torch.pi / 6, dtype=dtype))
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], dtype=dtype).expand(B, C, 3, 3)
    return Cameras(K, None, R, t)


def _points(B: int = 2, K: int = 3, dtype=torch.float64) -> torch.Tensor:
    gen = torch.Generator().manual_seed(1)
    return (torch.rand(B, K, 3, generator=gen, dtype=dtype) - 0.5) * 0.2


def _logits_at(uv: torch.Tensor, sigma: float = SIGMA) -> torch.Tensor:
    """Logits whose softmax is exactly the Gaussian target centred at ``uv (*, 2)``."""
    target, mask = gaussian_targets(uv, None, h, w, STRIDE, sigma)
    assert mask.all()
    return target.log()


# --------------------------------------------------------------------------------------------------------
# KL


def test_kl_zero_at_target_and_grows_with_displacement():
    centre = torch.tensor([30.3, 25.7], dtype=torch.float64)
    target, _ = gaussian_targets(centre, None, h, w, STRIDE, SIGMA)
    losses = []
    for shift in [0.0, 0.5, 1.0, 2.0, 4.0, 8.0]:
        logits = _logits_at(centre + torch.tensor([shift, -0.5 * shift], dtype=torch.float64)).float()
        losses.append(float(kl_loss(target, logits)))
    assert abs(losses[0]) < 1e-5
    assert all(b > a for a, b in zip(losses, losses[1:]))
    # Closed form for two Gaussians of the same width far from the border: |d|^2 / (2 sigma^2).
    d2 = 8.0**2 * 1.25
    assert losses[-1] == pytest.approx(d2 / (2 * SIGMA**2), rel=1e-3)


def test_kl_float32_masking_and_normalizer():
    uv = torch.tensor([[20.0, 20.0], [40.0, 10.0], [0.0, 0.0]])
    target, mask = gaussian_targets(uv, torch.tensor([True, True, False]), h, w, STRIDE, SIGMA)
    logits = torch.randn(3, h, w, dtype=torch.bfloat16, requires_grad=True)
    loss = kl_loss(target, logits, mask, normalizer=2)
    assert loss.dtype == torch.float32
    per_term = kl_divergence(target, logits)
    assert float(per_term[2].detach()) == 0.0  # all-zero target: no term
    torch.testing.assert_close(loss, per_term[:2].sum() / 2)
    loss.backward()
    assert torch.isfinite(logits.grad.float()).all()
    assert (logits.grad[2] == 0).all()
    with pytest.raises(ValueError, match="normalizer"):
        kl_loss(target, logits, mask, normalizer=0)
    with pytest.raises(ValueError, match="mask"):
        kl_loss(target, logits, mask[:2])
    with pytest.raises(ValueError, match="same shape"):
        kl_loss(target[:2], logits)


def test_kl_ignores_underflowing_probabilities_where_target_is_zero():
    target = torch.zeros(1, 4, 4)
    target[0, 0, 0] = 1.0
    logits = torch.zeros(1, 4, 4, requires_grad=True)
    with torch.no_grad():
        logits[0, 3, 3] = -1e30  # log P = -1e30 there: 0 * (-1e30) must stay 0
    loss = kl_loss(target, logits)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()


# --------------------------------------------------------------------------------------------------------
# Supervised


def _project_all(cams: Cameras, X: torch.Tensor) -> torch.Tensor:
    uv, depth = project(cams, X[:, None])
    assert (depth > 0).all()
    return uv


def test_supervised_loss_zero_at_target_and_grows():
    cams, X = _rig(), _points()
    uv = _project_all(cams, X)  # (B, C, K, 2)
    labels = torch.full_like(uv, float("nan"))
    label_mask = torch.zeros(uv.shape[:-1], dtype=torch.bool)
    label_mask[:, :2] = True  # labelled in cameras 0 and 1 only
    labels[label_mask] = uv[label_mask]
    losses = []
    for shift in [0.0, 1.0, 2.0, 4.0]:
        logits = _logits_at(uv + shift).float().requires_grad_()
        loss, info = supervised_loss(logits, cams, labels, label_mask, STRIDE, SIGMA)
        losses.append(loss.item())
    assert abs(losses[0]) < 1e-5
    assert all(b > a for a, b in zip(losses, losses[1:]))
    # Targets in all four cameras, at the projections of the triangulated labels.
    assert info["mask"].all() and int(info["num_terms"]) == uv.shape[0] * 4 * 3
    torch.testing.assert_close(info["points"], X, atol=1e-6, rtol=0)
    torch.testing.assert_close(info["target_uv"], uv, atol=1e-6, rtol=0)
    assert not info["targets"].requires_grad


def test_supervised_loss_is_per_frame():
    cams, X = _rig(B=1), _points(B=1)
    uv = _project_all(cams, X)
    logits = torch.randn(1, 4, 3, h, w)
    mask = torch.ones(1, 4, 3, dtype=torch.bool)
    one, _ = supervised_loss(logits, cams, uv, mask, STRIDE, SIGMA)
    cams2 = Cameras(*(x.expand(2, *x.shape[1:]) for x in (cams.K, cams.dist, cams.R, cams.t)))
    two, _ = supervised_loss(logits.expand(2, -1, -1, -1, -1), cams2, uv.expand(2, -1, -1, -1),
                             mask.expand(2, -1, -1), STRIDE, SIGMA)
    torch.testing.assert_close(one, two)


def test_supervised_loss_degenerate_labels_are_masked():
    cams, X = _rig(), _points()
    uv = _project_all(cams, X)
    label_mask = torch.zeros(uv.shape[:-1], dtype=torch.bool)
    label_mask[:, 2] = True  # every keypoint labelled in one camera only
    labels = torch.where(label_mask[..., None], uv, torch.full_like(uv, float("nan")))
    logits = torch.randn(2, 4, 3, h, w, requires_grad=True)
    loss, info = supervised_loss(logits, cams, labels, label_mask, STRIDE, SIGMA)
    assert not info["points_valid"].any() and not info["mask"].any()
    assert loss.item() == 0.0 and int(info["num_terms"]) == 0
    loss.backward()
    assert torch.isfinite(logits.grad).all() and (logits.grad == 0).all()

    # Keypoint 0 of frame 0 labelled twice in the same camera position (identical rays): degenerate too.
    cams_same = Cameras(cams.K, None, cams.R[:, :1].expand(2, 4, 3, 3), cams.t[:, :1].expand(2, 4, 3))
    uv_same = _project_all(cams_same, X)
    loss, info = supervised_loss(logits, cams_same, uv_same, torch.ones_like(label_mask), STRIDE, SIGMA)
    assert not info["points_valid"].any() and torch.isfinite(loss)


def test_supervised_loss_masks_points_behind_a_camera():
    cams, X = _rig(B=1), _points(B=1)
    uv = _project_all(cams, X)
    # Camera 3 turned around (same centre, looking away): the labelled points are behind it.
    flip = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    R = cams.R.clone()
    R[0, 3] = flip @ R[0, 3]
    t = cams.t.clone()
    t[0, 3] = -(R[0, 3] @ cams.centres()[0, 3])
    turned = Cameras(cams.K, None, R, t)
    mask = torch.zeros(1, 4, 3, dtype=torch.bool)
    mask[:, :3] = True
    logits = torch.randn(1, 4, 3, h, w, requires_grad=True)
    loss, info = supervised_loss(logits, turned, uv, mask, STRIDE, SIGMA)
    assert info["points_valid"].all()
    assert (info["depth"][0, 3] < 0).all()
    assert not info["mask"][0, 3].any() and info["mask"][0, :3].all()
    loss.backward()
    assert (logits.grad[0, 3] == 0).all() and torch.isfinite(logits.grad).all()


def test_supervised_loss_shape_errors():
    cams = _rig()
    logits = torch.randn(2, 4, 3, h, w)
    labels, mask = torch.zeros(2, 4, 3, 2), torch.ones(2, 4, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match="labels_uv"):
        supervised_loss(logits, cams, labels[..., 0], mask, 2, 3.0)
    with pytest.raises(ValueError, match="label_mask"):
        supervised_loss(logits, cams, labels, mask[0], 2, 3.0)
    with pytest.raises(ValueError, match="cams"):
        supervised_loss(logits, cams[:1], labels, mask, 2, 3.0)
    with pytest.raises(ValueError, match="logits"):
        supervised_loss(logits[0], cams, labels, mask, 2, 3.0)
    with pytest.raises(ValueError, match="weights"):
        self_supervised_loss(logits, cams, 2, 3.0, weights=torch.ones(2, 4))


# --------------------------------------------------------------------------------------------------------
# Self-supervised


def test_self_supervised_loss_zero_at_consistent_prediction_and_grows():
    cams, X = _rig(), _points()
    uv = _project_all(cams, X)
    logits = _logits_at(uv).float()
    loss, info = self_supervised_loss(logits, cams, STRIDE, SIGMA)
    assert abs(loss.item()) < 1e-4
    torch.testing.assert_close(info["points"], X, atol=1e-4, rtol=0)
    assert info["mask"].all()
    # Moving camera 0's prediction off the consensus of the others raises the loss.
    losses = [loss.item()]
    for shift in [1.0, 2.0, 4.0, 8.0]:
        moved = uv.clone()
        moved[:, 0] += torch.tensor([shift, shift], dtype=torch.float64)
        losses.append(float(self_supervised_loss(_logits_at(moved).float(), cams, STRIDE, SIGMA)[0]))
    assert all(b > a for a, b in zip(losses, losses[1:]))


def _manual_detached_loss(logits: torch.Tensor, cams: Cameras, detach: bool = True) -> torch.Tensor:
    """The self-supervised loss written out step by step; ``detach=False`` lets gradient reach the target."""
    source = logits.detach() if detach else logits
    probs = spatial_softmax(source)
    _, var = heatmap_moments(probs, STRIDE)
    mean_uv = peak_window_mean(probs, STRIDE, window_cells(SIGMA, STRIDE))  # the read-out's detection
    weights = confidence_weight(var, SIGMA)
    X, valid = triangulate_pixels(cams, mean_uv.double(), weights.double())
    uv, depth = project(cams, X[:, None])
    target, mask = gaussian_targets(uv, valid[:, None] & (depth > 1e-6), h, w, STRIDE, SIGMA)
    return kl_loss(target.float(), logits, mask, normalizer=logits.shape[0])


def test_self_supervised_target_gets_no_gradient():
    cams, X = _rig(), _points()
    uv = _project_all(cams, X)
    gen = torch.Generator().manual_seed(5)
    logits = (_logits_at(uv + 3 * torch.randn(uv.shape, generator=gen, dtype=torch.float64)).float()
              + 0.5 * torch.randn(2, 4, 3, h, w, generator=gen)).requires_grad_()
    loss, info = self_supervised_loss(logits, cams, STRIDE, SIGMA)
    for key in ("targets", "points", "weights", "mean_uv", "target_uv"):
        assert not info[key].requires_grad and info[key].grad_fn is None, key
    (grad,) = torch.autograd.grad(loss, logits)
    manual = _manual_detached_loss(logits, cams)
    (grad_manual,) = torch.autograd.grad(manual, logits)
    torch.testing.assert_close(loss, manual)
    torch.testing.assert_close(grad, grad_manual, atol=1e-6, rtol=1e-5)
    # Letting the gradient through the target gives a different gradient: the check above can fail.
    (grad_through,) = torch.autograd.grad(_manual_detached_loss(logits, cams, detach=False), logits)
    assert (grad_through - grad).abs().max() > 1e-4


@pytest.mark.parametrize("bad", ["zeros", "nan", "one_view"])
def test_self_supervised_degenerate_weights_are_masked(bad):
    cams, X = _rig(), _points()
    logits = _logits_at(_project_all(cams, X)).float().requires_grad_()
    weights = torch.ones(2, 4, 3)
    if bad == "zeros":
        weights.zero_()
    elif bad == "nan":
        weights.fill_(float("nan"))
    else:
        weights[:, 1:] = 0.0
    loss, info = self_supervised_loss(logits, cams, STRIDE, SIGMA, weights=weights)
    assert not info["mask"].any() and int(info["num_terms"]) == 0
    assert torch.isfinite(loss) and loss.item() == 0.0
    loss.backward()
    assert torch.isfinite(logits.grad).all() and (logits.grad == 0).all()


def test_self_supervised_points_behind_every_camera_are_masked():
    cams, X = _rig(B=1), _points(B=1)
    logits = _logits_at(_project_all(cams, X)).float().requires_grad_()
    # Every camera turned around: the rays now meet behind all of them.
    flip = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    R = flip @ cams.R
    t = -(R @ cams.centres()[..., None])[..., 0]
    loss, info = self_supervised_loss(logits, Cameras(cams.K, None, R, t), STRIDE, SIGMA)
    assert info["points_valid"].all() and (info["depth"] < 0).all()
    assert not info["mask"].any() and loss.item() == 0.0
    loss.backward()
    assert torch.isfinite(logits.grad).all()


def test_self_supervised_uniform_heatmaps_stay_finite():
    cams = _rig()
    logits = torch.zeros(2, 4, 3, h, w, requires_grad=True)
    loss, info = self_supervised_loss(logits, cams, STRIDE, SIGMA)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()
    # Uniform heatmaps are maximally unsure: low weights.
    assert (info["weights"] < 0.1).all()


# --------------------------------------------------------------------------------------------------------
# Weight decay


def test_l2_non_bias_skips_biases_and_norm_parameters():
    torch.manual_seed(0)
    net = UNet(3)
    expected = sum((m.weight**2).sum() for m in net.modules() if isinstance(m, (nn.Conv2d, nn.Linear)))
    torch.testing.assert_close(l2_non_bias(net), expected)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.weight.add_(1.0)
                m.bias.add_(1.0)
        net.head.bias.add_(3.0)
    torch.testing.assert_close(l2_non_bias(net), expected)
    net.zero_grad()
    l2_non_bias(net).backward()
    for name, p in net.named_parameters():
        if p.ndim > 1:
            torch.testing.assert_close(p.grad, 2 * p.detach(), msg=name)
        else:
            assert p.grad is None, name
    assert float(l2_non_bias(nn.ReLU())) == 0.0


def test_self_supervised_pseudo_label_leaves_out_a_view_off_the_consensus():
    cams, X = _rig(), _points()
    uv = _project_all(cams, X)
    confused = uv.clone()
    confused[:, 1, 0] += torch.tensor([9.0, -7.0], dtype=torch.float64)  # a sharp heatmap on the wrong spot
    logits = _logits_at(confused).float()
    _, plain = self_supervised_loss(logits, cams, STRIDE, SIGMA)
    _, robust = self_supervised_loss(logits, cams, STRIDE, SIGMA,
                                     rule=ReadoutConfig.for_pseudo_labels(max_residual_px=2.0))
    assert (plain["points"][:, 0] - X[:, 0]).norm(dim=-1).min() > 1e-3
    torch.testing.assert_close(robust["points"], X, atol=2e-4, rtol=0)
    assert (robust["weights"][:, 1, 0] == 0).all() and (robust["weights"][:, :, 1:] > 0).all()
    # the confused view still gets the consensus as its target
    assert robust["mask"][:, 1, 0].all()
    torch.testing.assert_close(robust["target_uv"][:, 1, 0], uv[:, 1, 0], atol=0.05, rtol=0)


def test_self_supervised_pseudo_label_from_target_logits():
    """With a teacher's logits the pseudo-label is the teacher's point, and the KL trains the student's."""
    cams, X = _rig(), _points()
    student = _logits_at(_project_all(cams, X + 0.01)).float().requires_grad_(True)
    teacher = _logits_at(_project_all(cams, X)).float()
    loss, info = self_supervised_loss(student, cams, STRIDE, SIGMA, target_logits=teacher)
    torch.testing.assert_close(info["points"], X, atol=1e-4, rtol=0)  # the teacher's, not the student's
    own, own_info = self_supervised_loss(student, cams, STRIDE, SIGMA)
    torch.testing.assert_close(own_info["points"], X + 0.01, atol=1e-4, rtol=0)
    assert loss.item() > 10 * abs(own.item())  # the student is pulled towards the teacher's point
    loss.backward()
    assert student.grad is not None and student.grad.abs().sum() > 0
    # the same logits as target: the same loss as without a teacher
    same, _ = self_supervised_loss(student, cams, STRIDE, SIGMA, target_logits=student.detach())
    assert same.item() == pytest.approx(own.item(), abs=1e-7)
    with pytest.raises(ValueError, match="target_logits"):
        self_supervised_loss(student, cams, STRIDE, SIGMA, target_logits=teacher[:, :2])


def test_self_supervised_pseudo_label_window_ignores_spread_probability():
    """Heatmaps with mass spread over them: the whole-heatmap means are pulled inwards, so the pseudo-label
    is off the true point; with a window around each peak it is on it."""
    cams, X = _rig(), _points()
    target, _ = gaussian_targets(_project_all(cams, X), None, h, w, STRIDE, SIGMA)
    logits = (0.8 * target + 0.2 / (h * w)).log().float()
    _, whole = self_supervised_loss(logits, cams, STRIDE, SIGMA,
                                    rule=ReadoutConfig.for_pseudo_labels(window=0))
    _, windowed = self_supervised_loss(logits, cams, STRIDE, SIGMA,
                                       rule=ReadoutConfig.for_pseudo_labels(window=5))
    assert (whole["points"] - X).norm(dim=-1).max() > 5e-3
    torch.testing.assert_close(windowed["points"], X, atol=1e-3, rtol=0)


def test_self_supervised_layout_check_masks_a_collapsed_pseudo_label():
    """Every keypoint's heatmaps on one spot: the views agree, so the pseudo-label is valid and teaches the
    collapse; held to the labelled layout it gives no term. An intact layout is untouched."""
    cams, X = _rig(), _points()
    ref = torch.cdist(X[0], X[0]).fill_diagonal_(float("nan"))
    same = X.clone()
    same[0] = X[0]
    same[1] = X[0] + 0.01  # frame 1 is frame 0's layout, moved
    collapsed = same.clone()
    collapsed[1] = X[0, :1].expand(3, 3)  # frame 1: every keypoint at keypoint 0's place
    _, plain = self_supervised_loss(_logits_at(_project_all(cams, collapsed)).float(), cams, STRIDE, SIGMA)
    assert plain["points_valid"].all()
    loss, held = self_supervised_loss(_logits_at(_project_all(cams, collapsed)).float(), cams, STRIDE, SIGMA,
                                      rule=ReadoutConfig.for_pseudo_labels(layout=ref, layout_tol=0.2))
    assert held["points_valid"][0].all() and not held["points_valid"][1].any()
    assert held["mask"][0].all() and not held["mask"][1].any()
    _, intact = self_supervised_loss(_logits_at(_project_all(cams, same)).float(), cams, STRIDE, SIGMA,
                                     rule=ReadoutConfig.for_pseudo_labels(layout=ref, layout_tol=0.2))
    assert intact["points_valid"].all()


def test_self_supervised_layout_fit_gives_the_layout_its_shape():
    """Detections off by a little (one keypoint of frame 0 a few millimetres off its place): the pseudo-label
    triangulates them as they are; with ``layout_fit`` the kept keypoints take the places of the labelled
    layout moved onto them, so their distances are the layout's, and nearer the truth in the squared sum."""
    cams, X = _rig(), _points()
    ref = torch.cdist(X[0], X[0]).fill_diagonal_(float("nan"))
    X = torch.stack([X[0], X[0] + 0.01])  # one rigid layout in both frames
    off = X.clone()
    off[0, 1] += torch.tensor([0.006, -0.004, 0.003], dtype=off.dtype)
    logits = _logits_at(_project_all(cams, off)).float()
    rule = ReadoutConfig.for_pseudo_labels(window=5, layout=ref, layout_tol=0.2)
    _, plain = self_supervised_loss(logits, cams, STRIDE, SIGMA, rule=rule)
    fit_rule = ReadoutConfig.for_pseudo_labels(window=5, layout=ref, layout_tol=0.2, layout_fit=True)
    _, fitted = self_supervised_loss(logits, cams, STRIDE, SIGMA, rule=fit_rule)
    assert plain["points_valid"].all() and fitted["points_valid"].all()
    torch.testing.assert_close(plain["points"], off, atol=1e-3, rtol=0)
    d = torch.cdist(fitted["points"].double(), fitted["points"].double())
    torch.testing.assert_close(d[0], ref.nan_to_num(0.0), atol=1e-4, rtol=0)
    assert ((fitted["points"][0] - X[0]) ** 2).sum() < 0.8 * ((plain["points"][0] - X[0]) ** 2).sum()



def test_coord_loss_is_the_mean_distance_in_target_widths_and_pulls_the_mean_in():
    """A heatmap whose mean sits on the target costs nothing; one whose mass leans 2 pixels off costs its
    distance over sigma (smoothed near zero); a gradient step moves the mean towards the target; masked terms
    cost nothing."""
    from s3k.train.losses import coord_loss

    stride, sigma = 2, 3.0
    target_uv = torch.tensor([[[20.3, 30.7], [10.0, 12.0]]])  # (B=1, K=2, 2)
    on, _ = gaussian_targets(target_uv, None, 32, 32, stride, sigma)
    mask = torch.tensor([[True, False]])
    assert float(coord_loss(on.log(), target_uv, mask, stride, sigma)) == pytest.approx(0.0, abs=1e-4)
    off_uv = target_uv + torch.tensor([2.0, 0.0])
    off, _ = gaussian_targets(off_uv, None, 32, 32, stride, sigma)
    logits = off.log().clone().requires_grad_(True)
    loss = coord_loss(logits, target_uv, mask, stride, sigma)
    assert float(loss.detach()) == pytest.approx(((2.0 / sigma) ** 2 + 0.01) ** 0.5 - 0.1, abs=1e-3)
    loss.backward()
    with torch.no_grad():
        moved = heatmap_moments(spatial_softmax(logits - 20.0 * logits.grad), stride)[0]
    assert float(moved[0, 0, 0]) < float(off_uv[0, 0, 0])  # towards 20.3
    assert torch.equal(logits.grad[0, 1], torch.zeros_like(logits.grad[0, 1]))  # the masked term
    assert float(coord_loss(off.log(), target_uv, torch.zeros_like(mask), stride, sigma)) == 0.0


def test_coord_weight_adds_the_coordinate_term_to_both_losses():
    """With ``coord_weight`` the supervised and self-supervised losses grow by that times ``coord_loss`` of
    their own targets, which ``info`` reports."""
    from s3k.train.losses import coord_loss

    cams = _rig()
    uv, _ = project(cams, _points()[:, None])
    logits = _logits_at(uv + torch.tensor([1.5, -1.0], dtype=uv.dtype)).float()  # off the labels
    labelled = torch.ones(uv.shape[:-1], dtype=torch.bool)
    base, info = supervised_loss(logits, cams, uv, labelled, STRIDE, SIGMA)
    plus, _ = supervised_loss(logits, cams, uv, labelled, STRIDE, SIGMA, coord_weight=0.5)
    extra = coord_loss(logits, info["target_uv"], info["mask"], STRIDE, SIGMA)
    assert info["mask"].any() and float(extra) > 0
    assert float(plus - base) == pytest.approx(0.5 * float(extra), rel=1e-4)
    base_u, info_u = self_supervised_loss(logits, cams, STRIDE, SIGMA)
    plus_u, _ = self_supervised_loss(logits, cams, STRIDE, SIGMA, coord_weight=2.0)
    extra_u = coord_loss(logits, info_u["target_uv"], info_u["mask"], STRIDE, SIGMA)
    assert info_u["mask"].any()
    assert float(plus_u - base_u) == pytest.approx(2.0 * float(extra_u), rel=1e-5)
