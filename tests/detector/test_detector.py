"""``s3k.Detector`` on every device and precision there is: the same points from frames of any size, crops cut
on the device exactly as the whole frame would be cut, and a two-pass detector's crop rule."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers.synthetic_rig import ring_cameras

from s3k.detector import CropRule, DetectorMeta, OnePassDetector, TwoPassDetector
from s3k.geometry import Cameras, project
from s3k.geometry.warp import crop_images, region_around, resample_regions
from s3k.model import UNet, UNetConfig


def _net(size: int, keypoints: int = 3) -> tuple[UNet, DetectorMeta]:
    torch.manual_seed(0)
    config = UNetConfig(channels=(8, 8), res_blocks=1)
    meta = DetectorMeta([f"k{i}" for i in range(keypoints)], [], (size, size), config.stride, 2.0,
                        config.to_dict(), units="m")
    return UNet(keypoints, config).eval(), meta


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_a_detector_reads_frames_on_any_device_and_gives_results_there(device, precision):
    net, meta = _net(32)
    detector = OnePassDetector(net.to(device), meta, device, precision)
    gen = torch.Generator().manual_seed(1)
    frames = torch.randint(0, 256, (2, 4, 64, 64, 3), dtype=torch.uint8, generator=gen).to(device)
    out = detector(frames, ring_cameras(64))
    assert out.X.device.type == torch.device(device).type and out.X.dtype == torch.float64
    assert out.X.shape == (2, 3, 3) and out.uv.shape == (2, 4, 3, 2)
    ref = OnePassDetector(net.cpu(), meta)(frames.cpu(), ring_cameras(64))  # float32 on the CPU
    tol = 1e-4 if precision == "float32" else 2.0  # bf16 moves an untrained network's peaks by pixels
    assert float((out.uv.cpu() - ref.uv).abs().max()) < tol


def test_frames_at_the_network_size_need_no_resampling_and_resized_frames_map_back():
    net, meta = _net(32)
    detector = OnePassDetector(net, meta)
    gen = torch.Generator().manual_seed(2)
    frames = torch.randint(0, 256, (1, 4, 32, 32, 3), dtype=torch.uint8, generator=gen)
    small = detector(frames, ring_cameras(32))
    assert torch.equal(small.pixel_maps[0, 0], torch.eye(3, dtype=torch.float64))
    big = detector(frames.repeat_interleave(2, 2).repeat_interleave(2, 3), ring_cameras(64))  # each pixel 2x2
    # the same network inputs (area averaging of the doubled pixels), detections in the big frames' pixels
    np.testing.assert_allclose(big.uv.numpy(), (small.uv.numpy() + 0.5) * 2 - 0.5, atol=1e-6)


def test_frames_are_cut_around_the_boxes_without_changing_the_resampling():
    gen = torch.Generator().manual_seed(3)
    image = torch.randint(0, 256, (2, 300, 400, 3), dtype=torch.uint8, generator=gen)
    cases = [([[101.3, 57.9, 163.1, 119.7], [180.0, 90.5, 250.2, 160.7]], (48, 48)),  # crops
             ([[40.0, 20.0, 296.0, 276.0], [8.0, 4.0, 264.0, 260.0]], (32, 32)),  # shrunk 8 times
             ([[-30.0, -20.0, 90.0, 100.0], [350.0, 250.0, 450.0, 350.0]], (40, 40))]  # past the frame
    for box_list, size in cases:
        boxes = torch.tensor(box_list)
        cut, moved = region_around(image, boxes.double(), size)
        whole = image.permute(0, 3, 1, 2).float()
        part = cut.permute(0, 3, 1, 2).float()
        for warp in (crop_images, resample_regions):
            # the same pixels sampled at the same places: equal up to float32 rounding of the coordinates
            torch.testing.assert_close(warp(part, moved.float(), size), warp(whole, boxes, size), atol=0.01,
                                       rtol=0)


def test_two_pass_detector_cuts_its_crops_around_the_coarse_points():
    """A refining network that reports where the crop's centre pixel is: the crop boxes follow the rule."""
    coarse_net, coarse_meta = _net(32)
    fine_net, fine_meta = _net(48)
    rule = CropRule(extent=0.3, size=48)
    detector = TwoPassDetector(OnePassDetector(coarse_net, coarse_meta), OnePassDetector(fine_net, fine_meta),
                               rule)
    gen = torch.Generator().manual_seed(4)
    frames = torch.randint(0, 256, (2, 4, 96, 96, 3), dtype=torch.uint8, generator=gen)
    cams = ring_cameras(96)
    out = detector(frames, cams, keep_heatmaps=True)
    assert out.coarse is not None and out.placed is not None and out.input_size == (48, 48)
    # the crop maps: the crop centre is the reprojection of each frame's crop centre
    from s3k.detector import crop_centres

    centres, _ = crop_centres(out.coarse.X, out.coarse.valid, cams)
    uv, _ = project(cams, centres[:, None, None, :].expand(-1, 4, 1, 3))
    at = torch.einsum("bcij,bcj->bci", out.pixel_maps[..., :2, :2], uv[:, :, 0]) + out.pixel_maps[..., :2, 2]
    np.testing.assert_allclose(at.numpy(), 23.5, atol=1e-6)  # the middle of a 48 px crop
    # a 3D extent of 0.3 m at about 1 m: the crop's side in the frame is f * extent / z pixels
    side = 48 / out.pixel_maps[..., 0, 0]
    assert bool(((side > 0.2 * 96 * 1.2) & (side < 0.5 * 96 * 1.2)).all())


