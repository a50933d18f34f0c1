"""MuJoCo camera <-> OpenCV camera, and camera placement.

MuJoCo's camera frame has x to the right, y up and looks along -z; ``data.cam_xmat`` holds the camera axes
as columns in world coordinates, so ``x_world = xmat @ x_mjcam + xpos``. OpenCV's camera frame has x right,
y down and looks along +z. Hence ``x_cv = diag(1, -1, -1) @ xmat.T @ (x_world - xpos)``, i.e.

    R = diag(1, -1, -1) @ xmat.T,    t = -R @ xpos.

MuJoCo's ``fovy`` is the full vertical field of view of a pinhole with square pixels whose principal point is
the image centre, and the rendered image's row 0 is the top (after the flip :mod:`mujoco.Renderer` does), so

    f = (H / 2) / tan(fovy / 2),    cx = (W - 1) / 2,    cy = (H - 1) / 2

with pixel (0, 0) at the centre of the top-left pixel. :func:`mujoco_to_opencv` is the only place in s3k
that does this conversion; ``tests/sim/test_sim.py`` checks it against segmentation renders.
"""

from __future__ import annotations

import numpy as np

# Flips MuJoCo's camera axes (x right, y up, looking down -z) to OpenCV's (x right, y down, looking down +z).
_MJ_TO_CV = np.diag([1.0, -1.0, -1.0])


def mujoco_to_opencv(
    xpos: np.ndarray, xmat: np.ndarray, fovy_deg: float, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Converts a MuJoCo camera pose and field of view to an OpenCV pinhole camera.

    Args:
        xpos: (3,) camera position in world coordinates (``data.cam_xpos[i]``).
        xmat: (3, 3) or (9,) camera orientation, columns = camera axes in world (``data.cam_xmat[i]``).
        fovy_deg: vertical field of view in degrees (``model.cam_fovy[i]``).
        width: rendered image width W in pixels.
        height: rendered image height H in pixels.

    Returns:
        ``(K (3, 3), R (3, 3), t (3,))`` float64 with ``x_cam = R @ x_world + t``, no lens distortion.

    Example:
        >>> K, R, t = mujoco_to_opencv(np.zeros(3), np.eye(3), 90.0, 5, 5)
        >>> K[0, 0], K[0, 2], R[2, 2]
        (2.5, 2.0, -1.0)
    """
    xpos = np.asarray(xpos, dtype=np.float64).reshape(3)
    xmat = np.asarray(xmat, dtype=np.float64).reshape(3, 3)
    if not 0.0 < fovy_deg < 180.0:
        raise ValueError(f"mujoco_to_opencv: fovy_deg must be in (0, 180), got {fovy_deg}")
    if width <= 0 or height <= 0:
        raise ValueError(f"mujoco_to_opencv: image size must be positive, got width={width} height={height}")
    R = _MJ_TO_CV @ xmat.T
    t = -R @ xpos
    f = (height / 2.0) / np.tan(np.deg2rad(fovy_deg) / 2.0)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K, R, t


def camera_from_model(model, data, camera: int, width: int, height: int):
    """OpenCV ``(K, R, t)`` of MuJoCo camera number ``camera`` (after ``mj_forward`` / ``mj_camlight``)."""
    return mujoco_to_opencv(data.cam_xpos[camera], data.cam_xmat[camera], float(model.cam_fovy[camera]),
                            width, height)


def look_at_xmat(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """MuJoCo camera orientation (3, 3) (columns: camera x, y, z in world) looking from ``eye`` at ``target``.

    The image's up direction is the projection of ``up``, then rotated by ``roll`` radians about the view
    axis.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    norm = np.linalg.norm(forward)
    if norm < 1e-12:
        raise ValueError("look_at_xmat: eye and target coincide")
    forward /= norm
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking along `up`: any right vector will do
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    c, s = np.cos(roll), np.sin(roll)
    x = c * right + s * cam_up
    y = -s * right + c * cam_up
    return np.stack([x, y, -forward], axis=1)


def project_points(
    K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection without distortion, for labels and tests (the library's own is ``s3k.geometry``).

    Args:
        K: (C, 3, 3) intrinsics; R: (C, 3, 3); t: (C, 3).
        X: (N, 3) world points.

    Returns:
        ``uv (C, N, 2)`` pixels and ``depth (C, N)`` camera-frame z. Points with depth <= 0 get finite uv.
    """
    Xc = np.einsum("cij,nj->cni", R, X) + t[:, None, :]
    depth = Xc[..., 2]
    z = np.where(np.abs(depth) < 1e-9, 1e-9, depth)
    xy = Xc[..., :2] / z[..., None]
    uv = np.einsum("cij,cnj->cni", K[:, :2, :2], xy) + K[:, None, :2, 2]
    return uv, depth
