"""Keypoints in the loop (docs/robot.md): a scripted grasp of the plush toy, a cable-insertion environment,
agents trained on it, and the results writer. The simulation itself is in :mod:`s3k.sim`."""
