"""Tests of the coarse-to-fine detector (``s3k train --two-pass``, :mod:`s3k.train.two_pass`)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch
from helpers.files import contents
from helpers.rig_inputs import rig_inputs
from helpers.synthetic_rig import KEYPOINTS, LAYOUT, count_decodes, make_dataset, random_rotation
from helpers.track_rig import CAMERAS as TRACK_CAMERAS
from helpers.track_rig import KEYPOINTS as TRACK_KEYPOINTS
from helpers.track_rig import NET_SIZE, VIDEO_SIZE, make_rig, moving_points, peaked_logits

from s3k import cli
from s3k.base.errors import UserError
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.tracks_csv import read_csv
from s3k.data.video import write_video
from s3k.detector import (
    TWO_PASS_FILE,
    CropRule,
    Detector,
    DetectorMeta,
    TwoPassDetector,
    crop_centres,
    extent_middle,
    read_two_pass,
)
from s3k.detector.geometry_record import dataset_identity
from s3k.geometry import Cameras, project
from s3k.geometry.warp import crop_maps, metric_crop_boxes
from s3k.model import UNetConfig
from s3k.readout.heatmaps import gaussian_targets, heatmap_size
from s3k.run_folder import RunFolder
from s3k.train.run_setup import _validation_frames
from s3k.train.two_pass import crop_rule_from_labels, estimates_and_crops, training_crops

CPU_FILE, ESTIMATES_FILE = RunFolder.CPU, RunFolder.ESTIMATES


def read_cpu(run) -> dict[str, float]:
    return RunFolder(run).read_cpu()


def _farthest_pair_radius(X: np.ndarray) -> float:
    d = np.linalg.norm(X[:, None] - X[None], axis=-1)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    return float(np.linalg.norm(X - 0.5 * (X[i] + X[j]), axis=-1).max())


def test_extent_middle_is_the_rectangle_centre_in_any_orientation():
    """Three corners of a 199 x 105 mm lid: the middle is the lid's centre, equally far from each corner,
    however the lid is turned (a bounding box in world axes would move with the rotation)."""
    corners = np.array([[-99.5, 52.5, 0.0], [99.5, 52.5, 0.0], [99.5, -52.5, 0.0]])
    rng = np.random.default_rng(0)
    for _ in range(20):
        R, shift = random_rotation(rng), rng.uniform(-500, 500, 3)
        X = corners @ R.T + shift
        c = extent_middle(X)
        np.testing.assert_allclose(c, shift, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(X - c, axis=-1), np.hypot(199, 105) / 2, rtol=1e-12)
    # the mean of the corners is not the centre: it lies towards the right-angle corner
    assert np.linalg.norm(corners.mean(0)) > 30


def test_extent_middle_ignores_missing_keypoints():
    X = np.array([[0.0, 0, 0], [np.nan, np.nan, np.nan], [2.0, 0, 0]])
    np.testing.assert_allclose(extent_middle(X), [1.0, 0, 0])
    np.testing.assert_allclose(extent_middle(X[:2]), [0.0, 0, 0])  # one keypoint: itself
    assert extent_middle(np.full((3, 3), np.nan)) is None



def test_crop_centres_fall_back_on_the_workspace_centre_where_no_keypoint_was_placed():
    """One rule for every consumer: the middle of the placed keypoints' extent, or where the cameras look."""
    R = [random_rotation(np.random.default_rng(i)) for i in range(3)]
    looking_at = np.array([0.1, -0.2, 0.3])
    t = [-(r @ looking_at) + np.array([0.0, 0.0, 1.5]) for r in R]  # the origin of each camera's axis
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]])
    cams = Cameras.from_numpy(np.stack([K] * 3), None, np.stack(R), np.stack(t), dtype=torch.float64)
    X = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0], [np.nan] * 3], [[np.nan] * 3] * 3], dtype=torch.float64)
    valid = torch.isfinite(X).all(-1)
    centres, placed = crop_centres(X, valid, cams)
    assert placed.tolist() == [True, False]
    np.testing.assert_allclose(centres[0].numpy(), [1.0, 0, 0])
    np.testing.assert_allclose(centres[1].numpy(), looking_at, atol=1e-9)


