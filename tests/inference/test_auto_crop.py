"""``s3k crops`` and :mod:`s3k.inference.auto_crop`: each camera's crop box around the detected keypoints, in
the full-resolution pixels ``s3k import --crop`` takes, checked against the dataset's labels."""

from __future__ import annotations

import argparse
import json
import logging
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.recordings import CAMS, KEYPOINTS, import_argv, write_recording
from helpers.tiny_detector import save_run

from s3k import cli
from s3k.base.errors import UserError
from s3k.cli.crops import aspect
from s3k.cli.options import parse_crops
from s3k.data import Dataset
from s3k.detector import DetectorMeta
from s3k.geometry import project
from s3k.inference.auto_crop import CropOptions, dataset_crop_boxes, find_boxes, frame_pixels, label_points
from s3k.model import UNetConfig

FRAME = (1280, 1024)


def _cluster(n: int = 100, seed: int = 0, centre=(500.0, 400.0), spread=50.0, cams: int = 2, k: int = 4):
    """``(n, cams, k, 2)`` keypoints scattered around ``centre`` in every camera."""
    rng = np.random.default_rng(seed)
    return np.asarray(centre) + rng.uniform(-spread, spread, (n, cams, k, 2))


def _plain(**kw) -> CropOptions:
    """No rounding, no common size or aspect: the box is the detections' extent grown by the margin."""
    return CropOptions(**{"margin": 0.0, "min_margin_px": 0.0, "quantile": 1.0, "aspect": None,
                          "same_size": False, "multiple": 1, **kw})


def _contains(box, uv) -> bool:
    uv = uv[np.isfinite(uv).all(-1)]
    x0, y0, x1, y1 = box
    return bool(((uv[:, 0] >= x0 - 0.5) & (uv[:, 0] <= x1 - 0.5) & (uv[:, 1] >= y0 - 0.5)
                 & (uv[:, 1] <= y1 - 0.5)).all())


def test_the_box_holds_the_keypoints_with_the_margin_and_no_more():
    points = _cluster()
    found = find_boxes(points, [FRAME] * 2, ["a", "b"], opts=_plain(margin=0.25))
    for c, cam in enumerate(found.cameras):
        lo, hi = points[:, c].reshape(-1, 2).min(0) + 0.5, points[:, c].reshape(-1, 2).max(0) + 0.5
        np.testing.assert_allclose(cam.extent, [*lo, *hi])
        size = hi - lo
        want = np.concatenate([lo - 0.25 * size, hi + 0.25 * size])
        box = np.asarray(cam.box, float)
        assert (box[:2] <= want[:2]).all() and (box[2:] >= want[2:]).all()  # the margin is kept
        assert (box[:2] > want[:2] - 1).all() and (box[2:] < want[2:] + 1).all()  # integer edges, no more
        assert cam.frames == 100 and not cam.outside


def test_one_point_gives_the_pixel_that_holds_it():
    """Pixel centres are integers and box edges lie half a pixel from them: the point at x 10, y 20 is in
    the pixel of edges 10..11 and 20..21, the box s3k import --crop cuts it out with."""
    points = np.array([10.0, 20.0]).reshape(1, 1, 1, 2)
    found = find_boxes(points, [FRAME], ["a"], opts=_plain())
    assert found.cameras[0].extent == (10.5, 20.5, 10.5, 20.5) and found.cameras[0].box == (10, 20, 11, 21)


def test_a_few_wrong_frames_do_not_stretch_the_box_but_the_largest_extent_would():
    points = _cluster()
    points[7] = [1200.0, 1000.0]  # one frame detected far away in every camera
    robust = find_boxes(points, [FRAME] * 2, ["a", "b"], opts=_plain(quantile=0.98))
    every = find_boxes(points, [FRAME] * 2, ["a", "b"], opts=_plain(quantile=1.0))
    assert robust.cameras[0].box[2] < 600 and every.cameras[0].box[2] >= 1200


def test_low_confidence_frames_do_not_count_and_a_camera_without_any_is_refused():
    points = _cluster(n=10)
    points[:4, :, 1:] = np.nan  # four frames placed one keypoint of four
    found = find_boxes(points, [FRAME] * 2, ["a", "b"], opts=_plain(min_keypoints=0.5))
    assert found.cameras[0].frames == 6
    points[:, 1] = np.nan
    with pytest.raises(UserError, match="camera b: .* none of its 10 views.*--min-confidence"):
        find_boxes(points, [FRAME] * 2, ["a", "b"])


