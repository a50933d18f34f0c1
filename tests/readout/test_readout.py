"""The read-out (s3k.readout) and its callers: the same logits give the same 3D points everywhere.

The logits are Gaussians at the projections of known 3D points plus noise, so the triangulations are well
defined but not exact; a stand-in network returns them whatever the images, so every caller (predict,
evaluate, track's pixel-mapped path, export's graph, model.detect, the self-supervised loss, the benchmarks)
reads out the same numbers.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.synthetic_rig import KEYPOINTS, make_dataset
from torch import nn

from s3k.data.frames import FrameStore, images_to_float, open_dataset
from s3k.detector import DetectorMeta, OnePassDetector
from s3k.geometry import Cameras, project
from s3k.geometry.warp import crop_resize_matrix
from s3k.inference.evaluate import evaluate_store
from s3k.inference.export import DetectorWithMoments
from s3k.inference.predict import detect_store
from s3k.model import detect
from s3k.readout import ReadoutConfig, read_out, select_views, triangulate, window_cells
from s3k.readout.heatmaps import (
    confidence_weight,
    gaussian_targets,
    heatmap_moments,
    peak_window_mean,
    spatial_softmax,
)
from s3k.train.losses import self_supervised_loss

SIZE, STRIDE, SIGMA = 32, 2, 2.0
#: A detector's description with this module's read-out settings (no outlier threshold).
META = DetectorMeta(list(KEYPOINTS), [], (SIZE, SIZE), STRIDE, SIGMA)


class FixedLogits(nn.Module):
    """A network stand-in: returns the same ``(N, K, h, w)`` logits for any ``N`` images."""

    def __init__(self, logits: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("logits", logits)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        assert images.shape[0] == self.logits.shape[0], "one logit map per image"
        return self.logits + 0.0 * images.sum()  # keeps the graph connected to the input for tracing


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A dataset's test frames, their cameras (B, C) and float32 logits peaked near the true points."""
    root = tmp_path_factory.mktemp("readout")
    path = make_dataset(root / "ds", size=SIZE, labelled=1, unlabelled=1, test=3)
    ds = open_dataset(path, (SIZE, SIZE))
    store = FrameStore(ds, ds.frames("test"), points=True)
    batch = store.get(np.arange(len(store)))
    uv, _ = project(batch.cams.to(dtype=torch.float64), batch.points.double()[:, None])  # (B, C, K, 2)
    h = w = SIZE // STRIDE
    target, mask = gaussian_targets(uv, None, h, w, STRIDE, SIGMA)
    assert bool(mask.all())
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(target.shape, generator=g, dtype=torch.float64)
    logits = target.clamp_min(1e-30).log() + 0.5 * noise
    logits = logits.clamp_min(-40.0).float()  # what a network outputs
    return SimpleNamespace(store=store, batch=batch, logits=logits, B=len(store), C=logits.shape[1])


