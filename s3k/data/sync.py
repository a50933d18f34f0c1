"""Camera clock offsets from the motion of 2D keypoints: :func:`estimate_frame_offsets`.

Cameras that are not synchronized (webcams) film the same instant under different frame numbers. A camera's
*frame offset* ``N`` says that its frame ``i`` shows the instant of the first camera's frame ``i + N``
(``s3k import --frame-offsets CAM=N`` applies it).

With a calibration, two cameras that film the same instant see each keypoint on corresponding epipolar lines;
a keypoint that moved between two instants leaves its line. For each pair of cameras ``a, b`` and each lag
``d``, the pair's residual compares camera ``a``'s frame ``i`` with camera ``b``'s frame ``i + d``: the signed
angle between each keypoint's ray in one camera and the epipolar plane of its ray in the other (both ways, in
pixels of the focal lengths), less that keypoint's median over the frames (a lasting disagreement between the
views' labels is not motion), its median absolute value over every keypoint and frame. Each pair's residuals
are divided by their median over the lags, so that a pair with a poor calibration (flat residuals) weighs no
more than a good one. The offsets minimize the sum over the pairs of their residual at the lag the offsets
give them (``d = N_a - N_b``): each camera's offset against the first camera's to start, then each camera in
turn until nothing changes.

An offset other than 0 is kept (``decided``) only where the motion tells it: the camera's keypoints move
(their displacement over ``max_offset`` frames is at least twice that between consecutive frames, not label
jitter), the offset lowers the camera's summed residual by at least ``min_gain`` from offset 0, and each half
of the keypoints (every other one) prefers it to 0 by half that. Otherwise the offset is 0 and ``decided``
False: keypoints that barely move, labels too sparse in time (no two frames ``d`` apart) or a camera whose
calibration is wrong cannot tell. On clean data of a moving object the residual at the true lags is zero and
the offsets are exact. Pure computation (no I/O); :mod:`s3k.data.validate` reports it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from s3k.geometry import Cameras, pixel_rays


@dataclass
class FrameOffsets:
    """The estimate of :func:`estimate_frame_offsets`, per camera (the first is the reference).

    Attributes:
        offsets: ``(C,)`` int: camera ``c``'s frame ``i`` shows the first camera's frame ``i + offsets[c]``.
        best: ``(C,)`` int: the offset of lowest residual, kept in ``offsets`` only where ``decided``.
        decided: ``(C,)`` bool: the motion tells the offset (False: too little motion or too few samples;
            ``offsets`` is then 0).
        residual_px: ``(C,)`` median epipolar residual (px) of the camera against the others at ``offsets``.
        residual_best_px: ``(C,)`` the same at ``best``.
        gain: ``(C,)`` the fraction by which ``best`` lowers the camera's normalized residual from offset 0.
        samples: ``(C,)`` keypoint pairs the camera's residual at ``offsets`` rests on.
    """

    offsets: np.ndarray
    best: np.ndarray
    decided: np.ndarray
    residual_px: np.ndarray
    residual_best_px: np.ndarray
    gain: np.ndarray
    samples: np.ndarray


def _rays(cams: Cameras, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per camera the world ray directions ``(C, T, K, 3)`` (NaN where unlabelled) and centres ``(C, 3)``."""
    C, T, K, _ = uv.shape
    flat = torch.as_tensor(np.nan_to_num(uv).reshape(C, T * K, 2), dtype=torch.float64)
    origins, dirs = pixel_rays(cams.to(torch.float64), flat)
    d = dirs.numpy().reshape(C, T, K, 3)
    d[~np.isfinite(uv).all(-1)] = np.nan
    return d, origins[:, 0].numpy()


def _epipolar(A: np.ndarray, B: np.ndarray, k: np.ndarray, e: np.ndarray, f_a: float,
              f_b: float) -> np.ndarray:
    """Absolute symmetric epipolar residuals (px) of rays ``A``, ``B`` ``(n, 3)`` of keypoints ``k``, less
    each keypoint's median over the samples (a lasting disagreement between the views is not motion)."""
    n_a, n_b = np.cross(e, A), np.cross(e, B)
    n_a /= np.maximum(np.linalg.norm(n_a, axis=1, keepdims=True), 1e-12)
    n_b /= np.maximum(np.linalg.norm(n_b, axis=1, keepdims=True), 1e-12)
    err = 0.5 * (f_b * (n_a * B).sum(1) - f_a * (n_b * A).sum(1))  # signed: both terms share a sign
    for kp in np.unique(k):
        err[k == kp] -= np.median(err[k == kp])
    return np.abs(err)


