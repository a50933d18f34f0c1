"""Tests of ``s3k track``: synchronized videos of a tiny synthetic rig -> anipose 3D CSV and overlays.

The rig: 3 cameras about 1 m (1000 mm) from the origin, 64 x 48 px videos (one camera with lens distortion),
three coloured dots moving in 3D; the detector is a tiny untrained U-Net saved as a run folder (32 x 32 input,
so frames are padded to the detector's aspect ratio). The network's accuracy is not under test here; the
pipeline after it is, with heatmaps peaked at known projections.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.paths import REPO
from helpers.rig_inputs import rig_inputs
from helpers.tiny_detector import save_run
from helpers.track_rig import (
    CAMERAS,
    FRAMES,
    KEYPOINTS,
    NET_SIZE,
    VIDEO_SIZE,
    OracleDetector,
    moving_points,
    peaked_logits,
    read_track_csv,
    run_track,
)

from s3k import cli
from s3k.data.tracks_csv import csv_header, read_csv
from s3k.data.video import frame_count, frame_size, synchronized_frames, write_video
from s3k.detector import DetectorMeta
from s3k.geometry import Cameras, project, triangulate_pixels
from s3k.geometry.warp import crop_resize_matrix
from s3k.inference.session import RigOptions, RigSession, fit_box
from s3k.model import UNetConfig
from s3k.readout import ReadoutConfig, read_out, window_cells
from s3k.readout.heatmaps import (
    confidence_weight,
    heatmap_moments,
    heatmap_size,
    peak_window_mean,
    spatial_softmax,
)

# ------------------------------------------------------------------------------------------------------------
# Input geometry


@pytest.mark.parametrize("mode", ["pad", "crop", "stretch"])
@pytest.mark.parametrize("video, net", [((64, 48), (32, 32)), ((48, 64), (32, 32)), ((60, 30), (64, 32)),
                                        ((640, 480), (96, 128))])
def test_fit_box_aspect_and_extent(mode, video, net):
    x0, y0, x1, y1 = fit_box(video, net, mode)
    W, H = video
    if mode == "stretch":
        assert (x0, y0, x1, y1) == (0, 0, W, H)
        return
    # Same aspect ratio as the network input, centred on the frame.
    assert (x1 - x0) * net[1] == pytest.approx((y1 - y0) * net[0])
    assert ((x0 + x1) / 2, (y0 + y1) / 2) == pytest.approx((W / 2, H / 2))
    if mode == "pad":  # contains the frame, touching it on two sides
        assert x0 <= 0 and y0 <= 0 and x1 >= W and y1 >= H
        assert min(-x0, -y0) == pytest.approx(0)
    else:  # inside the frame, touching it on two sides
        assert x0 >= 0 and y0 >= 0 and x1 <= W and y1 <= H
        assert min(x0, y0) == pytest.approx(0)


def test_fit_box_rejects_unknown_mode():
    with pytest.raises(ValueError, match="--fit"):
        fit_box((64, 48), (32, 32), "squash")


def test_rig_session_places_the_cameras_and_maps_projections_like_resize_crop(track_recording):
    """A detector placed on the rig: the calibration's cameras in the frames' order, each camera's box by
    --fit; network-input intrinsics K' = M K project as the video projection mapped by M."""
    from s3k.detector import Detector

    rig = track_recording["rig"]
    order = ["right", "left"]
    session = RigSession.place(Detector.load(track_recording["run"], "cpu"), {c: VIDEO_SIZE for c in order},
                               RigOptions(track_recording["calibration"]))
    assert session.names == order and session.units == "mm"
    cams = session.cameras
    np.testing.assert_allclose(cams.numpy()["K"], rig.select(order).cameras.numpy()["K"], atol=1e-9)
    X = torch.as_tensor(moving_points(1)[0])
    for c in range(len(order)):
        M = crop_resize_matrix(tuple(session.boxes[c]), NET_SIZE)
        np.testing.assert_allclose(M, crop_resize_matrix(fit_box(VIDEO_SIZE, NET_SIZE), NET_SIZE))
        uv, _ = project(cams[c], X)
        K_net = torch.as_tensor(M) @ cams.K[c]
        uv_net, _ = project(Cameras(K_net, cams.dist[c], cams.R[c], cams.t[c]), X)
        mapped = uv.numpy() @ M[:2, :2].T + M[:2, 2]
        np.testing.assert_allclose(uv_net.numpy(), mapped, atol=1e-9)


def test_synchronized_frames_pairs_by_index(track_recording):
    paths = [track_recording["videos"][c] for c in CAMERAS]
    got = list(synchronized_frames(paths, start=2, stop=5))
    assert [i for i, _ in got] == [2, 3, 4]
    assert all(len(imgs) == 3 and imgs[0].shape == (48, 64, 3) for _, imgs in got)
    assert list(synchronized_frames(paths, start=4))[-1][0] == FRAMES - 1


