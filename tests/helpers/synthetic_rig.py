"""A tiny synthetic multi-view dataset for training tests: coloured dots seen by a static 4-camera rig.

Three keypoints on a rigid triangle with a random pose per frame are drawn as discs of distinct colours into
every camera, so a detector can in principle learn them; written with ``DatasetWriter`` (no renderer needed).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from s3k.geometry import Cameras

KEYPOINTS = ["a", "b", "c"]
CAMERAS = ["cam0", "cam1", "cam2", "cam3"]
COLOURS = [(255, 40, 40), (40, 255, 40), (60, 60, 255)]
LAYOUT = np.array([[0.06, 0.0, 0.0], [-0.04, 0.05, 0.0], [-0.03, -0.05, 0.02]])


def rig(size: int, turn: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(K (C, 3, 3), dist (C, 5), R (C, 3, 3), t (C, 3)) of 4 cameras 1 m from the origin, looking at it;
    ``turn`` (radians) moves every camera around the vertical axis (another day's rig)."""
    Ks, Rs, ts = [], [], []
    f = size * 2.2
    for c in range(4):
        a = 2 * math.pi * c / 4 + 0.3 + turn
        centre = np.array([math.cos(a), math.sin(a), 0.6])
        centre = centre / np.linalg.norm(centre)
        z = -centre
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        Rs.append(R)
        ts.append(-R @ centre)
        Ks.append(np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]]))
    return np.stack(Ks), np.zeros((4, 5)), np.stack(Rs), np.stack(ts)


def project(K, R, t, X):
    """(C, 3, 3), (C, 3, 3), (C, 3), (N, 3) -> (C, N, 2)."""
    x = np.einsum("cij,nj->cni", R, X) + t[:, None]
    p = np.einsum("cij,cnj->cni", K, x)
    return p[..., :2] / p[..., 2:3]


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def make_dataset(path: str | Path, size: int = 32, labelled: int = 4, unlabelled: int = 8, test: int = 4,
                 seed: int = 0, label_cameras: int = 4) -> Path:
    """Write the dataset to ``path``; returns the path. Labels are given in the first ``label_cameras``
    cameras (1: no keypoint can be triangulated from the labels)."""
    from s3k.data import DatasetWriter

    rng = np.random.default_rng(seed)
    cal = rig(size)
    path = Path(path)
    with DatasetWriter(path, KEYPOINTS, CAMERAS, (size, size), "m", calibration=cal) as w:
        fid = 0
        for split, n in (("labelled", labelled), ("unlabelled", unlabelled), ("test", test)):
            for _ in range(n):
                _add_frame(w, fid, split, cal, size, rng, label_cameras)
                fid += 1
    return path


def _add_frame(w, fid: int, split: str, cal, size: int, rng: np.random.Generator, label_cameras: int = 4,
               extra: dict | None = None, calibration: bool = False, label_test: bool = False) -> None:
    """One frame of the dots at a random pose seen by the rig ``cal``, written by ``w``."""
    K, _, R, t = cal
    X = LAYOUT @ random_rotation(rng).T + rng.uniform(-0.03, 0.03, size=3)
    uv = project(K, R, t, X)
    images = np.full((4, size, size, 3), 90, np.uint8)
    for c in range(4):
        for k in range(3):
            centre = (int(round(uv[c, k, 0] * 4)), int(round(uv[c, k, 1] * 4)))
            cv2.circle(images[c], centre, 8, COLOURS[k], -1, cv2.LINE_AA, shift=2)
    labels = None
    if split == "labelled" or (label_test and split == "test"):
        labels = uv.copy()
        labels[label_cameras:] = np.nan
    w.add_frame(fid, split, images, cal if calibration else None, labels, points3d=X, extra=extra)


def make_sessions_dataset(path: str | Path, sessions: dict[str, float], size: int = 32, labelled: int = 3,
                          unlabelled: int = 4, test: int = 3, seed: int = 0) -> Path:
    """A dataset of several sessions, ``{name: turn}``: each its own rig (:func:`rig` turned by ``turn``),
    its frames in time order (``video_frame`` from 0: labelled, then unlabelled, then test frames), its
    frame rate and subject in s3k.json; test frames keep their labels."""
    from s3k.data import DatasetWriter

    rng = np.random.default_rng(seed)
    info = {name: {"frame_rate": 30.0, "subject": f"dots-{i}"} for i, name in enumerate(sessions)}
    with DatasetWriter(Path(path), KEYPOINTS, CAMERAS, (size, size), "m", sessions=info) as w:
        fid = 0
        for name, turn in sessions.items():
            splits = ["labelled"] * labelled + ["unlabelled"] * unlabelled + ["test"] * test
            for i, split in enumerate(splits):
                _add_frame(w, fid, split, rig(size, turn), size, rng, calibration=True, label_test=True,
                           extra={"session": name, "video_frame": i})
                fid += 1
    return Path(path)


def count_decodes(monkeypatch, module) -> list[str]:
    """The images ``module`` decodes from now on: its ``decode_image`` is patched to note each image's name
    (the dataset-relative name when it is given one, else the path) in the list returned."""
    decoded: list[str] = []
    real = module.decode_image

    def decode(path, name=None):
        decoded.append(str(path if name is None else name))
        return real(path, name)

    monkeypatch.setattr(module, "decode_image", decode)
    return decoded


def ring_cameras(size: int) -> Cameras:
    """Four cameras 1 m from the origin on a ring, looking at it (the detector's tests)."""
    import torch

    from s3k.geometry import Cameras

    R, t = [], []
    for a in np.linspace(0, 2 * np.pi, 5)[:-1]:
        pos = np.array([np.cos(a), np.sin(a), 0.5]) / np.linalg.norm([1, 0.5])
        z = -pos
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        Rc = np.stack([x, np.cross(z, x), z])
        R.append(Rc)
        t.append(-Rc @ pos)
    f = size * 1.2
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return Cameras.from_numpy(np.stack([K] * 4), None, np.stack(R), np.stack(t), dtype=torch.float64)