def _pair_residuals(d_a: np.ndarray, d_b: np.ndarray, base: np.ndarray, f_a: float, f_b: float,
                    lags: np.ndarray, min_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Median symmetric epipolar residual (px) and sample count of cameras ``a, b`` at each lag ``d``
    (``a``'s frame ``i`` against ``b``'s frame ``i + d``); NaN where fewer than ``min_samples``.

    The frames a lag can pair differ from lag to lag (frames labelled far apart pair only at lag 0), and
    their residuals differ for reasons other than time (another pose, another labelling session): each lag's
    residual is scaled by the lag-0 residual of the same frames over that of all frames, so that lags are
    compared on what their frames show, not on which frames they happen to hold."""
    T, K = d_a.shape[:2]
    e = base / max(np.linalg.norm(base), 1e-12)
    keypoint = np.broadcast_to(np.arange(K), (T, K))
    same = np.isfinite(d_a).all(-1) & np.isfinite(d_b).all(-1)  # (T, K): lag 0 pairs
    all_zero = (_epipolar(d_a[same], d_b[same], keypoint[same], e, f_a, f_b)
                if same.sum() >= min_samples else None)
    out, count = np.full(len(lags), np.nan), np.zeros(len(lags), dtype=np.int64)
    for j, lag in enumerate(lags):
        lo, hi = max(0, -lag), min(T, T - lag)
        if hi <= lo:
            continue
        ok = np.zeros((T, K), dtype=bool)
        ok[lo:hi] = np.isfinite(d_a[lo:hi]).all(-1) & np.isfinite(d_b[lo + lag:hi + lag]).all(-1)
        if ok.sum() < min_samples:
            continue
        rows, kps = np.nonzero(ok)
        err = _epipolar(d_a[rows, kps], d_b[rows + lag, kps], kps, e, f_a, f_b)
        value = float(np.median(err))
        both = ok & same
        if lag != 0 and all_zero is not None and both.sum() >= min_samples:
            zero_here = float(np.median(_epipolar(d_a[both], d_b[both], keypoint[both], e, f_a, f_b)))
            value *= float(np.median(all_zero)) / max(zero_here, 1e-12)
        out[j], count[j] = value, int(ok.sum())
    return out, count


def _moving(uv: np.ndarray, m: int) -> np.ndarray:
    """``(C,)``: whether a camera's keypoints move, not only jitter: their median displacement over ``m``
    frames is at least twice that from one frame to the next (still keypoints with label noise: about the
    same)."""
    out = np.zeros(uv.shape[0], dtype=bool)
    T = uv.shape[1]
    for c in range(uv.shape[0]):
        if T > m > 0:
            steps = [np.linalg.norm(uv[c, d:] - uv[c, :-d], axis=-1) for d in (1, m)]
            if all(np.isfinite(s).any() for s in steps):
                one, far = (float(np.nanmedian(s)) for s in steps)
                out[c] = far >= 2 * one and far > 0
    return out


def _camera_costs(norm: np.ndarray, c: int, offsets: np.ndarray, m: int) -> np.ndarray:
    """The sum over the other cameras ``j`` of the normalized residual of pair ``(c, j)`` at the lag
    ``x - offsets[j]``, for each candidate offset ``x`` of camera ``c`` in ``[-m, m]``."""
    C = norm.shape[0]
    total = np.zeros(2 * m + 1)
    for j in range(C):
        if j != c:
            total += norm[c, j, np.arange(-m, m + 1) - offsets[j] + 2 * m]
    return total


def estimate_frame_offsets(uv: np.ndarray, cams: Cameras, max_offset: int = 10, *, min_gain: float = 0.08,
                           min_samples: int = 20) -> FrameOffsets:
    """Each camera's frame offset from the keypoints' motion (see the module docstring).

    Args:
        uv: ``(C, T, K, 2)`` pixels of consecutive frames ``0 .. T-1`` of each camera's own video, NaN where
            unlabelled.
        cams: ``(C,)`` the calibration of those pixels.
        max_offset: offsets are searched in ``[-max_offset, max_offset]`` frames of the first camera's.
        min_gain: the fraction by which an offset must lower the camera's residual from offset 0 to be kept.
        min_samples: keypoint pairs a pair of cameras needs at a lag for its residual to count.
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 4 or uv.shape[-1] != 2 or uv.shape[0] != cams.shape[0]:
        raise ValueError(f"uv must be (C, T, K, 2) with C = {cams.shape[0]} cameras, got {uv.shape}")
    C, K, m = uv.shape[0], uv.shape[2], int(max_offset)
    dirs, centres = _rays(cams, uv)
    focal = np.abs(cams.K[:, 0, 0].detach().cpu().numpy())
    best, gain, raw, count, _ = _solve(dirs, centres, focal, m, min_samples)
    # Each half of the keypoints (its label noise its own, the motion shared) must prefer the offset to 0
    # too: noise alone makes some lag the lowest, but not the same lag in both halves.
    half_gain = np.ones(C)
    for part in (slice(0, None, 2), slice(1, None, 2)) if K > 1 else ():
        norm = _solve(dirs[:, :, part], centres, focal, m, min_samples)[4]
        for c in range(1, C):
            costs = _camera_costs(norm, c, best, m)
            half_gain[c] = min(half_gain[c], 1.0 - costs[m + best[c]] / costs[m] if costs[m] > 0 else 0.0)
    lags = np.arange(-2 * m, 2 * m + 1)
    sampled = np.array([bool((count[c].sum(0)[lags != 0] > 0).any()) for c in range(C)])
    decided = sampled & _moving(uv, m) & ((best == 0) | ((gain >= min_gain) & (half_gain >= min_gain / 2)))
    decided[0] = True
    offsets = np.where(decided, best, 0)
    residual, residual_best, samples = np.zeros(C), np.zeros(C), np.zeros(C, dtype=np.int64)
    for c in range(C):
        for target, out in ((offsets, residual), (best, residual_best)):
            at = [raw[c, j, target[c] - target[j] + 2 * m] for j in range(C) if j != c]
            out[c] = float(np.nanmedian(at)) if np.isfinite(at).any() else np.nan
        samples[c] = int(sum(count[c, j, offsets[c] - offsets[j] + 2 * m] for j in range(C) if j != c))
    return FrameOffsets(offsets, best, decided, residual, residual_best, gain, samples)


def _solve(dirs: np.ndarray, centres: np.ndarray, focal: np.ndarray, m: int,
           min_samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The offsets of lowest residual ``(C,)``, each one's gain over offset 0 ``(C,)``, and the pairs' raw
    residuals (px), sample counts and normalized residuals ``(C, C, 4m + 1)`` over the lags ``-2m .. 2m``."""
    C = dirs.shape[0]
    lags = np.arange(-2 * m, 2 * m + 1)
    raw = np.full((C, C, len(lags)), np.nan)
    count = np.zeros((C, C, len(lags)), dtype=np.int64)
    for a in range(C):
        for b in range(a + 1, C):
            raw[a, b], count[a, b] = _pair_residuals(dirs[a], dirs[b], centres[b] - centres[a], focal[a],
                                                     focal[b], lags, min_samples)
            raw[b, a], count[b, a] = raw[a, b, ::-1], count[a, b, ::-1]
    finite = np.isfinite(raw)
    scale = np.ones((C, C, 1))
    for a, b in zip(*np.nonzero(finite.any(axis=2))):
        scale[a, b, 0] = max(float(np.median(raw[a, b][finite[a, b]])), 1e-12)
    norm = np.where(finite, raw / scale, 1.0)  # a lag without samples is neutral
    best = np.zeros(C, dtype=np.int64)
    for c in range(1, C):
        best[c] = int(np.argmin(norm[c, 0, m:3 * m + 1])) - m  # against the first camera alone
    for _ in range(4 * C):  # each camera in turn against all the others, until nothing changes
        before = best.copy()
        for c in range(1, C):
            costs = _camera_costs(norm, c, best, m)
            best[c] = int(np.argmin(costs)) - m if costs.min() < costs[m + best[c]] else best[c]
        if np.array_equal(before, best):
            break
    gain = np.zeros(C)
    for c in range(1, C):
        costs = _camera_costs(norm, c, best, m)
        gain[c] = 1.0 - costs[m + best[c]] / costs[m] if costs[m] > 0 else 0.0
    return best, gain, raw, count, norm