# ------------------------------------------------------------------------------------------------------------
# After the network


def points_from_logits(logits, cams, maps, stride, sigma, min_weight=0.5) -> SimpleNamespace:
    """``read_out`` in the videos' pixels, as numpy arrays (a threshold of 0.5 drops flat heatmaps)."""
    r = read_out(logits, cams, stride, sigma, maps, ReadoutConfig(min_weight=min_weight))
    return SimpleNamespace(X=r.X.numpy(), valid=r.valid.numpy(), error=r.error.numpy(), ncams=r.ncams.numpy(),
                           score=r.score.numpy(), uv=r.uv.numpy(), weight=r.weights.numpy(),
                           used=r.used.numpy(), reproj=r.reproj.numpy())


@pytest.mark.parametrize("stride", [1, 2])
def test_points_from_heatmaps_at_known_projections(track_recording, stride):
    """Heatmaps peaked where the known 3D points project give those points back, with zero error."""
    rig = track_recording["rig"]
    inputs, cams = rig_inputs(track_recording["videos"], rig, NET_SIZE, "pad")
    maps = np.stack([c.M for c in inputs])
    X = torch.as_tensor(moving_points(4))  # (B, K, 3)
    uv, depth = project(cams, X[:, None])  # (B, C, K, 2) video pixels, distorted
    assert bool((depth > 0).all())
    M = torch.as_tensor(maps)
    uv_net = uv @ M[:, :2, :2].transpose(-1, -2) + M[:, None, :2, 2]
    sigma = 2.0
    logits = peaked_logits(uv_net, stride, sigma)

    out = points_from_logits(logits, cams, maps, stride, sigma)
    assert out.valid.all()
    np.testing.assert_allclose(out.X, X.numpy(), atol=1e-4)  # mm, at 1 m
    np.testing.assert_allclose(out.uv, uv.numpy(), atol=1e-6)
    assert np.all(out.error < 1e-6)
    assert np.all(out.ncams == 3)
    assert np.all(out.weight > 0.9)  # a sharp Gaussian of width sigma
    np.testing.assert_allclose(out.score, out.weight.mean(axis=1))
    np.testing.assert_allclose(out.reproj, uv.numpy(), atol=1e-6)

    # A flat heatmap in one view: that view is dropped, the point still follows from the other two.
    flat = logits.clone()
    flat[:, 1] = 0.0
    out = points_from_logits(flat, cams, maps, stride, sigma)
    assert out.valid.all() and np.all(out.ncams == 2)
    assert not out.used[:, 1].any() and out.used[:, [0, 2]].all()
    np.testing.assert_allclose(out.X, X.numpy(), atol=1e-4)
    # ... unless every view is kept (min_weight 0): the flat view's mean at the image centre pulls the point.
    soft = points_from_logits(flat, cams, maps, stride, sigma, min_weight=0.0)
    assert np.all(soft.ncams == 3) and np.all(np.abs(soft.X - X.numpy()).max(axis=-1) > 1e-2)

    # Only one informative view: invalid, NaN coordinates and error, finite score.
    flat[:, 2] = 0.0
    out = points_from_logits(flat, cams, maps, stride, sigma)
    assert not out.valid.any() and np.all(out.ncams == 1)
    assert np.isnan(out.X).all() and np.isnan(out.error).all() and np.isnan(out.reproj).all()
    assert np.isfinite(out.score).all()


