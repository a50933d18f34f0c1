"""The tiny rig of ``s3k track``'s tests: 3 cameras about 1 m (1000 mm) from the origin, 64 x 48 px videos
(one camera with lens distortion), three coloured dots moving in 3D, and a tiny untrained U-Net saved as a run
folder (32 x 32 input, so frames are padded to the detector's aspect ratio). ``tests/conftest.py`` writes it
once per session (the ``track_recording`` fixture)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from helpers.tiny_detector import save_run
from s3k import cli
from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.rig import Rig
from s3k.data.video import write_video
from s3k.detector import DetectorMeta
from s3k.geometry import Cameras, project
from s3k.model import UNetConfig
from s3k.readout.heatmaps import gaussian_targets, heatmap_size

CAMERAS = ["left", "top", "right"]
KEYPOINTS = ["nose", "ear", "tail"]
VIDEO_SIZE = (64, 48)
NET_SIZE = (32, 32)
FRAMES = 6
COLOURS = [(255, 40, 40), (40, 255, 40), (60, 60, 255)]


def _look_at(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = -centre / np.linalg.norm(centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def make_rig() -> Rig:
    W, H = VIDEO_SIZE
    Rs, ts, Ks = [], [], []
    for c in range(3):
        a = 2 * math.pi * c / 3 + 0.4
        R, t = _look_at(1000.0 * np.array([math.cos(a), math.sin(a), 0.7]) / math.hypot(1, 0.7))
        Rs.append(R)
        ts.append(t)
        Ks.append(np.array([[70.0 + 5 * c, 0, (W - 1) / 2 + c], [0, 72.0, (H - 1) / 2 - c], [0, 0, 1]]))
    dist = np.zeros((3, 5))
    dist[1] = [-0.08, 0.01, 0.001, -0.001, 0.0]
    sizes = np.tile(np.array(VIDEO_SIZE), (3, 1))
    cams = Cameras.from_numpy(np.stack(Ks), dist, np.stack(Rs), np.stack(ts), dtype=torch.float64)
    return Rig(list(CAMERAS), cams, sizes, "mm")


def moving_points(n: int) -> np.ndarray:
    """(n, 3, 3) keypoints in mm near the origin."""
    base = np.array([[60.0, 0.0, 0.0], [-40.0, 50.0, 10.0], [-30.0, -50.0, 20.0]])
    s = np.arange(n, dtype=np.float64)[:, None, None]
    return base + np.concatenate([10 * np.sin(0.5 * s), 8 * np.cos(0.3 * s), 5 * s], axis=-1)


def track_run(path: Path, stride: int = 2) -> Path:
    """A run folder holding an untrained tiny detector with non-trivial BatchNorm statistics."""
    meta = DetectorMeta(
        keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=NET_SIZE, stride=stride, sigma=2.0,
        model=UNetConfig(channels=(8, 8), res_blocks=1, stride=stride).to_dict(), units="mm",
        source_image_size=NET_SIZE,
    )
    return save_run(path, meta, seed=0)


def write_track_recording(root: Path) -> dict:
    """Videos (mp4) of the dots, calibration.toml and a run folder (:func:`track_run`) in ``root``:
    ``{"root", "rig", "calibration", "videos" {camera: path}, "run"}``."""
    rig = make_rig()
    calib = root / "calibration.toml"
    write_anipose_calibration(calib, rig)
    X = torch.as_tensor(moving_points(FRAMES))
    uv, _ = project(rig.cameras[None], X[:, None])  # (F, C, K, 2)
    videos = {}
    W, H = VIDEO_SIZE
    for c, name in enumerate(CAMERAS):
        frames = []
        for f in range(FRAMES):
            img = np.full((H, W, 3), 80, np.uint8)
            for k in range(3):
                centre = tuple(int(round(float(v) * 4)) for v in uv[f, c, k])
                cv2.circle(img, centre, 10, COLOURS[k], -1, cv2.LINE_AA, shift=2)
            frames.append(img)
        videos[name] = root / f"{name}.mp4"
        write_video(videos[name], frames, fps=25)
    return {"root": root, "rig": rig, "calibration": calib, "videos": videos, "run": track_run(root / "run")}


def run_track(recording: dict, out: Path, *extra: str, order=None) -> int:
    """``s3k track`` of the recording's videos (in ``order``) into ``out``; its exit code."""
    order = order or CAMERAS
    args = ["track", str(recording["run"]), "--calibration", str(recording["calibration"]), "--out", str(out),
            "--no-progress", "--videos", *[f"{c}={recording['videos'][c]}" for c in order], *extra]
    return cli.main(args)


def read_track_csv(path: Path) -> tuple[list[str], np.ndarray]:
    """A 3D CSV's header and its rows as floats."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(v) for v in r] for r in rows[1:]], dtype=np.float64)


def peaked_logits(uv_net: torch.Tensor, stride: int, sigma: float) -> torch.Tensor:
    """Logits whose softmax is the normalized Gaussian target at ``uv_net (B, C, K, 2)``."""
    h, w = heatmap_size(NET_SIZE[1], NET_SIZE[0], stride)
    target, mask = gaussian_targets(uv_net, None, h, w, stride, sigma)
    assert bool(mask.all())
    return target.clamp_min(1e-300).log()


class OracleDetector(torch.nn.Module):
    """A network stand-in: a Gaussian at the known projection of every keypoint, in the view it is shown.

    Each video frame is one grey level, ``20 + 10 f + 3 c`` for frame ``f`` of camera ``c``, which the oracle
    reads back from the image centre after the pipeline's decoding, cropping and resizing.
    """

    def __init__(self, uv_net: torch.Tensor, stride: int, sigma: float) -> None:
        super().__init__()
        self.logits = peaked_logits(uv_net, stride, sigma).float()  # (F, C, K, h, w)
        self.calls = 0

    def fused(self) -> OracleDetector:
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        H, W = images.shape[-2:]
        level = (images[:, 0, H // 2, W // 2] * 255).round().long() - 20
        f, c = level // 10, (level % 10) // 3
        self.calls += 1
        return self.logits[f, c]
