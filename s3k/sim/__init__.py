"""MuJoCo scenes of the S3K paper (box, distractors, category) and the `s3k simulate` dataset generator.

Importing this package picks an OpenGL back end for MuJoCo before MuJoCo is imported: the user's
``MUJOCO_GL`` when set, otherwise GLFW when a display exists, EGL when a GPU render node exists, else OSMesa
(software, CPU only).
"""

from __future__ import annotations

import glob
import os


def _choose_gl_backend() -> None:
    if "MUJOCO_GL" in os.environ:
        return
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return  # MuJoCo's default (GLFW) works with a display
    backend = "egl" if glob.glob("/dev/nvidia[0-9]*") else "osmesa"
    os.environ["MUJOCO_GL"] = backend
    os.environ.setdefault("PYOPENGL_PLATFORM", backend)


_choose_gl_backend()