def test_points_from_logits_matches_geometry(track_recording):
    """Same 2D means and weights -> the same 3D points as s3k.geometry.triangulate_pixels."""
    rig = track_recording["rig"]
    inputs, cams = rig_inputs(track_recording["videos"], rig, NET_SIZE, "crop")
    maps = np.stack([c.M for c in inputs])
    g = torch.Generator().manual_seed(3)
    h, w = heatmap_size(NET_SIZE[1], NET_SIZE[0], 2)
    logits = torch.randn(5, 3, 3, h, w, generator=g) * torch.linspace(0.5, 6, 5)[:, None, None, None, None]
    sigma = 2.0
    for min_weight in (0.0, 0.3):
        out = points_from_logits(logits.float(), cams, maps, 2, sigma, min_weight)
        # The means, mapped back to network pixels, are the heatmap moments of the logits (the mean within
        # the read-out's window of the peak, the variance the whole heatmap's).
        probs = spatial_softmax(logits.double())
        _, var = heatmap_moments(probs, 2)
        uv_net = peak_window_mean(probs, 2, window_cells(sigma, 2))
        back = out.uv @ maps[:, :2, :2].transpose(0, 2, 1) + maps[:, None, :2, 2]
        np.testing.assert_allclose(back, uv_net.numpy(), atol=1e-4)
        np.testing.assert_allclose(out.weight, confidence_weight(var, sigma).numpy(), atol=1e-6)
        used = out.weight > min_weight
        np.testing.assert_array_equal(out.used, used)
        np.testing.assert_array_equal(out.ncams, used.sum(axis=1))
        wt = torch.as_tensor(np.where(used, out.weight, 0.0))
        X_ref, valid_ref = triangulate_pixels(cams, torch.as_tensor(out.uv), wt)
        valid_ref = valid_ref.numpy() & (used.sum(axis=1) >= 2)
        np.testing.assert_array_equal(out.valid, valid_ref)
        np.testing.assert_allclose(out.X[valid_ref], X_ref.numpy()[valid_ref], rtol=1e-9, atol=1e-9)
        # error: mean over the used views of the distance between reprojection and detection
        reproj, _ = project(cams, torch.as_tensor(np.nan_to_num(out.X))[:, None])
        d = np.linalg.norm(reproj.numpy() - out.uv, axis=-1)
        err = (d * used).sum(axis=1) / np.maximum(used.sum(axis=1), 1)
        np.testing.assert_allclose(out.error[valid_ref], err[valid_ref], rtol=1e-9)
        assert valid_ref.any()


# ------------------------------------------------------------------------------------------------------------
# The command


def test_track_writes_anipose_csv_and_overlays(track_recording, tmp_path):
    out = tmp_path / "points3d.csv"
    assert run_track(track_recording, out, "--min-weight", "0", "--batch", "4",
                     "--overlay", str(tmp_path / "ov")) == 0
    header, values = read_track_csv(out)
    from s3k.data.tracks_csv import read_source

    assert read_source(out)["units"] == "mm"  # beside the CSV, for s3k export-tracks
    assert header == csv_header(KEYPOINTS)
    assert header[:6] == ["nose_x", "nose_y", "nose_z", "nose_error", "nose_ncams", "nose_score"]
    assert header[-1] == "fnum" and len(header) == 6 * len(KEYPOINTS) + 1
    assert values.shape == (FRAMES, len(header))
    np.testing.assert_array_equal(values[:, -1], np.arange(FRAMES))
    per_kp = values[:, :-1].reshape(FRAMES, len(KEYPOINTS), 6)
    # min-weight 0: every view counts, so with 3 cameras around the scene every point is defined.
    assert np.isfinite(per_kp).all()
    np.testing.assert_array_equal(per_kp[..., 4], 3)
    assert np.all((per_kp[..., 5] > 0) & (per_kp[..., 5] < 1))
    assert np.all(per_kp[..., 3] >= 0)
    for c in CAMERAS:
        path = tmp_path / "ov" / f"{c}.mp4"
        assert frame_count(path, exact=True) == FRAMES
        assert frame_size(path) == VIDEO_SIZE


def test_track_threshold_nan_where_invalid(track_recording, tmp_path):
    out = tmp_path / "points3d.csv"
    assert run_track(track_recording, out, "--min-weight", "0.5") == 0
    _, values = read_track_csv(out)
    per_kp = values[:, :-1].reshape(FRAMES, len(KEYPOINTS), 6)
    invalid = np.isnan(per_kp[..., 0])
    # Coordinates and error are NaN together, and exactly where fewer than 2 cameras pass the threshold
    # (or rays are parallel); ncams and score are always defined.
    for j in (1, 2, 3):
        np.testing.assert_array_equal(np.isnan(per_kp[..., j]), invalid)
    assert np.all(per_kp[..., 4][~invalid] >= 2)
    assert np.isfinite(per_kp[..., 4:]).all()
    # read_csv gives back the points, NaN included, keyed by frame number, in the order asked for.
    points = read_csv(out, KEYPOINTS[::-1])
    assert sorted(points) == list(range(FRAMES))
    for f in range(FRAMES):
        np.testing.assert_array_equal(points[f], per_kp[f, ::-1, :3])


def test_read_csv_names_file_and_missing_column(tmp_path):
    path = tmp_path / "points3d.csv"
    path.write_text(",".join(csv_header(["nose"])) + "\n1,2,3,0.5,2,0.9,7\n")
    np.testing.assert_array_equal(read_csv(path, ["nose"])[7], [[1.0, 2.0, 3.0]])
    with pytest.raises(ValueError, match=r"points3d\.csv.*tail_x"):
        read_csv(path, ["nose", "tail"])
    path.write_text(",".join(csv_header(["nose"])) + "\n1,oops,3,0.5,2,0.9,7\n")
    with pytest.raises(ValueError, match=r"points3d\.csv, line 2"):
        read_csv(path, ["nose"])


