"""Evaluation metrics on known predictions, the evaluate/predict commands and the report."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest
from helpers.synthetic_rig import CAMERAS, KEYPOINTS, make_dataset, project, rig

from s3k.base.draw import draw_views
from s3k.base.metrics import compute_metrics, mm_per_unit
from s3k.cli import main as cli_main
from s3k.data import Dataset
from s3k.data.frames import FrameStore, open_dataset
from s3k.data.tracks_csv import csv_header, read_csv
from s3k.detector import Detector, OnePassDetector, load_network
from s3k.inference.predict import detect_store
from s3k.train import train


def test_metrics_by_hand():
    B, C, K = 2, 2, 2
    gt = np.zeros((B, C, K, 2))
    pred = gt.copy()
    pred[0, 0, 0] = (3, 4)  # 5 px
    pred[1, 1, 1] = (0, 2)  # 2 px
    pred[1, 0, 1] = (100, 100)  # masked below: must not count
    mask = np.ones((B, C, K), bool)
    mask[1, 0, 1] = False
    reproj = gt.copy()
    reproj[:, :, 0] = (1, 0)  # 1 px for keypoint 0 everywhere
    reproj[0, :, 1] = (0, 50)  # frame 0 keypoint 1 is not triangulated: must not count
    X_gt = np.zeros((B, K, 3))
    X = X_gt.copy()
    X[0, 0, 0] = 0.001  # 1 mm
    X[1, 0, 1] = 0.002  # 2 mm
    X[1, 1, 2] = 0.004  # 4 mm
    X[0, 1] = 9.0  # invalid
    valid = np.array([[True, False], [True, True]])
    m = compute_metrics(pred, reproj, gt, mask, X, valid, X_gt, None, 1000.0, ["p", "q"], ["c0", "c1"])
    # 2D: 7 terms, squared errors 25 and 4
    assert m["rms_px"] == pytest.approx(math.sqrt((25 + 4) / 7))
    # reprojection: keypoint 0 in 4 views at 1 px, keypoint 1 of frame 1 in 1 unmasked view at 0 px
    assert m["rms_px_reproj"] == pytest.approx(math.sqrt(4 / 5))
    assert m["median_mm"] == pytest.approx(2.0)
    assert m["rms_mm"] == pytest.approx(math.sqrt((1 + 4 + 16) / 3))
    assert m["triangulated_fraction"] == pytest.approx(0.75)
    assert (m["n_frames"], m["n_2d"], m["n_3d"]) == (2, 7, 3)
    kp = m["per_keypoint"]
    assert kp["p"]["rms_px"] == pytest.approx(math.sqrt(25 / 4))
    assert kp["q"]["rms_px"] == pytest.approx(math.sqrt(4 / 3))
    assert kp["p"]["median_mm"] == pytest.approx(1.5) and kp["q"]["rms_mm"] == pytest.approx(4.0)
    cam = m["per_camera"]
    assert cam["c0"]["rms_px"] == pytest.approx(math.sqrt(25 / 3)) and cam["c0"]["n_2d"] == 3
    assert cam["c1"]["rms_px"] == pytest.approx(math.sqrt(4 / 4))
    json.dumps(m)  # serializable


def test_metrics_without_3d_and_bad_shapes():
    z = np.zeros((1, 2, 3, 2))
    m = compute_metrics(z, z, z + 1, np.ones((1, 2, 3), bool), np.zeros((1, 3, 3)), np.ones((1, 3), bool))
    assert m["rms_px"] == pytest.approx(math.sqrt(2)) and m["median_mm"] is None and m["rms_mm"] is None
    with pytest.raises(ValueError, match="pred_uv"):
        compute_metrics(z[:, :1], z, z, np.ones((1, 2, 3), bool), np.zeros((1, 3, 3)), np.ones((1, 3), bool))
    assert mm_per_unit("m") == 1000 and mm_per_unit("mm") == 1 and math.isnan(mm_per_unit("furlong"))


def test_draw_views_shape():
    probs = np.random.default_rng(0).random((4, 3, 8, 10))
    pred, true = np.full((4, 3, 2), 5.0), np.full((4, 3, 2), 7.0)
    img = draw_views(np.zeros((4, 16, 20, 3), np.uint8), probs, pred, true, scale=2)
    assert img.shape == (32, 160, 3) and img.dtype == np.uint8 and img.max() > 0


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("ev")
    ds = make_dataset(root / "ds", size=32, labelled=3, unlabelled=3, test=3, seed=1)
    from s3k.config import TrainConfig

    cfg = TrainConfig.from_flat(steps=2, batch_labelled=2, batch_unlabelled=2, channels=(8, 16),
                                res_blocks=1, warmup_steps=0, val_every=0, progress=False, threads=1)
    train(ds, root / "run", cfg)
    return root, ds, root / "run"


def test_evaluate_json_on_known_prediction(trained, capsys):
    """Ground truth placed at known offsets from the model's own triangulation gives known metrics."""
    from s3k.data import DatasetWriter

    root, ds_path, run = trained
    ds = Dataset.open(ds_path, cache="none")
    test_ids = ds.frames("test")
    (batch, pred), = list(detect_store(Detector.load(run, "cpu"), FrameStore(ds, test_ids), 16))
    assert pred.valid.all()
    offsets = np.array([[0.001, 0, 0], [0, 0.002, 0], [0, 0, 0.004]])  # 1, 2, 4 mm
    X_gt = pred.X.double().numpy() + offsets
    K, dist, R, t = rig(32)
    known = root / "known"
    with DatasetWriter(known, KEYPOINTS, CAMERAS, (32, 32), "m", calibration=(K, dist, R, t)) as w:
        for b, fid in enumerate(test_ids):
            w.add_frame(int(fid), "test", batch.images[b].numpy(), None, None, points3d=X_gt[b])
    assert cli_main(["evaluate", str(run), "--data", str(known), "--json", "--device", "cpu"]) == 0
    m = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert m["median_mm"] == pytest.approx(2.0, abs=1e-3)
    assert m["rms_mm"] == pytest.approx(math.sqrt((1 + 4 + 16) / 3), abs=1e-3)
    assert m["per_keypoint"]["c"]["median_mm"] == pytest.approx(4.0, abs=1e-3)
    gt_uv = np.stack([project(K, R, t, X_gt[b]) for b in range(len(test_ids))])  # (B, C, K, 2)
    rep_uv = np.stack([project(K, R, t, pred.X[b].double().numpy()) for b in range(len(test_ids))])
    want_reproj = np.sqrt(np.mean(np.sum((rep_uv - gt_uv) ** 2, -1)))
    want_px = np.sqrt(np.mean(np.sum((pred.uv.double().numpy() - gt_uv) ** 2, -1)))
    assert m["rms_px_reproj"] == pytest.approx(want_reproj, rel=1e-3, abs=1e-4)
    assert m["rms_px"] == pytest.approx(want_px, rel=1e-3, abs=1e-4)
    assert set(m["per_camera"]) == set(CAMERAS) and m["n_frames"] == len(test_ids)


