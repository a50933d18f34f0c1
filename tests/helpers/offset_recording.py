"""Synthetic recordings of points moving smoothly in 3D filmed by cameras whose clocks differ: the 2D points
``s3k.data.sync`` estimates the cameras' frame offsets from."""

from __future__ import annotations

import numpy as np
import torch

from helpers.charuco import look_at
from s3k.geometry import Cameras, project

W, H = 640, 480


def rig(n: int = 4, dist: float = 0.0) -> Cameras:
    """``n`` cameras around the origin at 600 mm, looking at it, from different heights."""
    Rs, ts = zip(*(look_at(np.array([np.cos(a), np.sin(a), 0.3 + 0.2 * i]) * 600.0)
                   for i, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3)))
    K = np.array([[500.0, 0, (W - 1) / 2], [0, 500.0, (H - 1) / 2], [0, 0, 1]])
    d = np.array([dist, dist / 4, 0, 0, 0])
    return Cameras.from_numpy(np.stack([K] * n), np.stack([d] * n), np.stack(Rs), np.stack(ts),
                              dtype=torch.float64)


def trajectory(n_instants: int, n_points: int, seed: int) -> np.ndarray:
    """``(n_instants, n_points, 3)`` mm: each point a sum of slow random sines (smooth, no repeat)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_instants)[:, None, None]
    amp = rng.uniform(10, 40, (1, n_points, 3, 3))
    freq = rng.uniform(0.01, 0.06, (1, n_points, 3, 3))
    phase = rng.uniform(0, 2 * np.pi, (1, n_points, 3, 3))
    start = rng.uniform(-30, 30, (n_points, 3))
    return (amp * np.sin(2 * np.pi * freq * t[..., None] + phase)).sum(-1) + start


def recording(cams: Cameras, offsets: list[int], n_frames: int = 90, n_points: int = 6, seed: int = 0,
              noise: float = 0.0, missing: float = 0.0) -> np.ndarray:
    """``(C, n_frames, K, 2)``: camera ``c``'s frame ``i`` shows the instant ``i + offsets[c] - min``."""
    lo = min(offsets)
    X = trajectory(n_frames + max(offsets) - lo, n_points, seed)
    rng = np.random.default_rng(seed + 1)
    out = []
    for c, off in enumerate(offsets):
        pts = torch.as_tensor(X[off - lo:off - lo + n_frames].reshape(-1, 3))
        uv = project(cams[c], pts)[0].numpy().reshape(n_frames, n_points, 2)
        uv = uv + rng.normal(0, noise, uv.shape) if noise else uv
        uv[rng.random(uv.shape[:2]) < missing] = np.nan
        out.append(uv)
    return np.stack(out)
