"""Small datasets for the labelling tests: coloured dots seen by a static 4-camera rig (``synthetic_rig``).

Frames 0-3 are a still stretch (one pose, identical images); frames 4 and 5 have other poses; frame 6 is a
test frame. Variants: per-frame calibration (camera 1 moves in frame 2, so a stretch over it is not still),
video-backed (ffv1, exact), and strong lens distortion in camera 2. No labels: the tests make them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from helpers.synthetic_rig import CAMERAS, COLOURS, KEYPOINTS, LAYOUT, random_rotation, rig
from helpers.tiny_detector import save_run
from s3k.detector import DetectorMeta
from s3k.geometry import Cameras, project
from s3k.model import UNetConfig

SPLITS = ["labelled", "unlabelled", "unlabelled", "unlabelled", "unlabelled", "unlabelled", "test"]


@dataclass
class Truth:
    """The ground truth of a label dataset: per frame ``K, dist, R, t`` (C, ...) and points (K, 3)."""

    path: Path
    calibration: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
    points: np.ndarray  # (N, K, 3)
    size: int

    def uv(self, frame: int) -> np.ndarray:
        """(C, K, 2) true projections of a frame's keypoints (lens distortion included)."""
        K, dist, R, t = self.calibration[frame]
        cams = Cameras.from_numpy(K, dist, R, t, dtype=torch.float64)
        uv, _ = project(cams, torch.as_tensor(self.points[frame])[None].expand(len(K), -1, -1))
        return uv.numpy()


def make_label_dataset(path: str | Path, size: int = 96, per_frame: bool = False, video: bool = False,
                       distortion: bool = False, seed: int = 3) -> Truth:
    from s3k.data import DatasetWriter
    from s3k.data.video import write_video

    rng = np.random.default_rng(seed)
    K, dist, R, t = rig(size)
    if distortion:  # camera 2 turned 7 degrees, so the object lies off its axis, where distortion bends
        a = np.radians(7.0)
        turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        R, t, dist = R.copy(), t.copy(), dist.copy()
        R[2], t[2] = turn @ R[2], turn @ t[2]
        dist[2] = [-6.0, 0.0, 0.0, 0.0, 0.0]
    poses = []
    still = LAYOUT @ random_rotation(rng).T
    for i in range(len(SPLITS)):
        poses.append(still if i < 4 else LAYOUT @ random_rotation(rng).T + rng.uniform(-0.02, 0.02, size=3))
    calib, images = [], []
    for i in range(len(poses)):
        Ki, Ri, ti = K.copy(), R.copy(), t.copy()
        if per_frame and i == 2:
            ti = t.copy()
            ti[1] = t[1] + np.array([0.004, 0.0, 0.0])  # camera 1 moves 4 mm
        calib.append((Ki, dist, Ri, ti))
        truth = Truth(Path(path), calib, np.stack(poses[: i + 1]), size)
        uv = truth.uv(i)
        frame = np.zeros((4, size, size, 3), np.uint8)
        frame[:] = np.linspace(40, 140, size, dtype=np.uint8)[None, :, None, None]
        for c in range(4):
            for k in range(3):
                centre = (int(round(uv[c, k, 0] * 4)), int(round(uv[c, k, 1] * 4)))
                cv2.circle(frame[c], centre, 3 * 4, COLOURS[k], -1, cv2.LINE_AA, shift=2)
        images.append(frame)
    path = Path(path)
    videos = None
    if video:
        tmp = path.parent / f"{path.name}-videos"
        tmp.mkdir(parents=True, exist_ok=True)
        videos = {}
        for c, cam in enumerate(CAMERAS):
            videos[cam] = tmp / f"{cam}.mkv"
            write_video(videos[cam], [im[c] for im in images], fps=10, codec="ffv1")
    with DatasetWriter(path, KEYPOINTS, CAMERAS, (size, size), "m",
                       calibration=None if per_frame else (K, dist, R, t),
                       per_frame_calibration=True if per_frame else None, videos=videos) as w:
        for i, split in enumerate(SPLITS):
            w.add_frame(i, split, None if video else images[i], calib[i] if per_frame else None,
                        points3d=poses[i])
    return Truth(path, calib, np.stack(poses), size)


FAR_PX = 45.0  # a wrong label's distance from its true place, beyond the app's check of 40 px
NEAR_PX = 8.0  # a careless label: within the check, above the usual residual


def moved(uv: np.ndarray, size: int, length: float) -> np.ndarray:
    """A point ``length`` px from ``uv``, towards the image corner farthest from it (inside the image)."""
    corners = np.array([[4.0, 4.0], [4.0, size - 5.0], [size - 5.0, 4.0], [size - 5.0, size - 5.0]])
    far = corners[np.argmax(np.linalg.norm(corners - uv, axis=1))]
    return uv + length * (far - uv) / np.linalg.norm(far - uv)


def label_true_projections(truth: Truth, wrong: dict[tuple[int, int, int], float], frames=(0, 4, 5)) -> None:
    """``frames`` labelled in every view at the true projections, through the label store, except ``wrong``:
    ``(frame, camera, keypoint)`` -> how many pixels off (:func:`moved`)."""
    from s3k.label.store import Edit, LabelStore

    store = LabelStore.open(truth.path)
    for f in frames:
        uv = truth.uv(f)
        edits = []
        for c, cam in enumerate(CAMERAS):
            for k, kp in enumerate(KEYPOINTS):
                p = uv[c, k] if (f, c, k) not in wrong else moved(uv[c, k], truth.size, wrong[f, c, k])
                edits.append(Edit(cam, kp, float(p[0]), float(p[1])))
        store.save(f, edits, store.version(f))


def save_label_run(path: Path, size: int = 32) -> Path:
    """A run folder of an untrained tiny detector of the rig's keypoints and cameras (``size`` px input,
    peaked heatmaps), for the app's suggestions."""
    meta = DetectorMeta(keypoints=list(KEYPOINTS), cameras=list(CAMERAS), image_size=(size, size), stride=2,
                        sigma=2.0, model=UNetConfig(channels=(8, 8), res_blocks=1, stride=2).to_dict(),
                        units="m", source_image_size=(96, 96))
    return save_run(path, meta, seed=0, head_std=0.5)
