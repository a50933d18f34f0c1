"""Tiny synthetic recordings for ``s3k import``: a calibrated 3-camera rig (anipose TOML, mm), ffv1 videos of
distinct frames, and DeepLabCut CSVs of the projected 3D points; another ``turn`` moves the cameras (another
day's recording). :func:`write_import_recording` adds SLEAP files and missing labels (``tests/conftest.py``
writes it once per session: the ``import_recording`` fixture)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

if TYPE_CHECKING:
    from s3k.data.rig import Rig

CAMS = ["north", "east", "south"]
KEYPOINTS = ["head", "body", "tail"]
W_IMG, H_IMG, N_FRAMES = 64, 48, 12


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


def write_sleap(path, locations, occupancy=None, nodes=("head", "body", "tail"), transpose=True, names=None):
    """SLEAP's writer: ``locations (F, K, 2, T)``, stored transposed (MATLAB order) by default."""
    import h5py

    F, K, _, T = locations.shape
    if occupancy is None:
        occupancy = np.ones((T, F), dtype=np.uint8)  # SLEAP builds (tracks, frames) then transposes
    names = names or [f"track_{i}" for i in range(T)]
    with h5py.File(path, "w") as f:
        f["tracks"] = locations.T if transpose else locations
        f["track_occupancy"] = occupancy.T if transpose else occupancy
        f["node_names"] = np.array([n.encode() for n in nodes], dtype="S")
        f["track_names"] = np.array([n.encode() for n in names], dtype="S")
        f["point_scores"] = np.ones((F, K, T)).T
        f["video_path"] = "cam.mp4"


def write_import_recording(root: Path) -> dict:
    """A 3-camera rig in mm, ffv1 videos, SLEAP files and DLC CSVs of the same projected 3D points in ``root``
    (``N_FRAMES`` frames, two labels missing, DLC labels on every other frame): ``{"root", "X" (F, K, 3), "uv"
    (F, C, K, 2), "frames" {cam: [images]}, "K"}``."""
    from s3k.data.formats import anipose
    from s3k.data.rig import Rig
    from s3k.data.video import write_video
    from s3k.geometry import Cameras

    Rs, ts = [], []
    for c in range(3):
        angle = 2 * np.pi * c / 3
        R, t = _look_at(np.array([np.cos(angle), np.sin(angle), 0.5]) * 400.0)
        Rs.append(R)
        ts.append(t)
    K = np.array([[70.0, 0, (W_IMG - 1) / 2], [0, 70.0, (H_IMG - 1) / 2], [0, 0, 1]])
    cams = Cameras.from_numpy(np.stack([K] * 3), np.zeros((3, 5)), np.stack(Rs), np.stack(ts),
                              dtype=torch.float64)
    calib = Rig(list(CAMS), cams, np.array([[W_IMG, H_IMG]] * 3), "mm", {"square_length": 20.0})
    anipose.write_anipose_calibration(root / "calibration.toml", calib)
    rng = np.random.default_rng(0)
    X = rng.uniform(-40, 40, (N_FRAMES, len(KEYPOINTS), 3))
    uv = np.stack(
        [cv2.projectPoints(X.reshape(-1, 3), cv2.Rodrigues(R)[0], t, K, None)[0].reshape(N_FRAMES, -1, 2)
         for R, t in zip(Rs, ts)],
        axis=1,
    )  # (F, C, K, 2)
    uv[3, 0, 1] = np.nan  # missing labels
    uv[5, :, 2] = np.nan
    frames = {}
    for c, cam in enumerate(CAMS):
        # Each frame a distinct pattern so that a frame mix-up is visible.
        images = [
            (rng.integers(0, 40, (H_IMG, W_IMG, 3)) + np.array([20 * f, 60 * c, 100])).clip(0, 255)
            .astype(np.uint8)
            for f in range(N_FRAMES)
        ]
        frames[cam] = images
        write_video(root / f"{cam}.mkv", images, fps=30, codec="ffv1")
        loc = uv[:, c, :, :, None]  # (F, K, 2, 1 track)
        write_sleap(root / f"{cam}.analysis.h5", loc, nodes=KEYPOINTS)
        rows = ["scorer" + ",me" * 6, "bodyparts," + ",".join(f"{k},{k}" for k in KEYPOINTS)]
        rows.append("coords" + ",x,y" * 3)
        for f in range(0, N_FRAMES, 2):  # DLC: every other frame labelled, written in shuffled order
            cells = ["" if np.isnan(v) else repr(float(v)) for v in uv[f, c].ravel()]
            rows.insert(3, f"labeled-data/rec_{cam}/img{f:04d}.png," + ",".join(cells))
        (root / f"CollectedData_{cam}.csv").write_text("\n".join(rows) + "\n")
    return {"root": root, "X": X, "uv": uv, "frames": frames, "K": K}