def test_rows_points_are_what_read_csv_reads_back_from_the_same_rows(tmp_path):
    from s3k.data.tracks_csv import csv_rows, rows_points, write_csv

    X = torch.tensor([[[0.1234567891, -2.0, 3.5], [float("nan")] * 3]], dtype=torch.float64)
    result = SimpleNamespace(X=X, error=torch.tensor([[0.5, float("nan")]]), ncams=torch.tensor([[3, 0]]),
                             score=torch.tensor([[0.9, 0.0]]))
    rows = csv_rows([11], result)
    with write_csv(tmp_path / "p.csv", ["a", "b"]) as writer:
        writer.writerows(rows)
    from_rows, from_file = rows_points(rows, 2), read_csv(tmp_path / "p.csv", ["a", "b"])
    assert list(from_rows) == list(from_file) == [11]
    np.testing.assert_array_equal(from_rows[11], from_file[11])  # NaN where not triangulated, in both
    assert from_rows[11][0, 0] != X[0, 0, 0]  # the value as written, not the float it came from


def test_track_range_batch_and_camera_order_do_not_change_results(track_recording, tmp_path):
    full, part = tmp_path / "full.csv", tmp_path / "part.csv"
    assert run_track(track_recording, full, "--min-weight", "0", "--batch", "8") == 0
    assert run_track(track_recording, part, "--min-weight", "0", "--batch", "2", "--start", "2", "--stop",
                     "5", order=["right", "left", "top"]) == 0
    # the detections (the filter sees the range it is given)
    h1, v1 = read_track_csv(full.with_name("full.raw.csv"))
    h2, v2 = read_track_csv(part.with_name("part.raw.csv"))
    assert h1 == h2
    np.testing.assert_array_equal(v2[:, -1], [2, 3, 4])
    np.testing.assert_allclose(v2, v1[2:5], rtol=1e-4, atol=1e-4)


def test_track_errors_name_camera_and_file(track_recording, tmp_path, capsys):
    out = tmp_path / "x.csv"
    v = track_recording["videos"]
    base = ["track", str(track_recording["run"]), "--calibration", str(track_recording["calibration"]),
            "--out", str(out), "--no-progress", "--videos"]

    assert cli.main(base + [f"left={v['left']}", f"bottom={v['top']}"]) == 1
    err = capsys.readouterr().err
    assert "'bottom'" in err and "left, top, right" in err

    missing = tmp_path / "nope.mp4"
    assert cli.main(base + [f"left={v['left']}", f"top={missing}"]) == 1
    assert str(missing) in capsys.readouterr().err

    assert cli.main(base + [f"left={v['left']}"]) == 1
    assert "at least 2 cameras" in capsys.readouterr().err

    assert cli.main(base + [f"left={v['left']}", "top"]) == 1
    assert "CAMERA=FILE" in capsys.readouterr().err

    small = tmp_path / "small.mp4"
    write_video(small, [np.zeros((32, 48, 3), np.uint8)] * 2, fps=25)
    assert cli.main(base + [f"left={v['left']}", f"top={small}"]) == 1
    err = capsys.readouterr().err
    assert "'top'" in err and str(small) in err and "48x32" in err and "64x48" in err

    assert cli.main(base + [f"left={v['left']}", f"top={v['top']}", "--start", "3", "--stop", "3"]) == 1
    assert "--start" in capsys.readouterr().err
    assert not out.exists()


# ------------------------------------------------------------------------------------------------------------
# End to end through an oracle detector


def _oracle_track(track_recording, tmp_path, monkeypatch):
    """Lossless videos of ``track_recording``'s rig (25 frames/s) and an oracle detector loaded for any run:
    ``(oracle, track arguments, CSV, true points)``."""
    import s3k.detector.detector

    rig = track_recording["rig"]
    W, H = VIDEO_SIZE
    videos = {}
    for c, name in enumerate(CAMERAS):  # lossless: the grey levels survive exactly
        frames = [np.full((H, W, 3), 20 + 10 * f + 3 * c, np.uint8) for f in range(FRAMES)]
        videos[name] = tmp_path / f"{name}.mkv"
        write_video(videos[name], frames, fps=25, codec="ffv1")
    inputs, cams = rig_inputs(videos, rig, NET_SIZE, "pad")
    X = torch.as_tensor(moving_points(FRAMES))  # (F, K, 3) mm
    uv, _ = project(cams, X[:, None])  # (F, C, K, 2) video pixels, with the lens distortion
    M = torch.as_tensor(np.stack([c.M for c in inputs]))
    uv_net = uv @ M[:, :2, :2].transpose(-1, -2) + M[:, None, :2, 2]
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=NET_SIZE, stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), stride=2).to_dict(), units="mm",
                        source_image_size=NET_SIZE)
    oracle = OracleDetector(uv_net, meta.stride, meta.sigma)
    monkeypatch.setattr(s3k.detector.detector, "load_network", lambda *args, **kwargs: (oracle, meta))

    out = tmp_path / "points3d.csv"
    args = ["track", "run", "--calibration", str(track_recording["calibration"]), "--out", str(out),
            "--no-progress", "--batch", "4", "--filter", "none",
            "--videos", *[f"{c}={videos[c]}" for c in CAMERAS]]
    return oracle, args, out, X