def test_every_caller_reads_out_the_same_points(scene):
    B, C, K = scene.logits.shape[:3]
    flat = scene.logits.reshape(B * C, *scene.logits.shape[2:])
    net = FixedLogits(flat).eval()
    cams = scene.batch.cams  # (B, C) float32, the network input's cameras
    images = images_to_float(scene.batch.images)
    ref = read_out(scene.logits, cams, STRIDE, SIGMA)
    assert ref.valid.all() and ref.X.dtype == torch.float64
    # Noise moved the detections: the points are not the truth, so agreement below is not by construction.
    assert float((ref.X - scene.batch.points.double()).abs().max()) > 1e-4
    X, valid = ref.X.numpy(), ref.valid.numpy()

    def same(got_X, got_valid, atol=1e-12):
        np.testing.assert_array_equal(np.asarray(got_valid), valid)
        np.testing.assert_allclose(np.asarray(got_X, dtype=np.float64), X, rtol=0, atol=atol)

    # s3k.Detector on frames of its input size (s3k predict, evaluate, track, stream, the labelling app and
    # the robot loop go through it).
    detector = OnePassDetector(net, META)
    pred = detector(scene.batch.images, cams)
    same(pred.X, pred.valid)
    (_, stored), = list(detect_store(detector, scene.store, batch_size=B))
    same(stored.X, stored.valid)
    _, arrays = evaluate_store(detector, scene.store, batch_size=B)
    same(arrays["X"], arrays["X_valid"])
    np.testing.assert_allclose(arrays["pred_uv"], ref.uv.numpy(), rtol=0, atol=1e-12)

    # s3k track: detections mapped to the original images' pixels (here a crop of a larger frame) and
    # triangulated in those cameras, K = M^-1 K'. Only the float64 round trip through M differs.
    M = crop_resize_matrix((-6.0, 3.0, 58.0, 67.0), (SIZE, SIZE))
    maps = np.repeat(M[None], C, axis=0)
    K_video = torch.as_tensor(np.linalg.inv(M)) @ cams.K.double()
    video_cams = Cameras(K_video, cams.dist.double(), cams.R.double(), cams.t.double())
    tracked = read_out(scene.logits, video_cams, STRIDE, SIGMA, maps)
    same(tracked.X, tracked.valid, atol=1e-9)
    back = tracked.uv.numpy() @ M[:2, :2].T + M[:2, 2]
    np.testing.assert_allclose(back, ref.uv.numpy(), rtol=0, atol=1e-9)

    # s3k export --with-moments: the graph's means and confidences (float32 outputs) triangulated.
    with torch.no_grad():
        _, means, conf = DetectorWithMoments(net, STRIDE, SIGMA)(images.reshape(B * C, *images.shape[2:]))
    means, conf = means.reshape(B, C, K, 2), conf.reshape(B, C, K)
    np.testing.assert_allclose(means.numpy(), ref.uv.numpy(), rtol=0, atol=1e-5)
    X_exp, valid_exp = triangulate(cams, means, conf, select_views(means, conf))
    same(X_exp, valid_exp, atol=1e-6)  # float32 means: a micrometre at 1 m

    # model.detect's moments.
    with torch.no_grad():
        _, mean_uv, var = detect(net, images, STRIDE, window_cells(SIGMA, STRIDE))
    w = confidence_weight(var, SIGMA)
    same(*triangulate(cams, mean_uv, w, select_views(mean_uv, w)))

    # Training's self-supervised target: the same point, in the cameras' float32.
    _, info = self_supervised_loss(scene.logits, cams, STRIDE, SIGMA)
    same(info["points"], info["points_valid"], atol=1e-7)

    # One frame of C images (the per-frame path of a controller or a live stream).
    one = OnePassDetector(FixedLogits(scene.logits[0]).eval(), META)
    first = one(scene.batch.images[0], cams[0])  # (C, H, W, 3), cameras (C,)
    np.testing.assert_allclose(first.X[0].numpy(), X[0], rtol=0, atol=1e-12)
    assert bool(first.valid.all())


def test_read_out_fields(scene):
    """Moments in float64 (the mean within the window of the peak, the variance the whole heatmap's),
    weights, views used, residuals and their summaries, by definition."""
    r = read_out(scene.logits, scene.batch.cams, STRIDE, SIGMA, keep_heatmaps=True)
    probs = spatial_softmax(scene.logits.double())
    whole_mean, var = heatmap_moments(probs, STRIDE)
    mean = peak_window_mean(probs, STRIDE, window_cells(SIGMA, STRIDE))
    torch.testing.assert_close(r.probs, probs)
    torch.testing.assert_close(r.uv, mean)
    # the paper's read-out
    whole = read_out(scene.logits, scene.batch.cams, STRIDE, SIGMA, config=ReadoutConfig(window=0))
    torch.testing.assert_close(whole.uv, whole_mean)
    torch.testing.assert_close(r.weights, confidence_weight(var, SIGMA))
    assert r.used.all() and (r.ncams == scene.C).all()  # every finite view (weights are always > 0)
    reproj, _ = project(scene.batch.cams.to(dtype=torch.float64), r.X[:, None])
    torch.testing.assert_close(r.reproj, reproj)
    torch.testing.assert_close(r.residual, (reproj - mean).norm(dim=-1))
    torch.testing.assert_close(r.error, r.residual.mean(dim=1))
    torch.testing.assert_close(r.score, r.weights.mean(dim=1))