def run_import(recording: dict, out: Path, *extra: str, labels: str = "sleap") -> int:
    """``s3k import`` of a recording written by :func:`write_import_recording` (its SLEAP, DLC or Lightning
    Pose labels) into ``out``; the exit code."""
    from s3k.cli import main

    root = recording["root"]
    argv = ["import", "--calibration", str(root / "calibration.toml"), "--videos"]
    argv += [f"{cam}={root / cam}.mkv" for cam in CAMS]
    if labels == "sleap":
        argv += ["--sleap"] + [f"{cam}={root / cam}.analysis.h5" for cam in CAMS]
    elif labels == "dlc":
        argv += ["--dlc"] + [f"{cam}={root}/CollectedData_{cam}.csv" for cam in CAMS]
    else:
        argv += ["--lightning-pose", str(root)]
    return main(argv + ["--out", str(out), *extra])


def recording_rig(recording: dict) -> Rig:
    """The rig of a recording's ``calibration.toml``."""
    from s3k.data.formats import anipose

    return anipose.read_anipose_calibration(recording["root"] / "calibration.toml")


def import_videos(recording: dict, calibration: Path, out: Path, *extra: str,
                  videos: dict | None = None) -> int:
    """``s3k import`` of the recording's videos (or ``videos``) with ``calibration`` into ``out``; the exit
    code."""
    from s3k.cli import main

    root = recording["root"]
    videos = videos or {cam: root / f"{cam}.mkv" for cam in CAMS}
    argv = ["import", "--calibration", str(calibration), "--videos", *[f"{c}={p}" for c, p in videos.items()],
            "--out", str(out), *extra]
    return main(argv)


def validated(path: Path):
    """The dataset at ``path``, checked to hold no error."""
    from s3k.data import check_dataset

    problems, ds = check_dataset(path)
    assert not [p for p in problems if p.severity == "error"], [str(p) for p in problems]
    return ds


def assert_same_cameras(ds, rig: Rig, atol: float = 1e-9) -> None:
    """The dataset's cameras are ``rig``'s."""
    got = ds.rig(np.float64).numpy()
    ref = rig.cameras.numpy()
    for key in ("K", "dist", "R", "t"):
        np.testing.assert_allclose(got[key], ref[key], atol=atol, err_msg=key)


def assert_labels(ds, recording: dict, camera_order=None, atol: float = 0.0) -> None:
    """The dataset's labels on its labelled frames are the recording's projected points."""
    ids = ds.frames("labelled")
    uv, mask = ds.labels(ids)
    ref = recording["uv"][ids]
    np.testing.assert_array_equal(mask, np.isfinite(ref).all(-1))
    np.testing.assert_allclose(uv[mask], ref[mask].astype(np.float32), atol=atol)


def df3d_calib(rig: Rig) -> dict:
    """DeepFly3D's calibration entries of ``rig``, camera by camera."""
    cams = rig.cameras.numpy()
    return {c: {"R": cams["R"][c], "tvec": cams["t"][c], "intr": cams["K"][c], "distort": cams["dist"][c]}
            for c in range(len(rig.names))}
