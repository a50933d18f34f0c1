"""The calibrated confidence (s3k.readout.confidence, docs/method.md#confidence): the monotone fit, the map,
the read-out's view selection on it, and a short run whose raw weights are far below the documented 0.5 while
its detections are right."""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math

import numpy as np
import pytest
import torch
from helpers.synthetic_rig import make_dataset

from s3k import cli
from s3k.config import TrainConfig
from s3k.data import Dataset
from s3k.detector import Detector, OnePassDetector
from s3k.geometry import Cameras
from s3k.inference.evaluate import evaluate_run
from s3k.readout import ConfidenceMap, ReadoutConfig, fit_confidence, read_out, reliability
from s3k.readout.confidence import pool_adjacent_violators
from s3k.train import train

# ---------------------------------------------------------------------------------------------------------
# the monotone fit


def _brute_isotonic(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The weighted least-squares non-decreasing fit by trying every partition into pooled runs."""
    n = len(values)
    best, best_cost = None, np.inf
    for cuts in itertools.product([False, True], repeat=n - 1):
        edges = [0, *[i + 1 for i, c in enumerate(cuts) if c], n]
        fit = np.concatenate([np.full(b - a, np.average(values[a:b], weights=counts[a:b]))
                              for a, b in zip(edges[:-1], edges[1:])])
        if (np.diff(fit) >= -1e-12).all():
            cost = float((counts * (fit - values) ** 2).sum())
            if cost < best_cost:
                best, best_cost = fit, cost
    assert best is not None
    return best


def test_pool_adjacent_violators_is_the_least_squares_monotone_fit():
    rng = np.random.default_rng(0)
    for _ in range(30):
        n = int(rng.integers(1, 8))
        values, counts = rng.uniform(size=n), rng.integers(1, 5, size=n).astype(float)
        fit = pool_adjacent_violators(values, counts)
        np.testing.assert_allclose(fit, _brute_isotonic(values, counts), atol=1e-12)
        assert (np.diff(fit) >= 0).all()
        assert (fit * counts).sum() == pytest.approx((values * counts).sum())  # pooling keeps the mass
    assert pool_adjacent_violators(np.array([0.1, 0.5, 0.3, 0.9]), np.ones(4)).tolist() == \
        pytest.approx([0.1, 0.4, 0.4, 0.9])
    with pytest.raises(ValueError, match="values and counts"):
        pool_adjacent_violators(np.ones(3), np.ones(2))


def test_the_fit_follows_the_share_of_right_views_and_is_monotone():
    rng = np.random.default_rng(1)
    w = rng.uniform(0.04, 0.1, 2000)  # a short run's weights: all far below 0.5
    truth = np.clip((w - 0.04) / 0.06, 0, 1)  # the chance a view of weight w is right
    right = rng.uniform(size=len(w)) < truth
    fitted = fit_confidence(w, right, 6.0)
    assert fitted is not None and fitted.views == 2000 and fitted.within_px == 6.0
    assert (np.diff(fitted.weights) > 0).all() and (np.diff(fitted.confidence) >= 0).all()
    grid = torch.linspace(0.045, 0.095, 11, dtype=torch.float64)
    np.testing.assert_allclose(fitted(grid).numpy(), ((grid - 0.04) / 0.06).numpy(), atol=0.1)
    # beyond the ends: the end values, never 0 or 1
    ends = fitted(torch.tensor([0.0, 1.0], dtype=torch.float64)).tolist()
    assert ends == [fitted.confidence[0], fitted.confidence[-1]] and 0 < ends[0] < ends[1] < 1


def test_a_small_validation_set_gives_a_coarse_map_and_too_few_views_none():
    rng = np.random.default_rng(2)
    w = rng.uniform(0.0, 1.0, 30)
    right = w > 0.5  # perfectly separated, but 30 views hold one step of 20 at the least
    fitted = fit_confidence(w, right, 4.0, min_count=20)
    assert fitted is not None and len(fitted.weights) == 1  # one step: one confidence for every view
    assert fitted.confidence[0] == pytest.approx((right.sum() + 1) / (30 + 2))  # one pseudo-view each way
    assert fit_confidence(w[:19], right[:19], 4.0, min_count=20) is None
    # every view right: the confidence stays below 1, every view wrong: above 0
    assert 0.9 < fit_confidence(w, np.ones(30, bool), 4.0).confidence[0] < 1  # type: ignore[union-attr]
    assert 0 < fit_confidence(w, np.zeros(30, bool), 4.0).confidence[0] < 0.1  # type: ignore[union-attr]
    # NaN weights do not count; equal weights are never split between two steps
    tied = fit_confidence(np.r_[np.full(25, 0.3), np.full(25, 0.6), np.nan], np.r_[np.zeros(25, bool),
                          np.ones(25, bool), True], 4.0, min_count=20)
    assert tied is not None and tied.weights == pytest.approx((0.3, 0.6)) and tied.views == 50


def test_the_map_interpolates_keeps_nan_and_round_trips():
    m = ConfidenceMap((0.1, 0.3), (0.2, 0.8), 6.0, 40)
    w = torch.tensor([0.0, 0.1, 0.2, 0.3, 0.9, float("nan")], dtype=torch.float64)
    out = m(w)
    np.testing.assert_allclose(out[:5].numpy(), [0.2, 0.2, 0.5, 0.8, 0.8])
    assert torch.isnan(out[5]) and out.dtype == torch.float64
    assert m(w.float()).dtype == torch.float32
    assert ConfidenceMap.from_dict(m.to_dict()) == m
    for bad in (((0.3, 0.1), (0.2, 0.8)), ((0.1, 0.3), (0.8, 0.2)), ((0.1,), (0.2, 0.3)), ((0.1,), (1.5,))):
        with pytest.raises(ValueError, match="confidence map"):
            ConfidenceMap(bad[0], bad[1], 6.0)


def test_reliability_bins_views_by_confidence():
    conf = np.array([0.1, 0.15, 0.5, 0.55, 0.95, 1.0, np.nan])
    right = np.array([False, True, True, True, True, True, True])
    rows = reliability(conf, right, (0.0, 0.2, 0.6, 1.0))
    assert [r["views"] for r in rows] == [2, 2, 2]
    assert rows[0]["within"] == 0.5 and rows[0]["confidence"] == pytest.approx(0.125)
    assert rows[2]["within"] == 1.0  # the last bin holds 1.0
    assert reliability(np.array([0.1]), np.array([True]), (0.0, 0.5, 1.0))[1]["within"] is None


# ---------------------------------------------------------------------------------------------------------
# the read-out: selection on the confidence, triangulation on the raw weight


def _three_views():
    """Logits of one frame seen by 3 cameras, 1 keypoint, sharp peaks a little apart (so that the weights
    move the point), and the cameras."""
    K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 15.5], [0, 0, 1]], dtype=torch.float64).expand(3, 3, 3)
    R = torch.stack([torch.tensor([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]],
                                  dtype=torch.float64) for a in (0.0, 0.5, -0.5)])
    t = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64).expand(3, 3)
    cams = Cameras(K.clone(), None, R, t.clone())
    yy, xx = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    peaks = [(7.5, 7.5), (8.0, 8.5), (7.0, 8.2)]
    logits = torch.stack([-((xx - u) ** 2 + (yy - v) ** 2) / 2 for u, v in peaks])
    return logits[None, :, None], cams


def test_the_selection_compares_the_calibrated_confidence_and_the_points_keep_the_raw_weights(device):
    logits, cams = _three_views()
    logits, cams = logits.to(device), cams.to(device=device)
    weights = torch.tensor([0.06, 0.05, 0.03], dtype=torch.float64, device=device)[None, :, None]
    plain = read_out(logits, cams, 2, 2.0, weights=weights)
    assert torch.equal(plain.confidence, plain.weights)  # no calibration: the raw weight
    raw = read_out(logits, cams, 2, 2.0, config=ReadoutConfig(min_weight=0.5), weights=weights)
    assert not raw.valid.any()  # the raw weights: no view passes 0.5
    m = ConfidenceMap((0.03, 0.06), (0.3, 0.9), 4.0, 100)
    config = ReadoutConfig(min_weight=0.5, confidence=m)
    calibrated = read_out(logits, cams, 2, 2.0, config=config, weights=weights)
    np.testing.assert_allclose(calibrated.confidence[0, :, 0].cpu().numpy(), [0.9, 0.7, 0.3])
    torch.testing.assert_close(calibrated.weights, weights)  # the paper's weights, unchanged
    assert calibrated.used[0, :, 0].tolist() == [True, True, False] and calibrated.valid.all()
    # the point is the raw-weighted triangulation of the two views used, not a confidence-weighted one
    two = read_out(logits[:, :2], cams[:2], 2, 2.0, weights=weights[:, :2])
    torch.testing.assert_close(calibrated.X, two.X)
    by_confidence = read_out(logits[:, :2], cams[:2], 2, 2.0, weights=calibrated.confidence[:, :2])
    assert not torch.allclose(by_confidence.X, two.X)
    # threshold 0 keeps every view, as without a calibration
    every = read_out(logits, cams, 2, 2.0, config=ReadoutConfig(confidence=m), weights=weights)
    assert every.used.all() and torch.allclose(every.X, plain.X)


# ---------------------------------------------------------------------------------------------------------
# a short run: raw weights far below 0.5, detections right


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """150 labels-only steps on 64 px views of the dots (fixed seeds): the detections are mostly within two
    target widths, the heatmaps still wide (raw weights near 0.05); and 12 other frames of the same rig."""
    tmp = tmp_path_factory.mktemp("short")
    data = make_dataset(tmp / "ds", size=64, labelled=6, unlabelled=0, test=8, seed=3)
    other = make_dataset(tmp / "other", size=64, labelled=0, unlabelled=0, test=12, seed=5)
    cfg = TrainConfig.from_flat(steps=150, batch_labelled=4, channels=(8, 16, 16), res_blocks=1, unsup=False,
                                augment=False, val_every=0, val_frames=8, checkpoint_every=150,
                                progress=False, threads=1)
    result = train(data, tmp / "run", cfg)
    return tmp / "run", other, result


def test_a_short_run_is_calibrated_so_the_documented_threshold_keeps_its_right_views(short_run):
    run, other, result = short_run
    assert result.meta.calibration is not None and result.meta.calibration["views"] == 8 * 4 * 3
    assert result.meta.calibration["within_px"] == pytest.approx(2 * result.meta.sigma)
    detector = Detector.load(run, "cpu")
    assert detector.meta.calibration == result.meta.calibration  # recorded in model.pt
    ds = Dataset.open(other)
    ids = ds.frames("test")
    images, cams = ds.images(ids), ds.calibration(ids)
    out = detector(images, cams)
    assert float(out.weights.median()) < 0.15  # far below the documented 0.5
    # the same detector without its calibration (today's behaviour for runs trained before it)
    raw = OnePassDetector.from_run(run, torch.device("cpu"))
    raw.readout = dataclasses.replace(raw.readout, confidence=None)
    assert float(raw(images, cams, min_weight=0.5).valid.float().mean()) < 0.2
    kept = detector(images, cams, min_weight=0.5)
    assert float(kept.valid.float().mean()) > 0.6  # most points valid with calibration
    assert float(kept.used.float().mean()) > 0.6
    torch.testing.assert_close(kept.weights, out.weights)


def test_the_calibrated_confidence_tracks_the_share_within_the_distance(short_run):
    run, other, _ = short_run
    report = evaluate_run(run, other, "test", "cpu")["confidence"]
    assert report["calibrated"] and report["within_px"] == pytest.approx(2 * 3.0)  # 2 sigma, sigma 3 px
    assert report["views"] == 12 * 4 * 3 and report["within"] > 0.5  # the detections are mostly right
    bins = [b for b in report["bins"] if b["views"] >= 20]
    assert sum(b["views"] for b in bins) > 0.8 * report["views"]
    for b in bins:
        assert abs(b["confidence"] - b["within"]) < 0.2, report["bins"]
    mean = sum(b["confidence"] * b["views"] for b in report["bins"] if b["views"]) / report["views"]
    assert abs(mean - report["within"]) < 0.1


def test_evaluate_prints_the_reliability_table(short_run, capsys):
    run, other, _ = short_run
    assert cli.main(["evaluate", str(run), "--data", str(other)]) == 0
    out = capsys.readouterr().out
    assert "confidence calibrated on 96 validation views; right: within 6 network-input px" in out
    assert "share within" in out and out.count("\n0.") >= 5


def test_a_run_without_truth_on_its_validation_frames_is_not_calibrated(tmp_path, caplog):
    data = make_dataset(tmp_path / "ds", size=32, labelled=4, unlabelled=2, test=0)
    cfg = TrainConfig.from_flat(steps=1, batch_labelled=2, batch_unlabelled=2, channels=(8, 8), res_blocks=1,
                                val_every=0, val_frames=2, val_split="unlabelled", progress=False, threads=1)
    # the unlabelled frames carry 3D points: strip them so that nothing tells the truth
    (data / "points3d.csv").unlink()
    with caplog.at_level(logging.INFO):
        result = train(data, tmp_path / "run", cfg)
    assert result.meta.calibration is None
    assert "too few views with a truth to calibrate the confidence" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="s3k"):
        detector = Detector.load(tmp_path / "run", "cpu")
        ds = Dataset.open(data)
        ids = ds.frames("labelled")[:1]
        detector(ds.images(ids), ds.calibration(ids))
        assert "has no confidence calibration" not in caplog.text  # no threshold asked for: nothing to say
        for _ in range(2):
            detector(ds.images(ids), ds.calibration(ids), min_weight=0.5)
    assert caplog.text.count("has no confidence calibration") == 1  # said once
