"""Bundle adjustment over every camera and board pose (and optionally extra 3D points seen by several cameras,
such as labelled keypoints): ``scipy.optimize.least_squares`` with a sparse Jacobian and a robust loss.

Parameters per camera: Rodrigues rotation (3), translation (3), ``f``, ``k1``, ``k2``, ``cx``, ``cy`` (11; the
principal point is held unless freed). Per board view: the board -> world pose (6). Per extra point: its world
position (3). The world is the first free camera's frame unless some cameras are held fixed (then theirs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from s3k.rigcal.solve import Intrinsics, Observations, project, rodrigues, to_rvec

NCP = 11  # camera parameters


@dataclass
class Adjusted:
    """Result: per camera ``intrinsics``, ``R (3, 3)``, ``t (3,)``; per board view ``(R, t)`` board -> world;
    extra points ``(P, 3)``; residual vectors of the board observations ``(n, 2)`` and extra points."""

    intrinsics: list[Intrinsics]
    R: list[np.ndarray]
    t: list[np.ndarray]
    views: list[tuple[np.ndarray, np.ndarray]]
    points: np.ndarray
    residuals: np.ndarray
    point_residuals: np.ndarray
    cost: float
    iterations: int


def _pack(intr, R, t, views, points) -> np.ndarray:
    cams = [np.r_[to_rvec(Rc), tc, i.f, i.k1, i.k2, i.cx, i.cy] for i, Rc, tc in zip(intr, R, t)]
    vs = [np.r_[to_rvec(Rv), tv] for Rv, tv in views]
    return np.concatenate([np.ravel(cams), np.ravel(vs) if vs else np.zeros(0), np.ravel(points)])


def _residuals(x: np.ndarray, C: int, V: int, obs: Observations, corners3d: np.ndarray) -> np.ndarray:
    cams = x[: C * NCP].reshape(C, NCP)
    views = x[C * NCP : C * NCP + V * 6].reshape(V, 6)
    points = x[C * NCP + V * 6 :].reshape(-1, 3)
    Rc = rodrigues(cams[:, :3])
    Rv = rodrigues(views[:, :3])
    Xw = np.einsum("nij,nj->ni", Rv[obs.view], corners3d[obs.corner]) + views[obs.view, 3:]
    Xc = np.einsum("nij,nj->ni", Rc[obs.cam], Xw) + cams[obs.cam, 3:6]
    p = cams[obs.cam]
    out = [(project(Xc, p[:, 6], p[:, 9], p[:, 10], p[:, 7], p[:, 8]) - obs.uv).ravel()]
    if len(obs.pcam):
        Xc = np.einsum("nij,nj->ni", Rc[obs.pcam], points[obs.ppoint]) + cams[obs.pcam, 3:6]
        q = cams[obs.pcam]
        out.append((project(Xc, q[:, 6], q[:, 9], q[:, 10], q[:, 7], q[:, 8]) - obs.puv).ravel())
    return np.concatenate(out)


def _sparsity(C: int, V: int, P: int, obs: Observations):
    """Which parameters each residual depends on: its camera's, its board view's or its point's."""

    n, m = len(obs.cam), len(obs.pcam)
    rows, cols = [], []

    def block(obs_rows: np.ndarray, first_col: np.ndarray, width: int) -> None:
        for k in (0, 1):
            for j in range(width):
                rows.append(2 * obs_rows + k)
                cols.append(first_col + j)

    block(np.arange(n), obs.cam * NCP, NCP)
    block(np.arange(n), C * NCP + obs.view * 6, 6)
    block(n + np.arange(m), obs.pcam * NCP, NCP)
    block(n + np.arange(m), C * NCP + V * 6 + obs.ppoint * 3, 3)
    r, c = np.concatenate(rows), np.concatenate(cols)
    return coo_matrix(
        (np.ones(len(r), np.int8), (r, c)), shape=(2 * (n + m), C * NCP + V * 6 + P * 3)
    ).tocsc()


def bundle_adjust(
    intr: list[Intrinsics],
    R: list[np.ndarray],
    t: list[np.ndarray],
    views: list[tuple[np.ndarray, np.ndarray]],
    obs: Observations,
    corners3d: np.ndarray,
    *,
    points: np.ndarray | None = None,
    fixed: list[int] | None = None,
    free_principal_point: bool = False,
    radial: int = 2,
    loss_scale_px: float = 1.0,
    max_evaluations: int = 200,
) -> Adjusted:
    """Refine cameras, board views and extra points jointly.

    Args:
        intr, R, t: initial cameras (``x_cam = R x_world + t``).
        views: initial board -> world poses.
        obs: the observations.
        corners3d: ``(N, 3)`` board corners in the board frame.
        points: ``(P, 3)`` initial extra points (``obs.ppoint`` indexes them).
        fixed: cameras held as they are (their pose then fixes the world); default: the first camera's pose
            (its intrinsics are refined).
        free_principal_point: refine ``cx, cy``.
        radial: radial distortion terms refined: 1 (``k1``, anipose's model) or 2 (``k1, k2``).
        loss_scale_px: the Huber loss's scale: residuals beyond it count linearly (bad detections).
    """

    C, V = len(intr), len(views)
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)
    x0 = _pack(intr, R, t, views, pts)
    free = np.ones(len(x0), bool)
    for c in range(C):
        if not free_principal_point:
            free[c * NCP + 9 : c * NCP + 11] = False
        if radial < 2:
            free[c * NCP + 8] = False
    if fixed:
        for c in fixed:
            free[c * NCP : (c + 1) * NCP] = False
    else:
        free[:6] = False  # gauge: the world is the first camera
    idx = np.flatnonzero(free)

    def fun(xf):
        x = x0.copy()
        x[idx] = xf
        return _residuals(x, C, V, obs, corners3d)

    S = _sparsity(C, V, len(pts), obs)[:, idx]
    sol = least_squares(
        fun,
        x0[idx],
        jac_sparsity=S,
        loss="huber",
        f_scale=loss_scale_px,
        x_scale="jac",
        method="trf",
        max_nfev=max_evaluations,
    )
    x = x0.copy()
    x[idx] = sol.x
    cams = x[: C * NCP].reshape(C, NCP)
    vs = x[C * NCP : C * NCP + V * 6].reshape(V, 6)
    res = _residuals(x, C, V, obs, corners3d)
    n = 2 * len(obs.cam)
    return Adjusted(
        [Intrinsics(p[6], p[9], p[10], p[7], p[8]) for p in cams],
        list(rodrigues(cams[:, :3])),
        [p[3:6].copy() for p in cams],
        [(rodrigues(v[:3]), v[3:].copy()) for v in vs],
        x[C * NCP + V * 6 :].reshape(-1, 3),
        res[:n].reshape(-1, 2),
        res[n:].reshape(-1, 2),
        float(sol.cost),
        int(sol.nfev),
    )