def test_evaluate_table_and_report(trained, capsys, tmp_path):
    root, ds_path, run = trained
    rep = tmp_path / "report"
    args = ["evaluate", str(run), "--data", str(ds_path), "--report", str(rep), "--overlays", "2"]
    assert cli_main(args) == 0
    out = capsys.readouterr().out
    assert "rms_px" in out and "kp a" in out and "cam cam0" in out
    for name in ("metrics.json", "errors_hist.png", "per_keypoint.png"):
        assert (rep / name).is_file(), name
    assert len(list(rep.glob("overlay_*.png"))) == 2


def test_predict_writes_the_track_csv(trained, tmp_path):
    root, ds_path, run = trained
    out = tmp_path / "pred.csv"
    assert cli_main(["predict", str(run), "--data", str(ds_path), "--out", str(out), "--split", "test"]) == 0
    assert out.read_text().splitlines()[0].split(",") == csv_header(KEYPOINTS)
    from s3k.data.tracks_csv import read_source

    assert read_source(out)["units"] == Dataset.open(ds_path).units  # the points' unit, beside the CSV
    ds = Dataset.open(ds_path, cache="none")
    (batch, pred), = list(detect_store(Detector.load(run, "cpu"), FrameStore(ds, ds.frames("test"))))
    points = read_csv(out, KEYPOINTS)
    assert sorted(points) == sorted(int(f) for f in batch.frame_ids)
    for b, fid in enumerate(batch.frame_ids):
        np.testing.assert_allclose(points[int(fid)], pred.X[b].numpy(), rtol=1e-6, atol=1e-9)
    rows = list(csv.DictReader(open(out)))
    assert float(rows[0]["b_score"]) == pytest.approx(float(pred.weights[0, :, 1].mean()), abs=1e-6)
    assert int(rows[0]["b_ncams"]) == len(CAMERAS)  # an untrained network's views agree within --outlier-px


