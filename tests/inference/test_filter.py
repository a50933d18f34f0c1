"""The filter over time of 3D tracks (s3k.inference.kalman, constraints, track_filter) on synthetic
trajectories with known noise."""

from __future__ import annotations

import numpy as np
import pytest

from s3k.inference.constraints import hold_limbs, hold_to_layout, limb_reference
from s3k.inference.kalman import CausalFilter, FilterSettings, smooth
from s3k.inference.track_filter import doubt, measurement_std

T, K, NOISE = 200, 3, 2.0


def trajectory(T: int = T, K: int = K) -> np.ndarray:
    """(T, K, 3) smooth motion in mm: each keypoint on its own slow curve."""
    t = np.arange(T, dtype=np.float64)[:, None]
    k = np.arange(K, dtype=np.float64)[None]
    return np.stack([40 * np.sin(0.04 * t + k), 25 * np.cos(0.03 * t + 2 * k), 0.2 * t + 10 * k], axis=-1)


def noisy(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    truth = trajectory()
    rng = np.random.default_rng(seed)
    return truth, truth + rng.normal(0, NOISE, truth.shape), np.full((T, K), NOISE)


def rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(((a - b) ** 2).sum(-1))))


def test_smoother_lowers_the_rms_error_of_a_noisy_track():
    truth, X, std = noisy()
    out = smooth(X, std, FilterSettings())
    assert out.valid.all() and not out.rejected.any()
    assert rms(out.X, truth) < 0.4 * rms(X, truth)
    # the noise it fits makes the measurements about as noisy as they are
    assert np.all((out.s >= 0.5) & (out.s <= 2))


@pytest.mark.parametrize("model", ["velocity", "acceleration"])
def test_an_injected_jump_is_rejected_and_the_point_stays_on_the_track(model):
    truth, X, std = noisy(1)
    X[80, 1] += [60.0, -40.0, 30.0]  # 30 noise deviations away
    out = smooth(X, std, FilterSettings(model=model))
    assert out.rejected[80, 1] and out.rejected.sum() <= 3  # chance rejects one in a thousand at 4 sigma
    assert out.valid[80, 1] and not out.measured[80, 1]
    assert np.linalg.norm(out.X[80, 1] - truth[80, 1]) < 2 * NOISE
    # without the gate the jump pulls the track
    free = smooth(X, std, FilterSettings(model=model, gate=0, process_noise=float(out.q[1]),
                                         noise_scale=float(out.s[1])))
    assert np.linalg.norm(free.X[80, 1] - truth[80, 1]) > 2 * np.linalg.norm(out.X[80, 1] - truth[80, 1])


def test_a_missing_point_is_bridged_and_a_long_gap_is_not():
    truth, X, std = noisy(2)
    X[50:54, 0] = np.nan  # 4 frames: bridged
    X[120:150, 2] = np.nan  # 30 frames > max_gap: left empty
    out = smooth(X, std, FilterSettings(max_gap=10))
    assert out.valid[50:54, 0].all() and out.bridged[50:54, 0].all()
    assert np.linalg.norm(out.X[50:54, 0] - truth[50:54, 0], axis=-1).max() < 3 * NOISE
    assert not out.valid[120:150, 2].any() and np.isnan(out.X[120:150, 2]).all()
    assert out.valid[150:, 2].all()  # it starts again at the next measurement


def test_the_causal_filter_uses_no_future_sample():
    truth, X, std = noisy(3)
    other = X.copy()
    other[120:] += np.random.default_rng(9).normal(0, 30, other[120:].shape)  # another future
    other[130, 0] = np.nan
    outs = []
    for track in (X, other):
        f = CausalFilter(K, FilterSettings())
        outs.append(np.stack([f(track[t], std[t])[0] for t in range(T)]))
    np.testing.assert_array_equal(outs[0][:120], outs[1][:120])
    assert not np.array_equal(outs[0][120:], outs[1][120:])
    # and it lowers the error, with no delay: the truth one frame later or earlier fits it worse
    a = outs[0][40:-2]
    assert rms(a, truth[40:-2]) < 0.75 * rms(X[40:-2], truth[40:-2])
    assert rms(a, truth[40:-2]) < min(rms(a, truth[39:-3]), rms(a, truth[41:-1]))


def test_a_rigid_layout_pulls_each_frame_towards_the_shape():
    shape = np.array([[0.0, 0, 0], [100, 0, 0], [0, 60, 0], [0, 0, 40]])
    rng = np.random.default_rng(4)
    angles = rng.uniform(0, 2 * np.pi, 50)
    R = np.stack([np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
                  for a in angles])
    truth = shape[None] @ R.transpose(0, 2, 1) + rng.normal(0, 100, (50, 1, 3))
    X = truth + rng.normal(0, 3.0, truth.shape)
    var = np.full((50, 4), 9.0)
    out, var2, std = hold_to_layout(X, var, np.ones((50, 4), bool), shape)
    assert rms(out, truth) < 0.8 * rms(X, truth) and np.all(var2 < var) and std > 0
    # the mirror image of the shape fits as well: a mirrored object keeps its handedness
    mirrored = truth * np.array([1.0, 1.0, -1.0])
    out_m, _, _ = hold_to_layout(mirrored, var, np.ones((50, 4), bool), shape, std=1.0)
    assert rms(out_m, mirrored) < 1.0


