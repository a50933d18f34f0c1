"""The detector's fast CPU path (a frozen network graph, every view's crop in one resampling) gives what the
plain path gives: the same logits, the same crops up to a rounding flip, the same 3D points to well under
0.1 mm."""

from __future__ import annotations

import torch
from helpers.synthetic_rig import ring_cameras
from helpers.tiny_detector import trained_like_batch_norm

from s3k.detector import CropRule, DetectorMeta, OnePassDetector, TwoPassDetector
from s3k.detector.frozen import FrozenNetwork
from s3k.geometry.warp import crop_images, region_around, regions_around
from s3k.model import UNet, UNetConfig


def _trained_like(size: int, seed: int) -> tuple[torch.nn.Module, DetectorMeta]:
    """A fused U-Net whose BatchNorm statistics are not the identity (as after training)."""
    torch.manual_seed(seed)
    config = UNetConfig(channels=(8, 16, 16), res_blocks=1)
    net = trained_like_batch_norm(UNet(3, config), var=(0.5, 2.0))
    meta = DetectorMeta(["a", "b", "c"], [], (size, size), config.stride, 2.0, config.to_dict(), units="m",
                        outlier_px=6.0)
    return net.eval().fused().to(memory_format=torch.channels_last), meta


def test_the_frozen_network_gives_the_eager_networks_logits():
    net, _ = _trained_like(48, 0)
    frozen = FrozenNetwork(net, torch.device("cpu"))
    x = torch.rand(4, 3, 48, 48, generator=torch.Generator().manual_seed(1))
    x = x.contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        frozen(x)  # a new shape: the eager answer, and the graph made and checked
        assert not frozen.eager and len(frozen.frozen) == 1
        fast, plain = frozen(x), net(x)  # the frozen graph's answer
    torch.testing.assert_close(fast, plain, atol=1e-5, rtol=1e-5)
    with torch.inference_mode():  # another batch size: its own graph, the same numbers
        frozen(x[:2])
        torch.testing.assert_close(frozen(x[:2]), net(x[:2]), atol=1e-5, rtol=1e-5)
    assert len(frozen.frozen) == 2


def test_training_autocast_and_untraceable_networks_run_eagerly():
    net, _ = _trained_like(32, 2)
    frozen = FrozenNetwork(net, torch.device("cpu"))
    x = torch.rand(2, 3, 32, 32)
    frozen(x)  # gradients on: the eager module, so that training sees its parameters
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        frozen(x)
    assert frozen.frozen == {}

    other = FrozenNetwork(torch.nn.Conv2d(3, 3, 1), torch.device("cpu"))  # not s3k's network: as it is
    assert other.eager

    class Counting(UNet):  # Python state the trace would freeze into a constant
        calls = 0

        def forward(self, images):
            self.calls += 1
            return super().forward(images) + self.calls

    counting = Counting(3, UNetConfig(channels=(8, 8), res_blocks=0)).eval()
    odd = FrozenNetwork(counting, torch.device("cpu"))
    with torch.no_grad():
        first, second = odd(x), odd(x)
    assert odd.eager and odd.frozen == {}  # the graph disagreed with the network: eager from then on
    with torch.no_grad():  # both calls gave the live network's answer, its count as it was then
        torch.testing.assert_close(first, UNet.forward(counting, x) + 1)
        torch.testing.assert_close(second, UNet.forward(counting, x) + counting.calls)


def test_every_views_crop_cut_at_once_matches_the_crop_cut_per_camera():
    gen = torch.Generator().manual_seed(3)
    frames = torch.randint(0, 256, (2, 3, 200, 240, 3), dtype=torch.uint8, generator=gen)
    views = list(frames.unbind(1))
    boxes = torch.tensor([[[30.3, 40.1, 90.7, 100.2], [150.2, 20.5, 230.9, 101.0], [-20.0, 150.0, 50, 220]],
                          [[35.0, 44.0, 95.0, 104.0], [10.0, 90.0, 120.0, 199.0], [200.0, 160.0, 260, 220]]],
                         dtype=torch.float64)  # the last box reaches past the frames' edges
    size = (48, 48)
    cut = regions_around(views, boxes, size)
    assert cut is not None
    regions, moved = cut
    images = regions.flatten(0, 1).permute(0, 3, 1, 2).float()
    together = crop_images(images, moved.flatten(0, 1).float(), size).reshape(2, 3, 3, 48, 48)
    for c, v in enumerate(views):
        part, box = region_around(v, boxes[:, c], size)
        alone = crop_images(part.permute(0, 3, 1, 2).float(), box.float(), size)
        torch.testing.assert_close(together[:, c], alone, atol=0.01, rtol=0)  # float32 coordinate rounding
    # cameras of different frame sizes cannot share one region: the per-camera cut is used
    assert regions_around([views[0], views[1][:, :100]], boxes[:, :2], size) is None


def test_the_fast_two_pass_detector_gives_the_plain_paths_points():
    rig = ring_cameras(192)
    rule = CropRule(extent=0.3, size=64)
    (coarse, coarse_meta), (fine, fine_meta) = _trained_like(48, 4), _trained_like(64, 5)

    def detector(fast: bool) -> TwoPassDetector:
        return TwoPassDetector(OnePassDetector(coarse, coarse_meta, fast=fast),
                               OnePassDetector(fine, fine_meta, fast=fast), rule)

    fast_detector, plain_detector = detector(True), detector(False)
    gen = torch.Generator().manual_seed(6)
    frames = torch.randint(0, 256, (3, 4, 192, 192, 3), dtype=torch.uint8, generator=gen)
    fast_detector(frames, rig)  # the first frames of a shape make the frozen graphs
    fast, plain = fast_detector(frames, rig), plain_detector(frames, rig)
    assert fast_detector.fine.pass_.run.frozen and not plain_detector.fine.pass_.run.frozen
    assert torch.equal(fast.valid, plain.valid) and bool(fast.valid.any())
    ok = fast.valid
    assert float((fast.X[ok] - plain.X[ok]).norm(dim=-1).max()) < 1e-4  # 0.1 mm in metres
    assert float((fast.uv - plain.uv).abs().max()) < 0.05  # pixels
