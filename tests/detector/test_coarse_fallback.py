"""A rigid two-pass detector's fallback: a frame whose refining points break the object's layout, where the
coarse points hold it, takes the coarse read-out; every other frame keeps the refining one."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from helpers.synthetic_rig import LAYOUT, ring_cameras

from s3k.detector import CropRule, DetectorMeta, OnePassDetector, TwoPassDetector
from s3k.detector.detector import Detection
from s3k.geometry import project
from s3k.model import UNet, UNetConfig
from s3k.readout import breaks_layout, coarse_stands_in

DISTANCES = torch.as_tensor(np.linalg.norm(LAYOUT[:, None] - LAYOUT[None], axis=-1), dtype=torch.float64)
DISTANCES.fill_diagonal_(float("nan"))


def _points(broken: list[bool], shift: float = 0.0) -> torch.Tensor:
    """``(B, 3, 3)`` the layout moved by ``shift``, with keypoint 0 pulled 40% of the way to keypoint 1 in
    the frames marked ``broken``."""
    X = torch.as_tensor(LAYOUT, dtype=torch.float64).repeat(len(broken), 1, 1) + shift
    for b, bad in enumerate(broken):
        if bad:
            X[b, 0] = X[b, 0] + 0.4 * (X[b, 1] - X[b, 0])
    return X


def _detection(X: torch.Tensor, cams, fill: float) -> Detection:
    """A detection of the points ``X``: their projections, weights and variances all ``fill``."""
    B, K, _ = X.shape
    uv, _ = project(cams, X[:, None].expand(-1, len(cams), -1, -1))
    full = torch.full((B, len(cams), K), fill, dtype=torch.float64)
    return Detection(uv, full.clone(), full.clone(), torch.ones(B, len(cams), K, dtype=torch.bool), X.clone(),
                     torch.ones(B, K, dtype=torch.bool), cams)


def test_breaks_layout_flags_the_frames_whose_points_break_it():
    X = _points([False, True, False])
    valid = torch.ones(3, 3, dtype=torch.bool)
    assert breaks_layout(X, valid, DISTANCES, 0.1).tolist() == [False, True, False]
    valid[1, 0] = False  # the keypoint that breaks it is not valid: the rest hold
    assert breaks_layout(X, valid, DISTANCES, 0.1).tolist() == [False, False, False]


def test_the_coarse_read_out_stands_in_only_where_the_refining_one_breaks_the_layout_and_it_holds():
    cams = ring_cameras(64)
    fine = _detection(_points([False, True, True]), cams, 0.9)
    coarse = _detection(_points([False, False, True], shift=0.01), cams, 0.2)
    residual = fine.residual.clone()  # cached before: it must follow the points
    before = _detection(_points([False, True, True]), cams, 0.9)
    swap = coarse_stands_in(fine, coarse, DISTANCES, 0.1)
    assert swap.tolist() == [False, True, False]  # frame 2: both break it, the refining one stays
    for name in ("uv", "var", "weights", "used", "X", "valid", "confidence"):
        got, theirs, mine = getattr(fine, name), getattr(coarse, name), getattr(before, name)
        torch.testing.assert_close(got[1], theirs[1])
        torch.testing.assert_close(got[[0, 2]], mine[[0, 2]])
    torch.testing.assert_close(fine.residual, coarse.residual * torch.tensor([0, 1, 0])[:, None, None]
                               + residual * torch.tensor([1, 0, 1])[:, None, None])


def test_a_coarse_frame_with_fewer_valid_keypoints_does_not_stand_in():
    cams = ring_cameras(64)
    fine = _detection(_points([True]), cams, 0.9)
    coarse = _detection(_points([False]), cams, 0.2)
    coarse.valid[0, 2] = False
    coarse.X[0, 2] = float("nan")
    assert coarse_stands_in(fine, coarse, DISTANCES, 0.1).tolist() == [False]
    assert bool(fine.valid.all()) and bool(torch.isfinite(fine.X).all())


def _net(size: int, layout=None) -> OnePassDetector:
    torch.manual_seed(0)
    config = UNetConfig(channels=(8, 8), res_blocks=1)
    meta = DetectorMeta(["a", "b", "c"], [], (size, size), config.stride, 2.0, config.to_dict(), units="m")
    if layout is not None:
        meta = dataclasses.replace(meta, layout=layout, layout_tol=0.1)
    return OnePassDetector(UNet(3, config).eval(), meta)


def test_a_rigid_two_pass_detector_gives_the_coarse_points_where_its_refining_points_break_the_layout():
    """Both passes' read-outs replaced by fixed ones: frame 1's refining points break the layout, the coarse
    points of every frame hold it. Without a layout, or with the fallback off, the refining points stay."""
    cams = ring_cameras(96)
    frames = torch.randint(0, 256, (2, 4, 96, 96, 3), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(4))
    layout = DISTANCES.tolist()
    coarse_X, fine_X = _points([False, False], shift=0.005), _points([False, True])
    for fine_layout, fallback, expect in ((layout, True, [False, True]), (layout, False, None),
                                          (None, True, None)):
        coarse, fine = _net(32, layout), _net(48, fine_layout)
        coarse._detect = lambda *a, **k: _detection(coarse_X, cams, 0.2)  # type: ignore[method-assign]
        fine._detect = lambda *a, **k: _detection(fine_X, cams, 0.9)  # type: ignore[method-assign]
        out = TwoPassDetector(coarse, fine, CropRule(extent=0.3, size=48), coarse_fallback=fallback)(frames,
                                                                                                     cams)
        if expect is None:
            assert out.fallback is None
            torch.testing.assert_close(out.X, fine_X)
        else:
            assert out.fallback is not None and out.fallback.tolist() == expect
            torch.testing.assert_close(out.X, torch.stack([fine_X[0], coarse_X[1]]))
            torch.testing.assert_close(out.weights[1], torch.full((4, 3), 0.2, dtype=torch.float64))