def test_boxes_are_square_of_one_size_rounded_and_inside_the_frame():
    points = _cluster(centre=(40.0, 60.0), spread=30.0)  # near the top-left corner
    points[:, 1] += [800.0, 300.0]
    points[:, 1, :, 0] = 840 + 1.5 * (points[:, 1, :, 0] - 840)  # a wider object in the second camera
    found = find_boxes(points, [FRAME, (1000, 800)], ["a", "b"], opts=CropOptions(multiple=16))
    sizes = {(x1 - x0, y1 - y0) for x0, y0, x1, y1 in found.boxes().values()}
    assert len(sizes) == 1
    (w, h), = sizes
    assert w == h and w % 16 == 0
    for cam, (W, H) in zip(found.cameras, [FRAME, (1000, 800)]):
        x0, y0, x1, y1 = cam.box
        assert 0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H
        assert _contains(cam.box, points[:, found.cameras.index(cam)])
    assert found.cameras[0].box[:2] == (0, 0)  # moved into the frame, not cut


def test_a_box_larger_than_the_frame_is_cut_to_it():
    points = _cluster(centre=(60.0, 40.0), spread=40.0)
    found = find_boxes(points, [(120, 80)] * 2, ["a", "b"], opts=CropOptions(margin=0.5))
    assert found.cameras[0].box == (0, 0, 120, 80) and found.cameras[0].clamped


def test_a_label_outside_the_box_is_named_and_refused_or_grows_the_box(caplog):
    points = _cluster(n=20, k=3)
    labels = np.full((2, 2, 3, 2), np.nan)
    labels[0, 1] = [510.0, 400.0]  # inside
    labels[1, 1, 2] = [900.0, 420.0]  # camera b, frame id 31, keypoint tail: far right
    args = dict(labels=labels, label_ids=np.array([30, 31]), keypoints=["head", "body", "tail"])
    with pytest.raises(UserError, match=r"1 label\(s\) .*b frame 31 tail at 900,420.*--outside grow"):
        find_boxes(points, [FRAME] * 2, ["a", "b"], opts=CropOptions(outside="refuse"), **args)
    with caplog.at_level(logging.INFO, logger="s3k"):
        found = find_boxes(points, [FRAME] * 2, ["a", "b"], opts=CropOptions(min_margin_px=16), **args)
    b = found.cameras[1]
    assert b.labels == 4 and found.cameras[0].labels == 0
    assert "b: grown to hold 1 label(s) outside the detections' box: b frame 31 tail at 900,420" \
        in caplog.text
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warned == ["b: 1 of its 4 labels lie outside the box of the detections, which miss much of the "
                      "object: train the run longer (the box holds the labels, not the frames without them)"]
    assert [(o.frame, o.keypoint) for o in b.outside] == [(31, "tail")] and not found.cameras[0].outside
    assert b.box[2] >= 900 + 0.5 + 16 and _contains(b.box, labels[:, 1])
    assert found.to_dict()["cameras"]["b"]["labels_outside"][0]["u"] == 900.0


def test_the_aspect_option_reads_ratios_numbers_and_free():
    assert aspect("4:3") == pytest.approx(4 / 3) and aspect("1") == 1.0 and aspect("free") is None
    for bad in ("0", "nan", "4:0", "wide", "-1"):
        with pytest.raises(argparse.ArgumentTypeError):
            aspect(bad)
    found = find_boxes(_cluster(), [FRAME] * 2, ["a", "b"], opts=CropOptions(aspect=4 / 3, multiple=16))
    x0, y0, x1, y1 = found.cameras[0].box
    assert (x1 - x0) % 16 == 0 and abs((x1 - x0) / (y1 - y0) - 4 / 3) < 0.01


# ------------------------------------------------------------------------------------------------------------
# Through a dataset imported with a crop and a scale


