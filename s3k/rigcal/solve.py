"""A rig from board detections: each camera's intrinsics and distortion (OpenCV), extrinsics chained over the
camera graph of shared board views, then one bundle adjustment over every camera and board pose
(``scipy.optimize.least_squares``, sparse Jacobian, robust loss).

Camera model (OpenCV, what anipose's ``calibration.toml`` holds): ``x_cam = R x_world + t``, one focal length
``f`` (square pixels), principal point at the image centre unless freed, radial ``k1, k2``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from s3k.base.errors import UserError


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """``(..., 3)`` Rodrigues vectors -> ``(..., 3, 3)`` rotation matrices."""
    r = np.asarray(rvec, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1, keepdims=True)
    k = r / np.where(theta > 1e-12, theta, 1.0)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(kx)
    Kx = np.stack(
        [np.stack([zero, -kz, ky], -1), np.stack([kz, zero, -kx], -1), np.stack([-ky, kx, zero], -1)], -2
    )
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    eye = np.broadcast_to(np.eye(3), Kx.shape)
    return eye + s * Kx + (1 - c) * (Kx @ Kx)


def to_rvec(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle, radians) of the rotation matrix ``R``."""
    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].reshape(3)


@dataclass
class Intrinsics:
    """``f, cx, cy, k1, k2`` of one camera (pixels)."""

    f: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0

    def K(self) -> np.ndarray:
        return np.array([[self.f, 0.0, self.cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]])

    def dist(self) -> np.ndarray:
        return np.array([self.k1, self.k2, 0.0, 0.0, 0.0])


def project(X_cam: np.ndarray, f, cx, cy, k1, k2) -> np.ndarray:
    """Points in camera coordinates ``(n, 3)`` to pixels ``(n, 2)``; camera parameters broadcast per point."""
    z = X_cam[:, 2]
    xy = X_cam[:, :2] / np.where(np.abs(z) > 1e-9, z, 1e-9)[:, None]
    r2 = (xy**2).sum(1)
    radial = 1 + k1 * r2 + k2 * r2**2
    return np.stack([f * xy[:, 0] * radial + cx, f * xy[:, 1] * radial + cy], 1)


OUTLIER_VIEW_FACTOR = 3.0  # a view whose own error exceeds this many times the median view's is left out


def initial_intrinsics(
    name: str,
    frames: dict,
    corners3d: np.ndarray,
    size: tuple[int, int],
    free_principal_point: bool,
    radial: int = 2,
) -> tuple[Intrinsics, dict[int, tuple[np.ndarray, np.ndarray]], float]:
    """One camera's intrinsics from its own board views (``cv2.calibrateCamera``) and the board pose
    ``(R, t)`` (board -> camera) in each view; returns ``(intrinsics, poses, rms px)``."""

    keys = [k for k, (ids, _) in frames.items() if len(ids) >= 6]
    if len(keys) < 3:
        raise UserError(
            f"camera {name}: the board was found in {len(keys)} frame(s); calibrating a camera "
            "needs at least 3 views of the board",
            hint="show the board to it in more frames",
        )
    W, H = size
    K0 = np.array([[max(W, H), 0.0, (W - 1) / 2], [0.0, max(W, H), (H - 1) / 2], [0.0, 0.0, 1.0]])
    flags = (
        cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K3
    )
    if not free_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if radial < 2:
        flags |= cv2.CALIB_FIX_K2

    def fit(keys):
        obj = [corners3d[frames[k][0]].astype(np.float32) for k in keys]
        img = [frames[k][1].astype(np.float32) for k in keys]
        return cv2.calibrateCameraExtended(obj, img, (W, H), K0, np.zeros(5), flags=flags)

    rms, K, dist, rvecs, tvecs, _, _, per_view = fit(keys)
    # A wrong detection (a grid taken from the wrong corner) spoils the fit of every view: refit without the
    # views that fit much worse than the others (the bundle adjustment's robust loss handles the rest).
    per_view = per_view.reshape(-1)
    keep = [k for k, e in zip(keys, per_view) if e <= max(OUTLIER_VIEW_FACTOR * np.median(per_view), 1.0)]
    if len(keep) < len(keys) and len(keep) >= 3:
        keys = keep
        rms, K, dist, rvecs, tvecs, _, _, _ = fit(keys)
    d = dist.reshape(-1)
    intr = Intrinsics(float(K[0, 0]), float(K[0, 2]), float(K[1, 2]), float(d[0]), float(d[1]))
    poses = {k: (cv2.Rodrigues(r)[0], t.reshape(3)) for k, r, t in zip(keys, rvecs, tvecs)}
    return intr, poses, float(rms)


def _mean_rotation(Rs: list[np.ndarray]) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def relative_pose(poses_a: dict, poses_b: dict, shared: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Pose of camera b in camera a's frame (``x_a = R x_b + t``) from board views both saw: per view
    ``T_a,board T_b,board^-1``, the rotation averaged over the views closest to the median, translation the
    median."""
    Rs, ts = [], []
    for k in shared:
        Ra, ta = poses_a[k]
        Rb, tb = poses_b[k]
        R = Ra @ Rb.T
        Rs.append(R)
        ts.append(ta - R @ tb)
    t_med = np.median(ts, axis=0)
    dev = np.linalg.norm(np.asarray(ts) - t_med, axis=1)
    keep = dev <= max(np.median(dev) * 2, 1e-9)
    return _mean_rotation([R for R, k in zip(Rs, keep) if k]), np.median(np.asarray(ts)[keep], axis=0)


def chain_extrinsics(names: list[str], poses: list[dict]) -> list[tuple[np.ndarray, np.ndarray]]:
    """World (= the first camera) -> camera poses, chained over a spanning tree of the camera graph whose
    edges
    are board views shared by two cameras (the edges with the most shared views first). A camera that shares
    no board view with the others is a one-line error naming it."""
    C = len(names)
    shared = {(a, b): sorted(set(poses[a]) & set(poses[b])) for a in range(C) for b in range(C) if a != b}
    known = {0: (np.eye(3), np.zeros(3))}
    while len(known) < C:
        best = max(
            ((len(shared[a, b]), a, b) for a in known for b in range(C) if b not in known), default=(0, 0, 0)
        )
        if best[0] < 1:
            lost = [names[b] for b in range(C) if b not in known]
            raise UserError(
                f"camera {lost[0]} shares no board view with the others "
                f"({', '.join(names[a] for a in known)}): "
                "no frame shows the board to it and to one of them at once",
                hint="record frames where the board is seen by it and by a neighbouring camera, or leave "
                "it out",
            )
        _, a, b = best
        R_ab, t_ab = relative_pose(poses[a], poses[b], shared[a, b])  # x_a = R_ab x_b + t_ab
        Ra, ta = known[a]
        # x_b = R_ab^T (x_a - t_ab) = R_ab^T (Ra x + ta - t_ab)
        known[b] = (R_ab.T @ Ra, R_ab.T @ (ta - t_ab))
    return [known[c] for c in range(C)]


@dataclass
class Observations:
    """Every detected board corner: camera ``cam (n,)``, board view ``view (n,)``, corner ``corner (n,)``,
    pixel
    ``uv (n, 2)``; and extra points (labels) ``pcam, ppoint, puv`` seen by several cameras."""

    cam: np.ndarray
    view: np.ndarray
    corner: np.ndarray
    uv: np.ndarray
    pcam: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    ppoint: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    puv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
