"""s3k.experiments.poses (behind benchmarks/error_by_pose.py and benchmarks/label_poses.py): the pose classes
and the collapse count on a case with known answers; the labelled frames of each choice counted by pose."""

from __future__ import annotations

import numpy as np
import pytest

from s3k.experiments.poses import by_pose, pose_classes

FLAT = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.1, 0.05, 0]])  # counter-clockwise seen from above: normal up


def test_pose_classes_and_collapse():
    down = FLAT[::-1].copy()  # the same triangle in the other order: its normal points down
    side = FLAT[:, [0, 2, 1]] + [0, 0, 0.2]  # in the x-z plane: normal horizontal
    truth = np.stack([FLAT, down, side, FLAT + 0.3])
    assert pose_classes(truth).tolist() == ["normal up", "normal down", "on a side", "normal up"]
    pred = truth + np.array([0.001, 0.0, 0.0])  # 1 mm off everywhere...
    pred[3] = truth[3].mean(axis=0)  # ...but frame 3: every keypoint at the centroid
    out = by_pose(pred, truth, mm=1000.0)
    assert out["frames"] == 4 and out["collapsed_frames"] == 1
    assert out["by_pose"]["normal up"]["collapsed_frames"] == 1
    assert out["by_pose"]["normal down"]["median_mm"] == pytest.approx(1.0)
    assert out["by_pose"]["on a side"]["rms_mm"] == pytest.approx(1.0)
    assert out["not_collapsed"]["median_mm"] == pytest.approx(1.0) and out["not_collapsed"]["n"] == 9
    centroid_err = 1000 * np.linalg.norm(truth[3] - truth[3].mean(axis=0), axis=-1)
    assert out["collapsed"]["median_mm"] == pytest.approx(np.median(centroid_err))
    assert out["collapsed"]["share_of_squared_error"] + out["not_collapsed"]["share_of_squared_error"] \
        == pytest.approx(1.0)
    assert out["all"]["pck_10mm"] == pytest.approx(9 / 12)
    # "normal down" (one frame, the triangle reversed): its keypoint frame's y (keypoint 2 to 1) runs along
    # world x, so 1 mm along x is 1 mm along y, and nothing is left once that constant is taken away
    np.testing.assert_allclose(out["by_pose"]["normal down"]["bias_mm"], [[0.0, 1.0, 0.0]] * 3, atol=1e-9)
    assert out["by_pose"]["normal down"]["median_mm_without_bias"] == pytest.approx(0.0)


def test_bias_separates_a_lean_from_scatter():
    """Keypoints pushed 2 mm along the keypoints' own normal in every frame, whatever the frame's rotation,
    plus +-1 mm of scatter along x: a bias of (0, 0, 2) mm and 1 mm left without it."""
    from s3k.experiments.poses import bias, keypoint_frames

    rng = np.random.default_rng(0)
    truth, pred = [], []
    for i in range(8):
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        X = FLAT @ R.T + rng.normal(size=3)
        axes = keypoint_frames(X[None])[0]
        truth.append(X)
        pred.append(X + 0.002 * axes[2] + (0.001 if i % 2 else -0.001) * axes[0])
    out = bias(np.array(pred), np.array(truth), mm=1000.0)
    np.testing.assert_allclose(out["bias_mm"], [[0.0, 0.0, 2.0]] * 3, atol=1e-6)
    assert out["median_mm_without_bias"] == pytest.approx(1.0)