class TruthDetector:
    """A detector stand-in that detects every keypoint where it projects (the recording's 3D points through
    the cameras it is given), frame after frame in the order the frames are read."""

    def __init__(self, X: np.ndarray, ids: np.ndarray, doubtful: int | None = None) -> None:
        self.X, self.ids, self.next = torch.as_tensor(X), list(ids), 0
        self.keypoints = list(KEYPOINTS)
        self.doubtful = doubtful  # this frame's detections are far off in every view, at confidence 0.3

    def __call__(self, images, cams):
        B = len(images)
        rows = self.ids[self.next:self.next + B]
        self.next += B
        uv, _ = project(cams.to(dtype=torch.float64), self.X[rows][:, None])
        confidence = torch.ones(uv.shape[:-1], dtype=torch.float64)
        for b, row in enumerate(rows):
            if row == self.doubtful:
                uv[b] += 15.0
                confidence[b] = 0.3
        return _Read(uv=uv, confidence=confidence)


class _Read(SimpleNamespace):
    """What the boxes read of a detection: each view's points and their confidence."""

    def cpu(self) -> _Read:
        return self


@pytest.fixture(scope="module")
def cropped(tmp_path_factory):
    """A recording of 64x48 videos imported cropped to 8,4,56,44 and scaled by 0.5 (24x20 images)."""
    root = tmp_path_factory.mktemp("auto-crop")
    rec = write_recording(root / "rec")
    data = root / "cropped"
    assert cli.main(import_argv(rec, "--crop", "8,4,56,44", "--scale", "0.5", "--labelled", "4", "--test",
                                "2", "--out", str(data))) == 0
    return rec, data


def test_boxes_map_back_to_the_video_pixels_through_the_import_crop_and_scale(cropped):
    rec, data = cropped
    ds = Dataset.open(data, cache="none")
    assert ds.image_size == (24, 20)
    ids = ds.frames()
    detector = TruthDetector(rec["X"], ids, doubtful=int(ids[3]))
    found = dataset_crop_boxes(detector, ds, _plain(margin=0.1, min_margin_px=1.0), batch_size=5)
    assert [cam.frames for cam in found.cameras] == [len(ids) - 1] * 3  # the doubtful views left out
    truth = rec["uv"][np.delete(ids, 3)]  # (N, C, K, 2) video pixels, projected by OpenCV
    for c, cam in enumerate(found.cameras):
        lo, hi = truth[:, c].reshape(-1, 2).min(0) + 0.5, truth[:, c].reshape(-1, 2).max(0) + 0.5
        np.testing.assert_allclose(cam.extent, [*lo, *hi], atol=1e-4)
        assert _contains(cam.box, truth[:, c]) and cam.frame_size == (64, 48)
    label_ids, labels = label_points(ds)
    video, _ = frame_pixels(ds, labels)
    known = np.isfinite(video).all(-1)
    assert known.sum() > 10
    np.testing.assert_allclose(video[known], rec["uv"][label_ids][known], atol=1e-3)


def test_the_command_prints_crop_arguments_that_parse_and_hold_every_label(cropped, tmp_path, capsys):
    rec, _ = cropped
    whole = tmp_path / "whole"
    assert cli.main(import_argv(rec, "--scale", "0.5", "--labelled", "4", "--test", "2",
                                "--out", str(whole))) == 0
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMS), image_size=(32, 24), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        units="mm", source_image_size=(32, 24))
    run = save_run(tmp_path / "run", meta, seed=0)
    capsys.readouterr()
    out = tmp_path / "crops.json"
    argv = ["crops", str(run), "--data", str(whole), "--min-confidence", "0", "--min-keypoints", "0.3",
            "--multiple", "4", "--out", str(out)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr()
    line = printed.out.strip()
    assert line.startswith("--crop ") and len(line.splitlines()) == 1
    boxes = parse_crops(line.split()[1:], list(CAMS))
    doc = json.loads(out.read_text())
    assert {c: tuple(float(v) for v in b) for c, b in doc["crop"].items()} == boxes
    assert all(f"{cam}: " in printed.err for cam in CAMS)
    ds = Dataset.open(whole, cache="none")
    _, labels = label_points(ds)
    video, sizes = frame_pixels(ds, labels)
    for c, cam in enumerate(CAMS):
        x0, y0, x1, y1 = boxes[cam]
        assert 0 <= x0 < x1 <= 64 and 0 <= y0 < y1 <= 48 and (x1 - x0) % 4 == 0
        assert _contains(boxes[cam], video[:, c])
    assert cli.main(argv) == 1  # --out exists
    assert "--overwrite" in capsys.readouterr().err
