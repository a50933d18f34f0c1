"""A keypoint dataset of the cable-insertion environment, to train the detector its agent can use.

Frames come from episodes of the scripted demonstrator with noise added to its actions, so they cover the
states an agent meets (plug swinging, above the socket, inside it, the gripper anywhere in the workspace).
The rig is the environment's own fixed 4-camera rig (``camera_seed``), stored as a static calibration;
labelled and test frames get the projections of the three keypoints (``plug_tip`` at the hole's opening
once inside, as the environment defines it) wherever they fall inside the image; every frame gets the
ground-truth 3D keypoints, for evaluation. A run trained on it is what ``s3k robot train-agent --run RUN``
and ``InsertionEnv(detector=RunDetector(RUN, KEYPOINTS))`` read keypoints with.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from s3k.base.errors import UserError
from s3k.data import DatasetWriter
from s3k.robot.insertion_env import KEYPOINTS, InsertionEnv, scripted_action
from s3k.sim.camera import project_points
from s3k.sim.scene import in_image


def write_insertion_dataset(out: str | Path, labelled: int = 10, unlabelled: int = 2000, test: int = 200,
                            size: int = 64, seed: int = 0, camera_seed: int = 0, noise: float = 0.5,
                            overwrite: bool = False, progress: bool = True) -> dict:
    """Renders the dataset into folder ``out``; returns ``{"path", "frames"}``.

    Args:
        labelled, unlabelled, test: frames per split. Test frames come from episodes of their own.
        size: image width and height.
        seed: draws the episodes and the demonstrator's noise.
        camera_seed: the environment's camera rig (``InsertionEnv(camera_seed=...)``; agents use 0).
        noise: standard deviation of the Gaussian noise added to the demonstrator's actions (in [-1, 1]).
    """

    for name, n in (("labelled", labelled), ("unlabelled", unlabelled), ("test", test)):
        if n < 0:
            raise UserError(f"{name} (--{name}): frame count must be >= 0, got {n}")
    if labelled + unlabelled + test == 0:
        raise UserError("labelled + unlabelled + test: no frames to render",
                        hint="give --labelled, --unlabelled or --test a positive count")
    if size < 16:
        raise UserError(f"size (--size): images must be at least 16 px, got {size}")
    env = InsertionEnv(image_size=size, camera_seed=camera_seed)
    cameras = [f"cam{i}" for i in range(4)]
    env.reset(seed=seed)
    _, K, R, t = env.views()
    writer = DatasetWriter(
        out, KEYPOINTS, cameras, (size, size), units="m", calibration=(K, np.zeros((4, 5)), R, t),
        description="cable insertion: a plug on a flexible cable held by a gripper, and a socket",
        source={"generator": "s3k robot simulate-insertion", "size": size, "seed": seed,
                "camera_seed": camera_seed, "noise": noise},
        overwrite=overwrite,
    )
    plan = ["labelled"] * labelled + ["unlabelled"] * unlabelled
    rng = np.random.default_rng([seed, 0x1D5])
    frame_id = 0
    with tqdm(total=len(plan) + test, unit="frame", desc="simulate insertion", disable=not progress) as bar:
        for splits, stream in ((plan, 0), (["test"] * test, 1)):
            # Test frames come from episodes of their own (their own seed stream).
            episode_rng = np.random.default_rng([seed, 0xE915, stream])
            obs, _ = env.reset(seed=int(episode_rng.integers(1 << 31)))
            order = rng.permutation(len(splits)) if stream == 0 else np.arange(len(splits))
            for i in order:  # labelled frames spread over the episodes, not the first few steps
                split = splits[i]
                images = env.views()[0]
                X = env.true_keypoints()
                labels = None
                if split != "unlabelled":
                    uv, depth = project_points(K, R, t, X)
                    labels = (uv, in_image(uv, depth, size, size))
                writer.add_frame(frame_id, split, images, labels=labels, points3d=X)
                frame_id += 1
                bar.update(1)
                action = np.clip(scripted_action(obs) + rng.normal(0.0, noise, 6), -1.0, 1.0)
                obs, _, term, trunc, _ = env.step(action.astype(np.float32))
                if term or trunc:
                    obs, _ = env.reset(seed=int(episode_rng.integers(1 << 31)))
    env.close()
    return {"path": str(writer.close()), "frames": frame_id}