def test_track_recovers_known_points_through_an_oracle_detector(track_recording, tmp_path, monkeypatch,
                                                                 capsys):
    oracle, args, out, X = _oracle_track(track_recording, tmp_path, monkeypatch)
    assert cli.main(args) == 0
    assert oracle.calls == 2 and "warning" not in capsys.readouterr().err
    points = read_csv(out, KEYPOINTS)
    assert sorted(points) == list(range(FRAMES))
    got = np.stack([points[f] for f in range(FRAMES)])
    np.testing.assert_allclose(got, X.numpy(), rtol=0, atol=1e-3)  # mm, at 1 m
    _, values = read_track_csv(out)
    per_kp = values[:, :-1].reshape(FRAMES, len(KEYPOINTS), 6)
    assert np.all(per_kp[..., 3] < 1e-3) and np.all(per_kp[..., 4] == 3)  # error px, ncams

    # A threshold no view reaches: still exit 0, all nan, and one warning naming the option.
    assert cli.main([*args, "--min-weight", "0.99", "--overwrite"]) == 0
    err = capsys.readouterr().err.strip()
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "--min-weight" in warnings[0]
    assert "no confidence calibration" in err  # a threshold asked of a run without a map: what it compares
    assert np.isnan(np.stack(list(read_csv(out, KEYPOINTS).values()))).all()

    # An existing output is kept without --overwrite.
    before = out.read_bytes()
    assert cli.main(args) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(out) in err and "--overwrite" in err
    assert out.read_bytes() == before


def test_track_reads_image_sequences_like_videos(track_recording, tmp_path):
    from s3k.data.video import extract_frames

    videos = {}
    for c in CAMERAS:
        pattern = "frame{:03d}.jpg" if c == CAMERAS[0] else "frame{:03d}.png"
        extract_frames(track_recording["videos"][c], tmp_path / "seq" / c, pattern=pattern)
        videos[c] = tmp_path / "seq" / c
    videos[CAMERAS[1]] = tmp_path / "seq" / CAMERAS[1] / "frame%03d.png"  # a printf pattern
    assert run_track(track_recording, tmp_path / "video.csv", "--min-weight", "0") == 0
    args = ["track", str(track_recording["run"]), "--calibration", str(track_recording["calibration"]),
            "--out", str(tmp_path / "seq.csv"), "--no-progress", "--min-weight", "0",
            "--videos", *[f"{c}={p}" for c, p in videos.items()]]
    # The first camera's frames went through JPEG: compare the cameras whose PNGs are exact.
    assert cli.main(args) == 0
    _, from_video = read_track_csv(tmp_path / "video.csv")
    _, from_seq = read_track_csv(tmp_path / "seq.csv")
    assert from_seq.shape == from_video.shape
    np.testing.assert_array_equal(from_seq[:, -1], np.arange(FRAMES))
    assert np.isfinite(from_seq[:, :-1]).all()
    exact = {c: tmp_path / "seq" / c for c in CAMERAS}
    for c in CAMERAS:
        extract_frames(track_recording["videos"][c], tmp_path / "png" / c)
        exact[c] = tmp_path / "png" / c
    args[5] = str(tmp_path / "png.csv")
    args[args.index("--videos") + 1:] = [f"{c}={p}" for c, p in exact.items()]
    assert cli.main(args) == 0
    _, from_png = read_track_csv(tmp_path / "png.csv")
    np.testing.assert_array_equal(from_png, from_video)


def test_track_says_why_every_point_is_nan(track_recording, tmp_path, capsys):
    # The untrained detector's confidence weights never reach 0.99: no view is used, the CSV is all nan.
    assert run_track(track_recording, tmp_path / "empty.csv", "--min-weight", "0.99") == 0
    _, values = read_track_csv(tmp_path / "empty.csv")
    assert np.isnan(values[:, :-1].reshape(FRAMES, len(KEYPOINTS), 6)[..., 0]).all()
    err = capsys.readouterr().err
    assert "every keypoint is 0% valid" in err and "train longer" in err and "lower --min-weight" in err
    assert run_track(track_recording, tmp_path / "full.csv", "--min-weight", "0", "--overwrite") == 0
    assert "0% valid" not in capsys.readouterr().err


