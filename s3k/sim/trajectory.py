"""A box moving on the table, rendered as synchronized videos of a fixed rig with its true keypoints: the
ground truth that tracking and filtering over time are measured against (``benchmarks/filter_tracks.py``).

The rig, the lighting and the table are drawn once (as :meth:`s3k.sim.scene.Scene.sample` draws a frame's);
the box rests on one face, slides along a smooth closed curve within the placement radius of the training
frames and turns about the vertical, so every frame is a pose the box scene's datasets show.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from s3k.data.formats.anipose import write_anipose_calibration
from s3k.data.rig import Rig
from s3k.data.video import write_video
from s3k.geometry import Cameras

__all__ = ["BoxTrajectory", "box_path", "render_box_trajectory"]


@dataclass
class BoxTrajectory:
    """What :func:`render_box_trajectory` wrote: ``videos`` ``{camera: file}``, the anipose ``calibration``
    file, the true keypoints ``points (T, K, 3)`` in metres, the ``keypoints``' names and the ``fps``."""

    videos: dict[str, Path]
    calibration: Path
    points: np.ndarray
    keypoints: list[str]
    fps: float


def box_path(frames: int, fps: float, radius: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(xy (T, 2), yaw (T,))``: a smooth closed curve within ``radius`` of the centre (two sines of
    incommensurate periods of 5-9 s) and a heading that turns back and forth (up to about 100 degrees/s)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    px, py, pa = rng.uniform(5.0, 9.0, 3)
    phase = rng.uniform(0, 2 * math.pi, 3)
    xy = 0.7 * radius * np.stack([np.sin(2 * math.pi * t / px + phase[0]),
                                  np.sin(2 * math.pi * t / py + phase[1])], axis=-1)
    yaw = 1.5 * np.sin(2 * math.pi * t / pa + phase[2]) + 0.3 * t
    return xy, yaw


def render_box_trajectory(out: str | Path, frames: int = 300, size: int = 96, fps: float = 30.0,
                          seed: int = 0, object_seed: int = 0, lossless: bool = False) -> BoxTrajectory:
    """Render the box scene's box along :func:`box_path` into ``out`` (``<camera>.mp4``, ``calibration.toml``,
    ``points3d.npy``).

    Args:
        out: folder to write.
        frames: frames of the videos.
        size: image width and height in pixels.
        fps: frame rate.
        seed: draws the rig, the lighting, the resting face and the path.
        object_seed: the box's look (as ``s3k simulate --object-seed``: a detector trained on that box).
        lossless: encode the videos losslessly (default H.264, as a camera would).
    """

    from s3k.sim.scene import axis_rotation, resting_box_pose
    from s3k.sim.scenes import BoxScene

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, 0x7EAC])
    images: list[list[np.ndarray]] = []
    points = []
    with BoxScene(size=size, seed=object_seed) as scene:
        scene.sample_environment(rng)
        scene.set_cameras(*scene.cameras_sampler.sample(rng, scene.num_cameras))
        base, z, _ = resting_box_pose(rng, scene.box_half, p_faces=(1, 0, 0, 0, 0, 0))  # lid up
        xy, yaw = box_path(frames, fps, scene.placement_radius, int(rng.integers(2**31)))
        for f in range(frames):
            scene.place_box(np.array([xy[f, 0], xy[f, 1], z]), axis_rotation("z", float(yaw[f])) @ base)
            scene.forward()
            rendered = scene.renderer.render(scene.data, scene.camera_ids)["rgb"]
            images.append(list(rendered))
            points.append(scene.keypoints_world())
        K, R, t = scene.calibration()
        names = list(scene.camera_names)
        keypoints = list(scene.keypoints)
    videos = {}
    for c, name in enumerate(names):
        videos[name] = out / f"{name}.mp4"
        write_video(videos[name], [im[c] for im in images], fps=fps, lossless=lossless)
    cams = Cameras.from_numpy(K, np.zeros((len(names), 5)), R, t, dtype=torch.float64)
    calibration = out / "calibration.toml"
    write_anipose_calibration(calibration, Rig(names, cams, np.tile([size, size], (len(names), 1)), "m"))
    truth = np.stack(points)
    np.save(out / "points3d.npy", truth)
    return BoxTrajectory(videos, calibration, truth, keypoints, fps)