def test_detector_reads_out_with_its_training_outlier_threshold(tmp_path):
    """A detector keeps its training's --outlier-px and s3k predict drops the views that miss the others'
    consensus by more; a run trained before the meta kept it takes it from its config.json."""
    from s3k.config import TrainConfig
    from s3k.detector import MODEL_FILE, atomic_save, load_torch_file

    ds_path = make_dataset(tmp_path / "ds", size=32, labelled=2, unlabelled=2, test=3, seed=4)
    cfg = TrainConfig.from_flat(steps=1, batch_labelled=2, batch_unlabelled=2, channels=(8, 16), res_blocks=1,
                                val_every=0, progress=False, threads=1, outlier_px=0.01)
    run = tmp_path / "run"
    train(ds_path, run, cfg)
    model, meta = load_network(run)
    assert meta.outlier_px == 0.01 and meta.max_residual_px == 0.01
    ds = Dataset.open(ds_path, cache="none")
    store = FrameStore(ds, ds.frames("test"))
    (_, every), = list(detect_store(OnePassDetector(model, replace(meta, outlier_px=0.0)), store))
    (_, kept), = list(detect_store(OnePassDetector(model, meta), store))
    assert int(kept.used.sum()) < int(every.used.sum())  # an untrained network's views disagree slightly
    out = tmp_path / "p.csv"
    assert cli_main(["predict", str(run), "--data", str(ds_path), "--out", str(out)]) == 0
    rows = list(csv.DictReader(open(out)))
    assert [int(r["a_ncams"]) for r in rows] == kept.used[:, :, 0].sum(dim=1).tolist()
    points = read_csv(out, KEYPOINTS)
    for b, fid in enumerate(ds.frames("test")):
        np.testing.assert_allclose(points[int(fid)], kept.X[b].numpy(), rtol=1e-6, atol=1e-9)
    # a model file without the field: the run's config.json gives it
    state = load_torch_file(run / MODEL_FILE, "model", ("meta", "model"))
    del state["meta"]["outlier_px"]
    atomic_save(state, run / MODEL_FILE)
    assert load_network(run)[1].outlier_px == 0.01
    (run / "config.json").unlink()
    assert load_network(run)[1].max_residual_px is None