def test_limb_lengths_are_held_near_their_median_with_the_doubtful_point_moving_most():
    rng = np.random.default_rng(5)
    a = rng.normal(0, 50, (100, 3))
    b = a + np.array([30.0, 0, 0])
    X = np.stack([a, b], axis=1) + rng.normal(0, 1.0, (100, 2, 3))
    X[10, 1] += [12.0, 0, 0]  # a limb 12 mm too long, its far end placed with little confidence
    var = np.ones((100, 2))
    var[10, 1] = 25.0
    L, spread = limb_reference(X, [(0, 1)])
    assert abs(L[0] - 30) < 1 and spread[0] < 3
    out = hold_limbs(X, var, np.ones((100, 2), bool), [(0, 1)], L, spread)
    before = np.linalg.norm(X[:, 0] - X[:, 1], axis=-1)
    after = np.linalg.norm(out[:, 0] - out[:, 1], axis=-1)
    assert np.std(after - 30) < np.std(before - 30)
    assert abs(after[10] - 30) < 2
    assert np.linalg.norm(out[10, 1] - X[10, 1]) > 10 * np.linalg.norm(out[10, 0] - X[10, 0])


def test_measurement_noise_grows_with_residual_and_shrinks_with_confidence():
    cams = {"K": np.tile(np.array([[500.0, 0, 0], [0, 500, 0], [0, 0, 1]]), (2, 1, 1)),
            "R": np.tile(np.eye(3), (2, 1, 1)), "t": np.array([[0, 0, 1000.0], [0, 0, 2000]])}
    X = np.zeros((3, 1, 3))
    used = np.ones((3, 2, 1), bool)
    error, score = np.array([[1.0], [4.0], [1.0]]), np.array([[0.9], [0.9], [0.2]])
    std = measurement_std(X, cams, used, error, score, 1.0)
    assert std[1, 0] > 2.5 * std[0, 0] and std[2, 0] > 2 * std[0, 0]
    # one pixel at 1.5 m (mean depth) and f = 500 px is 3 mm; sqrt(2) px of noise at confidence 0.9, 2 views
    np.testing.assert_allclose(std[0, 0], 3.0 * np.sqrt(2) / np.sqrt(0.9), rtol=1e-9)


def test_doubt_ranks_a_rejected_jump_a_large_residual_and_a_missing_point_first():
    T, C, K = 6, 3, 2
    w = np.full((T, C, K), 0.9)
    r = np.ones((T, C, K))
    valid = np.ones((T, K), bool)
    rejected = np.zeros((T, K), bool)
    r[2, 1, 0] = 15.0
    rejected[4, 1] = True
    valid[5, 0] = False
    w[1] = 0.3
    d = doubt(w, r, valid, rejected)["doubt"]
    order = list(np.argsort(-d))
    assert order[0] == 5 and set(order[1:3]) == {2, 4} and order[3] == 1


def test_the_benchmarks_delay_finds_a_lag_of_one_frame():
    from s3k.experiments.track_filter import delay, jitter

    truth = trajectory()
    lagged = np.concatenate([truth[:1], truth[:-1]])  # each frame shows the one before
    assert delay(lagged, truth)[0] == 1 and delay(truth, truth)[0] == 0
    assert jitter(truth) < jitter(truth + np.random.default_rng(0).normal(0, 1, truth.shape))


def test_paired_difference_cancels_the_frames_shared_difficulty():
    from s3k.experiments.track_filter import paired_difference

    rng = np.random.default_rng(0)
    hard = rng.gamma(2.0, 2.0, (60, 1)) * np.ones((60, 5))  # frames of very different difficulty
    a = hard + rng.normal(0, 0.01, hard.shape)
    b = a + 0.05  # every point 0.05 further
    b[3, 2] = np.nan  # a point missing in one is left out of both
    d = paired_difference(a, b)
    assert d["median"] == pytest.approx(0.05, abs=0.02) and d["frames"] == 60
    assert 0 < d["median_ci95"][0] <= d["median_ci95"][1] < 0.1  # the spread of frames cancels
    assert d["p90"] == pytest.approx(0.05, abs=0.02) and 0 < d["p90_ci95"][0]
    same = paired_difference(a, a + rng.normal(0, 0.01, a.shape))
    assert same["median_ci95"][0] < 0 < same["median_ci95"][1]
    p80 = np.percentile(a, 80)
    tail = np.where(a > p80, p80 + (a - p80) * 0.5, a)  # only the largest errors shrink
    d = paired_difference(a, tail)
    assert d["p90_ci95"][1] < 0 and d["rms_ci95"][1] < 0 and d["median"] == pytest.approx(0, abs=1e-9)