def test_read_out_reads_the_peak_not_the_spread(scene):
    """Heatmaps with a tenth of their mass spread evenly: the whole heatmap's mean is pulled towards the
    heatmap's centre, the read-out's windowed mean stays where the peak is, and the confidence (from the
    whole heatmap's spread) falls."""
    cams = scene.batch.cams
    sharp = read_out(scene.logits, cams, STRIDE, SIGMA)
    h, w = scene.logits.shape[-2:]
    probs = spatial_softmax(scene.logits.double())
    spread = (0.9 * probs + 0.1 / (h * w)).log()
    windowed = read_out(spread, cams, STRIDE, SIGMA)
    whole = read_out(spread, cams, STRIDE, SIGMA, config=ReadoutConfig(window=0))
    pull = (whole.uv - sharp.uv).norm(dim=-1)
    assert pull.median() > 0.2  # pixels
    assert (windowed.uv - sharp.uv).norm(dim=-1).median() < 0.25 * pull.median()
    assert (windowed.weights < sharp.weights).all()


def test_min_weight_drops_views_and_invalid_points_are_nan(scene):
    logits = scene.logits.clone()
    logits[:, 1:] = 0.0  # flat heatmaps in all but one camera: weight about 0.05
    soft = read_out(logits, scene.batch.cams, STRIDE, SIGMA)
    assert soft.valid.all()  # every view counts, weighted
    hard = read_out(logits, scene.batch.cams, STRIDE, SIGMA, config=ReadoutConfig(min_weight=0.5))
    assert (hard.ncams == 1).all() and not hard.valid.any()
    assert torch.isnan(hard.X).all() and torch.isnan(hard.reproj).all() and torch.isnan(hard.error).all()
    assert torch.isfinite(hard.score).all()
    with pytest.raises(ValueError, match="logits"):
        read_out(logits[0], scene.batch.cams, STRIDE, SIGMA)
    with pytest.raises(ValueError, match="cams"):
        read_out(logits[:, :2], scene.batch.cams, STRIDE, SIGMA)
    with pytest.raises(ValueError, match="pixel_maps"):
        read_out(logits, scene.batch.cams, STRIDE, SIGMA, np.eye(3)[None])


def _rig_views(B=5):
    """A 4-camera rig, B frames of the synthetic layout and their exact projections."""
    from helpers.synthetic_rig import LAYOUT, rig

    K, dist, R, t = rig(64)
    cams = Cameras.from_numpy(K, dist, R, t, dtype=torch.float64)
    gen = torch.Generator().manual_seed(3)
    X = torch.as_tensor(LAYOUT)[None] + 0.02 * torch.randn(B, 1, 3, generator=gen, dtype=torch.float64)
    uv, _ = project(cams, X[:, None])  # (B, C, K, 2)
    return cams, X, uv


def test_outlier_rejection_ignores_a_corrupted_view():
    from s3k.readout import reject_outliers

    cams, X, uv = _rig_views()
    weights = torch.full(uv.shape[:-1], 0.9, dtype=torch.float64)
    bad = uv.clone()
    bad[:, 2, 0] += torch.tensor([25.0, -15.0], dtype=torch.float64)  # camera 2 sees keypoint 0 elsewhere
    used = select_views(bad, weights)
    plain, _ = triangulate(cams, bad, weights, used)
    assert (plain[:, 0] - X[:, 0]).norm(dim=-1).min() > 1e-3  # the weighted point is pulled off
    kept = reject_outliers(cams, bad, weights, used, max_residual_px=3.0)
    assert not kept[:, 2, 0].any() and kept[:, :, 1:].all() and kept[:, [0, 1, 3], 0].all()
    robust, valid = triangulate(cams, bad, weights, kept)
    assert valid.all()
    torch.testing.assert_close(robust, X, atol=1e-9, rtol=0)
    # the same through read_out's option, and nothing is dropped from consistent views
    assert reject_outliers(cams, uv, weights, select_views(uv, weights), 3.0).all()