def test_crop_rule_from_labels_covers_every_keypoint_with_the_margin(tmp_path):
    ds = Dataset.open(make_dataset(tmp_path / "d", size=48, labelled=5), cache="none")
    r = _farthest_pair_radius(LAYOUT)  # the labels are exact projections of the rigid layout
    for margin in (0.0, 0.3):
        rule = crop_rule_from_labels(ds, size=64, margin=margin)
        assert rule.size == 64 and rule.margin == margin
        assert rule.extent == pytest.approx(2 * r * (1 + margin), rel=1e-6)


def test_crop_rule_needs_triangulated_labels(tmp_path):
    from s3k.base.errors import UserError

    ds = Dataset.open(make_dataset(tmp_path / "d", size=32, labelled=3, label_cameras=1), cache="none")
    with pytest.raises(UserError, match="--crop-extent"):
        crop_rule_from_labels(ds, size=64)


def test_the_refining_view_keeps_the_pixel_tolerances_their_size_in_the_scene():
    from s3k.config import TrainConfig

    cfg = TrainConfig.from_flat(outlier_px=6.0, shift_px=10.0, pseudo_window=5, sigma=1.0, image_size=96)
    same = cfg.refining(128)
    s = same.self_supervision
    assert (s.outlier_px, same.augmentation.shift_px, s.pseudo_window) == (6.0, 10.0, 5)
    assert same.model.image_size == 0
    finer = cfg.refining(192)
    s = finer.self_supervision
    assert (s.outlier_px, finer.augmentation.shift_px, s.pseudo_window) == (9.0, 15.0, 8)
    assert finer.model.sigma == 1.0 and finer.augmentation.rotation_deg == cfg.augmentation.rotation_deg
    off = cfg.replace(outlier_px=0.0, pseudo_window=0).refining(256)
    assert (off.self_supervision.outlier_px, off.self_supervision.pseudo_window) == (0.0, 0)