def test_track_crops_videos_as_the_run_was_trained(track_recording, tmp_path, capsys):
    """Without --crop, each video is cropped to the box the run's training images showed (its record, here
    made by hand), exactly as with that --crop; --fit or another --crop overrides, the latter with a
    warning."""
    boxes = {"left": [8.0, 0.0, 56.0, 48.0], "top": [16.0, 8.0, 48.0, 40.0], "right": [0.0, 0.0, 64.0, 48.0]}
    meta = DetectorMeta(
        keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=NET_SIZE, stride=2, sigma=2.0,
        model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(), units="mm",
        geometry={"cameras": {c: {"box": b, "frame_size": list(VIDEO_SIZE)} for c, b in boxes.items()},
                  "image_size": list(NET_SIZE)})
    run = save_run(tmp_path / "run", meta, seed=0)
    rec = dict(track_recording, run=run)
    crop = [f"{c}={','.join(f'{v:g}' for v in b)}" for c, b in boxes.items()]
    assert run_track(rec, tmp_path / "recorded.csv", "--min-weight", "0") == 0
    assert "crop boxes the run was trained on (--crop or --fit overrides): left=8,0,56,48 top=16,8,48,40 " \
           "right=0,0,64,48" in capsys.readouterr().out
    assert run_track(rec, tmp_path / "given.csv", "--min-weight", "0", "--crop", *crop) == 0
    assert capsys.readouterr().err == ""
    assert run_track(rec, tmp_path / "fit.csv", "--min-weight", "0", "--fit", "pad") == 0
    recorded, given, fit = (read_track_csv(tmp_path / f"{n}.csv")[1] for n in ("recorded", "given", "fit"))
    np.testing.assert_array_equal(recorded, given)
    assert not np.allclose(recorded, fit, equal_nan=True)
    capsys.readouterr()
    assert run_track(rec, tmp_path / "other.csv", "--min-weight", "0", "--crop", "top=0,0,64,48") == 0
    assert "warning: --crop top=0,0,64,48 differs from the box the run was trained on, top=16,8,48,40" in \
        capsys.readouterr().err


def test_track_summary_gives_a_reason_for_every_invalid_keypoint(track_recording, tmp_path, capsys):
    from s3k.inference.track import keypoint_line

    assert run_track(track_recording, tmp_path / "empty.csv", "--min-weight", "0.99") == 0
    out = capsys.readouterr().out
    for kp in KEYPOINTS:
        assert (f"  {kp}: 0% valid; no point: 100% of frames have fewer than 2 views with a confidence "
                "above --min-weight 0.99 (lower --min-weight") in out
    assert "nan px" not in out
    # frames with enough views but no point have a reason of their own; a fully valid keypoint needs none
    assert keypoint_line(0.6, 1.5, 0.8, 0.5, 10) == (
        "60% valid, median error 1.50 px; no point: 20% of frames have fewer than 2 views with a confidence "
        "above --min-weight 0.5 (lower --min-weight (0 uses every view, weighted)); in 20% of frames "
        "its views triangulate to no valid point (rays near parallel or the point behind a camera: check "
        "--calibration, --video-region and --crop)")
    assert keypoint_line(1.0, 2.0, 1.0, 0.5, 10) == "100% valid, median error 2.00 px"


