"""Tiny synthetic recordings for ``s3k import``: a calibrated 3-camera rig (anipose TOML, mm), ffv1 videos of
distinct frames, and DeepLabCut CSVs of the projected 3D points; another ``turn`` moves the cameras (another
day's recording)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

CAMS = ["north", "east", "south"]
KEYPOINTS = ["head", "body", "tail"]
W_IMG, H_IMG = 64, 48


def _look_at(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = -np.asarray(centre, float) / np.linalg.norm(centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def write_recording(root: Path, turn: float = 0.0, n_frames: int = 12, seed: int = 0,
                    cameras: list[str] | None = None) -> dict:
    """Write ``calibration.toml``, ``<cam>.mkv`` and ``CollectedData_<cam>.csv`` (every frame labelled) to
    ``root``; returns ``{"root", "X" (F, K, 3), "uv" (F, C, K, 2), "frames" {cam: [images]}}``."""
    from s3k.data.formats import anipose
    from s3k.data.rig import Rig
    from s3k.data.video import write_video
    from s3k.geometry import Cameras

    cameras = cameras or CAMS
    root.mkdir(parents=True, exist_ok=True)
    Rs, ts = [], []
    for c in range(len(cameras)):
        angle = 2 * np.pi * c / len(cameras) + turn
        R, t = _look_at(np.array([np.cos(angle), np.sin(angle), 0.5]) * 400.0)
        Rs.append(R)
        ts.append(t)
    K = np.array([[70.0, 0, (W_IMG - 1) / 2], [0, 70.0, (H_IMG - 1) / 2], [0, 0, 1]])
    C = len(cameras)
    cams = Cameras.from_numpy(np.stack([K] * C), np.zeros((C, 5)), np.stack(Rs), np.stack(ts),
                              dtype=torch.float64)
    anipose.write_anipose_calibration(root / "calibration.toml",
                                      Rig(list(cameras), cams, np.array([[W_IMG, H_IMG]] * C), "mm", {}))
    rng = np.random.default_rng(seed)
    X = rng.uniform(-40, 40, (n_frames, len(KEYPOINTS), 3))
    uv = np.stack([cv2.projectPoints(X.reshape(-1, 3), cv2.Rodrigues(R)[0], t, K, None)[0]
                   .reshape(n_frames, -1, 2) for R, t in zip(Rs, ts)], axis=1)
    frames = {}
    for c, cam in enumerate(cameras):
        images = [(rng.integers(0, 40, (H_IMG, W_IMG, 3)) + np.array([20 * f, 60 * c, 100])).clip(0, 255)
                  .astype(np.uint8) for f in range(n_frames)]
        frames[cam] = images
        write_video(root / f"{cam}.mkv", images, fps=25, codec="ffv1")
        rows = ["scorer" + ",me" * 6, "bodyparts," + ",".join(f"{k},{k}" for k in KEYPOINTS),
                "coords" + ",x,y" * 3]
        rows += [f"labeled-data/rec_{cam}/img{f:04d}.png,"
                 + ",".join(repr(float(v)) for v in uv[f, c].ravel()) for f in range(n_frames)]
        (root / f"CollectedData_{cam}.csv").write_text("\n".join(rows) + "\n")
    return {"root": root, "X": X, "uv": uv, "frames": frames}


def import_argv(rec: dict, *extra: str, cameras: list[str] | None = None) -> list[str]:
    """``s3k import`` arguments of a recording written by :func:`write_recording`."""
    root = rec["root"]
    cameras = cameras or list(rec["frames"])
    return ["import", "--calibration", str(root / "calibration.toml"),
            "--videos", *(f"{cam}={root / cam}.mkv" for cam in cameras),
            "--dlc", *(f"{cam}={root}/CollectedData_{cam}.csv" for cam in cameras), *extra]