def test_layout_rejection_drops_collapsed_and_misplaced_keypoints():
    from s3k.readout import reject_layout

    layout = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [0, 0.2, 0]], dtype=torch.float64)
    ref = torch.cdist(layout, layout).fill_diagonal_(float("nan"))
    misplaced = layout.clone()
    misplaced[2] = torch.tensor([0.05, 0.01, 0.0], dtype=torch.float64)  # keypoint 2 detected between 0 and 1
    collapsed = torch.full((3, 3), 0.03, dtype=torch.float64)  # all three on one spot
    shifted = layout + torch.tensor([0.3, -0.1, 0.5], dtype=torch.float64)  # the layout moved: intact
    X = torch.stack([layout, misplaced, collapsed, shifted])
    valid = torch.ones(4, 3, dtype=torch.bool)
    kept = reject_layout(X, valid, ref, tol=0.2)
    assert kept.tolist() == [[True] * 3, [True, True, False], [False] * 3, [True] * 3]
    # a keypoint already invalid is not checked against, and one with no pair to check is kept
    partial = valid.clone()
    partial[1, 0] = False  # misplaced frame without keypoint 0: 1-2 is broken, nothing vouches for either
    partial[3, 1:] = False  # one keypoint alone: nothing to check
    assert reject_layout(X, partial, ref, 0.2).tolist() == [[True] * 3, [False] * 3, [False] * 3,
                                                            [True, False, False]]
    unknown = ref.clone()
    unknown[:] = float("nan")  # no reference: nothing is dropped
    assert reject_layout(X, valid, unknown, 0.2).all()
    assert reject_layout(X, valid, ref, tol=10.0).all()  # everything within a loose tolerance


