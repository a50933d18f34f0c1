"""The click count of docs/labelling.md (:mod:`s3k.experiments.label_clicks`, behind
``benchmarks/label_clicks.py``) on a small generated dataset: the simulated labeller's ways of working do
what they say through the app's API."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.label_data import make_label_dataset
from helpers.synthetic_rig import CAMERAS, KEYPOINTS

pytest.importorskip("fastapi")

from s3k.experiments.label_clicks import run_way  # noqa: E402


@pytest.fixture
def truth(tmp_path):
    t = make_label_dataset(tmp_path / "ds", size=96)
    frames = list(range(4, 7))
    uv = np.stack([t.uv(f) for f in range(7)])
    visible = np.ones(uv.shape[:3], bool)
    visible[5, 1, 2] = False  # keypoint c hidden in cam1 in frame 5
    return t.path, frames, {"frames": np.arange(7), "uv": uv, "visible": visible, "points": t.points,
                            "cameras": CAMERAS, "keypoints": KEYPOINTS, "size": (96, 96), "units": "m"}


def test_exact_clicks_need_two_views_per_keypoint(truth):
    data, frames, t = truth
    every = run_way("every_view", data, t, frames, None, noise=0.0, tol=1.5, seed=0)
    reproj = run_way("reprojection", data, t, frames, None, noise=0.0, tol=1.5, seed=0)
    assert every["clicks_total"] == int(t["visible"][frames].sum()) == 3 * 12 - 1
    assert reproj["clicks_total"] == 3 * 3 * 2  # exact clicks reproject exactly: no correction
    assert every["max_3d_error_mm"] < 1e-3 and reproj["max_3d_error_mm"] < 1e-3
    assert (data / "labels.csv").exists() is False  # the dataset itself is not changed


def test_noisy_clicks_are_corrected_until_every_view_is_close(truth):
    data, frames, t = truth
    reproj = run_way("reprojection", data, t, frames, None, noise=1.0, tol=1.0, seed=1)
    assert 3 * 3 * 2 <= reproj["clicks_total"] <= 3 * 12 - 1
    assert reproj["untriangulated"] == 0 and reproj["median_3d_error_mm"] < 5.0


def test_suggestions_are_accepted_only_where_right(truth, tmp_path, monkeypatch):
    from helpers.label_data import save_label_run

    from s3k.label.suggest import Suggestions

    data, frames, t = truth
    run = save_label_run(tmp_path / "run")
    # an untrained run's suggestions are nowhere near: every keypoint is labelled by reprojection instead
    untrained = run_way("suggestions", data, t, frames, run, noise=0.0, tol=1.5, seed=0)
    assert untrained["keypoints_accepted"] == 0 and untrained["clicks_total"] == 3 * 3 * 2

    def perfect(self, frame, cameras):  # suggestions at the true projections
        return {kp: {cam: {"u": float(t["uv"][frame, c, k, 0]), "v": float(t["uv"][frame, c, k, 1]),
                           "weight": 1.0, "residual": 0.0} for c, cam in enumerate(cameras)}
                for k, kp in enumerate(KEYPOINTS)}

    monkeypatch.setattr(Suggestions, "suggestion", perfect)
    right = run_way("suggestions", data, t, frames, run, noise=0.0, tol=1.5, seed=0)
    assert right["keypoints_accepted"] == 9 and right["clicks_total"] == 9
    assert right["suggestion_median_px"] == 0.0 and right["max_3d_error_mm"] < 1e-3
