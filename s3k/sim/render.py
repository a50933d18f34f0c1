"""Off-screen multi-camera rendering of a MuJoCo model: colour, segmentation and depth.

Shadows and multisampling are switched off in the scene XML (``<quality shadowsize="0" offsamples="0"/>``),
which keeps a 128 px image at a few milliseconds on a CPU with OSMesa.
"""

from __future__ import annotations

import atexit
import importlib
import os
import weakref

import mujoco
import numpy as np


def _match_gl_backend() -> None:
    """Makes MuJoCo's renderer use the back end named by ``MUJOCO_GL`` even when mujoco was imported first.

    MuJoCo picks its OpenGL context class when it is imported; a program that imported mujoco before
    :mod:`s3k.sim` on a machine without a display would otherwise try GLFW and fail.
    """
    want = os.environ.get("MUJOCO_GL", "").lower()
    if want not in ("osmesa", "egl"):
        return
    try:
        from mujoco.rendering.classic import gl_context
    except ImportError:  # layout of older or newer mujoco releases: leave it to mujoco
        return
    if getattr(gl_context, "_MUJOCO_GL", want) != want:
        gl_context.GLContext = importlib.import_module(f"mujoco.{want}").GLContext


class MultiViewRenderer:
    """Renders every camera of a model into preallocated arrays.

    Args:
        model: the compiled ``mujoco.MjModel`` (textures must be final: they are uploaded here).
        width: image width W in pixels.
        height: image height H in pixels.

    Attributes:
        option: the ``mujoco.MjvOption`` used for colour and segmentation renders (e.g. its ``geomgroup``
            hides geom groups).
    """

    def __init__(self, model: mujoco.MjModel, width: int, height: int):
        self.model = model
        self.width = int(width)
        self.height = int(height)
        _match_gl_backend()
        self._renderer = mujoco.Renderer(model, height=self.height, width=self.width)
        self.option = mujoco.MjvOption()
        self._group_option = mujoco.MjvOption()
        # Free the OpenGL context before the interpreter tears modules down (MuJoCo's finaliser fails then).
        ref = weakref.ref(self)

        def close_at_exit() -> None:
            renderer = ref()
            if renderer is not None:
                renderer.close()

        atexit.register(close_at_exit)

    def render(
        self,
        data: mujoco.MjData,
        cameras: list[int],
        segmentation: bool = False,
        depth: bool = False,
        group_depth: tuple[int, ...] | None = None,
        group_depth_cameras: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Renders ``cameras`` of the current ``data``.

        Args:
            data: the state to draw (after ``mj_kinematics`` and ``mj_camlight``).
            cameras: camera ids; their order is the output's C axis.
            segmentation: also return the geom id per pixel.
            depth: also return the camera-frame depth per pixel.
            group_depth: also return the depth of only the geoms in these geom groups (e.g. the occluders).
            group_depth_cameras: bool (C,): render ``group_depth`` only for these cameras (the others get
                ``inf``, as if nothing were drawn); default all.

        Returns:
            ``{"rgb": uint8 (C, H, W, 3)}``, plus ``"segmentation": int32 (C, H, W)`` (geom id, -1 where
            no geom), ``"depth"`` and ``"group_depth"``: float32 (C, H, W) camera-frame z in metres (the far
            clipping distance where nothing is drawn), when asked.
        """
        C, H, W = len(cameras), self.height, self.width
        out = {"rgb": np.empty((C, H, W, 3), np.uint8)}
        if segmentation:
            out["segmentation"] = np.empty((C, H, W), np.int32)
            seg = np.empty((H, W, 2), np.int32)
        if depth:
            out["depth"] = np.empty((C, H, W), np.float32)
        if group_depth is not None:
            out["group_depth"] = np.full((C, H, W), np.inf, np.float32)
            if group_depth_cameras is None:
                group_depth_cameras = np.ones(C, bool)
            groups = range(len(self._group_option.geomgroup))
            self._group_option.geomgroup[:] = [1 if g in group_depth else 0 for g in groups]
        r = self._renderer
        for i, cam in enumerate(cameras):
            r.update_scene(data, camera=cam, scene_option=self.option)
            r.render(out=out["rgb"][i])
            if segmentation:
                r.enable_segmentation_rendering()
                r.render(out=seg)
                r.disable_segmentation_rendering()
                # Channel 0 is the object id, channel 1 its type; keep geoms only.
                is_geom = seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
                out["segmentation"][i] = np.where(is_geom, seg[..., 0], -1)
            if depth:
                r.enable_depth_rendering()
                r.render(out=out["depth"][i])
                r.disable_depth_rendering()
            if group_depth is not None and group_depth_cameras is not None and group_depth_cameras[i]:
                r.update_scene(data, camera=cam, scene_option=self._group_option)
                r.enable_depth_rendering()
                r.render(out=out["group_depth"][i])
                r.disable_depth_rendering()
        return out

    def close(self) -> None:
        """Frees the OpenGL context."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> MultiViewRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