def test_outlier_rejection_keeps_at_least_min_views():
    from s3k.readout import reject_outliers

    cams, X, uv = _rig_views()
    noisy = uv + 10.0 * torch.randn(uv.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    weights = torch.ones(uv.shape[:-1], dtype=torch.float64)
    kept = reject_outliers(cams, noisy, weights, select_views(noisy, weights), max_residual_px=0.01)
    assert (kept.sum(dim=1) == 2).all()  # every view misses by more than 0.01 px: down to two views, no fewer


def test_outlier_threshold_is_in_network_pixels_whatever_the_pixel_maps(scene):
    """A detector's ``--outlier-px`` holds in the pixels it saw: read out through a pixel map (track, the
    refining pass's crops) it drops the same views, and gives the same points, as in the network's cameras."""
    cams = scene.batch.cams
    logits = scene.logits.clone()
    logits[:, 2, 0] = logits[:, 2, 0].roll(shifts=(3, -2), dims=(-2, -1))  # camera 2: keypoint 0 elsewhere
    plain = read_out(logits, cams, STRIDE, SIGMA)
    # Network pixels: camera 2's keypoint 0 misses by more, the noisy views by less than the threshold but by
    # more than a third of it (in pixels three times as fine they would miss by more).
    threshold = 1.0
    assert float(plain.residual[:, 2, 0].min()) > threshold
    ref = read_out(logits, cams, STRIDE, SIGMA, config=ReadoutConfig(max_residual_px=threshold))
    assert not ref.used[:, 2, 0].any() and int(ref.used.sum()) == int(plain.used.sum()) - scene.B
    assert float(ref.residual[ref.used].max()) > threshold / 3
    assert (ref.X[:, 0] - plain.X[:, 0]).norm(dim=-1).min() > 1e-4  # the outlier moved the plain point
    # The same frames in video pixels three times as fine as the network's: M scales by 1/3.
    M = crop_resize_matrix((-6.0, 3.0, 3 * SIZE - 6.0, 3 * SIZE + 3.0), (SIZE, SIZE))
    maps = np.repeat(M[None], scene.C, axis=0)
    video = Cameras(torch.as_tensor(np.linalg.inv(M)) @ cams.K.double(), cams.dist.double(), cams.R.double(),
                    cams.t.double())
    tracked = read_out(logits, video, STRIDE, SIGMA, maps, ReadoutConfig(max_residual_px=threshold))
    assert torch.equal(tracked.used, ref.used)
    torch.testing.assert_close(tracked.X, ref.X, rtol=0, atol=1e-9)


def _rotation(axis, angle: float) -> torch.Tensor:
    """The rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    a = torch.as_tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    A = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * A + (1 - math.cos(angle)) * A @ A


def test_layout_shape_and_fit_hold_points_to_a_rigid_layout():
    from s3k.readout import fit_layout, layout_shape

    Y = torch.tensor([[0.0, 0, 0], [0.2, 0, 0], [0.2, 0.1, 0], [0, 0.05, 0.08]], dtype=torch.float64)
    ref = torch.cdist(Y, Y).fill_diagonal_(float("nan"))
    shape = layout_shape(ref)
    torch.testing.assert_close(torch.cdist(shape, shape), torch.cdist(Y, Y), rtol=0, atol=1e-9)
    unknown = ref.clone()
    unknown[0, 3] = unknown[3, 0] = float("nan")
    assert layout_shape(unknown) is None and layout_shape(ref[:2, :2]) is None
    R, t = _rotation([1.0, 2.0, -0.5], 0.7), torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64)
    truth = Y @ R.T + t
    mirrored = (Y * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)) @ R.T + t
    gen = torch.Generator().manual_seed(1)
    noisy = truth + 0.004 * torch.randn(truth.shape, generator=gen, dtype=torch.float64)
    Y5 = torch.cat([Y, torch.tensor([[0.1, 0.1, -0.05]], dtype=torch.float64)])
    ref5 = torch.cdist(Y5, Y5).fill_diagonal_(float("nan"))
    truth5 = Y5 @ R.T + t
    missing = truth5.clone()
    missing[4] = float("nan")  # not triangulated: four keypoints in three dimensions place it
    flat = truth5.clone()
    flat[3:] = float("nan")  # three keypoints on a plane: the fifth could be on either side, not placed
    both = torch.stack([missing, flat])
    five, placed5 = fit_layout(both, torch.isfinite(both)[..., 0], layout_shape(ref5))
    assert placed5.tolist() == [[True] * 5, [True, True, True, False, False]]
    torch.testing.assert_close(five[0], truth5, rtol=0, atol=1e-9)
    torch.testing.assert_close(five[1, :3], truth5[:3], rtol=0, atol=1e-9)
    X = torch.stack([truth, mirrored, noisy, noisy])
    valid = torch.ones(4, 4, dtype=torch.bool)
    valid[3, 2:] = False  # two keypoints: too few to fit
    fit, placed = fit_layout(X, valid, shape)
    assert placed.tolist() == [[True] * 4] * 3 + [[False] * 4]
    torch.testing.assert_close(fit[0], truth, rtol=0, atol=1e-9)
    torch.testing.assert_close(fit[1], mirrored, rtol=0, atol=1e-9)  # the mirror image fits too
    torch.testing.assert_close(fit[3], noisy, rtol=0, atol=0)
    assert (fit[2] - truth).norm(dim=-1).mean() < 0.8 * (noisy - truth).norm(dim=-1).mean()
    torch.testing.assert_close(torch.cdist(fit[2], fit[2]), torch.cdist(Y, Y), rtol=0, atol=1e-9)


def test_layout_locus_is_where_the_distances_hold():
    from s3k.readout import layout_locus

    a = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    b = a + torch.tensor([0.05, 0.12, -0.04], dtype=torch.float64)
    places = layout_locus(a, b, 0.2, 0.15, 90)
    assert places.shape == (90, 3)
    torch.testing.assert_close((places - a).norm(dim=-1), torch.full((90,), 0.2, dtype=torch.float64))
    torch.testing.assert_close((places - b).norm(dim=-1), torch.full((90,), 0.15, dtype=torch.float64))
    assert torch.cdist(places, places).max() > 0.2  # a circle, not one point


def _mixed_logits(cams, X, size, sigma, parts):
    """``(B, C, K, size, size)`` stride-1 logits: each keypoint's heatmap the mixture ``parts[k]`` of
    Gaussians at the projections of keypoints (``[(keypoint, share), ...]``)."""
    uv, _ = project(cams, X[:, None])  # (B, C, K, 2)
    probs = torch.zeros(uv.shape[:3] + (size, size), dtype=torch.float64)
    for k, mixture in enumerate(parts):
        for j, share in mixture:
            target, _ = gaussian_targets(uv[:, :, j], None, size, size, 1, sigma)
            probs[:, :, k] += share * target / target.sum(dim=(-2, -1), keepdim=True)
    return probs.clamp_min(1e-30).log().clamp_min(-40.0)


def test_layout_read_out_finds_a_keypoint_taken_for_its_neighbour():
    """Keypoint 0's heatmaps peak on keypoint 1 in every view, with a faint second peak on its own place:
    the views agree, so neither the confidence nor the outlier check sees it; held to the labelled layout,
    the read-out looks for it where the layout puts it and finds it, also through a pixel map."""
    cams, X, _ = _rig_views()
    size, sigma = 64, 1.0
    ref = torch.cdist(X[0], X[0]).fill_diagonal_(float("nan"))
    good = _mixed_logits(cams, X, size, sigma, [[(0, 1.0)], [(1, 1.0)], [(2, 1.0)]])
    confused = _mixed_logits(cams, X, size, sigma, [[(1, 0.95), (0, 0.05)], [(1, 1.0)], [(2, 1.0)]])
    plain = read_out(confused, cams, 1, sigma)
    assert float((plain.X[:, 0] - X[:, 1]).norm(dim=-1).max()) < 2e-3  # on its neighbour
    held = read_out(confused, cams, 1, sigma, config=ReadoutConfig(layout=ref, layout_tol=0.1))
    assert held.valid.all()
    assert float((held.X - X).norm(dim=-1).max()) < 1e-3
    assert float((plain.X[:, 1:] - X[:, 1:]).norm(dim=-1).max()) < 1e-3
    # right detections stay right, and nothing changes without a tolerance
    rigid, off = ReadoutConfig(layout=ref, layout_tol=0.1), ReadoutConfig(layout=ref, layout_tol=0.0)
    torch.testing.assert_close(read_out(good, cams, 1, sigma, config=rigid).X, X, rtol=0, atol=1e-3)
    torch.testing.assert_close(read_out(confused, cams, 1, sigma, config=off).X, plain.X)
    # the same heatmaps read in video pixels three times as fine as the network's
    M = crop_resize_matrix((-6.0, 3.0, 3 * size - 6.0, 3 * size + 3.0), (size, size))
    maps = np.repeat(M[None], cams.shape[0], axis=0)
    video = Cameras(torch.as_tensor(np.linalg.inv(M)) @ cams.K, cams.dist, cams.R, cams.t)
    tracked = read_out(confused, video, 1, sigma, maps, ReadoutConfig(layout=ref, layout_tol=0.1))
    torch.testing.assert_close(tracked.X, held.X, rtol=0, atol=1e-9)


def test_detector_meta_keeps_the_layout_through_json():
    import json

    ref = [[float("nan"), 0.2, 0.3], [0.2, float("nan"), 0.1], [0.3, 0.1, float("nan")]]
    meta = DetectorMeta(list(KEYPOINTS), [], (SIZE, SIZE), STRIDE, SIGMA, layout=ref, layout_tol=0.1)
    back = DetectorMeta.from_dict(json.loads(json.dumps(meta.to_dict(), allow_nan=False)))
    np.testing.assert_array_equal(np.asarray(back.layout), np.asarray(ref))
    assert back.layout_tol == 0.1 and back.layout_distances.shape == (3, 3)
    assert DetectorMeta(list(KEYPOINTS), [], (SIZE, SIZE), STRIDE, SIGMA, layout=ref).layout_distances is None


def test_a_layout_tie_is_settled_by_the_heatmaps():
    """Keypoint 2 is seen in its place by camera 0 only; the other views peak on a point at its distance from
    keypoint 1 but not from keypoint 0. The layout check finds one broken pair, 0-2, and nothing in the
    distances tells which of the two is off: the read-out weighs both ways by the heatmaps and looks for
    keypoint 2 again, where camera 0 sees it, instead of moving keypoint 0."""
    from s3k.readout import reject_layout, settle_ties

    cams, X, _ = _rig_views(B=3)
    size, sigma = 64, 1.0
    ref = torch.cdist(X[0], X[0]).fill_diagonal_(float("nan"))
    # the wrong point: keypoint 2 turned about keypoint 1, in the plane of the three, by 0.6 rad
    wrong = torch.empty_like(X)
    for b in range(len(X)):
        axis = torch.linalg.cross(X[b, 0] - X[b, 1], X[b, 2] - X[b, 1])
        wrong[b] = X[b]
        wrong[b, 2] = X[b, 1] + (X[b, 2] - X[b, 1]) @ _rotation(axis, 0.6).T
    seen = _mixed_logits(cams, X, size, sigma, [[(0, 1.0)], [(1, 1.0)], [(2, 1.0)]])
    misled = _mixed_logits(cams, wrong, size, sigma, [[(0, 1.0)], [(1, 1.0)], [(2, 0.9)]])
    faint = _mixed_logits(cams, X, size, sigma, [[(2, 1.0)]] * 3)  # keypoint 2's own place, faintly
    logits = seen.clone()
    logits[:, 1:, 2] = torch.logaddexp(misled[:, 1:, 2], faint[:, 1:, 2] + math.log(0.1))
    plain = read_out(logits, cams, 1, sigma)
    # the tie itself: only the pair 0-2 breaks, and the check drops keypoint 0, the one in the right place
    rel = (torch.cdist(plain.X, plain.X) - ref).abs() / ref
    broken = (rel > 0.1) & torch.isfinite(rel)
    assert broken[:, 0, 2].all() and not broken[:, 0, 1].any() and not broken[:, 1, 2].any()
    kept = reject_layout(plain.X, plain.valid, ref, 0.1)
    assert kept.tolist() == [[False, True, True]] * 3
    assert float((plain.X[:, 0] - X[:, 0]).norm(dim=-1).max()) < 1e-3
    probs = torch.softmax(logits.flatten(-2), -1).view_as(logits)
    settled, found = settle_ties(probs, cams, 1, plain.X, plain.valid, kept, ref, 0.1,
                                 window_cells(sigma, 1, None))
    assert settled.tolist() == [[True, True, False]] * 3
    # the frames settled come with the search for keypoint 2, which need not run again
    assert sorted(found) == [0, 1, 2] and all([f[:2] for f in found[b]] == [(b, 2)] for b in found)
    held = read_out(logits, cams, 1, sigma, config=ReadoutConfig(layout=ref, layout_tol=0.1))
    assert held.valid.all()
    # keypoint 0 stays where every view saw it, and keypoint 2 comes nearer its place (its detections in
    # cameras 1-3 are still read next to the stronger wrong peak)
    assert float((held.X[:, :2] - X[:, :2]).norm(dim=-1).max()) < 1e-3
    assert bool(((held.X[:, 2] - X[:, 2]).norm(dim=-1) < 0.8 * (plain.X[:, 2] - X[:, 2]).norm(dim=-1)).all())


def test_a_layout_prior_tells_a_keypoint_from_its_mirror_image():
    """Keypoint 0's heatmaps peak on keypoint 1, with faint equal peaks on its own place and on its mirror
    image across the line through keypoints 1 and 2, where every distance holds too: the views cannot tell
    the two apart. Another network's heatmaps of the same frames (a two-pass detector's coarse pass) can,
    whichever place they favour."""
    from s3k.readout import LayoutPrior

    cams, X, _ = _rig_views(B=3)
    size, sigma = 64, 1.0
    ref = torch.cdist(X[0], X[0]).fill_diagonal_(float("nan"))
    line = (X[:, 2] - X[:, 1]) / (X[:, 2] - X[:, 1]).norm(dim=-1, keepdim=True)
    foot = X[:, 1] + ((X[:, 0] - X[:, 1]) * line).sum(dim=-1, keepdim=True) * line
    mirror = X.clone()
    mirror[:, 0] = 2 * foot - X[:, 0]
    torch.testing.assert_close(torch.cdist(mirror, mirror), torch.cdist(X, X))
    both = torch.stack([X, mirror], dim=2).flatten(1, 2)  # (B, 6, 3): keypoint 0 at 0, its mirror at 1
    parts = [[(2, 0.9), (0, 0.05), (1, 0.05)], [(2, 1.0)], [(4, 1.0)]]
    confused = _mixed_logits(cams, both, size, sigma, parts)[:, :, :3]
    plain = read_out(confused, cams, 1, sigma, config=ReadoutConfig(layout=ref, layout_tol=0.1))
    for favoured, other in ((X, mirror), (mirror, X)):
        coarse = _mixed_logits(cams, favoured, size, 3 * sigma, [[(0, 1.0)], [(1, 1.0)], [(2, 1.0)]]).exp()
        prior = LayoutPrior(coarse, cams, 1)
        held = read_out(confused, cams, 1, sigma, config=ReadoutConfig(layout=ref, layout_tol=0.1),
                        prior=prior)
        near, far = ((held.X[:, 0] - P[:, 0]).norm(dim=-1) for P in (favoured, other))
        assert bool((near < 0.2 * far).all()), (near, far)
    # the side the heatmaps alone chose is one of the two
    near = torch.minimum(*((plain.X[:, 0] - P[:, 0]).norm(dim=-1) for P in (X, mirror)))
    assert float(near.max()) < 0.03
    # and with the prior favouring its own place, the read-out is as exact as with clear heatmaps
    coarse = _mixed_logits(cams, X, size, 3 * sigma, [[(0, 1.0)], [(1, 1.0)], [(2, 1.0)]]).exp()
    held = read_out(confused, cams, 1, sigma, config=ReadoutConfig(layout=ref, layout_tol=0.1),
                    prior=LayoutPrior(coarse, cams, 1))
    assert float((held.X - X).norm(dim=-1).max()) < 1e-3


@pytest.mark.parametrize("B", [3, 600])
def test_outlier_rounds_on_rays_cast_once_match_triangulating_each_round(B):
    """The outlier rounds cast the views' rays once and change only the weights: the views they keep and
    the points of those views are those of triangulating the detections anew in every round (a few points,
    solved with the rays' projectors, and thousands, solved in the large-batch layout)."""
    from s3k.geometry import triangulate_pixels
    from s3k.readout.views import outliers_and_points, reject_outliers, view_rays

    g = torch.Generator().manual_seed(4)
    C, K = 4, 5
    cams = Cameras(torch.tensor([[300.0, 0, 63.5], [0, 300.0, 63.5], [0, 0, 1]], dtype=torch.float64)
                   .expand(C, 3, 3), torch.randn(C, 5, generator=g, dtype=torch.float64) * 0.01,
                   *_ring_rotations_and_translations(C))
    X = torch.randn(B, K, 3, generator=g, dtype=torch.float64) * 0.1
    uv, _ = project(cams, X[:, None])  # (B, C, K, 2)
    uv = uv + torch.randn(uv.shape, generator=g, dtype=torch.float64) * 0.5
    uv[0, 1, 0] += 40.0  # one view on the wrong object
    uv[1, 2, 3] = float("nan")  # one view missing
    weights = torch.rand(B, C, K, generator=g, dtype=torch.float64) * 0.9 + 0.05
    used = select_views(uv, weights)

    def anew(used):  # the used detections' pixels through s3k.geometry, unused views at pixel 0, weight 0
        zero = torch.zeros((), dtype=torch.float64)
        X, valid = triangulate_pixels(cams, torch.where(used[..., None], uv, zero),
                                      torch.where(used, weights, zero))
        return X, valid & (used.sum(dim=1) >= 2)

    def each_round(used):  # the rounds as written before: triangulate the used detections anew each time
        for _ in range(C - 2):
            Xr, valid = anew(used)
            reproj, _ = project(cams, Xr[:, None])
            res = (reproj - uv).norm(dim=-1)
            res = torch.where(used & valid[:, None], res, torch.full_like(weights, -1.0))
            worst, c = res.max(dim=1)
            drop = (worst > 3.0) & (used.sum(1) > 2)
            if not bool(drop.any()):
                break
            used = used & ~(torch.nn.functional.one_hot(c, C).permute(0, 2, 1).bool() & drop[:, None])
        return used

    want_used = each_round(used)
    assert int(used.sum() - want_used.sum()) >= 1  # the wrong view is dropped
    want_X, want_valid = anew(want_used)
    X_views, valid_views = triangulate(cams, uv, weights, want_used)
    assert torch.equal(valid_views, want_valid)
    torch.testing.assert_close(X_views, want_X, rtol=0, atol=1e-12)
    assert torch.equal(reject_outliers(cams, uv, weights, used, 3.0), want_used)
    got_used, got_X, got_valid = outliers_and_points(cams, uv, weights, used, 3.0,
                                                     rays=view_rays(cams, uv, used))
    assert torch.equal(got_used, want_used) and torch.equal(got_valid, want_valid)
    torch.testing.assert_close(got_X, want_X, rtol=0, atol=1e-12)


def _ring_rotations_and_translations(C: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R (C, 3, 3), t (C, 3))`` of cameras on a ring 1 unit from the origin, looking at it."""
    az = torch.linspace(0, 2 * torch.pi, C + 1, dtype=torch.float64)[:-1]
    pos = torch.stack([az.cos() * 0.9, az.sin() * 0.9, torch.full_like(az, 0.45)], -1)
    z = -pos / pos.norm(dim=-1, keepdim=True)
    x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(z))
    x = x / x.norm(dim=-1, keepdim=True)
    R = torch.stack([x, torch.linalg.cross(z, x), z], dim=-2)
    return R, -(R @ pos[..., None])[..., 0]