def test_swapped_frames_count_symmetric_confusions():
    """A frame whose first two keypoints trade places is swapped; a frame off by a little, a collapsed frame
    (counted as collapsed) and a frame without a detection are not."""
    from s3k.experiments.poses import swapped_frames

    truth = np.stack([FLAT] * 4)
    pred = truth + 0.002
    pred[1, [0, 1]] = FLAT[[1, 0]]  # keypoints 0 and 1 detected on each other's corners
    pred[2] = FLAT.mean(axis=0)  # collapsed onto the centroid
    pred[3] = np.nan  # nothing detected
    assert swapped_frames(pred, truth).tolist() == [False, True, True, False]
    out = by_pose(pred, truth, mm=1000.0)
    assert out["collapsed_frames"] == 1 and out["swapped_frames"] == 1  # the collapse is not counted twice
    assert out["by_pose"]["normal up"]["swapped_frames"] == 1
    assert out["swapped"]["n"] == 3 and out["swapped"]["median_mm"] == pytest.approx(100.0)
    assert out["neither"]["n"] == 3
    # which keypoint each detection was taken for, the collapsed frame left out: frame 1's first two swap,
    # frame 3 has no detection
    assert out["nearest_true"] == [[1, 1, 0], [1, 1, 0], [0, 0, 2]]
    assert out["neither"]["median_mm"] == pytest.approx(1000 * np.sqrt(3) * 0.002)


def test_poses_on_a_side_split_by_which_way_the_first_edge_runs():
    """On a side, the edge from keypoint 0 to 1 level (a box on its long edge) or upright (on its end); a
    swap there is counted in its own row."""
    level = FLAT[:, [0, 2, 1]]  # in the x-z plane, edge 0-1 along x
    upright = FLAT[:, [2, 1, 0]]  # in the z-y plane, edge 0-1 along z
    truth = np.stack([level, level + 0.3, upright, FLAT])
    assert pose_classes(truth).tolist() == ["on a side"] * 3 + ["normal up"]
    pred = truth + 0.001
    pred[1, [0, 1]] = truth[1, [1, 0]]  # the second level frame taken the wrong way round
    edges = by_pose(pred, truth, mm=1000.0)["by_pose"]["on a side"]["by_edge"]
    assert edges["edge 0-1 level"]["frames"] == 2 and edges["edge 0-1 level"]["swapped_frames"] == 1
    assert edges["edge 0-1 upright"]["frames"] == 1 and edges["edge 0-1 upright"]["swapped_frames"] == 0
    assert edges["edge 0-1 upright"]["median_mm"] == pytest.approx(1000 * np.sqrt(3) * 0.001)


def test_pose_counts_split_the_sides_by_edge():
    from s3k.experiments.poses import pose_counts

    truth = np.stack([FLAT, FLAT[::-1], FLAT[:, [0, 2, 1]], FLAT[:, [2, 1, 0]], FLAT[:, [2, 1, 0]]])
    assert pose_counts(truth) == {"normal up": 1, "normal down": 1, "on a side, edge 0-1 level": 1,
                                  "on a side, edge 0-1 upright": 2}


def test_label_poses_counts_each_choice_of_labels_by_pose(tmp_path):
    import json

    from helpers.synthetic_rig import make_dataset

    from s3k.experiments.grid import LABEL_CHOICES
    from s3k.experiments.poses import label_poses

    pool = make_dataset(tmp_path / "pool", labelled=12, unlabelled=3, test=6)
    got = json.loads(json.dumps(label_poses([str(pool)], list(LABEL_CHOICES), labelled=4, seed=1)))
    assert got["labelled"] == 4
    (report,) = got["pools"]
    assert report["seed"] == 1
    assert sum(report["pool_poses"].values()) == 12 and sum(report["test_poses"].values()) == 6
    for choice in ("random", "coverage", "representative"):
        labels = report["labels"][choice]
        assert sum(labels.values()) == 4
        # a pose is reported without a label exactly when the test frames show it and no label does
        assert report["unlabelled_poses"][choice] == [p for p, n in report["test_poses"].items()
                                                      if n and not labels[p]]
        assert got["missing"][choice] == int(bool(report["unlabelled_poses"][choice]))
    with pytest.raises(SystemExit, match="no s3k.json"):
        label_poses([str(tmp_path / "nowhere")], list(LABEL_CHOICES), labelled=4, seed=None)
