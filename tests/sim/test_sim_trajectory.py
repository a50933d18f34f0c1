"""The box trajectory rendered as synchronized videos of a fixed rig, with its truth (s3k.sim.trajectory)."""

from __future__ import annotations

import numpy as np
import torch

from s3k.data.formats.anipose import read_anipose_calibration
from s3k.data.video import frame_count, frame_size
from s3k.geometry import project
from s3k.sim.trajectory import box_path, render_box_trajectory


def test_box_path_is_smooth_and_stays_within_the_radius():
    xy, yaw = box_path(300, 30.0, 0.05, seed=3)
    assert np.linalg.norm(xy, axis=-1).max() <= 0.05
    step = np.linalg.norm(np.diff(xy, axis=0), axis=-1)
    assert step.max() < 0.005 and np.abs(np.diff(yaw)).max() < 0.1  # m and rad per frame at 30 fps


def test_rendered_trajectory_has_videos_a_calibration_and_the_truth_in_view(tmp_path):
    traj = render_box_trajectory(tmp_path, frames=4, size=32, seed=1, lossless=True)
    assert traj.points.shape == (4, 3, 3) and np.isfinite(traj.points).all()
    rig = read_anipose_calibration(traj.calibration)
    assert rig.names == list(traj.videos) and rig.units == "m"
    for path in traj.videos.values():
        assert frame_count(path) == 4 and frame_size(path) == (32, 32)
    uv, depth = project(rig.cameras, torch.as_tensor(traj.points)[:, None])  # (T, C, K, 2)
    assert (depth > 0).all() and ((uv > -0.5) & (uv < 31.5)).all()
    # the lid keypoints stand on the box above the table
    assert np.allclose(traj.points[..., 2], traj.points[0, 0, 2]) and traj.points[0, 0, 2] > 0.01