def test_two_pass_train_evaluate_predict_and_refusals(tmp_path, capsys):
    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=6, test=3)
    run = tmp_path / "run"
    args = ["train", str(data), "--out", str(run), "--two-pass", "--steps", "3", "--coarse-size", "32",
            "--crop-size", "32", "--channels", "8,8", "--res_blocks", "1", "--val_every", "0",
            "--warmup_steps", "1", "--ramp_steps", "1", "--no-progress", "--threads", "1",
            "--rotation_deg", "15", "--coarse-rotation", "180"]
    assert cli.main(args) == 0
    rule, coarse, fine = read_two_pass(run)
    coarse_cfg = json.loads((coarse / "config.json").read_text())["config"]
    fine_cfg = json.loads((fine / "config.json").read_text())["config"]
    assert coarse_cfg["rotation_deg"] == 180
    assert fine_cfg["rotation_deg"] == 15
    # 32 px crops: the refining pass's pixel tolerances are a quarter of the options given (at 128 px)
    assert (coarse_cfg["outlier_px"], coarse_cfg["shift_px"], coarse_cfg["pseudo_window"]) == (6.0, 10.0, 5)
    assert (fine_cfg["outlier_px"], fine_cfg["shift_px"], fine_cfg["pseudo_window"]) == (1.5, 2.5, 1)
    assert rule.size == 32 and rule.extent == pytest.approx(2 * _farthest_pair_radius(LAYOUT) * 1.3, rel=1e-6)
    assert (coarse / "model.pt").is_file() and (fine / "model.pt").is_file()
    assert coarse_cfg["image_size"] == 32
    # each pass calibrated its confidence on its own validation frames, the refining pass on their crops:
    # the two-pass detector's thresholds compare the refining pass's
    detector = Detector.load(run, "cpu")
    assert isinstance(detector, TwoPassDetector) and detector.coarse.meta.calibration is not None
    assert detector.fine.readout.confidence is not None
    assert detector.fine.readout.confidence.within_px == pytest.approx(2 * detector.fine.meta.sigma)
    spent = read_cpu(run)  # CPU seconds per stage
    assert set(spent) == {"coarse", "crops", "fine"} and min(spent.values()) > 0
    # the crops were cut in memory; the estimates give the same crops again
    assert not (run / "crops").exists()
    crops = training_crops(data, read_csv(run / ESTIMATES_FILE, KEYPOINTS), rule)
    source = Dataset.open(data, cache="none")
    fresh = estimates_and_crops(coarse, source, tmp_path / "again.csv", rule)  # decoded once for both
    assert dataset_identity(fresh) == dataset_identity(crops)  # what --resume compares
    np.testing.assert_array_equal(fresh.images_array, crops.images_array)
    assert crops.image_size == (32, 32) and list(crops.keypoints) == KEYPOINTS
    for split in ("labelled", "unlabelled", "test"):
        np.testing.assert_array_equal(crops.frames(split), source.frames(split))
    # the crops' cameras see the ground truth where the labels put it (K' = M K)
    ids = crops.frames("labelled")
    uv, mask = crops.labels(ids)
    X, _ = crops.points3d(ids)
    proj, _ = project(crops.calibration(ids, np.float64), torch.as_tensor(X, dtype=torch.float64)[:, None])
    np.testing.assert_allclose(proj.numpy()[mask], uv[mask], atol=1e-3)

    # a complete run: --resume checks it and computes and writes nothing (no estimates or crops, no CPU time,
    # history or log line); without --resume or --overwrite the folder is kept
    before = contents(run)
    capsys.readouterr()
    assert cli.main([*args, "--resume", "--threads", "2"]) == 0
    assert contents(run) == before
    assert f"refining pass: {fine} is complete" in capsys.readouterr().out
    # a complete pass trained otherwise than the call asks is refused, not silently kept
    capsys.readouterr()
    assert cli.main([*args[:-1], "90", "--resume"]) == 1
    err = capsys.readouterr().err
    assert "coarse pass" in err and "rotation_deg is 90" in err and "180" in err and "--overwrite" in err
    assert cli.main([*args, "--resume", "--crop-size", "48"]) == 1  # crops of another size
    err = capsys.readouterr().err
    assert str(run) in err and "at 32 px" in err and "at 48 px" in err
    capsys.readouterr()
    assert cli.main(args) == 1
    assert "--resume" in capsys.readouterr().err
    assert cli.main([*args, "--image-size", "48"]) == 1
    assert "--coarse-size" in capsys.readouterr().err

    # evaluate and predict go through both passes, on the source dataset's own images
    assert cli.main(["evaluate", str(run), "--data", str(data), "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["two_pass"]["size"] == 32 and metrics["two_pass"]["coarse_frames_placed"] == 3
    assert metrics["n_frames"] == 3 and metrics["image_size"] == [32, 32]
    # its pixel metrics are in crop pixels; rms_px_image is the same error in the dataset's own pixels

    test_ids = source.frames("test")
    cams = source.calibration(test_ids, np.float64)
    got = Detector.load(run, "cpu")(source.images(test_ids), cams)
    X_true, known = source.points3d(test_ids)
    uv_true, _ = project(cams, torch.as_tensor(X_true, dtype=torch.float64)[:, None])
    err = torch.linalg.vector_norm(got.uv - uv_true, dim=-1)
    inside = ((uv_true >= -0.5) & (uv_true <= 63.5)).all(-1) & torch.as_tensor(known)[:, None]
    assert metrics["rms_px_image"] == pytest.approx(float(err[inside].pow(2).mean().sqrt()), rel=1e-6)
    assert cli.main(["evaluate", str(run), "--data", str(data)]) == 0
    assert ("rms_px and rms_px_reproj are in pixels of the refining pass's 32 px crops"
            in capsys.readouterr().out)
    out = tmp_path / "p.csv"
    assert cli.main(["predict", str(run), "--data", str(data), "--out", str(out)]) == 0
    assert sorted(read_csv(out, KEYPOINTS)) == list(source.frames("test"))
    # export writes both passes and the crop rule; ONNX Runtime's detector gives PyTorch's 3D points
    capsys.readouterr()
    assert cli.main(["export", str(run), "--format", "onnx", "--out", str(tmp_path / "m.onnx")]) == 0
    printed = capsys.readouterr().out
    assert "max 3D difference" in printed
    for name in ("m.coarse.onnx", "m.fine.onnx", "m.json"):
        assert (tmp_path / name).is_file()
    from s3k.inference.export import load_exported

    ids = source.frames("test")
    images, cams = source.images(ids), source.calibration(ids, dtype=np.float64)
    ref = Detector.load(run, "cpu")(images, cams)
    got = load_exported(tmp_path / "m.json")(images, cams)
    assert torch.equal(ref.valid, got.valid) and bool(ref.valid.any())
    diff_mm = torch.linalg.vector_norm(ref.X - got.X, dim=-1)[ref.valid] * 1000  # the dataset is in metres
    assert float(diff_mm.max()) < 0.1



def test_stage_clock_keeps_a_killed_attempts_cpu_time(tmp_path):
    from s3k.train.two_pass import _StageClock

    (tmp_path / CPU_FILE).write_text(json.dumps({"coarse": 5.0}))  # an earlier attempt's time
    with pytest.raises(KeyboardInterrupt), _StageClock(RunFolder(tmp_path), "fine", every=10) as clock:
        clock.tick(10)  # a training step that writes
        assert read_cpu(tmp_path)["fine"] >= 0 and read_cpu(tmp_path)["coarse"] == 5.0
        raise KeyboardInterrupt  # a kill
    assert set(read_cpu(tmp_path)) == {"coarse", "fine"}
    first = read_cpu(tmp_path)["fine"]
    with _StageClock(RunFolder(tmp_path), "fine") as clock:
        t = time.process_time()
        while time.process_time() - t < 0.05:  # some CPU work
            pass
    spent = read_cpu(tmp_path)
    assert spent["fine"] >= first + 0.05 and spent["coarse"] == 5.0
    (tmp_path / CPU_FILE).write_text("[1, 2]")
    with pytest.raises(UserError, match=CPU_FILE):
        read_cpu(tmp_path)


class _GreyOracle(torch.nn.Module):
    """A network stand-in that reads frame ``f`` and camera ``c`` from an image's centre (grey level
    ``20 + 10 f + 3 c``) and answers with precomputed logits ``(F, C, K, h, w)``."""

    def __init__(self, logits: torch.Tensor):
        super().__init__()
        self.logits = logits.float()
        self.calls = 0

    def fused(self):
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        H, W = images.shape[-2:]
        level = (images[:, 0, H // 2, W // 2] * 255).round().long() - 20
        self.calls += 1
        return self.logits[level // 10, (level % 10) // 3]


def test_track_through_both_passes_recovers_the_points(tmp_path, monkeypatch):
    """``s3k track`` with a two-pass run: the coarse pass is off by 8 mm, the refining pass sees crops cut
    around the coarse estimate from the full-resolution videos and gives the true points back: the crop
    boxes, their pixel maps and the read-out in video pixels compose exactly."""
    import s3k.detector.detector

    rig = make_rig()
    calib = tmp_path / "calibration.toml"
    write_anipose_calibration(calib, rig)
    F, (W, H) = 6, VIDEO_SIZE
    videos = {}
    for c, name in enumerate(TRACK_CAMERAS):  # lossless, one grey level per frame and camera
        videos[name] = tmp_path / f"{name}.mkv"
        write_video(videos[name], [np.full((H, W, 3), 20 + 10 * f + 3 * c, np.uint8) for f in range(F)],
                    fps=25, codec="ffv1")
    X = torch.as_tensor(moving_points(F))  # (F, K, 3) mm
    inputs, cams = rig_inputs(videos, rig, NET_SIZE, "pad")
    M = torch.as_tensor(np.stack([c.M for c in inputs]))
    X_coarse = X + torch.tensor([8.0, 0.0, 0.0])
    uv, _ = project(cams, X_coarse[:, None])
    coarse = _GreyOracle(peaked_logits(uv @ M[:, :2, :2].transpose(-1, -2) + M[:, None, :2, 2], 2, 2.0))
    # the refining oracle's answer: the true points in the crops the run's rule cuts around the coarse points
    rule = CropRule(extent=400.0, size=40)
    centres = torch.as_tensor(np.stack([extent_middle(x) for x in X_coarse.numpy()]))[:, None]
    boxes, _ = metric_crop_boxes(cams, centres, rule.extent)
    maps = crop_maps(boxes, (rule.size, rule.size))  # (F, C, 3, 3)
    uv_true, _ = project(cams, X[:, None])
    uv_crop = uv_true @ maps[..., :2, :2].transpose(-1, -2) + maps[..., None, :2, 2]
    h, w = heatmap_size(rule.size, rule.size, 2)
    target, inside = gaussian_targets(uv_crop, None, h, w, 2, 2.0)
    assert bool(inside.all())
    fine = _GreyOracle(target.clamp_min(1e-300).log())

    def meta(size):
        return DetectorMeta(keypoints=list(TRACK_KEYPOINTS), cameras=list(TRACK_CAMERAS), image_size=size,
                            stride=2, sigma=2.0, model=UNetConfig(channels=(8, 8), stride=2).to_dict(),
                            units="mm", source_image_size=size)

    passes = {"coarse": (coarse, meta(NET_SIZE)), "fine": (fine, meta((rule.size, rule.size)))}
    monkeypatch.setattr(s3k.detector.detector, "load_network",
                        lambda path, *a, **k: passes[str(path).split("/")[-1]])
    run = tmp_path / "run"
    run.mkdir()
    (run / TWO_PASS_FILE).write_text(json.dumps({"extent": rule.extent, "size": rule.size, "coarse": "coarse",
                                                 "fine": "fine"}))
    out = tmp_path / "points3d.csv"
    assert cli.main(["track", str(run), "--calibration", str(calib), "--out", str(out), "--no-progress",
                     "--batch", "4", "--min-weight", "0", "--videos",
                     *[f"{c}={videos[c]}" for c in TRACK_CAMERAS]]) == 0
    assert coarse.calls == 2 and fine.calls == 2
    got = np.stack([read_csv(out, TRACK_KEYPOINTS)[f] for f in range(F)])
    np.testing.assert_allclose(got, X.numpy(), rtol=0, atol=1e-3)  # the truth, not the coarse points


def test_coarse_stride_sets_the_coarse_pass_alone_and_resume_keeps_it(tmp_path, capsys):
    """``--coarse-stride 2 --stride 4``: the coarse pass at stride 2 places the crops, the refining pass reads
    them at stride 4; a resume with no options keeps both, and evaluation reads each pass at its own.
    ``--coarse-lr`` likewise sets the coarse pass's learning rate apart from ``--lr``."""
    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=4, test=2)
    run = tmp_path / "run"
    args = ["train", str(data), "--out", str(run), "--two-pass", "--steps", "2", "--coarse-size", "32",
            "--crop-size", "32", "--channels", "8,8", "--res_blocks", "1", "--val_every", "0",
            "--warmup_steps", "1", "--ramp_steps", "1", "--no-progress", "--threads", "1", "--lr", "0.002",
            "--coarse-lr", "0.0005", "--stride", "4", "--coarse-stride", "2"]
    assert cli.main(args) == 0
    _, coarse, fine = read_two_pass(run)

    def settings():
        configs = [json.loads((p / "config.json").read_text())["config"] for p in (coarse, fine)]
        return [(c["stride"], c["lr"]) for c in configs]

    assert settings() == [(2, 0.0005), (4, 0.002)]
    # the resume takes every option from the run: the coarse pass would be refused at stride 4 or lr 0.002
    assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--resume", "--no-progress"]) == 0
    assert settings() == [(2, 0.0005), (4, 0.002)]
    # the options of a run from before they were recorded are read from its passes
    (run / "two_pass_options.json").unlink()
    assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--resume", "--no-progress"]) == 0
    assert settings() == [(2, 0.0005), (4, 0.002)]
    capsys.readouterr()
    assert cli.main(["evaluate", str(run), "--data", str(data), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_frames"] == 2
    assert cli.main([*args[:-1], "3", "--out", str(tmp_path / "other")]) == 1  # not a stride there is
    assert not (tmp_path / "other").exists()
    assert "--coarse-stride" in capsys.readouterr().err


def test_a_two_pass_training_decodes_each_image_once(tmp_path, monkeypatch):
    """The frames the coarse pass decodes for its small images are kept for the crops, so each image file is
    decoded once; with ``--preload-mb 0`` nothing is kept and the crops decode every file again (the coarse
    pass, not preloading, decodes only the frames its few steps draw). The estimates are the same."""
    import s3k.data.sources as sources

    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=6, test=3)
    decoded = count_decodes(monkeypatch, sources)
    files = len(Dataset.open(data, cache="none")) * 4
    estimates = {}
    for preload in ("2048", "0"):
        decoded.clear()
        monkeypatch.setenv("S3K_CACHE_DIR", str(tmp_path / f"cache-{preload}"))
        run = tmp_path / f"run-{preload}"
        assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--steps", "3",
                         "--coarse-size", "32", "--crop-size", "32", "--channels", "8,8", "--res_blocks", "1",
                         "--val_every", "0", "--warmup_steps", "1", "--ramp_steps", "1", "--no-progress",
                         "--threads", "1", "--preload-mb", preload]) == 0
        assert len(set(decoded)) == files
        assert (len(decoded) == files) if preload == "2048" else (len(decoded) > files)
        estimates[preload] = (run / ESTIMATES_FILE).read_text()
    assert estimates["2048"] == estimates["0"]


def test_the_crops_are_cut_for_the_frames_the_refining_pass_reads(tmp_path):
    """Labels only: the labelled frames and the validation frames are estimated and cropped, not the
    unlabelled ones nor the rest of the test split; the refining pass validates on the same frames as it
    would on every frame's crops, and a resumed run cuts the same frames again from the estimates."""
    data = make_dataset(tmp_path / "d", size=64, labelled=4, unlabelled=6, test=5)
    run = tmp_path / "run"
    assert cli.main(["train", str(data), "--out", str(run), "--two-pass", "--steps", "2", "--no-unsup",
                     "--coarse-size", "32", "--crop-size", "32", "--channels", "8,8", "--res_blocks", "1",
                     "--val_every", "0", "--val_frames", "2", "--no-progress", "--threads", "1"]) == 0
    ds = Dataset.open(data, cache="none")
    test = ds.frames("test")
    estimates = read_csv(run / ESTIMATES_FILE, KEYPOINTS)
    assert sorted(estimates) == sorted([*ds.frames("labelled"), test[0], test[-1]])
    rule, _, fine = read_two_pass(run)
    cfg = json.loads((fine / "config.json").read_text())["config"]
    assert cfg["unsup"] is False and cfg["val_frames"] == 2
    refining = TrainConfig.from_flat(**cfg)
    some = training_crops(ds, estimates, rule, frames=list(estimates))
    every = training_crops(ds, {**{f: np.full((3, 3), np.nan) for f in ds.frames()}, **estimates}, rule)
    assert sorted(some.frame_ids) == sorted(estimates)
    picked = [_validation_frames(c, refining, c.frames("labelled"), c.frames("unlabelled"))
              for c in (some, every)]
    np.testing.assert_array_equal(*picked)
    np.testing.assert_array_equal(picked[0], [test[0], test[-1]])