def test_a_rigid_two_pass_detector_lends_its_coarse_heatmaps_to_the_layout_search(monkeypatch):
    """The refining pass's rigid read-out scores the places it searches with the coarse pass's heatmaps too
    (s3k.readout.LayoutPrior): the coarse heatmaps, with the coarse network's cameras; without a layout there
    is nothing to search and none are kept."""
    import s3k.detector.detector as detector_module
    from s3k.readout import LayoutPrior

    priors = []

    def spy(*args, **kwargs):
        priors.append(kwargs.get("prior"))
        return read_out(*args, **kwargs)

    read_out = detector_module.read_out
    monkeypatch.setattr(detector_module, "read_out", spy)
    coarse_net, coarse_meta = _net(32)
    fine_net, fine_meta = _net(48)
    layout = [[float("nan"), 0.1, 0.2], [0.1, float("nan"), 0.15], [0.2, 0.15, float("nan")]]
    rigid_meta = dataclasses.replace(fine_meta, layout=layout, layout_tol=0.1)
    frames = torch.randint(0, 256, (2, 4, 96, 96, 3), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(4))
    cams = ring_cameras(96)
    for meta in (rigid_meta, fine_meta):
        detector = TwoPassDetector(OnePassDetector(coarse_net, coarse_meta), OnePassDetector(fine_net, meta),
                                   CropRule(extent=0.3, size=48))
        out = detector(frames, cams, keep_heatmaps=True)
        assert priors[0] is None  # the coarse pass's own read-out
        prior = priors[1]
        if meta is fine_meta:
            assert prior is None
        else:
            assert isinstance(prior, LayoutPrior) and prior.stride == coarse_meta.stride
            assert out.coarse is not None and out.coarse.probs is not None
            torch.testing.assert_close(prior.probs, out.coarse.probs)
            torch.testing.assert_close(prior.cams.K, out.coarse.network_cameras().K.expand_as(prior.cams.K))
            assert detector(frames, cams).coarse.probs is None  # kept only when asked for
        priors.clear()


def test_frames_the_detector_would_misread_are_refused_in_one_line():
    """Float frames in [0, 1], frames twice (or half) the size the intrinsics describe, and a list that reads
    as cameras and as frames alike are refused; the same frames given right are read."""
    from s3k.base.errors import UserError

    net, meta = _net(32)
    detector = OnePassDetector(net, meta)
    gen = torch.Generator().manual_seed(2)
    frames = torch.randint(0, 256, (4, 4, 64, 64, 3), dtype=torch.uint8, generator=gen)
    cams = ring_cameras(64)
    ref = detector(frames, cams)
    with pytest.raises(UserError, match="float32 frames; the detector reads uint8") as err:
        detector(frames.float() / 255, cams)
    assert "\n" not in str(err.value)
    with pytest.raises(UserError, match=r"camera 0's frames are 128x128 px but its intrinsics .* describe "
                                        r"64x64 px frames \(2x\)"):
        detector(frames.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3), cams)
    with pytest.raises(UserError, match="describe 64x64 px frames"):
        detector(frames[:, :, ::2, ::2], cams)
    # a calibration whose principal point lies off the centre, as calibrated ones do: still told apart
    off = Cameras(cams.K.clone(), cams.dist, cams.R, cams.t)
    off.K[:, 0, 2] += 3.0
    off.K[:, 1, 2] -= 2.0
    detector(frames, off)
    with pytest.raises(UserError, match=r"camera 0's frames are 128x128 px"):
        detector(frames.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3), off)
    # four cameras' arrays of four frames each, or four frames of four cameras: refused, naming the fix
    with pytest.raises(UserError, match=r"reads both as 4 cameras' frames and as 4 frames of 4 cameras"):
        detector(list(frames.unbind(1)), cams)
    # unambiguous: a list of another length of frames, or per-camera arrays of another batch size
    out = detector(list(frames[:3].unbind(1)), cams)
    assert torch.equal(out.X, ref.X[:3])
    np.testing.assert_array_equal(detector(frames.numpy(), cams).X.numpy(), ref.X.numpy())