def test_resized_run_predicts_in_dataset_pixels(tmp_path):
    """A network trained at 24 px on 32 px images: the same points, errors in the dataset's pixels."""
    from s3k.config import TrainConfig

    ds_path = make_dataset(tmp_path / "ds", size=32, labelled=2, unlabelled=2, test=2, seed=2)
    cfg = TrainConfig.from_flat(steps=1, batch_labelled=2, batch_unlabelled=2, channels=(8, 16),
                                res_blocks=1, image_size=24, val_every=0, progress=False, threads=1)
    train(ds_path, tmp_path / "run", cfg)
    model, meta = load_network(tmp_path / "run")
    assert meta.image_size == (24, 24) and meta.source_image_size == (32, 32)
    resized = open_dataset(ds_path, meta.image_size)  # resized as training resized it
    (_, net), = list(detect_store(OnePassDetector(model, meta), FrameStore(resized, resized.frames("test"))))
    ds = Dataset.open(ds_path, cache="none")
    (_, own), = list(detect_store(Detector.load(tmp_path / "run", "cpu"), FrameStore(ds, ds.frames("test"))))
    s = 24 / 32  # u_net = s (u + 0.5) - 0.5
    assert own.pixel_maps is not None
    np.testing.assert_allclose(own.pixel_maps[0, 0].numpy(), [[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5],
                                                              [0, 0, 1]], atol=1e-12)
    # the detector resamples the dataset's own images as the resized dataset did (area averaging, up to
    # one grey level of rounding): the same detections, in the dataset's own pixels
    np.testing.assert_allclose(own.uv.numpy(), (net.uv.numpy() + 0.5) / s - 0.5, atol=0.05)
    np.testing.assert_allclose(own.X.numpy(), net.X.numpy(), rtol=0, atol=1e-4)
    out = tmp_path / "p.csv"
    assert cli_main(["predict", str(tmp_path / "run"), "--data", str(ds_path), "--out", str(out)]) == 0
    rows = list(csv.DictReader(open(out)))
    assert float(rows[0]["a_error"]) == pytest.approx(float(own.error[0, 0]), rel=1e-6)