def test_track_filters_the_points_keeps_the_raw_ones_and_ranks_the_frames_by_doubt(track_recording, tmp_path):
    out, plain = tmp_path / "points3d.csv", tmp_path / "plain.csv"
    assert run_track(track_recording, out, "--min-weight", "0", "--filter-gate", "3",
                  "--filter-model", "acceleration") == 0
    assert run_track(track_recording, plain, "--min-weight", "0", "--filter", "none") == 0
    assert not (tmp_path / "plain.raw.csv").exists()
    # the raw points are what an unfiltered track writes; the filtered CSV has the same layout
    assert (tmp_path / "points3d.raw.csv").read_text() == plain.read_text()
    h1, filtered = read_track_csv(out)
    h2, raw = read_track_csv(plain)
    assert h1 == h2 and np.array_equal(filtered[:, -1], raw[:, -1])
    source = json.loads((tmp_path / "points3d.csv.s3k.json").read_text())
    assert source["raw"] == "points3d.raw.csv" and source["doubt"] == "points3d.doubt.csv"
    settings = source["filter"]["settings"]
    assert settings["model"] == "acceleration" and settings["gate"] == 3
    assert len(source["filter"]["process_noise"]) == len(KEYPOINTS)
    assert source["videos"] == {c: str(track_recording["videos"][c]) for c in CAMERAS}
    with open(tmp_path / "points3d.doubt.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted(int(r["fnum"]) for r in rows) == list(range(FRAMES))
    assert [int(r["rank"]) for r in rows] == list(range(1, FRAMES + 1))
    doubts = [float(r["doubt"]) for r in rows]
    assert doubts == sorted(doubts, reverse=True)


def test_readme_export_tracks_takes_the_frame_rate_from_the_tracks(track_recording, tmp_path, monkeypatch,
                                                                   capsys):
    """The README's ``s3k export-tracks points3d.csv --format nwb --out tracks.nwb`` runs as written on what
    ``s3k track`` wrote: the frame rate (25 frames/s) comes from the CSV's ``.s3k.json``."""
    import re
    import shlex

    pytest.importorskip("pynwb")
    from s3k.data.formats.nwb import read_nwb_tracks

    readme = (REPO / "README.md").read_text()
    command = re.search(r"`(s3k export-tracks [^`]*)`", readme)
    assert command is not None, "the README shows no s3k export-tracks command"
    argv = shlex.split(command.group(1))[1:]
    assert "--fps" not in argv
    _, args, out, _ = _oracle_track(track_recording, tmp_path, monkeypatch)
    assert out.name == "points3d.csv" and cli.main(args) == 0
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 0, capsys.readouterr().err
    _, times, *_ = read_nwb_tracks(tmp_path / "tracks.nwb")
    np.testing.assert_allclose(times, np.arange(FRAMES) / 25.0)
    # a CSV without a recorded rate (as s3k predict writes) is refused in one line naming --fps
    (tmp_path / "points3d.csv.s3k.json").write_text('{"units": "mm"}')
    assert cli.main([*argv, "--overwrite"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "frame rate" in err and "--fps" in err


def test_a_track_is_of_a_run_only_while_the_run_is_unchanged_since(tmp_path):
    """``tracked_with``: a CSV whose record names the run and that is newer than every file of the run is a
    track of its present weights (a benchmark may reuse it); trained on since, another run, no record: not."""
    import os

    from s3k.data.tracks_csv import tracked_with, write_source

    def touch(path: Path, when: float) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("x")
        os.utime(path, (when, when))
        return path

    run, other = touch(tmp_path / "run" / "fine" / "model.pt", 1000.0).parents[1], tmp_path / "other"
    touch(other / "model.pt", 1000.0)
    out = tmp_path / "tracked.csv"
    assert not tracked_with(out, run)  # no track yet
    touch(out, 2000.0)
    assert not tracked_with(out, run)  # no record beside it
    write_source(out, "mm", run=str(run))
    assert tracked_with(out, run)
    assert not tracked_with(out, other)
    touch(run / "fine" / "model.pt", 3000.0)  # trained on since
    assert not tracked_with(out, run)
    touch(out, 4000.0)
    assert tracked_with(out, tmp_path / "run" / "fine" / "..")  # the same folder, named another way


def test_python_track_writes_the_files_the_command_writes(track_recording, tmp_path, capsys):
    """``s3k.track(...)`` with a loaded detector writes what ``s3k track`` writes with the same settings: the
    filtered and raw CSVs, the doubt ranking and the JSON companions byte for byte, and the overlays; the
    detector is reused for a second track without loading it again."""
    import s3k

    cli_dir, py_dir = tmp_path / "cli", tmp_path / "py"
    assert run_track(track_recording, cli_dir / "points3d.csv", "--min-weight", "0", "--batch", "4",
                  "--filter-gate", "3", "--overlay", str(cli_dir / "ov")) == 0
    said = capsys.readouterr().out
    detector = s3k.Detector.load(track_recording["run"], "cpu")
    config = s3k.TrackConfig.from_flat(min_weight=0.0, batch=4, filter_gate=3.0, overlay=str(py_dir / "ov"),
                                       progress=False)
    out = py_dir / "points3d.csv"
    result = s3k.track(detector, track_recording["videos"], track_recording["calibration"], out, config)
    names = ["points3d.csv", "points3d.raw.csv", "points3d.doubt.csv", "points3d.csv.s3k.json",
             "points3d.raw.csv.s3k.json"]
    for name in names:
        assert (py_dir / name).read_bytes() == (cli_dir / name).read_bytes(), name
    overlays = [sorted(p.name for p in (d / "ov").iterdir()) for d in (py_dir, cli_dir)]
    assert overlays[0] == overlays[1]
    assert {p.name for p in result.files} == {*names, *(f"{c}.mp4" for c in CAMERAS)}
    assert "wrote 6 filtered frames" in said and result.frames == FRAMES
    # the same detector again, another setting: no second load, the same files but unfiltered
    again = s3k.track(detector, track_recording["videos"], track_recording["calibration"],
                      py_dir / "plain.csv",
                      s3k.TrackConfig.from_flat(min_weight=0.0, filter="none", progress=False))
    assert again.session.detector is detector
    assert (py_dir / "plain.csv").read_bytes() == (py_dir / "points3d.raw.csv").read_bytes()


def test_track_settings_are_the_track_config_with_ranges_and_print_config(track_recording, tmp_path, capsys):
    """s3k track's settings are TrackConfig's fields: --help states each one's default and range, a value out
    of range is refused as it is parsed, --print-config prints the resolved settings and tracks nothing;
    s3k stream offers the same filter settings with the filter off by default."""
    with pytest.raises(SystemExit):
        cli.main(["track", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--filter-gate SIGMAS" in text and "(default: 4.0; in [0, 100])" in text
    assert "--min-weight FLOAT" in text and "in [0, 1)" in text and "--no-progress" in text
    out = tmp_path / "x.csv"
    assert run_track(track_recording, out, "--filter-gate", "5", "--filter-limbs", "nose,ear",
                     "--print-config") == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["filter_gate"] == 5.0 and printed["filter_limbs"] == ["nose,ear"] and printed["batch"] == 8
    assert not out.exists()
    with pytest.raises(SystemExit):
        run_track(track_recording, out, "--filter-gate", "-1")
    assert "--filter-gate" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["stream", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "filter the 3D points over time" in text and "(default: none)" in text and "--batch" not in text


def test_track_and_stream_read_the_run_folder_once(track_recording, tmp_path, monkeypatch, capsys):
    """One s3k track or s3k stream call of a run that records its geometry (as s3k train does) opens the
    run's model file once and no other file of the run: the rig's checks, crop boxes and calibration notes
    read the loaded detector's meta."""
    import builtins
    import io

    whole = {c: {"box": [0.0, 0.0, *map(float, VIDEO_SIZE)], "frame_size": list(VIDEO_SIZE)} for c in CAMERAS}
    meta = DetectorMeta(
        keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=NET_SIZE, stride=2, sigma=2.0,
        model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(), units="mm",
        geometry={"cameras": whole, "image_size": list(NET_SIZE),
                  "dataset": {"path": str(tmp_path / "gone")}})
    run = save_run(tmp_path / "run", meta, seed=0).resolve()
    recording = dict(track_recording, run=run)
    opened: list[str] = []
    real_open, real_io_open = builtins.open, io.open

    def spy(opener):
        def open_(file, *args, **kwargs):
            if isinstance(file, (str, Path)) and Path(file).resolve().parent == run:
                opened.append(Path(file).name)
            return opener(file, *args, **kwargs)
        return open_

    monkeypatch.setattr(builtins, "open", spy(real_open))
    monkeypatch.setattr(io, "open", spy(real_io_open))
    assert run_track(recording, tmp_path / "x.csv") == 0
    assert opened == ["model.pt"]
    opened.clear()
    sources = [f"{c}={recording['videos'][c]}" for c in CAMERAS]
    assert cli.main(["stream", str(recording["run"]), "--calibration", str(recording["calibration"]),
                     "--sources", *sources, "--max-frames", "2"]) == 0
    assert opened == ["model.pt"]
    capsys.readouterr()


def test_track_config_validate_names_the_option_of_a_value_out_of_range_or_choice():
    """TrackConfig.validate: one line naming the option, for a range and for a choice set directly."""
    from s3k.base.errors import UserError
    from s3k.inference.track_config import FilteringConfig, TrackConfig

    with pytest.raises(UserError, match="--filter-gate"):
        TrackConfig.from_flat(filter_gate=-1.0).validate()
    with pytest.raises(UserError, match="--filter must be one of kalman, none, got 'kalmn'"):
        TrackConfig(filtering=FilteringConfig(filter="kalmn")).validate()  # type: ignore[arg-type]
    with pytest.raises(UserError, match="--filter-limbs 'nose'"):
        TrackConfig.from_flat(filter_limbs=["nose"]).validate()
    assert TrackConfig.from_flat(filter_limbs=["none"]).validate().limb_pairs() == []


def test_track_config_is_read_and_set_only_through_its_sections():
    """TrackConfig's fields are its sections' attributes; a flat name is not one (nor can it be set)."""
    from s3k.config import leaf_fields
    from s3k.inference.track_config import TrackConfig

    config = TrackConfig.from_flat(batch=4, filter="none")
    for _, f, _ in leaf_fields(TrackConfig):
        assert not hasattr(config, f.name), f.name
    with pytest.raises(AttributeError):
        config.batch = 2  # type: ignore[attr-defined]
    assert (config.chunks.batch, config.filtering.filter, config.filtering_on) == (4, "none", False)