def test_predict_refuses_to_overwrite(trained, tmp_path, capsys):
    root, ds_path, run = trained
    labels = ds_path / "labels.csv"
    before = labels.read_bytes()
    for extra in ([], ["--overwrite"]):  # a file of the dataset: never
        assert cli_main(["predict", str(run), "--data", str(ds_path), "--out", str(labels), *extra]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(labels) in err and "file of the dataset" in err
    assert labels.read_bytes() == before
    out = tmp_path / "pred.csv"
    out.write_text("keep me\n")
    assert cli_main(["predict", str(run), "--data", str(ds_path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(out) in err and "--overwrite" in err
    assert out.read_text() == "keep me\n"
    assert cli_main(["predict", str(run), "--data", str(ds_path), "--out", str(out), "--overwrite"]) == 0
    assert out.read_text().startswith("a_x,")


def test_evaluate_matches_keypoints_by_name(trained, tmp_path, capsys):
    """Keypoints in another order are matched by name; other names are refused in one line naming them."""
    from s3k.data import DatasetWriter

    root, ds_path, run = trained
    ds = Dataset.open(ds_path, cache="none")
    ids = ds.frames("test")
    batch = FrameStore(ds, ids, points=True).get(np.arange(len(ids)))
    X = batch.points.double().numpy()
    K, dist, R, t = rig(32)

    def write(path, names, order):
        with DatasetWriter(path, names, CAMERAS, (32, 32), "m", calibration=(K, dist, R, t)) as w:
            for b, fid in enumerate(ids):
                w.add_frame(int(fid), "test", batch.images[b].numpy(), None, None, points3d=X[b][order])
        return path

    same = write(tmp_path / "same", KEYPOINTS, [0, 1, 2])
    shuffled = write(tmp_path / "shuffled", [KEYPOINTS[i] for i in (2, 0, 1)], [2, 0, 1])
    assert cli_main(["evaluate", str(run), "--data", str(same), "--json"]) == 0
    m_same = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert cli_main(["evaluate", str(run), "--data", str(shuffled), "--json"]) == 0
    m_shuffled = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("rms_px", "rms_px_reproj", "median_mm", "rms_mm"):
        assert m_shuffled[key] == pytest.approx(m_same[key], rel=1e-9)
    for kp in KEYPOINTS:
        assert m_shuffled["per_keypoint"][kp] == pytest.approx(m_same["per_keypoint"][kp], rel=1e-9)

    other = write(tmp_path / "other", ["a", "b", "tail"], [0, 1, 2])
    assert cli_main(["evaluate", str(run), "--data", str(other), "--json"]) == 1
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert captured.out == "" and len(err.splitlines()) == 1
    assert err.startswith("s3k evaluate: error:") and "missing c" in err and "extra tail" in err


@pytest.mark.slow  # renders a small box scene and trains two tiny models: about a minute
def test_demo_quick(tmp_path, capsys):
    pytest.importorskip("mujoco")
    assert cli_main(["demo", "--out", str(tmp_path / "demo"), "--quick", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "| labels only |" in out and "| S3K |" in out
    summary = json.loads((tmp_path / "demo" / "report" / "comparison.json").read_text())
    for name in ("labels only", "S3K"):
        assert summary[name]["rms_px"] is not None and summary[name]["median_mm"] is not None
    picture = tmp_path / "demo" / "report" / "demo.png"
    assert picture.is_file() and picture.stat().st_size > 10_000
    assert (tmp_path / "demo" / "report" / "s3k" / "metrics.json").is_file()
    # the recommended configuration, and ten of the pool's labelled frames
    data = json.loads((tmp_path / "demo" / "data" / "s3k.json").read_text())
    assert data["source"]["labelled"] == 10 and data["source"]["label_choice"] == "representative"
    assert "--preset box-fast" in summary["scale"]
    assert json.loads((tmp_path / "demo" / "s3k" / "two_pass.json").read_text())["margin"] == 0.1
    # wide rotations for the coarse pass that finds the box, narrow ones for the refining pass
    for model in ("s3k", "baseline"):
        for part, degrees in (("coarse", 180.0), ("fine", 15.0)):
            cfg = json.loads((tmp_path / "demo" / model / part / "config.json").read_text())["config"]
            assert cfg["rotation_deg"] == degrees


def test_pck_counts_misses_and_failed_triangulations():
    from s3k.base.metrics import compute_metrics

    B, C, K = 4, 2, 2
    uv = np.zeros((B, C, K, 2))
    gt_mask = np.ones((B, C, K), bool)
    X_gt = np.zeros((B, K, 3))
    X = np.zeros((B, K, 3))
    # errors of keypoint 0 in mm: 1, 4, 7, 20; keypoint 1: 3, 3, 12 and one failed triangulation
    X[:, 0, 0] = np.array([1, 4, 7, 20]) / 1000
    X[:, 1, 1] = np.array([3, 3, 12, 0]) / 1000
    valid = np.ones((B, K), bool)
    valid[3, 1] = False
    m = compute_metrics(uv, uv, uv, gt_mask, X, valid, X_gt, None, 1000.0, ["a", "b"], ["c0", "c1"])
    assert m["pck_5mm"] == pytest.approx(4 / 8) and m["pck_10mm"] == pytest.approx(5 / 8)
    assert m["per_keypoint"]["a"]["pck_5mm"] == pytest.approx(2 / 4)
    assert m["per_keypoint"]["b"]["pck_10mm"] == pytest.approx(2 / 4)
    assert m["median_mm"] == pytest.approx(np.median([1, 4, 7, 20, 3, 3, 12]))
    no3d = compute_metrics(uv, uv, uv, gt_mask, X, valid)
    assert no3d["pck_5mm"] is None


@pytest.mark.parametrize("distance,f", [(1.0, 247.0), (2.5, 400.0)])
def test_mm_per_px_at_the_workspace_centre(distance, f):
    import torch

    from s3k.base.metrics import pixel_sizes_mm
    from s3k.geometry import Cameras

    # four cameras on a circle, all looking at (0.1, -0.2, 0.3): the point their optical axes meet
    target = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    Ks, Rs, ts = [], [], []
    for i in range(4):
        a = 2 * np.pi * i / 4
        direction = torch.tensor([np.cos(a), np.sin(a), 0.5], dtype=torch.float64) / np.sqrt(1.25)
        centre = target + distance * direction
        z = (target - centre) / (target - centre).norm()
        x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        x = x / x.norm()
        R = torch.stack([x, torch.linalg.cross(z, x), z])
        Ks.append(torch.tensor([[f, 0, 47.5], [0, f, 47.5], [0, 0, 1]], dtype=torch.float64))
        Rs.append(R)
        ts.append(-R @ centre)
    cams = Cameras(K=torch.stack(Ks)[None], dist=None, R=torch.stack(Rs)[None], t=torch.stack(ts)[None])
    sizes = pixel_sizes_mm(cams, 1000.0)
    assert sizes.shape == (1, 4)
    np.testing.assert_allclose(sizes, 1000.0 * distance / f, rtol=1e-9)
    # one camera alone has no workspace centre
    assert np.isnan(pixel_sizes_mm(cams[:, :1], 1000.0)).all()


def test_evaluate_without_3d_truth_scores_against_triangulated_labels(trained, capsys, tmp_path):
    """A dataset with 2D labels only: the 3D figures are the distance to the labels triangulated from every
    labelled view (known offsets 2 and 4 mm for keypoints b and c), with intervals; the leave-one-view-out
    error is zero for exact labels and shows a label moved in one view; the report's mm panels are filled."""
    from s3k.data import DatasetWriter

    root, ds_path, run = trained
    ds = Dataset.open(ds_path, cache="none")
    test_ids = ds.frames("test")
    (batch, pred), = list(detect_store(Detector.load(run, "cpu"), FrameStore(ds, test_ids), 16))
    assert pred.valid.all()
    X_lab = pred.X.double().numpy() + np.array([[0, 0, 0], [0, 0.002, 0], [0, 0, 0.004]])  # b 2 mm, c 4 mm
    K, dist, R, t = rig(32)
    labels_only = tmp_path / "labels_only"
    with DatasetWriter(labels_only, KEYPOINTS, CAMERAS, (32, 32), "m", calibration=(K, dist, R, t)) as w:
        for b, fid in enumerate(test_ids):
            uv = project(K, R, t, X_lab[b])  # (C, K, 2)
            uv[0, 0] += [1.5, 0.0]  # keypoint a moved 1.5 px in cam0
            w.add_frame(int(fid), "test", batch.images[b].numpy(), None, uv, None)
    rep = tmp_path / "report"
    assert cli_main(["evaluate", str(run), "--data", str(labels_only), "--json", "--device", "cpu",
                     "--report", str(rep)]) == 0
    m = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert m["reference_3d"] == "triangulated labels"
    ref = m["labels_3d"]
    b3, c3 = (ref["per_keypoint"][k]["model_to_labels_3d"] for k in ("b", "c"))
    assert b3["median"] == pytest.approx(2.0, abs=1e-3) and c3["mean"] == pytest.approx(4.0, abs=1e-3)
    assert b3["ci95_mean"][0] <= b3["mean"] <= b3["ci95_mean"][1]
    assert b3["n"] == len(test_ids)
    assert m["per_keypoint"]["c"]["median_mm"] == pytest.approx(4.0, abs=1e-3)  # the mm columns are filled
    loo_b = ref["per_keypoint"]["b"]["labels_leave_one_view_out_px"]
    loo_a = ref["per_keypoint"]["a"]["labels_leave_one_view_out_px"]
    assert loo_b["median"] == pytest.approx(0.0, abs=1e-3) and loo_b["n"] == len(test_ids) * len(CAMERAS)
    assert loo_a["mean"] > 0.3
    with open(rep / "metrics.json") as f:
        assert json.load(f)["median_mm"] is not None
    assert cli_main(["evaluate", str(run), "--data", str(labels_only), "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "3D distance to the labels triangulated" in out and "95% CI" in out
